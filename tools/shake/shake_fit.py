"""How well each camera-shake model can explain a generated scene's shaken photos (prints a table). Run from the
repository root::

    python -m tools.shake.shake_fit --data shaken-scene --sharp its-sharp-twin [--views 8]

``--data`` is a generated scene degraded by ``motion`` (``gsmsdr-synth --variant motion-strong``: its
``degradation.json`` keeps each training view's true exposure path, ``depth/`` each view's depth); ``--sharp`` the
same scene rendered sharp (``gsmsdr-synth --variant sharp`` with the same scene settings). No training: per shaken
training view, the sharp twin is blurred by each model, fitted to the photo where the model has free parameters,
and compared with the photo (PSNR in sRGB over the view minus a margin the shake reaches beyond the border):

* ``none``: the sharp image itself;
* ``kernel``: the best single kernel of ``--kernel-size`` px (least squares in linear light; mode ``view``);
* ``rotation``: the true path's rotations alone, translations dropped;
* ``path``: the best rotation path (``--path-samples`` samples, fitted from the true rotations; what
  ``camera_shake`` learns, without its cubic form), then ``path + kernel`` with the best kernel after it (the
  ``gsmsdr-cpu`` model's ceiling);
* ``moving path``: the best path of rotations and translations (``--path-samples`` samples, from the fitted
  rotation path at rest), each pixel moved by the view's depth (:func:`gsmsdr_ns.blur.shake.shake_sample_grid`,
  what ``shake_translation`` learns when the depth is right);
* ``6-DoF``: the true rotations and translations, each pixel moved by the view's depth.
* ``6-DoF occluding``: the same, each time sample reading the sharp view along the depth its own camera sees
  (:func:`gsmsdr_ns.blur.shake.apply_camera_shake_occluding`, what ``shake_occlusion`` models).
* ``sampled 6-DoF occluding``: the same true path read at only ``--path-samples`` time samples, the midpoints of
  equal time bins (where the trained model samples its paths; the generator averages many more sub-frames), then
  ``sampled 6-DoF occluding + kernel`` with the best kernel after it: what the path's discretisation costs.

What the best fit of a model leaves is what training with that model cannot explain however well it learns. The
fitted columns are local optima of L-BFGS from the starts named above: approximate ceilings, which can move by a
few tenths of a dB with the start or with rounding.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np
import torch
import tyro
from kornia.color import linear_rgb_to_rgb, rgb_to_linear_rgb
from torch import Tensor

from gsmsdr_ns.blur.shake import (
    apply_camera_shake,
    apply_camera_shake_occluding,
    apply_camera_shake_with_depth,
    rotation_homographies,
    shake_sample_grid,
    shake_sample_times,
)
from gsmsdr_ns.io.images import read_image_float
from gsmsdr_ns.ops.pixel_kernels import apply_image_kernels

MODELS = ("none", "kernel", "rotation", "path", "path + kernel", "moving path", "6-DoF", "6-DoF occluding",
          "sampled 6-DoF occluding", "sampled 6-DoF occluding + kernel")  # fmt: skip
"""Columns of the table, in order."""


def midpoint_samples(num_frames: int, num_samples: int) -> Tensor:
    """Indices of the ``num_frames`` recorded sub-frames (equal bins of the exposure) nearest the times a learnt path
    of ``num_samples`` is sampled at (:func:`gsmsdr_ns.blur.shake.shake_sample_times`) -> [num_samples]."""
    centres = (shake_sample_times(num_samples) + 0.5) * num_frames - 0.5
    return centres.round().long().clamp(0, num_frames - 1)


def psnr(a: Tensor, b: Tensor, margin: int) -> float:
    """PSNR of ``a`` against ``b`` ([1, 3, H, W] sRGB in [0, 1]) inside ``margin`` px of the border."""
    d = (a - b)[..., margin : a.shape[-2] - margin, margin : a.shape[-1] - margin]
    return float(-10.0 * torch.log10((d**2).mean().clamp_min(1e-12)))


def rotation_blur(image: Tensor, K: Tensor, rotvecs: Tensor) -> Tensor:
    """``image`` [1, C, H, W] (already linear) averaged along the camera rotations ``rotvecs`` [T, 3]."""
    return apply_camera_shake(image, rotation_homographies(K, rotvecs), linear_light=False)


def depth_blur(image: Tensor, K: Tensor, rotvecs: Tensor, translations: Tensor, depth: Tensor) -> Tensor:
    """``image`` [1, C, H, W] (already linear) averaged along a 6-DoF path, each pixel moved by its ``depth``
    [H, W]."""
    return apply_camera_shake_with_depth(image, shake_sample_grid(K, rotvecs, translations, depth), linear_light=False)


def fit_kernel(source: Tensor, target: Tensor, size: int, margin: int, iters: int = 100) -> Tensor:
    """``source`` [1, C, H, W] blurred by the ``size`` x ``size`` kernel (shared by the channels,
    :func:`~gsmsdr_ns.ops.pixel_kernels.apply_image_kernels`) that best matches ``target`` in least squares inside
    ``margin`` px of the border."""
    H, W = source.shape[-2:]
    kernel = torch.zeros(1, size * size, dtype=source.dtype)
    kernel[0, (size * size) // 2] = 1.0
    kernel.requires_grad_(True)

    def loss() -> Tensor:
        d = apply_image_kernels(source, kernel) - target
        return (d[..., margin : H - margin, margin : W - margin] ** 2).mean()

    _minimise([kernel], loss, iters)
    with torch.no_grad():
        return apply_image_kernels(source, kernel)


def fit_rotation_path(source: Tensor, target: Tensor, K: Tensor, start: Tensor, margin: int, iters: int = 40) -> Tensor:
    """Rotation vectors [T, 3] (from ``start``) whose :func:`rotation_blur` of ``source`` best matches ``target``."""
    rotvecs = start.clone().requires_grad_(True)
    H, W = source.shape[-2:]

    def loss() -> Tensor:
        d = rotation_blur(source, K, rotvecs) - target
        return (d[..., margin : H - margin, margin : W - margin] ** 2).mean()

    _minimise([rotvecs], loss, iters)
    return rotvecs.detach()


def fit_moving_path(source: Tensor, target: Tensor, K: Tensor, rotvecs: Tensor, depth: Tensor, margin: int,
                    iters: int = 40) -> Tuple[Tensor, Tensor]:  # fmt: skip
    """Rotations and translations [T, 3] each (from ``rotvecs`` and no translation) whose :func:`depth_blur` of
    ``source`` best matches ``target``."""
    rot = rotvecs.clone().requires_grad_(True)
    move = torch.zeros_like(rotvecs).requires_grad_(True)
    H, W = source.shape[-2:]

    def loss() -> Tensor:
        d = depth_blur(source, K, rot, move, depth) - target
        return (d[..., margin : H - margin, margin : W - margin] ** 2).mean()

    _minimise([rot, move], loss, iters)
    return rot.detach(), move.detach()


def _minimise(params: List[Tensor], loss, iters: int) -> None:
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=iters, history_size=20, line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        opt.zero_grad()
        value = loss()
        value.backward()
        return value

    opt.step(closure)


def view_fits(sharp: Tensor, photo: Tensor, K: Tensor, record: Dict, depth: Tensor, kernel_size: int,
              path_samples: int, models: Tuple[str, ...] = MODELS) -> Dict[str, float]:  # fmt: skip
    """PSNR of each of ``models`` (columns of :data:`MODELS`) for one view: ``sharp`` and ``photo`` [1, 3, H, W]
    sRGB, ``K`` [3, 3], ``record`` the view's motion record (camera-to-reference ``rotvecs`` / ``translations``),
    ``depth`` [H, W]."""
    margin = int(np.ceil(float(record.get("max_displacement_px", record["blur_px"])))) + 2
    src, tgt = rgb_to_linear_rgb(sharp), rgb_to_linear_rgb(photo)
    rotvecs = -torch.tensor(record["rotvecs"], dtype=sharp.dtype)  # camera-to-reference -> the view's rotation
    translations = torch.tensor(record.get("translations") or np.zeros_like(record["rotvecs"]), dtype=sharp.dtype)

    def shown(linear: Tensor) -> Tensor:
        return linear_rgb_to_rgb(linear.clamp_min(0.0)).clamp(0.0, 1.0)

    cache: Dict[str, Tensor] = {}

    def along_path() -> Tensor:  # the fitted rotation path's blur, shared by three columns
        if "path" not in cache:
            pick = torch.linspace(0, rotvecs.shape[0] - 1, path_samples).round().long()
            cache["rotvecs"] = fit_rotation_path(src, tgt, K, rotvecs[pick], margin)
            cache["path"] = rotation_blur(src, K, cache["rotvecs"])
        return cache["path"]

    def moving_path() -> Tensor:
        along_path()
        return depth_blur(src, K, *fit_moving_path(src, tgt, K, cache["rotvecs"], depth, margin), depth)

    def sampled_true_path() -> Tensor:
        if "sampled" not in cache:
            pick = midpoint_samples(rotvecs.shape[0], path_samples)
            cache["sampled"] = apply_camera_shake_occluding(src, K, rotvecs[pick], translations[pick], depth, False)
        return cache["sampled"]

    blurred = {
        "none": lambda: src,
        "kernel": lambda: fit_kernel(src, tgt, kernel_size, margin),
        "rotation": lambda: rotation_blur(src, K, rotvecs),
        "path": along_path,
        "path + kernel": lambda: fit_kernel(along_path(), tgt, kernel_size, margin),
        "moving path": moving_path,
        "6-DoF": lambda: depth_blur(src, K, rotvecs, translations, depth),
        "6-DoF occluding": lambda: apply_camera_shake_occluding(src, K, rotvecs, translations, depth, False),
        "sampled 6-DoF occluding": sampled_true_path,
        "sampled 6-DoF occluding + kernel": lambda: fit_kernel(sampled_true_path(), tgt, kernel_size, margin),
    }
    return {m: psnr(shown(blurred[m]()), photo, margin) for m in models}


def scene_intrinsics(scene: Path, dtype: torch.dtype = torch.float32) -> Tensor:
    """A generated scene's pinhole intrinsics [3, 3] (its ``scene.json``; principal point in the pixel-edge
    convention)."""
    intrinsics = json.loads((scene / "scene.json").read_text())["intrinsics"]
    return torch.tensor([[intrinsics["fx"], 0.0, intrinsics["cx"]], [0.0, intrinsics["fy"], intrinsics["cy"]],
                         [0.0, 0.0, 1.0]], dtype=dtype)  # fmt: skip


def _image(path: Path) -> Tensor:
    return torch.from_numpy(read_image_float(path)).permute(2, 0, 1)[None]


@dataclass
class ShakeFit:
    data: Path
    """Generated shaken scene (degradation.json with the true paths, depth/, images/)."""
    sharp: Path
    """The same scene rendered sharp (its images/ hold every view)."""
    views: int = 0
    """Shaken training views to fit (0: all)."""
    models: Tuple[str, ...] = MODELS
    """Models to evaluate (a subset of the columns; the fitted ones take minutes per view)."""
    kernel_size: int = 33
    """Side of the fitted kernels in pixels (gsmsdr-cpu's full-resolution size)."""
    path_samples: int = 9
    """Time samples of the fitted paths and of the sampled true path (the camera_shake model's default)."""

    def main(self) -> None:
        torch.set_num_threads(1)
        K = scene_intrinsics(self.data)
        records = json.loads((self.data / "degradation.json").read_text())["images"]
        names = [n for n, r in sorted(records.items()) if r["split"] == "train" and "motion" in r.get("effects", {})]
        if not names:
            raise SystemExit(f"{self.data}: no shaken training view with a motion record in degradation.json")
        names = names[: self.views] if self.views > 0 else names
        print(f"{self.data} against {self.sharp}: {len(names)} views, {self.kernel_size} px kernels, "
              f"{self.path_samples}-sample paths; PSNR (dB) of each model's best fit to the shaken photo")  # fmt: skip
        unknown = sorted(set(self.models) - set(MODELS))
        if unknown:
            raise SystemExit(f"--models: unknown {unknown}; choose from {list(MODELS)}")
        print("| view | blur px | " + " | ".join(self.models) + " |")
        print("| --- | ---: | " + " | ".join("---:" for _ in self.models) + " |")
        rows = []
        for name in names:
            record = records[name]["effects"]["motion"]
            depth = torch.from_numpy(np.load(self.data / "depth" / f"{Path(name).stem}.npy").astype(np.float32))
            fits = view_fits(_image(self.sharp / "images" / name), _image(self.data / "images" / name), K, record,
                             depth, self.kernel_size, self.path_samples, self.models)  # fmt: skip
            rows.append(fits)
            cells = " | ".join(f"{fits[m]:.2f}" for m in self.models)
            print(f"| {name} | {record['blur_px']:.1f} | {cells} |", flush=True)
        means = " | ".join(f"{np.mean([r[m] for r in rows]):.2f}" for m in self.models)
        print(f"| mean | | {means} |")


def entrypoint(argv=None) -> None:
    tyro.cli(ShakeFit, args=argv).main()


if __name__ == "__main__":
    entrypoint()
