"""C++/OpenMP kernel for the fused thin-lens defocus op on CPU (csrc/disk_kernels.cpp), JIT-compiled on first use.

Built by the loader it shares with the rasterizer and the pixel-kernel op (`gsmsdr_ns._cpp_ext`) into
~/.cache/gsmsdr_ns/torch_extensions/<torch version>/gsmsdr_disk_kernels_cpu_<isa> (or $TORCH_EXTENSIONS_DIR), at most
once per process. `disk_kernels_cpp_available()` and `disk_kernels_cpp_error()` never raise, so the caller can fall back
to the PyTorch twin (`gsmsdr_ns.ops.disk_defocus`) with a clear reason.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Tuple

from torch import Tensor

from gsmsdr_ns._cpp_ext import CppExtension

EXTENSION = CppExtension(
    name="gsmsdr_disk_kernels_cpu",
    source=Path(__file__).resolve().parent / "csrc" / "disk_kernels.cpp",
    namespace="gsmsdr_defocus",
    what="C++ thin-lens defocus op",
)


# This module's loader API, bound to its extension (`CppExtension`): where it is built; build once and return
# `torch.ops.gsmsdr_defocus` (RuntimeError saying what is missing otherwise); and whether / why not it loads.
build_directory = EXTENSION.build_directory
load_disk_kernels_extension = EXTENSION.load
disk_kernels_cpp_available = EXTENSION.available
disk_kernels_cpp_error = EXTENSION.error


def disk_defocus_fwd_cpp(
    image: Tensor, radius: Tensor, inverse_depth: Tensor, kernel_size: int, softness: float, occlusion: bool
) -> Tuple[Tensor, Tensor]:
    """Raw forward: contiguous CPU float32/float64 image [B, C, H, W], radius and inverse_depth [B, 1, H, W] ->
    (blurred [B, C, H, W], per-pixel weight sums [B, 1, H, W])."""
    ops = load_disk_kernels_extension()
    return ops.disk_defocus_fwd(image, radius, inverse_depth, kernel_size, softness, occlusion)


def disk_defocus_bwd_cpp(
    grad_out: Tensor,
    image: Tensor,
    radius: Tensor,
    inverse_depth: Tensor,
    out: Tensor,
    weight_sum: Tensor,
    kernel_size: int,
    softness: float,
    occlusion: bool,
    need_image: bool,
    need_radius: bool,
) -> Tuple[Optional[Tensor], Optional[Tensor]]:
    """Raw backward: (grad_image or None, grad_radius or None); all inputs contiguous, same dtype; ``out`` and
    ``weight_sum`` are the forward's outputs."""
    ops = load_disk_kernels_extension()
    return ops.disk_defocus_bwd(
        grad_out, image, radius, inverse_depth, out, weight_sum, kernel_size, softness, occlusion, need_image,
        need_radius,
    )  # fmt: skip
