"""Sparse 'SfM' point cloud: exact surface points with true colours and exact, occlusion-checked tracks."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cameras import project, world_to_camera
from .raycast import cast, pixel_rays, shade, surface_attributes
from .scene import Scene

VIS_REL_TOL = 1e-5  # a camera sees X if the first hit along C -> X is X itself (t = 1 up to this tolerance)
MIN_COS_VIEW = 0.08  # drop grazing observations (> ~85 deg from the normal): not matchable in practice
BORDER_PX = 0.5  # keep observations at least half a pixel inside the image


@dataclass
class SparsePoints:
    """Point cloud with flattened observations (one row per (point, image) pair)."""

    xyz: np.ndarray  # [P, 3] float64 world positions
    rgb: np.ndarray  # [P, 3] uint8 shaded colour (what a photo shows)
    obs_point: np.ndarray  # [O] int64 index into xyz
    obs_view: np.ndarray  # [O] int64 view index (0-based, capture order)
    obs_uv: np.ndarray  # [O, 2] float64 exact COLMAP pixel coordinates


def visibility(
    scene: Scene, xyz: np.ndarray, normals: np.ndarray, c2w: np.ndarray, K: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Which points one camera sees. xyz, normals: [N, 3]; c2w: [4, 4] -> (visible [N] bool, uv [N, 2])."""
    uv, z = project(xyz, world_to_camera(c2w), K)
    inside = (
        (z > 1e-6)
        & (uv[:, 0] >= BORDER_PX)
        & (uv[:, 0] <= width - BORDER_PX)
        & (uv[:, 1] >= BORDER_PX)
        & (uv[:, 1] <= height - BORDER_PX)
    )
    to_cam = c2w[:3, 3] - xyz
    dist = np.linalg.norm(to_cam, axis=-1)
    facing = np.einsum("ij,ij->i", normals, to_cam) > MIN_COS_VIEW * dist
    vis = inside & facing
    cand = np.flatnonzero(vis)
    if cand.size:
        o = np.broadcast_to(c2w[:3, 3], (cand.size, 3))
        t, _ = cast(scene, o, xyz[cand] - o)  # direction C -> X, so X itself sits at t = 1
        vis[cand] = t >= 1.0 - VIS_REL_TOL
    return vis, uv


def sample_sparse_points(
    scene: Scene,
    c2ws: np.ndarray,
    Ks: np.ndarray,
    width: int,
    height: int,
    num_points: int,
    rng: np.random.Generator,
    min_track_length: int = 2,
) -> SparsePoints:
    """Sample `num_points` surface points seen by >= min_track_length views.

    Points are where random rays of random views hit the scene (so density follows image coverage, like
    SfM); colour is the view-independent shaded radiance. c2ws: [V, 4, 4]; Ks: [V, 3, 3].
    """
    V = c2ws.shape[0]
    xyz_l, rgb_l, vis_l, uv_l = [np.zeros((0, 3))], [np.zeros((0, 3))], [np.zeros((0, V), bool)], [np.zeros((0, V, 2))]
    have = 0
    for _round in range(20):  # a few rounds of oversampling; almost every candidate survives
        if have >= num_points:
            break
        m = max(int(1.3 * (num_points - have)) + 16, 64)
        view = rng.integers(V, size=m)
        px = rng.uniform(0, width, size=m)
        py = rng.uniform(0, height, size=m)
        o = np.empty((m, 3))
        d = np.empty((m, 3))
        for v in np.unique(view):
            sel = view == v
            o[sel], d[sel] = pixel_rays(c2ws[v], Ks[v], px[sel], py[sel])
        t, idx = cast(scene, o, d)
        ok = idx >= 0
        p = o[ok] + t[ok, None] * d[ok]
        idx = idx[ok]
        normals, _ = surface_attributes(scene, p, idx)
        vis = np.zeros((p.shape[0], V), dtype=bool)
        uv = np.zeros((p.shape[0], V, 2))
        for v in range(V):
            vis[:, v], uv[:, v] = visibility(scene, p, normals, c2ws[v], Ks[v], width, height)
        keep = vis.sum(axis=1) >= min_track_length
        keep &= np.cumsum(keep) <= num_points - have
        xyz_l.append(p[keep])
        rgb_l.append(shade(scene, p[keep], idx[keep]))
        vis_l.append(vis[keep])
        uv_l.append(uv[keep])
        have += int(keep.sum())
    xyz = np.concatenate(xyz_l)
    vis = np.concatenate(vis_l)
    uv = np.concatenate(uv_l)
    rgb = np.clip(np.round(np.concatenate(rgb_l) * 255.0), 0, 255).astype(np.uint8)
    obs_point, obs_view = np.nonzero(vis)  # row-major: grouped by point, views ascending
    return SparsePoints(xyz=xyz, rgb=rgb, obs_point=obs_point, obs_view=obs_view, obs_uv=uv[obs_point, obs_view])
