"""CPU ray caster: nearest-hit queries, Lambertian shading and the pure `render_view` used by every variant."""

from __future__ import annotations

import numpy as np

from .geometry import T_EPS
from .scene import Scene
from .textures import eval_texture

# Rays per chunk: bounds memory for large renders (~40 float64 arrays of [chunk, 3] live at once).
CHUNK_RAYS = 1 << 17
SHADOW_OFFSET = 1e-5  # push shadow-ray origins off the surface to avoid self-shadowing acne


def cast(
    scene: Scene, o: np.ndarray, d: np.ndarray, shadow_casters_only: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of rays o + t d. o, d: [N, 3] -> (t [N] (inf on miss), primitive index [N] (-1 on miss))."""
    n = o.shape[0]
    t_best = np.full(n, np.inf)
    idx = np.full(n, -1, dtype=np.int64)
    prims = [(i, p) for i, p in enumerate(scene.primitives) if p.casts_shadow or not shadow_casters_only]
    planes = [(i, p) for i, p in prims if p.bounding_radius is None]
    if planes:
        # All (one-sided) planes in one [N, P] pass: the room faces are hit-tested by every ray.
        normals = np.stack([p.normal for _, p in planes], axis=1)  # [3, P]
        offsets = np.array([p.point @ p.normal for _, p in planes])  # [P]
        denom = d @ normals
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (offsets[None] - o @ normals) / denom
        t = np.where((denom < -1e-12) & (t > T_EPS), t, np.inf)
        k = np.argmin(t, axis=1)
        t_best = t[np.arange(n), k]
        idx = np.where(np.isfinite(t_best), np.array([i for i, _ in planes])[k], -1)
    bounded = [(i, p) for i, p in prims if p.bounding_radius is not None]
    if bounded:
        # Bounding-sphere cull: objects cover a small part of the image, exact tests only where needed.
        # |C - o|^2 and (C - o).d expanded so each object costs two mat-vecs instead of [N, 3] temporaries.
        dd = np.einsum("ij,ij->i", d, d)
        od = np.einsum("ij,ij->i", o, d)
        oo = np.einsum("ij,ij->i", o, o)
        for i, prim in bounded:
            c = prim.center
            b = d @ c - od
            cc = oo - 2.0 * (o @ c) + c @ c
            r2 = (prim.bounding_radius * (1.0 + 1e-9)) ** 2  # a hair conservative against round-off
            cand = np.flatnonzero((cc * dd - b * b <= r2 * dd) & ((b > 0) | (cc <= r2)))
            if cand.size == 0:
                continue
            t = prim.intersect(o[cand], d[cand])
            closer = t < t_best[cand]
            t_best[cand[closer]] = t[closer]
            idx[cand[closer]] = i
    return t_best, idx


def surface_attributes(scene: Scene, p: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normals and albedo at hit points p [N, 3] of primitives idx [N] -> (normal [N, 3], albedo [N, 3])."""
    normal = np.zeros_like(p)
    albedo = np.zeros_like(p)
    present = np.flatnonzero(np.bincount(idx[idx >= 0], minlength=len(scene.primitives)))
    for i in present:  # bincount, not np.unique: avoids sorting every ray index
        m = idx == i
        prim = scene.primitives[int(i)]
        n, uv = prim.surface(p[m])
        normal[m] = n
        albedo[m] = eval_texture(prim.texture, uv)
    return normal, albedo


def shade(scene: Scene, p: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """View-independent Lambertian radiance at hit points (so every view sees the same colour). -> [N, 3]."""
    normal, albedo = surface_attributes(scene, p, idx)
    ndotl = np.clip(normal @ scene.light_dir, 0.0, None)
    if scene.shadows:
        lit = ndotl > 0
        if np.any(lit):
            o = p[lit] + SHADOW_OFFSET * normal[lit]
            d = np.broadcast_to(scene.light_dir, o.shape)
            t, _ = cast(scene, o, d, shadow_casters_only=True)
            ndotl[np.flatnonzero(lit)[np.isfinite(t)]] = 0.0
    return np.clip(albedo * (scene.ambient + (1.0 - scene.ambient) * ndotl)[:, None], 0.0, 1.0)


def pixel_rays(c2w: np.ndarray, K: np.ndarray, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays through COLMAP pixel coordinates (top-left pixel centre = (0.5, 0.5)).

    c2w: [4, 4] OpenCV camera-to-world (x right, y down, z forward); K: [3, 3]; px, py: [N].
    Returns origins [N, 3] and directions [N, 3] scaled so their camera-z component is 1 (t = z-depth).
    """
    x = (px - K[0, 2] - K[0, 1] * (py - K[1, 2]) / K[1, 1]) / K[0, 0]
    y = (py - K[1, 2]) / K[1, 1]
    d_cam = np.stack([x, y, np.ones_like(x)], axis=-1)
    d = d_cam @ c2w[:3, :3].T
    o = np.broadcast_to(c2w[:3, 3], d.shape)
    return o, d


def _trace(scene: Scene, o: np.ndarray, d: np.ndarray, want_color: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """Chunked cast (+ shade). -> (t [N], rgb [N, 3] or None)."""
    n = o.shape[0]
    t_all = np.empty(n)
    rgb_all = np.empty((n, 3)) if want_color else None
    for s in range(0, n, CHUNK_RAYS):
        oc, dc = o[s : s + CHUNK_RAYS], d[s : s + CHUNK_RAYS]
        t, idx = cast(scene, oc, dc)
        t_all[s : s + CHUNK_RAYS] = t
        if want_color:
            hit = idx >= 0
            rgb = np.zeros((oc.shape[0], 3))
            rgb[hit] = shade(scene, oc[hit] + t[hit, None] * dc[hit], idx[hit])
            rgb_all[s : s + CHUNK_RAYS] = rgb
    return t_all, rgb_all


def render_view(
    scene: Scene, camera_to_world: np.ndarray, K: np.ndarray, width: int, height: int, supersample: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Render one pinhole view.

    camera_to_world: [4, 4] OpenCV convention; K: [3, 3] in pixels (COLMAP centre convention).
    Returns rgb [H, W, 3] float32 in [0, 1] (box filter over supersample^2 stratified samples) and
    depth [H, W] float32: z-depth along the camera axis at the exact pixel centre (inf where nothing is hit).
    Colour stays float so later variants can average sub-frames before quantising.
    """
    c2w = np.asarray(camera_to_world, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    s = int(supersample)
    offs = (np.arange(s) + 0.5) / s  # stratified sub-pixel grid inside [0, 1)
    jj, ii = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    sy, sx = np.meshgrid(offs, offs, indexing="ij")
    px = (ii[:, :, None] + sx.reshape(-1)[None, None]).reshape(-1)  # [H*W*s*s], sub-samples innermost
    py = (jj[:, :, None] + sy.reshape(-1)[None, None]).reshape(-1)
    o, d = pixel_rays(c2w, K, px, py)
    _, rgb = _trace(scene, o, d, want_color=True)
    rgb = rgb.reshape(height, width, s * s, 3).mean(axis=2)
    # Depth from a separate centre ray: averaging sub-sample depths would invent depths at occlusion edges.
    o, d = pixel_rays(c2w, K, ii.reshape(-1) + 0.5, jj.reshape(-1) + 0.5)
    depth, _ = _trace(scene, o, d, want_color=False)
    return rgb.astype(np.float32), depth.reshape(height, width).astype(np.float32)
