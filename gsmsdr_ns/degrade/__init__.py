"""Degraded captures: motion blur, defocus, mixed resolution and sensor noise applied to a sharp scene, written in
the Deblur-NeRF layout (sharp test views every `hold`-th view, images_test/ twins, degradation.json).

Public API:
    DegradeConfig (+ MotionConfig, DefocusConfig, MixresConfig, NoiseConfig), load_preset
    degrade_scene(input_dir, out_dir, config, overwrite=False) -> Path
    generate_variant(out_dir, scene_config, variant, ...) -> Path   procedural scene straight to a degraded variant
    load_source(root) -> SourceScene                                   COLMAP or transforms.json input
    kernels (pure, [B, C, H, W] tensors): disk_kernel, motion_kernel_from_trajectory, convolve_psf,
        plane_homography, homography_blur, rotational_shake_blur, defocus_radius, disk_blur, apply_defocus,
        mixres_factors, apply_mixres, add_noise (+ module twins PSFBlur, RotationalShakeBlur, LayeredDefocus)
"""

from ..data.mixres import mixres_factors
from ..ops.mixres import apply_mixres
from .config import (
    DefocusConfig,
    DegradeConfig,
    MixresConfig,
    MotionConfig,
    NoiseConfig,
    load_preset,
    normalize_effects,
)
from .kernels import (
    LayeredDefocus,
    PSFBlur,
    RotationalShakeBlur,
    add_noise,
    apply_defocus,
    convolve_psf,
    defocus_radius,
    disk_blur,
    disk_kernel,
    homography_blur,
    motion_kernel_from_trajectory,
    path_extent,
    plane_homography,
    radius_levels,
    rotational_shake_blur,
)
from .pipeline import degrade_scene, llff_poses_bounds
from .source import SourceScene, load_source
from .trajectory import ShakeTrajectory, calibrated_shake, pixel_paths
from .variants import VARIANTS, generate_variant

__all__ = [
    "DegradeConfig",
    "MotionConfig",
    "DefocusConfig",
    "MixresConfig",
    "NoiseConfig",
    "load_preset",
    "normalize_effects",
    "degrade_scene",
    "generate_variant",
    "VARIANTS",
    "llff_poses_bounds",
    "SourceScene",
    "load_source",
    "ShakeTrajectory",
    "calibrated_shake",
    "pixel_paths",
    "disk_kernel",
    "motion_kernel_from_trajectory",
    "convolve_psf",
    "plane_homography",
    "homography_blur",
    "rotational_shake_blur",
    "path_extent",
    "defocus_radius",
    "disk_blur",
    "radius_levels",
    "apply_defocus",
    "mixres_factors",
    "apply_mixres",
    "add_noise",
    "PSFBlur",
    "RotationalShakeBlur",
    "LayeredDefocus",
]
