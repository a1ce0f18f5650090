"""Shake paths read from a generated scene's records (``DegradationConfig.shake_paths`` "records"): the closest
cubic to a recorded path, the recorded path's blur of the sharp twin, and the degradation model that holds them
fixed. A tiny real generated scene and its sharp twin, written to disk; no nerfstudio trainer."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from gsmsdr_ns.bench.scenes import SceneSpec, ensure_scene
from gsmsdr_ns.blur.degradation_config import DegradationConfig
from gsmsdr_ns.blur.degradation_model import DegradationModel
from gsmsdr_ns.blur.field import BlurFieldConfig
from gsmsdr_ns.blur.profile import DegradationProfile, motion_records
from gsmsdr_ns.blur.recorded_shake import recorded_path
from gsmsdr_ns.blur.shake import CameraShake, path_coefficients
from tools.shake.shake_fit import _image, psnr

SPEC = SceneSpec(variant="motion-strong", width=96, height=72, num_views=6, hold=3, num_points=300, seed=0)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("recorded")
    return ensure_scene(root, SPEC), ensure_scene(root, SPEC.with_variant("sharp"))


def train_records(scene: Path) -> dict:
    images = json.loads((scene / "degradation.json").read_text())["images"]
    return {n: r for n, r in sorted(images.items()) if r["split"] == "train"}


def test_the_closest_cubic_reproduces_a_cubic_and_rejects_too_few_samples() -> None:
    times = torch.linspace(-0.5, 0.5, 7, dtype=torch.float64)
    coefficients = torch.tensor([[1.0, -2.0], [0.5, 0.0], [-3.0, 4.0]], dtype=torch.float64)
    values = torch.stack([times, times**2, times**3], dim=1) @ coefficients
    assert torch.allclose(path_coefficients(times, values), coefficients, atol=1e-9)
    # two samples (a short shake's record): the line through them, no curvature
    line = path_coefficients(torch.tensor([-0.25, 0.25], dtype=torch.float64), torch.tensor([[-1.0], [1.0]]))
    assert torch.allclose(line, torch.tensor([[4.0], [0.0], [0.0]], dtype=torch.float64))
    with pytest.raises(ValueError, match="S >= 1"):
        path_coefficients(times[:0], values[:0])


def test_the_recorded_path_blurs_the_sharp_twin_into_the_photo(scenes) -> None:
    """The generator's path is a cubic through the mid-exposure pose: the module's 9 samples of its closest cubic,
    applied to the sharp twin with the true depth, explain the shaken photo far better than the sharp image does and
    than the same path with the rotations' sign flipped (the convention the records are read in matters)."""
    shaken, sharp = scenes
    name, record = next(iter(train_records(shaken).items()))
    motion = record["effects"]["motion"]
    intr = json.loads((shaken / "scene.json").read_text())["intrinsics"]
    K = torch.tensor([[intr["fx"], 0.0, intr["cx"]], [0.0, intr["fy"], intr["cy"]], [0.0, 0.0, 1.0]])
    depth = torch.from_numpy(np.load(shaken / "depth" / f"{Path(name).stem}.npy").astype(np.float32))
    source, photo = _image(sharp / "images" / name), _image(shaken / "images" / name)  # linear light
    times, rotvecs, translations = recorded_path(motion)
    assert translations is not None and times.min() > -0.5 and times.max() < 0.5
    # the cubic fit is the recorded path itself (the generator draws cubic Bezier paths)
    cubic = torch.stack([times, times**2, times**3], 1) @ path_coefficients(times, rotvecs)
    assert float((cubic - rotvecs).abs().max()) < 1e-3 * float(rotvecs.abs().max()), (cubic, rotvecs)

    def blurred(sign: float) -> torch.Tensor:
        shake = CameraShake(1, num_samples=9, translation=True)
        shake.set_path(0, times, sign * rotvecs, translations)
        with torch.no_grad():
            return shake(source, K, torch.tensor([0]), centred=False, linear_light=False, depth=depth)

    margin = int(np.ceil(float(motion.get("max_displacement_px", motion["blur_px"])))) + 2
    none, true, flipped = (
        psnr(source, photo, margin),
        psnr(blurred(1.0), photo, margin),
        psnr(blurred(-1.0), photo, margin),
    )
    assert true > none + 5.0 and true > flipped + 3.0, (none, true, flipped)


