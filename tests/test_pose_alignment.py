"""Test-pose alignment (``gsmsdr-eval``): the frozen scene, each test camera's pose optimised on the photometric loss.

Uses the session's real ``ns-train gsmsdr`` run (``trained_run``) and loads it as ns-eval does."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest
import torch
from conftest import TrainedRun
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from gsmsdr_ns.plugin.pose_alignment import (
    PoseAlignmentConfig,
    align_camera,
    corrected_pose,
    evaluate_with_alignment,
    frozen_for_alignment,
)


def _load(run: TrainedRun):
    from nerfstudio.utils.eval_utils import eval_setup

    import gsmsdr_ns.plugin  # noqa: F401

    return eval_setup(run.config)[1]


def _perturbation(seed: int, degrees: float, distance: float):
    """A rotation of ``degrees`` about a random axis and a move of ``distance`` in a random direction."""
    g = torch.Generator().manual_seed(seed)
    axis = torch.nn.functional.normalize(torch.randn(3, generator=g), dim=0)
    direction = torch.nn.functional.normalize(torch.randn(3, generator=g), dim=0)
    return axis * math.radians(degrees), direction * distance


def _trajectory_diameter(pipeline) -> float:
    centres = torch.cat([pipeline.datamanager.train_dataset.cameras.camera_to_worlds[:, :3, 3],
                         pipeline.datamanager.eval_dataset.cameras.camera_to_worlds[:, :3, 3]])  # fmt: skip
    return float(torch.cdist(centres, centres).max())


def test_corrected_pose_rotates_about_the_camera_centre():
    pose = torch.cat([torch.eye(3), torch.tensor([[1.0], [2.0], [3.0]])], dim=1)
    moved = corrected_pose(pose, torch.tensor([0.0, 0.0, math.pi / 2]), torch.tensor([0.5, 0.0, 0.0]))
    torch.testing.assert_close(moved[:, 3], torch.tensor([1.5, 2.0, 3.0]))
    torch.testing.assert_close(moved[:, :3], axis_angle_to_rotation_matrix(torch.tensor([[0.0, 0.0, math.pi / 2]]))[0])


def test_alignment_recovers_a_perturbed_pose_from_the_models_own_render(trained_run):
    """Ground truth rendered by the model at the true pose (twice the test view's size): aligning from a pose 0.5
    degrees and 1% of the trajectory off recovers the true pose far closer than the perturbation."""
    pipeline = _load(trained_run)
    model = pipeline.model
    camera, _ = pipeline.datamanager.fixed_indices_eval_dataloader[0]
    camera.rescale_output_resolution(2.0)
    true_pose = camera.camera_to_worlds.reshape(3, 4).clone()
    diameter = _trajectory_diameter(pipeline)
    rotation, translation = _perturbation(0, 0.5, 0.01 * diameter)
    with frozen_for_alignment(model):
        with torch.no_grad():
            image = model.get_outputs(camera)["rgb"]
        camera.camera_to_worlds = corrected_pose(true_pose, rotation, translation)[None]
        result = align_camera(model, camera, image, PoseAlignmentConfig())
    assert not result.kept_given_pose and result.loss_after < 0.2 * result.loss_before
    found = corrected_pose(camera.camera_to_worlds.reshape(3, 4), result.rotation, result.translation)
    relative = found[:, :3].T @ true_pose[:, :3]
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(torch.trace(relative)) - 1.0) / 2.0))))
    offset = float((found[:, 3] - true_pose[:, 3]).norm())
    print(
        f"rotation error {angle:.3f} deg (from 0.5), centre error {offset / diameter:.4%} of the trajectory (from 1%)"
    )
    assert angle < 0.25
    assert offset < 0.005 * diameter


@pytest.fixture(scope="module")
def well_trained_run(tmp_path_factory) -> TrainedRun:
    """A sharp 128x96 scene trained for 3000 steps: fitted well enough that half a degree of pose error shows."""
    from conftest import TRAIN_FLAGS, make_tiny_scene, run_cli

    work = tmp_path_factory.mktemp("aligned")
    scene = make_tiny_scene(work / "scene", num_views=24, width=128, height=96, num_points=2000)
    steps = 3000
    args = ["gsmsdr-lite", "--data", scene, "--output-dir", work / "outputs", "--timestamp", "run",
            "--max-num-iterations", steps, "--steps-per-save", steps, *TRAIN_FLAGS]  # fmt: skip
    proc = run_cli("ns-train", args, cwd=work, timeout=7200)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-6000:]
    run_dir = work / "outputs" / scene.name / "gsmsdr-lite" / "run"
    return TrainedRun(scene, run_dir, run_dir / "config.yml", run_dir / "nerfstudio_models", proc.stdout, steps)


@pytest.mark.slow
def test_aligned_metrics_of_perturbed_test_poses_match_the_unperturbed_ones(well_trained_run):
    """On real (generated) test images: test poses perturbed by 0.5 degrees and 1% of the trajectory, metrics after
    alignment within 0.3 dB of the metrics with the unperturbed poses, while the perturbation alone costs more."""
    pipeline = _load(well_trained_run)
    config = PoseAlignmentConfig()
    given, _, _ = evaluate_with_alignment(pipeline, config, align=False)
    cameras = pipeline.datamanager.eval_dataset.cameras
    diameter = _trajectory_diameter(pipeline)
    for index in range(cameras.shape[0]):
        rotation, translation = _perturbation(index + 1, 0.5, 0.01 * diameter)
        cameras.camera_to_worlds[index] = corrected_pose(cameras.camera_to_worlds[index], rotation, translation)
    perturbed, aligned, views = evaluate_with_alignment(pipeline, config, align=True)
    print(f"psnr: unperturbed {given['psnr']:.3f}, perturbed {perturbed['psnr']:.3f}, aligned {aligned['psnr']:.3f}")
    assert perturbed["psnr"] < given["psnr"] - 0.3  # the perturbation is visible in the metrics
    assert abs(aligned["psnr"] - given["psnr"]) <= 0.3
    assert all(v["psnr_aligned"] >= v["psnr"] - 1e-6 for v in views)


def test_gsmsdr_eval_writes_given_and_aligned_metrics(trained_run, tmp_path):
    out = tmp_path / "eval.json"
    code = "from gsmsdr_ns.plugin.eval_cli import entrypoint; entrypoint()"
    args = [sys.executable, "-c", code, "--load-config", str(trained_run.config), "--output-path", str(out),
            "--alignment.steps-per-stage", "10"]  # fmt: skip
    proc = subprocess.run(args, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    payload = json.loads(out.read_text())
    assert payload["method_name"] == "gsmsdr"
    assert {"psnr", "ssim"} <= set(payload["results"]) and {"psnr", "ssim"} <= set(payload["results_aligned"])
    assert len(payload["views"]) == 2  # the tiny scene's two test views
    assert payload["results_aligned"]["psnr"] >= payload["results"]["psnr"] - 1e-6
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eval.json"]  # no temporary file left
    assert "aligned poses" in proc.stdout
