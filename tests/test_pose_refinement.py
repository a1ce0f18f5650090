"""Pose refinement (nerfstudio's camera optimizer) on the views with a degradation model: a real in-process trainer
on a generated scene where some training photos are recorded sharp; their poses must stay as given, the degraded
ones' move, and ``camera_optimizer_views all`` refines every view (splatfacto)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import cpu_trainer_config

SHARP_VIEWS = ("frame_00001.png", "frame_00003.png")


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    from gsmsdr_ns.bench.scenes import SceneSpec, ensure_scene

    data = ensure_scene(tmp_path_factory.mktemp("poses"), SceneSpec("motion", 48, 36, 10, 0, 5, num_points=300))
    path = data / "degradation.json"
    doc = json.loads(path.read_text(encoding="utf8"))
    for name in SHARP_VIEWS:  # recorded sharp: plain splatfacto steps, given poses kept
        doc["images"][name] = {"split": "train", "degraded": False, "effects": {}}
    path.write_text(json.dumps(doc), encoding="utf8")
    return data


def _pose_adjustments(scene: Path, out: Path, views: str):
    config = cpu_trainer_config(scene, out, max_steps=12)
    config.pipeline.datamanager.dataparser.estimate_degradations = True
    model = config.pipeline.model
    model.camera_optimizer.mode = "SO3xR3"
    model.camera_optimizer_views = views
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    names = [Path(f).name for f in trainer.pipeline.datamanager.train_dataset.image_filenames]
    adjustment = trainer.pipeline.model.camera_optimizer.pose_adjustment.detach().abs().sum(dim=1)
    return dict(zip(names, adjustment.tolist()))


def test_only_degraded_views_have_their_poses_refined(scene, tmp_path):
    moved = _pose_adjustments(scene, tmp_path / "degraded", "degraded")
    assert set(SHARP_VIEWS) <= set(moved)
    for name, amount in moved.items():
        if name in SHARP_VIEWS:
            assert amount == 0.0, (name, moved)
        else:
            assert amount > 0.0, (name, moved)


def test_all_views_are_refined_on_request(scene, tmp_path):
    moved = _pose_adjustments(scene, tmp_path / "all", "all")
    assert all(amount > 0.0 for amount in moved.values()), moved
