"""Smooth random camera-shake trajectories over one exposure, and their pixel paths.

A trajectory is sampled at T equally spaced times t in (0, 1) (sample midpoints) and holds, per sample, the pose
of the camera at time t in the REFERENCE camera's frame (camera-to-reference): rotation vector rotvecs [T, 3]
(axis * angle, radians) and translation [T, 3] (scene units). The reference pose is the pose at mid-exposure,
t = 0.5, which is the pose written to the COLMAP model (the path passes through it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from torch import Tensor

from .kernels import path_extent


@dataclass
class ShakeTrajectory:
    """Camera poses during one exposure, relative to the reference (mid-exposure) camera."""

    times: np.ndarray  # [T] sample times in (0, 1)
    rotvecs: np.ndarray  # [T, 3] camera-to-reference rotation vectors (radians)
    translations: np.ndarray  # [T, 3] camera-to-reference translations (scene units)

    def rotations(self) -> Tensor:
        """Camera-to-reference rotation matrices [T, 3, 3] (float64)."""
        return rotvec_to_matrix(self.rotvecs)

    def reference_to_camera(self) -> tuple[Tensor, Tensor]:
        """(R [T, 3, 3], t [T, 3]) with X_t = R X_ref + t: the inverse of each camera-to-reference pose."""
        Rc = self.rotations()
        R = Rc.transpose(-1, -2)
        t = -(R @ torch.as_tensor(self.translations, dtype=torch.float64)[..., None])[..., 0]
        return R, t

    def to_json(self, digits: int = 8) -> dict:
        r = lambda a: np.round(np.asarray(a, dtype=np.float64), digits).tolist()  # noqa: E731
        return {"times": r(self.times), "rotvecs": r(self.rotvecs), "translations": r(self.translations)}


def rotvec_to_matrix(rotvecs: np.ndarray | Tensor) -> Tensor:
    """Rotation vectors [..., 3] -> rotation matrices [..., 3, 3] (float64, kornia's Rodrigues)."""
    v = torch.as_tensor(np.asarray(rotvecs), dtype=torch.float64)
    shape = v.shape[:-1]
    return axis_angle_to_rotation_matrix(v.reshape(-1, 3)).reshape(*shape, 3, 3)


def sample_times(num_samples: int) -> np.ndarray:
    """Midpoints of num_samples equal time bins of the exposure [0, 1] -> [T]."""
    return (np.arange(num_samples) + 0.5) / num_samples


def smooth_path(rng: np.random.Generator, times: np.ndarray, dims: int = 3, curvature: float = 0.5) -> np.ndarray:
    """Random smooth path through 0 at t = 0.5, unit-ish amplitude -> [T, dims].

    A blend of a straight line (P0 -> P3) and a cubic Bezier curve (P0, P1, P2, P3), control points ~ N(0, I);
    curvature 0 is the line, 1 the Bezier. The value at mid-exposure is subtracted.
    """
    P = rng.normal(size=(4, dims))

    def curve(t: np.ndarray) -> np.ndarray:
        t = t[:, None]
        line = (1 - t) * P[0] + t * P[3]
        bez = (1 - t) ** 3 * P[0] + 3 * (1 - t) ** 2 * t * P[1] + 3 * (1 - t) * t**2 * P[2] + t**3 * P[3]
        return (1 - curvature) * line + curvature * bez

    path = curve(np.asarray(times, dtype=np.float64)) - curve(np.array([0.5]))
    scale = np.abs(path).max()
    return path / scale if scale > 0 else path


def pixel_paths(
    K: np.ndarray,  # [3, 3]
    traj: ShakeTrajectory,
    uv: np.ndarray,  # [N, 2]
    inv_depth: np.ndarray,  # [N]
) -> Tensor:
    """Pixel positions over time of N scene points seen at uv (COLMAP pixels) with inverse depth in the reference.

    x_t ~ K (R_t X_ref + t_t) with X_ref = ray(uv) / inv_depth, written as K (R_t ray + inv_depth t_t) so points at
    infinity (inv_depth 0) work. -> [T, N, 2]
    """
    Kt = torch.as_tensor(K, dtype=torch.float64)
    uv1 = torch.cat([torch.as_tensor(uv, dtype=torch.float64), torch.ones(len(uv), 1, dtype=torch.float64)], 1)
    ray = uv1 @ torch.linalg.inv(Kt).T  # [N, 3], z = 1
    R, t = traj.reference_to_camera()
    rho = torch.as_tensor(inv_depth, dtype=torch.float64)
    X = torch.einsum("tij,nj->tni", R, ray) + rho[None, :, None] * t[:, None, :]
    x = X @ Kt.T
    return x[..., :2] / x[..., 2:3]


def probe_points(width: int, height: int, n: int = 7) -> np.ndarray:
    """n x n grid of pixel positions spanning the image (corner pixels included) -> [n*n, 2] COLMAP pixels."""
    xs = np.linspace(0.5, width - 0.5, n)
    ys = np.linspace(0.5, height - 0.5, n)
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], -1)


