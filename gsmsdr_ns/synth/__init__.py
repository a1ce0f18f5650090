"""Procedural default scene: textured analytic primitives ray-cast on the CPU from known cameras.

Public API:
    SynthSceneConfig, load_preset          config dataclass / YAML preset
    generate_scene(out_dir, config, overwrite=False) -> Path
    build_scene(config) -> Scene            deterministic scene from config.seed
    orbit_cameras(config) -> [V, 4, 4]      OpenCV camera-to-world poses (capture order)
    intrinsics(width, height, fov_deg) -> [3, 3]
    render_view(scene, c2w, K, width, height, supersample) -> (rgb [H, W, 3], depth [H, W])
"""

from .cameras import intrinsics, look_at, orbit_cameras, project, world_to_camera
from .config import SynthSceneConfig, load_preset
from .generate import generate_scene
from .raycast import render_view
from .scene import WORLD_UP, Scene, build_scene

__all__ = [
    "SynthSceneConfig",
    "load_preset",
    "generate_scene",
    "build_scene",
    "Scene",
    "WORLD_UP",
    "orbit_cameras",
    "intrinsics",
    "look_at",
    "project",
    "world_to_camera",
    "render_view",
]
