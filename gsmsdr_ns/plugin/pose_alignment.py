"""Test-pose alignment before metrics: the scene is frozen and each test camera's pose is optimised on the photometric
loss against its ground-truth image, as deblurring methods evaluate real captures (the test poses were estimated
together with blurry training photos, so part of a render's error can be pose error, not scene error).

Metrics are the model's own (``get_image_metrics_and_images``, the definition ``ns-eval`` uses), computed with the
given pose and with the aligned one. A camera keeps its given pose when alignment does not lower the full-resolution
loss, so aligned metrics are never computed on a worse-fitting pose.
"""

from __future__ import annotations

import contextlib
import copy
from dataclasses import dataclass, field
from typing import Dict, Iterator, List, Tuple

import torch
import torch.nn.functional as F
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor


@dataclass
class PoseAlignmentConfig:
    """How each test camera's pose is optimised (Adam on the mean squared error of the sharp render)."""

    steps_per_stage: int = 60
    """Adam steps at each render downscale of ``downscales``."""
    downscales: Tuple[int, ...] = (4, 2, 1)
    """Coarse to fine: render (and ground truth) shrunk by these factors in turn; coarse stages widen the basin."""
    rotation_lr: float = 2e-3
    """Adam step size of the rotation (axis-angle, radians)."""
    translation_lr: float = 2e-3
    """Adam step size of the camera centre, in scene units (nerfstudio's normalised scene: cameras within ~[-1, 1])."""


@dataclass
class AlignedPose:
    """One camera's alignment: the correction found and the loss before and after it."""

    rotation: Tensor  # [3] axis-angle (radians) applied in world axes about the camera centre
    translation: Tensor  # [3] added to the camera centre
    loss_before: float
    loss_after: float
    kept_given_pose: bool = field(default=False)

    @property
    def rotation_degrees(self) -> float:
        return float(torch.rad2deg(self.rotation.norm()))


def corrected_pose(camera_to_world: Tensor, rotation: Tensor, translation: Tensor) -> Tensor:
    """A camera-to-world pose rotated about its centre and moved.

    Args:
        camera_to_world: [3, 4] pose (any axis convention: the rotation acts in world axes).
        rotation: [3] axis-angle in radians. translation: [3] in world units.

    Returns:
        [3, 4] pose with rotation ``exp(rotation) @ R`` and centre ``c + translation``.
    """
    delta = axis_angle_to_rotation_matrix(rotation[None])[0]
    return torch.cat([delta @ camera_to_world[:, :3], camera_to_world[:, 3:] + translation[:, None]], dim=1)


def camera_with_pose(camera: Cameras, camera_to_world: Tensor, downscale: int = 1) -> Cameras:
    """A copy of one camera at pose ``camera_to_world`` [3, 4], its output resolution shrunk by ``downscale``."""
    moved = copy.deepcopy(camera)
    moved.camera_to_worlds = camera_to_world.reshape(1, 3, 4)
    if downscale > 1:
        moved.rescale_output_resolution(1.0 / downscale)
    return moved


def _shrink(image: Tensor, size: Tuple[int, int]) -> Tensor:
    """[H, W, C] image area-resampled to ``size`` (h, w)."""
    if tuple(image.shape[:2]) == size:
        return image
    return F.interpolate(image.permute(2, 0, 1)[None], size=size, mode="area")[0].permute(1, 2, 0)


@contextlib.contextmanager
def frozen_for_alignment(model: torch.nn.Module) -> Iterator[None]:
    """Evaluation mode, no parameter gradients, and no viewer-only outputs while poses are optimised."""
    was_training = model.training
    flags = [(p, p.requires_grad) for p in model.parameters()]
    config = getattr(model, "config", None)
    viewer_outputs = getattr(config, "viewer_blur_outputs", None)
    model.eval()
    for param, _ in flags:
        param.requires_grad_(False)
    if viewer_outputs is not None:
        config.viewer_blur_outputs = False
    try:
        yield
    finally:
        for param, flag in flags:
            param.requires_grad_(flag)
        if viewer_outputs is not None:
            config.viewer_blur_outputs = viewer_outputs
        model.train(was_training)


def _render_loss(model, camera: Cameras, camera_to_world: Tensor, image: Tensor, downscale: int) -> Tensor:
    render = model.get_outputs(camera_with_pose(camera, camera_to_world, downscale))["rgb"]
    target = _shrink(image, tuple(render.shape[:2]))
    return F.mse_loss(render, target)


