"""Pinhole intrinsics, look-at poses and the jittered orbit of capture cameras (OpenCV / COLMAP conventions)."""

from __future__ import annotations

import numpy as np

from .config import SynthSceneConfig
from .scene import WORLD_UP, seed_streams


def intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    """PINHOLE K for a horizontal field of view, square pixels, principal point at the image centre. -> [3, 3]"""
    f = 0.5 * width / np.tan(0.5 * np.deg2rad(fov_deg))
    return np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = WORLD_UP) -> np.ndarray:
    """OpenCV camera-to-world [4, 4] (x right, y down, z forward towards target), no roll w.r.t. `up`."""
    fwd = target - eye
    fwd = fwd / np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    right = right / np.linalg.norm(right)
    down = np.cross(fwd, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, fwd, eye
    return c2w


def world_to_camera(c2w: np.ndarray) -> np.ndarray:
    """Rigid inverse. c2w: [..., 4, 4] -> w2c [..., 4, 4] (COLMAP cam_from_world)."""
    R = c2w[..., :3, :3]
    t = c2w[..., :3, 3]
    w2c = np.zeros_like(c2w)
    w2c[..., :3, :3] = np.swapaxes(R, -1, -2)
    w2c[..., :3, 3] = -np.einsum("...ji,...j->...i", R, t)
    w2c[..., 3, 3] = 1.0
    return w2c


def project(points: np.ndarray, w2c: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP projection. points: [N, 3]; w2c: [4, 4]; K: [3, 3] -> (uv [N, 2] pixels, z [N] camera depth)."""
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = pc @ K.T
        uv = uvw[:, :2] / uvw[:, 2:3]
    return uv, z


def orbit_cameras(cfg: SynthSceneConfig) -> np.ndarray:
    """Jittered orbit of look-at cameras around the scene centre, ordered by azimuth (capture order).

    Elevation oscillates twice per orbit (plus jitter) so centres span a band of the hemisphere rather
    than one circle. Uses only the 'cameras' random stream. -> c2w [num_views, 4, 4]
    """
    rng = seed_streams(cfg.seed)[1]
    n = cfg.num_views
    base_target = cfg.target_height * WORLD_UP
    phase = rng.uniform(0, 2 * np.pi)
    c2ws = np.empty((n, 4, 4))
    for i in range(n):
        az = phase + 2 * np.pi * i / n + np.deg2rad(rng.uniform(-1, 1) * cfg.azimuth_jitter_deg)
        el_deg = (
            cfg.elevation_deg
            + cfg.elevation_amplitude_deg * np.sin(2 * (az - phase))
            + rng.uniform(-1, 1) * cfg.elevation_jitter_deg
        )
        el = np.deg2rad(np.clip(el_deg, -80.0, 80.0))
        radius = cfg.orbit_radius + rng.uniform(-1, 1) * cfg.radius_jitter
        target = base_target + rng.normal(size=3) * cfg.target_jitter
        offset = (
            radius * np.array([np.cos(el) * np.cos(az), 0.0, np.cos(el) * np.sin(az)]) + radius * np.sin(el) * WORLD_UP
        )
        c2ws[i] = look_at(base_target + offset, target)
    return c2ws
