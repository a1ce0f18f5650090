"""Per-pixel blur kernels predicted on a coarse grid and applied at every pixel, without a full-resolution copy.

The blur field's feature network can run on a grid ``r`` times coarser than the render (blur varies smoothly across
a photo). Its kernels, [B, K*K, h, w] on that grid, are resampled bilinearly to each pixel and applied there::

    apply_grid_kernels(image, grid, r)
        == apply_pixel_kernels(image, upsample_grid(grid, r, image.shape[-2:]))

``upsample_grid`` is ``F.interpolate(grid, scale_factor=r, mode="bilinear", align_corners=False)`` cropped to the
image: grid cell (gy, gx) covers pixels [r gy, r gy + r) x [r gx, r gx + r). Convex combinations of normalised
kernels stay normalised, so softmax kernels on the grid give normalised kernels at every pixel.

On CPU (float32 / float64) a C++/OpenMP kernel (``csrc/grid_kernels.cpp``) rebuilds each row of the
full-resolution weights when it needs it, so neither the forward nor the backward holds a [B, K*K, H, W] tensor: at
K = 17 that tensor costs as much time to resample and to differentiate as the blur itself. Elsewhere (CUDA, half
precision, no compiler) the two-step PyTorch twin runs.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple, Optional, Sequence, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.function import once_differentiable

from gsmsdr_ns._cpp_ext import CppExtension
from gsmsdr_ns.ops.pixel_kernels import apply_image_kernels, apply_pixel_kernels, pixel_kernel_size

__all__ = [
    "GridKernels",
    "apply_grid_kernels",
    "as_dense",
    "grid_kernels_cpp_available",
    "grid_size",
    "pool_to_grid",
    "upsample_grid",
]

EXTENSION = CppExtension(
    name="gsmsdr_grid_kernels_cpu",
    source=Path(__file__).resolve().parent / "csrc" / "grid_kernels.cpp",
    namespace="gsmsdr_grid",
    what="C++ grid-kernel op",
)
grid_kernels_cpp_available = EXTENSION.available


def grid_size(size: Sequence[int], factor: int) -> Tuple[int, int]:
    """(h, w) of the grid ``factor`` times coarser than an image of ``size`` (H, W): ``ceil(H / factor)``,
    ``ceil(W / factor)`` (the last cell may cover fewer pixels)."""
    return (-(-int(size[0]) // int(factor)), -(-int(size[1]) // int(factor)))


def pool_to_grid(x: Tensor, factor: int) -> Tensor:
    """Mean of each grid cell: [B, C, H, W] -> [B, C, ceil(H / factor), ceil(W / factor)] (a partial last cell
    averages the pixels it covers)."""
    if factor == 1:
        return x
    return F.avg_pool2d(x, factor, stride=factor, ceil_mode=True, count_include_pad=False)


def upsample_grid(grid: Tensor, factor: int, size: Sequence[int]) -> Tensor:
    """Bilinear resampling of grid values to pixels: [B, C, h, w] -> [B, C, H, W] (``size`` = (H, W), at most
    (h * factor, w * factor)); grid cell centres sit at pixel ``factor * g + (factor - 1) / 2``."""
    if factor == 1:
        return grid
    full = F.interpolate(grid, scale_factor=factor, mode="bilinear", align_corners=False)
    return full[..., : size[0], : size[1]]


class GridKernels(NamedTuple):
    """Per-pixel kernels held on a grid ``factor`` times coarser than the image they blur."""

    weights: Tensor
    """[B, K*K, ceil(H / factor), ceil(W / factor)] kernel weights at the grid cells."""
    factor: int
    """Grid cell size in pixels."""
    size: Tuple[int, int]
    """(H, W) of the image."""

    def dense(self) -> Tensor:
        """[B, K*K, H, W]: the kernels resampled to every pixel (:func:`upsample_grid`); a grid of one cell is
        expanded (stride 0) instead of copied."""
        if self.weights.shape[-2:] == (1, 1):
            return self.weights.expand(-1, -1, *self.size)
        return upsample_grid(self.weights, self.factor, self.size)


def as_dense(kernels: Union[Tensor, GridKernels]) -> Tensor:
    """[B, K*K, H, W] kernels at every pixel, from either form."""
    return kernels.dense() if isinstance(kernels, GridKernels) else kernels


def _check(image: Tensor, grid: Tensor, factor: int) -> int:
    if image.dim() != 4 or grid.dim() != 4:
        raise ValueError(f"image and grid must be [B, C, H, W] / [B, K*K, h, w], got {list(image.shape)}, "
                         f"{list(grid.shape)}")  # fmt: skip
    K = pixel_kernel_size(grid.shape[1])
    if int(factor) != factor or factor < 1:
        raise ValueError(f"factor must be an integer >= 1, got {factor}")
    expected = (image.shape[0], K * K, *grid_size(image.shape[-2:], factor))
    if tuple(grid.shape) != expected:
        raise ValueError(f"grid: expected shape {list(expected)} for image {list(image.shape)} and factor {factor}, "
                         f"got {list(grid.shape)}")  # fmt: skip
    if grid.dtype != image.dtype or grid.device != image.device:
        raise ValueError(f"image and grid must share dtype and device, got {image.dtype} on {image.device} and "
                         f"{grid.dtype} on {grid.device}")  # fmt: skip
    return K


class _GridKernelsCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, image: Tensor, grid: Tensor, K: int, factor: int) -> Tensor:
        ops = EXTENSION.load()
        image_c, grid_c = image.contiguous(), grid.contiguous()
        ctx.K, ctx.factor = K, factor
        ctx.save_for_backward(image_c, grid_c)
        return ops.grid_kernels_fwd(image_c, grid_c, K, factor)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor) -> Tuple[Optional[Tensor], Optional[Tensor], None, None]:
        image, grid = ctx.saved_tensors
        need_image, need_grid = ctx.needs_input_grad[:2]
        grad_image, grad_grid = EXTENSION.load().grid_kernels_bwd(
            grad_out.contiguous(), image, grid, ctx.K, ctx.factor, need_image, need_grid
        )
        return grad_image, grad_grid, None, None


def apply_grid_kernels(
    image: Tensor,  # [B, C, H, W]
    grid: Tensor,  # [B, K*K, ceil(H / factor), ceil(W / factor)]
    factor: int,
    backend: str = "auto",
) -> Tensor:  # [B, C, H, W]
    """Blur every pixel with the kernel bilinearly resampled from ``grid`` (see the module docstring).

    Args:
        image: [B, C, H, W] floating-point image.
        grid: [B, K*K, ceil(H / factor), ceil(W / factor)] kernels on the coarse grid (odd K), same dtype and
            device; used as given (softmax them beforehand for normalised kernels).
        factor: grid cell size in pixels (1: ``apply_pixel_kernels``; a grid of one cell is one kernel for the whole
            image: ``apply_image_kernels``).
        backend: "cpp" (CPU float32/float64), "torch" (resample, then ``apply_pixel_kernels``) or "auto".
    Returns:
        [B, C, H, W]; differentiable in ``image`` and ``grid`` (first order).
    """
    K = _check(image, grid, factor)
    if grid.shape[-2:] == (1, 1):  # a grid of one cell: one kernel for the whole image
        return apply_image_kernels(image, grid[:, :, 0, 0])
    if factor == 1:
        return apply_pixel_kernels(image, grid)
    chosen = EXTENSION.backend_for(
        image, backend, unavailable="C++ grid-kernel op", fallback="resampling the kernels to every pixel"
    )
    if chosen == "cpp":
        return _GridKernelsCpp.apply(image, grid, K, int(factor))
    return apply_pixel_kernels(image, upsample_grid(grid, int(factor), image.shape[-2:]))
