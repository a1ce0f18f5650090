"""Differentiable Gaussian rasterization: gsplat on CUDA, our own tile rasterizer on CPU.

Imports no nerfstudio code. The C++ kernel is compiled lazily on first CPU use.
"""

from gsmsdr_ns.render.gsplat_backend import GsplatUnavailableError, require_gsplat_cuda
from gsmsdr_ns.render.projection import Projection, covariance_3d, project_gaussians, quat_to_rotmat
from gsmsdr_ns.render.rasterization import rasterization, rasterize_to_pixels, resolve_cpu_backend
from gsmsdr_ns.render.sh import eval_sh_colors, num_sh_bases, sh_basis
from gsmsdr_ns.render.tiles import isect_offset_encode, isect_tiles

__all__ = [
    "GsplatUnavailableError",
    "Projection",
    "covariance_3d",
    "eval_sh_colors",
    "isect_offset_encode",
    "isect_tiles",
    "num_sh_bases",
    "project_gaussians",
    "quat_to_rotmat",
    "rasterization",
    "rasterize_to_pixels",
    "require_gsplat_cuda",
    "resolve_cpu_backend",
    "sh_basis",
]
