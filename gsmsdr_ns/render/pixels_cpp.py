"""Fast CPU rasterize_to_pixels: a C++/OpenMP kernel (csrc/rasterize_cpu.cpp), JIT-compiled on first use.

The build goes through torch.utils.cpp_extension.load, like gsplat's CUDA code, into
~/.cache/gsmsdr_ns/torch_extensions/<torch version>/ (or $TORCH_EXTENSIONS_DIR), by the loader shared with the blur
kernels (`gsmsdr_ns._cpp_ext`). It happens at most once per process; torch's file lock serialises concurrent builds.
`cpp_backend_available()` and `cpp_backend_error()` never raise, so callers can fall back to the PyTorch kernel
with a clear reason.
"""

from __future__ import annotations

import weakref
from pathlib import Path
from typing import Optional, Tuple

import torch
from torch import Tensor

from gsmsdr_ns._cpp_ext import CppExtension

EXTENSION = CppExtension(
    name="gsmsdr_rasterize_cpu",
    source=Path(__file__).resolve().parent / "csrc" / "rasterize_cpu.cpp",
    namespace="gsmsdr_ns",
    what="C++ rasterizer",
)


# This module's loader API, bound to its extension (`CppExtension`): where it is built; build once and return
# `torch.ops.gsmsdr_ns` (RuntimeError saying what is missing otherwise); and whether / why not it loads (never raise).
build_directory = EXTENSION.build_directory
load_cpu_extension = EXTENSION.load
cpp_backend_available = EXTENSION.available
cpp_backend_error = EXTENSION.error


def _check_inputs(
    means2d: Tensor,
    conics: Tensor,
    colors: Tensor,
    opacities: Tensor,
    image_width: int,
    image_height: int,
    tile_size: int,
    isect_offsets: Tensor,
    flatten_ids: Tensor,
    backgrounds: Optional[Tensor],
) -> None:
    """Raise ValueError naming expected vs actual shapes / dtypes."""
    if means2d.dim() != 3 or means2d.shape[-1] != 2:
        raise ValueError(f"means2d: expected shape [C, N, 2], got {list(means2d.shape)}")
    C, N = means2d.shape[:2]
    if means2d.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"means2d: expected dtype float32 or float64, got {means2d.dtype}")
    expected = {
        "conics": (conics, [C, N, 3]),
        "opacities": (opacities, [C, N]),
    }
    if colors.dim() != 3 or list(colors.shape[:2]) != [C, N] or colors.shape[2] < 1:
        raise ValueError(f"colors: expected shape [C={C}, N={N}, D>=1], got {list(colors.shape)}")
    D = colors.shape[2]
    expected["colors"] = (colors, [C, N, D])
    if backgrounds is not None:
        expected["backgrounds"] = (backgrounds, [C, D])
    for name, (tensor, shape) in expected.items():
        if list(tensor.shape) != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {list(tensor.shape)}")
        if tensor.dtype != means2d.dtype:
            raise ValueError(f"{name}: expected dtype {means2d.dtype} (same as means2d), got {tensor.dtype}")
    for name, (tensor, _) in {"means2d": (means2d, None), **expected}.items():
        if tensor.device.type != "cpu":
            raise ValueError(f"{name}: expected a CPU tensor, got device {tensor.device}")
    if tile_size <= 0 or image_width <= 0 or image_height <= 0:
        raise ValueError(
            f"expected positive image_width, image_height, tile_size, got {image_width}, {image_height}, {tile_size}"
        )
    tile_h = (image_height + tile_size - 1) // tile_size
    tile_w = (image_width + tile_size - 1) // tile_size
    if list(isect_offsets.shape) != [C, tile_h, tile_w]:
        raise ValueError(
            f"isect_offsets: expected shape [C, tile_height, tile_width] = {[C, tile_h, tile_w]}, "
            f"got {list(isect_offsets.shape)}"
        )
    if flatten_ids.dim() != 1:
        raise ValueError(f"flatten_ids: expected shape [n_isects], got {list(flatten_ids.shape)}")
    for name, tensor in (("isect_offsets", isect_offsets), ("flatten_ids", flatten_ids)):
        if tensor.dtype not in (torch.int32, torch.int64):
            raise ValueError(f"{name}: expected dtype int32, got {tensor.dtype}")
        if tensor.device.type != "cpu":
            raise ValueError(f"{name}: expected a CPU tensor, got device {tensor.device}")
    if isect_offsets.numel() > 0:
        flat = isect_offsets.reshape(-1)
        if int(flat[0]) < 0 or int(flat[-1]) > flatten_ids.numel() or bool((flat[1:] < flat[:-1]).any()):
            raise ValueError(
                f"isect_offsets: expected non-decreasing values in [0, n_isects={flatten_ids.numel()}] "
                "(tile lists sorted by camera and tile)"
            )
    if flatten_ids.numel() > 0:
        lo, hi = int(flatten_ids.min()), int(flatten_ids.max())
        if lo < 0 or hi >= C * N:
            raise ValueError(f"flatten_ids: expected values in [0, C*N={C * N}), got range [{lo}, {hi}]")


