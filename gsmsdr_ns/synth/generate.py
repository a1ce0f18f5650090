"""Write a complete synthetic capture (images, depth, COLMAP model, scene.json) atomically.

Layout (Mip-NeRF 360 / COLMAP style, for nerfstudio's `colmap` dataparser with colmap_path=sparse/0):
    <out>/images/<prefix>00000.png   8-bit RGB, names sort in capture order
    <out>/depth/<prefix>00000.npy    float32 [H, W] z-depth at pixel centres (world units)
    <out>/sparse/0/{cameras,images,points3D}.bin (+ rigs.bin, frames.bin from pycolmap 4)
    <out>/scene.json                 generator config, seed and conventions
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..io.atomic import atomic_dir
from ..io.colmap import write_colmap_model
from ..io.errors import require_free_space
from ..io.images import write_image
from .cameras import intrinsics, orbit_cameras, world_to_camera
from .config import SynthSceneConfig
from .points import sample_sparse_points
from .raycast import render_view
from .scene import WORLD_UP, build_scene, seed_streams

FORMAT_VERSION = 1


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """[H, W, 3] float in [0, 1] -> uint8 with round-to-nearest."""
    return np.clip(np.round(rgb.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)


def image_names(cfg: SynthSceneConfig) -> list[str]:
    """Zero-padded names so lexical order == capture order."""
    return [f"{cfg.image_prefix}{i:05d}.png" for i in range(cfg.num_views)]


def _check_target(out: Path, overwrite: bool) -> None:
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise FileExistsError(f"{out} exists and is not a directory")
        if any(out.iterdir()) and not overwrite:
            raise FileExistsError(
                f"{out} exists and is not empty; pass overwrite=True (CLI: --overwrite) to replace it"
            )


# Public name for other writers of scene directories (gsmsdr_ns.degrade) that refuse the same targets.
check_target = _check_target


def _write_all(root: Path, cfg: SynthSceneConfig, log: Callable[[str], None]) -> dict:
    """Render and write everything under root (a fresh directory). Returns summary stats."""
    t0 = time.perf_counter()
    scene = build_scene(cfg)
    c2ws = orbit_cameras(cfg)
    K = intrinsics(cfg.width, cfg.height, cfg.fov_deg)
    names = image_names(cfg)
    (root / "images").mkdir()
    (root / "depth").mkdir()
    for i, name in enumerate(names):
        rgb, depth = render_view(scene, c2ws[i], K, cfg.width, cfg.height, cfg.supersample)
        write_image(root / "images" / name, to_uint8(rgb))
        np.save(root / "depth" / (Path(name).stem + ".npy"), depth)
        log(f"rendered {i + 1}/{len(names)} {name}")
    Ks = np.repeat(K[None], cfg.num_views, axis=0)
    points = sample_sparse_points(
        scene, c2ws, Ks, cfg.width, cfg.height, cfg.num_points, seed_streams(cfg.seed)[2], cfg.min_track_length
    )
    rec = write_colmap_model(
        root / "sparse" / "0", names, Ks, [(cfg.width, cfg.height)] * cfg.num_views, world_to_camera(c2ws), points
    )
    stats = {
        "num_images": cfg.num_views,
        "num_points3D": int(points.xyz.shape[0]),
        "mean_track_length": float(rec.compute_mean_track_length()) if points.xyz.shape[0] else 0.0,
        "render_seconds": round(time.perf_counter() - t0, 3),  # informative only; not part of the content hash
    }
    meta = {
        "generator": "gsmsdr_ns.synth",
        "format_version": FORMAT_VERSION,
        "seed": cfg.seed,
        "config": dataclasses.asdict(cfg),
        "conventions": {
            "world_up": WORLD_UP.tolist(),
            "poses": "COLMAP cam_from_world in sparse/0; camera x right, y down, z forward",
            "pixel_centers": "COLMAP: top-left pixel centre at (0.5, 0.5)",
            "depth": "depth/<image stem>.npy float32 [H, W], z-depth along the camera axis at pixel centres",
        },
        "camera_model": "PINHOLE",
        "intrinsics": {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]},
        "num_images": stats["num_images"],
        "num_points3D": stats["num_points3D"],
    }
    with open(root / "scene.json", "w", encoding="utf8") as f:
        json.dump(meta, f, indent=2, sort_keys=True)
        f.write("\n")
    return stats


def generate_scene(
    out_dir: str | Path,
    config: SynthSceneConfig | None = None,
    overwrite: bool = False,
    log: Callable[[str], None] | None = None,
) -> Path:
    """Generate the scene for `config` into out_dir and return its path.

    Everything is written into a hidden temp directory next to out_dir and renamed into place at the end,
    so a failed or interrupted run never leaves a half-written out_dir. An existing non-empty out_dir is
    refused (FileExistsError) unless overwrite=True.
    """
    cfg = config if config is not None else SynthSceneConfig()
    out = Path(out_dir).absolute()
    _check_target(out, overwrite)
    # at most the raw pixels (PNG compresses them) and the float32 depth maps of every view, plus the model files
    pixels = cfg.width * cfg.height * cfg.num_views
    require_free_space(
        out.parent, 7 * pixels + 2**20, "gsmsdr-synth", "Free some space, or choose --out on a disk with room."
    )
    with atomic_dir(out) as tmp:
        _write_all(tmp, cfg, log or (lambda _msg: None))
        _check_target(out, overwrite)  # re-check: something may have appeared while we rendered
    return out
