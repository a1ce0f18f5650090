"""C++/OpenMP kernel for `apply_pixel_kernels` on CPU (csrc/pixel_kernels.cpp), JIT-compiled on first use.

Built by the loader it shares with the rasterizer's kernel (`gsmsdr_ns._cpp_ext`) into
~/.cache/gsmsdr_ns/torch_extensions/<torch version>/gsmsdr_pixel_kernels_cpu_<isa> (or $TORCH_EXTENSIONS_DIR), at most
once per process. `pixel_kernels_cpp_available()` and `pixel_kernels_cpp_error()` never raise, so the caller
can fall back to the PyTorch twin with a clear reason.

Why a compiled kernel at all: the PyTorch twin issues about 3 K^2 small ops per forward+backward, and with OpenMP
every op is a parallel region ending in a barrier. On a machine shared with other processes each barrier waits for a
descheduled thread. The C++ kernel opens one region per call.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Tuple

from torch import Tensor

from gsmsdr_ns._cpp_ext import CppExtension

EXTENSION = CppExtension(
    name="gsmsdr_pixel_kernels_cpu",
    source=Path(__file__).resolve().parent / "csrc" / "pixel_kernels.cpp",
    namespace="gsmsdr_blur",
    what="C++ pixel-kernel op",
)


# This module's loader API, bound to its extension (`CppExtension`): where it is built; build once and return
# `torch.ops.gsmsdr_blur` (RuntimeError saying what is missing otherwise); and whether / why not it loads (never raise).
build_directory = EXTENSION.build_directory
load_pixel_kernels_extension = EXTENSION.load
pixel_kernels_cpp_available = EXTENSION.available
pixel_kernels_cpp_error = EXTENSION.error


def pixel_kernels_fwd_cpp(image: Tensor, weights: Tensor, kernel_size: int) -> Tensor:
    """Raw forward: contiguous CPU float32/float64 [B, C, H, W] and [B, K*K, H, W] -> [B, C, H, W]."""
    return load_pixel_kernels_extension().pixel_kernels_fwd(image, weights, kernel_size)


def pixel_kernels_bwd_cpp(
    grad_out: Tensor, image: Tensor, weights: Tensor, kernel_size: int, need_image: bool, need_weights: bool
) -> Tuple[Optional[Tensor], Optional[Tensor]]:
    """Raw backward: (grad_image or None, grad_weights or None); all inputs contiguous, same dtype."""
    ops = load_pixel_kernels_extension()
    return ops.pixel_kernels_bwd(grad_out, image, weights, kernel_size, need_image, need_weights)
