"""`gsmsdr-bench raster`: CPU rasterizer forward+backward time against the dense all-pairs baseline.

The Gaussians are placed like a trained scene (on surfaces, flattened along the normal, sized by the distance to
their nearest neighbours) rather than as uniform noise, because tile occupancy, not the Gaussian count, decides
the cost.
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass
from typing import Callable, Dict, List, Tuple

import numpy as np
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from gsmsdr_ns.bench.dense import rasterize_dense
from gsmsdr_ns.render.projection import covariance_3d, project_gaussians
from gsmsdr_ns.render.rasterization import rasterization, resolve_cpu_backend
from gsmsdr_ns.render.sh import eval_sh_colors


@dataclass
class SurfaceScene:
    """Gaussians and one camera; tensors are float32 leaves that require grad."""

    means: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4]
    scales: torch.Tensor  # [N, 3]
    opacities: torch.Tensor  # [N]
    sh: torch.Tensor  # [N, 16, 3]
    viewmat: torch.Tensor  # [1, 4, 4]
    K: torch.Tensor  # [1, 3, 3]
    width: int
    height: int

    def leaves(self) -> List[torch.Tensor]:
        return [self.means, self.quats, self.scales, self.opacities, self.sh]


def _sample_surfaces(n: int, rng: np.random.Generator) -> Tuple[np.ndarray, np.ndarray]:
    """Points and unit normals on a floor, a back wall and three spheres, by area."""
    spheres = [((-0.8, 0.55, 0.4), 0.45), ((0.7, 0.65, 0.1), 0.35), ((0.0, 0.4, 1.2), 0.6)]
    areas = np.array([4.0 * 4.0, 4.0 * 2.5] + [4 * math.pi * r * r for _, r in spheres])
    which = rng.choice(len(areas), size=n, p=areas / areas.sum())
    pts, nrm = np.zeros((n, 3)), np.zeros((n, 3))
    k = which == 0  # floor y = 1 (y points down in this scene)
    pts[k] = np.stack([rng.uniform(-2, 2, k.sum()), np.ones(k.sum()), rng.uniform(-1.5, 2.5, k.sum())], -1)
    nrm[k] = (0, -1, 0)
    k = which == 1  # back wall z = 2.5
    pts[k] = np.stack([rng.uniform(-2, 2, k.sum()), rng.uniform(-1.5, 1, k.sum()), np.full(k.sum(), 2.5)], -1)
    nrm[k] = (0, 0, -1)
    for i, (centre, radius) in enumerate(spheres):
        k = which == i + 2
        d = rng.normal(size=(k.sum(), 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        pts[k], nrm[k] = np.asarray(centre) + radius * d, d
    return pts, nrm


def make_surface_scene(n: int, width: int = 240, height: int = 135, seed: int = 0) -> SurfaceScene:
    """A trained-looking scene of n Gaussians seen by one pinhole camera at (0, 0, -3) looking along +z."""
    rng = np.random.default_rng(seed)
    pts, nrm = _sample_surfaces(n, rng)
    knn, _ = cKDTree(pts).query(pts, k=4)
    size = knn[:, 1:].mean(axis=1)
    # local z axis along the surface normal, so the Gaussian is a disc lying on the surface
    tangent = np.cross(nrm, rng.normal(size=(n, 3)))
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    rot = np.stack([tangent, np.cross(nrm, tangent), nrm], axis=-1)
    quats = Rotation.from_matrix(rot).as_quat()[:, [3, 0, 1, 2]]
    scales = np.stack([size, size * rng.uniform(0.5, 1.0, n), 0.1 * size], -1)
    sh = np.zeros((n, 16, 3))
    sh[:, 0] = rng.uniform(-1.5, 1.5, (n, 3))
    sh[:, 1:] = rng.normal(scale=0.05, size=(n, 15, 3))
    f = 0.8 * width
    to_t = lambda a: torch.tensor(a, dtype=torch.float32).requires_grad_(True)  # noqa: E731
    viewmat = torch.eye(4)
    viewmat[2, 3] = 3.0
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    return SurfaceScene(
        to_t(pts), to_t(quats), to_t(scales), to_t(rng.uniform(0.3, 1.0, n)), to_t(sh), viewmat[None], K[None],
        width, height,
    )  # fmt: skip


def _render_tiled(scene: SurfaceScene, backend: str) -> torch.Tensor:
    img, alpha, meta = rasterization(
        scene.means, scene.quats, scene.scales, scene.opacities, scene.sh, scene.viewmat, scene.K, scene.width,
        scene.height, sh_degree=3, packed=False, absgrad=True, cpu_backend=backend,
    )  # fmt: skip
    return torch.cat([img, alpha], -1)


def _render_dense(scene: SurfaceScene) -> torch.Tensor:
    proj = project_gaussians(
        scene.means, covariance_3d(scene.quats, scene.scales), scene.viewmat, scene.K, scene.width, scene.height
    )
    dirs = scene.means - torch.linalg.inv(scene.viewmat)[0, :3, 3]
    colors = torch.clamp_min(eval_sh_colors(3, dirs, scene.sh) + 0.5, 0.0)
    img, alpha = rasterize_dense(
        proj.means2d[0], proj.conics[0], colors, scene.opacities, proj.depths[0], proj.radii[0], scene.width,
        scene.height,
    )  # fmt: skip
    return torch.cat([img, alpha], -1)


def time_forward_backward(render: Callable[[], torch.Tensor], leaves, repeats: int) -> Tuple[float, float]:
    """Median forward and backward seconds over `repeats` runs after one warm-up run."""
    fwd, bwd = [], []
    for i in range(repeats + 1):
        for p in leaves:
            p.grad = None
        t0 = time.perf_counter()
        out = render()
        t1 = time.perf_counter()
        out.sum().backward()
        t2 = time.perf_counter()
        if i > 0:
            fwd.append(t1 - t0)
            bwd.append(t2 - t1)
    return statistics.median(fwd), statistics.median(bwd)


def run_raster_benchmark(
    sizes=(5000, 20000, 80000), paths=("cpp", "torch", "dense"), repeats: int = 3, dense_max: int = 20000
) -> List[Dict]:
    """Time every path at every size; one row per (size, path)."""
    rows = []
    for n in sizes:
        scene = make_surface_scene(n)
        with torch.no_grad():
            _, _, meta = rasterization(scene.means, scene.quats, scene.scales, scene.opacities, scene.sh,
                                       scene.viewmat, scene.K, scene.width, scene.height, sh_degree=3,
                                       packed=False, cpu_backend="torch")  # fmt: skip
        isects = int(meta["flatten_ids"].numel())
        for path in paths:
            if path == "dense" and n > dense_max:
                rows.append(dict(gaussians=n, path=path, forward_s=None, backward_s=None, intersections=isects))
                continue
            if path == "cpp" and resolve_cpu_backend("auto") != "cpp":
                rows.append(dict(gaussians=n, path=path, forward_s=None, backward_s=None, intersections=isects))
                continue
            render = (lambda: _render_dense(scene)) if path == "dense" else (lambda p=path: _render_tiled(scene, p))
            f, b = time_forward_backward(render, scene.leaves(), repeats if path != "dense" else 1)
            rows.append(dict(gaussians=n, path=path, forward_s=f, backward_s=b, intersections=isects))
    dense = {r["gaussians"]: r for r in rows if r["path"] == "dense" and r["forward_s"] is not None}
    for r in rows:
        d = dense.get(r["gaussians"])
        ok = d is not None and r["forward_s"] is not None
        r["speedup_vs_dense"] = (d["forward_s"] + d["backward_s"]) / (r["forward_s"] + r["backward_s"]) if ok else None
    return rows


def format_table(rows: List[Dict], width: int = 240, height: int = 135) -> str:
    def ms(x):
        return "n/a" if x is None else f"{1000 * x:.1f}"

    lines = [
        f"CPU rasterizer, {width}x{height}, SH degree 3, forward+backward (median), torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads",
        "| gaussians | path | intersections | forward ms | backward ms | total ms | speed-up vs dense |",
        "|---:|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        total = None if r["forward_s"] is None else r["forward_s"] + r["backward_s"]
        speed = "n/a" if r["speedup_vs_dense"] is None else f"{r['speedup_vs_dense']:.1f}x"
        lines.append(
            f"| {r['gaussians']} | {r['path']} | {r['intersections']} | {ms(r['forward_s'])} | "
            f"{ms(r['backward_s'])} | {ms(total)} | {speed} |"
        )
    return "\n".join(lines)