def align_camera(model, camera: Cameras, image: Tensor, config: PoseAlignmentConfig) -> AlignedPose:
    """Optimise one camera's pose so that the frozen model's sharp render matches ``image``.

    Args:
        model: a model in :func:`frozen_for_alignment` whose ``get_outputs(camera)["rgb"]`` is differentiable in
            the camera pose (ours is, on CPU and CUDA).
        camera: one camera. image: [H, W, 3] ground truth in [0, 1] on the model's device.

    Returns:
        The correction and the full-resolution loss with the given and the corrected pose; when the correction does
        not lower the loss, it is zero (``kept_given_pose``).
    """
    pose = camera.camera_to_worlds.reshape(3, 4).to(image.device, image.dtype)
    rotation = torch.zeros(3, device=image.device, dtype=image.dtype, requires_grad=True)
    translation = torch.zeros(3, device=image.device, dtype=image.dtype, requires_grad=True)
    optimizer = torch.optim.Adam(
        [{"params": [rotation], "lr": config.rotation_lr}, {"params": [translation], "lr": config.translation_lr}]
    )
    for downscale in config.downscales:
        for _ in range(config.steps_per_stage):
            optimizer.zero_grad(set_to_none=True)
            loss = _render_loss(model, camera, corrected_pose(pose, rotation, translation), image, downscale)
            loss.backward()
            optimizer.step()
    with torch.no_grad():
        before = float(_render_loss(model, camera, pose, image, 1))
        after = float(_render_loss(model, camera, corrected_pose(pose, rotation, translation), image, 1))
    if not after < before:
        zero = torch.zeros(3, device=image.device, dtype=image.dtype)
        return AlignedPose(zero, zero.clone(), before, before, kept_given_pose=True)
    return AlignedPose(rotation.detach(), translation.detach(), before, after)


def aligned_camera(model, camera: Cameras, image: Tensor, config: PoseAlignmentConfig) -> Tuple[Cameras, AlignedPose]:
    """One camera moved to the pose :func:`align_camera` finds for ``image`` (same arguments), and the correction."""
    correction = align_camera(model, camera, image, config)
    pose = corrected_pose(camera.camera_to_worlds.reshape(3, 4).to(image), correction.rotation, correction.translation)
    return camera_with_pose(camera, pose), correction


def evaluate_with_alignment(
    pipeline, config: PoseAlignmentConfig, align: bool = True, progress=None
) -> Tuple[Dict[str, float], Dict[str, float], List[Dict[str, float]]]:
    """Metrics of every test view of ``pipeline`` with the given poses and, if ``align``, with aligned poses.

    Returns:
        (mean metrics with given poses, mean metrics with aligned poses or {}, per-view rows with both and the
        correction found). Metric names are the model's (psnr, ssim, and lpips when available).
    """
    model = pipeline.model
    views = list(pipeline.datamanager.fixed_indices_eval_dataloader)
    task = progress.add_task("aligning test poses" if align else "evaluating", total=len(views)) if progress else None
    rows: List[Dict[str, float]] = []
    names: List[str] = []  # the model's metric names (psnr, ssim, lpips when available)
    with frozen_for_alignment(model):
        for index, (camera, batch) in enumerate(views):
            camera = camera.to(model.device)
            with torch.no_grad():
                outputs = model.get_outputs(camera)
                given, _ = model.get_image_metrics_and_images(outputs, batch)
            # the ground truth as the metrics see it: [0, 1] floats, alpha composited on the render's background
            image = model.composite_with_background(model.get_gt_img(batch["image"]), outputs["background"])
            names = list(given)
            row = {"view": index, **{name: float(value) for name, value in given.items()}}
            if align:
                moved, aligned_pose = aligned_camera(model, camera, image, config)
                with torch.no_grad():
                    aligned, _ = model.get_image_metrics_and_images(model.get_outputs(moved), batch)
                row.update({f"{name}_aligned": float(value) for name, value in aligned.items()})
                row["rotation_deg"] = aligned_pose.rotation_degrees
                row["translation"] = float(aligned_pose.translation.norm())
            rows.append(row)
            if progress:
                progress.advance(task)
    mean = {name: sum(r[name] for r in rows) / len(rows) for name in names}
    mean_aligned = {name: sum(r[f"{name}_aligned"] for r in rows) / len(rows) for name in names} if align else {}
    return mean, mean_aligned, rows