class _RasterizeToPixelsCPU(torch.autograd.Function):
    """C++ forward/backward. Inputs are made contiguous here so gradients flow to the caller's tensors."""

    @staticmethod
    def forward(
        ctx,
        means2d: Tensor,  # [C, N, 2]
        conics: Tensor,  # [C, N, 3]
        colors: Tensor,  # [C, N, D]
        opacities: Tensor,  # [C, N]
        backgrounds: Optional[Tensor],  # [C, D]
        image_width: int,
        image_height: int,
        tile_size: int,
        isect_offsets: Tensor,  # [C, tile_height, tile_width] int32
        flatten_ids: Tensor,  # [n_isects] int32
        absgrad: bool,
    ) -> Tuple[Tensor, Tensor]:
        ops = load_cpu_extension()
        # the caller's own object: absgrad must land on it, not on a contiguous copy
        ctx.means2d_ref = weakref.ref(means2d)
        args = [t.contiguous() for t in (means2d, conics, colors, opacities)]
        bg = backgrounds.contiguous() if backgrounds is not None else None
        offsets = isect_offsets.to(torch.int32).contiguous()
        ids = flatten_ids.to(torch.int32).contiguous()
        render_colors, render_alphas, last_ids = ops.rasterize_to_pixels_fwd(
            *args, bg, image_width, image_height, tile_size, offsets, ids, torch.get_num_threads()
        )
        ctx.save_for_backward(*args, bg, offsets, ids, last_ids)
        ctx.dims = (image_width, image_height, tile_size)
        ctx.absgrad = absgrad
        return render_colors, render_alphas

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, v_render_colors: Tensor, v_render_alphas: Tensor):
        means2d, conics, colors, opacities, bg, offsets, ids, last_ids = ctx.saved_tensors
        image_width, image_height, tile_size = ctx.dims
        dtype = means2d.dtype
        v_means2d, v_conics, v_colors, v_opacities, v_bg, v_abs = torch.ops.gsmsdr_ns.rasterize_to_pixels_bwd(
            means2d,
            conics,
            colors,
            opacities,
            bg,
            image_width,
            image_height,
            tile_size,
            offsets,
            ids,
            last_ids,
            v_render_colors.to(dtype).contiguous(),
            v_render_alphas.to(dtype).contiguous(),
            ctx.absgrad,
            torch.get_num_threads(),
        )
        if ctx.absgrad:
            target = ctx.means2d_ref()
            if target is not None:
                target.absgrad = v_abs
        v_bg = v_bg if ctx.needs_input_grad[4] else None
        return v_means2d, v_conics, v_colors, v_opacities, v_bg, None, None, None, None, None, None


def rasterize_to_pixels_cpp(
    means2d: Tensor,  # [C, N, 2]
    conics: Tensor,  # [C, N, 3]
    colors: Tensor,  # [C, N, D]
    opacities: Tensor,  # [C, N]
    image_width: int,
    image_height: int,
    tile_size: int,
    isect_offsets: Tensor,  # [C, tile_height, tile_width]
    flatten_ids: Tensor,  # [n_isects]
    backgrounds: Optional[Tensor] = None,  # [C, D]
    absgrad: bool = False,
) -> Tuple[Tensor, Tensor]:
    """Rasterize depth-sorted Gaussians into images with the C++ kernel (gsplat 1.4.0 semantics).

    Args:
        means2d: [C, N, 2] pixel-space centres. conics: [C, N, 3] inverse 2D covariances (a, b, c).
        colors: [C, N, D] any D >= 1. opacities: [C, N]. All float32 or all float64.
        isect_offsets: [C, tile_height, tile_width] int32 start of each tile's list in flatten_ids.
        flatten_ids: [n_isects] int32 indices into the flattened [C * N] arrays, front to back per tile.
        backgrounds: [C, D] colour behind the Gaussians, optional.
        absgrad: after backward, `means2d.absgrad` [C, N, 2] holds the sum over pixels of |d loss / d means2d|.

    Returns:
        render_colors: [C, H, W, D]; render_alphas: [C, H, W, 1].

    Raises:
        ValueError: bad shapes, dtypes or devices. RuntimeError: the extension cannot be built.
    """
    _check_inputs(
        means2d,
        conics,
        colors,
        opacities,
        image_width,
        image_height,
        tile_size,
        isect_offsets,
        flatten_ids,
        backgrounds,
    )
    return _RasterizeToPixelsCPU.apply(
        means2d,
        conics,
        colors,
        opacities,
        backgrounds,
        int(image_width),
        int(image_height),
        int(tile_size),
        isect_offsets,
        flatten_ids,
        bool(absgrad),
    )