def test_the_degradation_model_holds_the_recorded_paths_fixed(scenes) -> None:
    shaken, _ = scenes
    records = [{**r, "name": n} for n, r in train_records(shaken).items()]
    profiles = [DegradationProfile.from_metadata(r) for r in records]
    assert all(p.motion and p.exact_pose for p in profiles)
    config = DegradationConfig(camera_shake=True, shake_translation=True, shake_paths="records")
    field = BlurFieldConfig(kernel_sizes=(5, 9, 17))
    model = DegradationModel(
        profiles, field, config, shake_records=motion_records(records, len(records)), pose_scale=2.0
    )
    shake = model.camera_shake
    assert shake is not None and not any(p.requires_grad for p in shake.parameters())
    times, rotvecs, translations = recorded_path(records[0]["effects"]["motion"], pose_scale=2.0)
    assert torch.allclose(shake.coefficients[0].double(), path_coefficients(times, rotvecs) / 0.01, atol=1e-4)
    assert translations is not None and shake.translation_coefficients is not None
    assert torch.allclose(
        shake.translation_coefficients[0].double(), path_coefficients(times, translations) / 0.01, atol=1e-4
    )
    # learnt paths stay trainable; records without a path, or without the pose scale their translations need, fail
    learnt = DegradationModel(profiles, field, DegradationConfig(camera_shake=True, shake_translation=True))
    assert learnt.camera_shake is not None and learnt.camera_shake.coefficients.requires_grad
    with pytest.raises(ValueError, match="training view 1 has no recorded shake path"):
        missing = motion_records(records, len(records))
        missing[1] = None
        DegradationModel(profiles, field, config, shake_records=missing, pose_scale=1.0)
    with pytest.raises(ValueError, match="pose scale"):
        DegradationModel(profiles, field, config, shake_records=motion_records(records, len(records)))


def test_recorded_paths_need_the_shake_and_not_the_parallax_offsets() -> None:
    with pytest.raises(ValueError, match="camera_shake on and shake_parallax off"):
        DegradationConfig(shake_paths="records")
    with pytest.raises(ValueError, match="camera_shake on and shake_parallax off"):
        DegradationConfig(camera_shake=True, shake_translation=True, shake_parallax=True, shake_paths="records")
    with pytest.raises(ValueError, match="shake_paths must be"):
        DegradationConfig(camera_shake=True, shake_paths="true")  # type: ignore[arg-type]


def test_path_error_is_zero_for_the_true_path_either_way_in_time_and_not_for_a_wrong_one(scenes, tmp_path, capsys):
    """tools/shake/path_error.py on a run record holding the true paths (read forwards, then backwards in time:
    the same blur) and the true paths turned the other way."""
    from gsmsdr_ns.blur.shake import shake_sample_times
    from tools.shake.path_error import PathError

    shaken, _ = scenes
    times = shake_sample_times(9)
    basis = torch.stack([times, times**2, times**3], dim=1)

    def run_file(name: str, rotation_sign: float, reverse: bool) -> Path:
        views = []
        for view, record in train_records(shaken).items():
            record_times, rotvecs, translations = recorded_path(record["effects"]["motion"], pose_scale=0.5)
            rot = basis @ path_coefficients(record_times, rotation_sign * rotvecs)
            move = basis @ path_coefficients(record_times, translations)
            rot, move = (rot.flip(0), move.flip(0)) if reverse else (rot, move)
            views.append({"name": view, "motion": True, "rotvecs": rot.tolist(), "translations": move.tolist()})
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps({"shake_paths": {"times": times.tolist(), "pose_scale": 0.5, "views": views}}))
        return path

    def mean_row(path: Path) -> list[float]:
        PathError(run=path, data=shaken, stride=2).main()
        return [float(x) for x in capsys.readouterr().out.splitlines()[-1].strip("| ").split("|")[1:]]

    extent, error, offset, shape = mean_row(run_file("true", 1.0, reverse=False))
    assert extent > 0.5 and error < 0.05 * extent and offset < 0.05 * extent and shape <= error + 1e-9
    assert mean_row(run_file("reversed", 1.0, reverse=True))[1] < 0.05 * extent
    wrong = mean_row(run_file("turned", -1.0, reverse=False))
    assert wrong[1] > 0.5 * extent and wrong[3] <= wrong[1] + 1e-9, wrong
    with pytest.raises(SystemExit, match="no shake_paths"):
        (tmp_path / "none.json").write_text("{}")
        PathError(run=tmp_path / "none.json", data=shaken).main()


def test_kernels_after_a_shake_path_are_centred_on_exact_poses_only_when_asked() -> None:
    """An exact mid-exposure pose leaves the field's kernels uncentred (the blur of a curved shake is not centred on
    its midpoint) unless ``kernel_centre_after_shake``, and then only where a shake path runs first; a pose estimated
    from the photo is always centred."""
    exact, estimated = DegradationProfile(motion=True, exact_pose=True), DegradationProfile(motion=True)
    field = BlurFieldConfig(kernel_sizes=(5, 9, 17))

    def centred(config: DegradationConfig, profiles: list) -> list:
        model = DegradationModel(profiles, field, config)
        return [model.plan(v, render_downscale=1, step=10_000).kernel_centre_loss for v in range(len(profiles))]

    shake = dict(camera_shake=True, shake_translation=True, shake_parallax=True)
    assert centred(DegradationConfig(**shake), [exact, estimated]) == [False, True]
    assert centred(DegradationConfig(**shake, kernel_centre_after_shake=True), [exact, estimated]) == [True, True]
    assert centred(DegradationConfig(kernel_centre_after_shake=True), [exact, estimated]) == [False, True]