def border_points(width: int, height: int, per_edge: int = 33) -> np.ndarray:
    """``per_edge`` pixel centres along each of the four image borders (corners included) -> [4 * per_edge, 2]
    COLMAP pixels."""
    xs = np.linspace(0.5, width - 0.5, per_edge)
    ys = np.linspace(0.5, height - 0.5, per_edge)
    top, bottom = np.stack([xs, np.full_like(xs, 0.5)], -1), np.stack([xs, np.full_like(xs, height - 0.5)], -1)
    left, right = np.stack([np.full_like(ys, 0.5), ys], -1), np.stack([np.full_like(ys, width - 0.5), ys], -1)
    return np.concatenate([top, bottom, left, right])


def border_reach_px(K: np.ndarray, traj: ShakeTrajectory, width: int, height: int) -> float:
    """How far the reference view's border pixels move over the shake (distant scene: rotation only): the width
    of the band along the border whose blurred pixels read from outside the photo. K: [3, 3]."""
    uv = border_points(width, height)
    paths = pixel_paths(K, traj, uv, np.zeros(len(uv)))  # [T, N, 2]
    return float((paths - torch.as_tensor(uv, dtype=paths.dtype)).norm(dim=-1).max())


def calibrated_shake(
    rng: np.random.Generator,
    K: np.ndarray,
    width: int,
    height: int,
    extent_px: float,
    num_samples: int,
    curvature: float,
    roll_fraction: float,
    translation_fraction: float = 0.0,
    depth: np.ndarray | None = None,
) -> tuple[ShakeTrajectory, float]:
    """Random smooth 6-DoF shake scaled so that the view's blur extent (`path_extent` max over a probe grid) is
    extent_px. translation_fraction > 0 needs `depth` [H, W] (z-depth of the reference view): the translation
    is sized so that it alone would cause that share of the blur at the median depth.
    -> (trajectory, measured extent in pixels).
    """
    times = sample_times(num_samples)
    rot_shape = smooth_path(rng, times, 3, curvature) * np.array([1.0, 1.0, roll_fraction])
    trans_shape = smooth_path(rng, times, 3, curvature) * np.array([1.0, 1.0, 0.5])
    uv = probe_points(width, height)
    if depth is not None:
        cols = np.clip(uv[:, 0].astype(int), 0, width - 1)
        rows = np.clip(uv[:, 1].astype(int), 0, height - 1)
        inv_depth = 1.0 / depth[rows, cols].astype(np.float64)
        finite = np.isfinite(depth) & (depth > 0)
        med_inv = 1.0 / float(np.median(depth[finite])) if finite.any() else 0.0
    else:
        inv_depth, med_inv = np.zeros(len(uv)), 0.0
    if translation_fraction > 0 and med_inv <= 0:
        raise ValueError("a shake with translation needs a depth map with finite depths")

    def extent(a: float, b: float, probe_uv: np.ndarray = uv, probe_rho: np.ndarray = inv_depth) -> float:
        traj = ShakeTrajectory(times, a * rot_shape, b * trans_shape)
        return float(path_extent(pixel_paths(K, traj, probe_uv, probe_rho)).max())

    if extent_px <= 0:
        return ShakeTrajectory(times, 0 * rot_shape, 0 * trans_shape), 0.0
    probe = 1e-3
    f = float(K[0, 0])
    a = (1 - translation_fraction) * extent_px / max(extent(probe / f, 0.0) / (probe / f), 1e-12)
    b = 0.0
    if translation_fraction > 0:
        centre = np.array([[0.5 * width, 0.5 * height]])
        unit = extent(0.0, probe, centre, np.array([med_inv])) / probe
        b = translation_fraction * extent_px / max(unit, 1e-12)
    for _ in range(3):  # the extent is nearly linear in the amplitude: a few fixed-point steps
        e = extent(a, b)
        if e <= 0:
            break
        a, b = a * extent_px / e, b * extent_px / e
    traj = ShakeTrajectory(times, a * rot_shape, b * trans_shape)
    return traj, extent(a, b)
