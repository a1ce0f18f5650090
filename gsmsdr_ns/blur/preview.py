"""The small maths behind the viewer's blur outputs (pure functions on tensors).

:func:`kernel_spread` (blur extent of per-pixel kernels), :func:`nearest_view` (training view closest to a viewer
camera), :func:`preview_downscale` (resolution budget of the blur outputs) and :func:`coarsen_kernels` (the same
blur expressed on a coarser pixel grid).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from gsmsdr_ns.ops.pixel_kernels import kernel_centroids, kernel_tap_offsets, pixel_kernel_size

__all__ = ["kernel_spread", "nearest_view", "preview_downscale", "coarsen_kernels"]


def kernel_spread(weights: Tensor) -> Tensor:
    """Blur extent of per-pixel kernels: the RMS distance (pixels) of each kernel's weights from its centroid.

    ``sqrt(sum_k w_k |o_k - mu|^2)`` with ``o_k`` the (row, column) offset of kernel entry k and ``mu = sum_k w_k o_k``
    (weights are assumed to sum to 1, as the blur field's softmax kernels do). A delta kernel, shifted or not, has
    extent 0; a uniform K x K box has ``sqrt((K^2 - 1) / 6)``.

    Args:
        weights: [B, K*K, H, W], row-major kernel index (``apply_pixel_kernels``' convention).
    Returns:
        [B, 1, H, W]
    """
    if weights.dim() != 4:
        raise ValueError(f"weights: expected shape [B, K*K, H, W], got {list(weights.shape)}")
    offsets = kernel_tap_offsets(pixel_kernel_size(weights.shape[1]), weights.device, weights.dtype)
    mean = kernel_centroids(weights)  # [B, 2, H, W]
    second = torch.einsum("k,bkhw->bhw", offsets.square().sum(0), weights)
    variance = second - mean.square().sum(1)
    return variance.clamp_min(0.0).sqrt()[:, None]


def nearest_view(centres: Tensor, position: Tensor) -> int:
    """Index of the training camera centre closest to ``position``; rows with NaN are skipped (0 if all are).

    Args:
        centres: [N, 3] training camera centres (NaN rows: unknown).
        position: [3] camera centre to match.
    """
    if centres.dim() != 2 or centres.shape[-1] != 3 or position.shape != (3,):
        raise ValueError(f"expected centres [N, 3] and position [3], got {list(centres.shape)}, {list(position.shape)}")
    distance = (centres - position.to(centres)).norm(dim=-1)
    distance = torch.where(torch.isfinite(distance), distance, torch.full_like(distance, math.inf))
    if distance.numel() == 0 or not bool(torch.isfinite(distance).any()):
        return 0
    return int(torch.argmin(distance))


def preview_downscale(height: int, width: int, max_side: int, at_least: int = 1) -> int:
    """Smallest power of two d >= ``at_least`` with ``max(height, width) / d <= max_side`` (``max_side`` <= 0: no
    limit)."""
    if at_least < 1 or at_least & (at_least - 1):
        raise ValueError(f"at_least must be a power of two >= 1, got {at_least}")
    d = at_least
    while max_side > 0 and max(height, width) > max_side * d and min(height, width) >= 2 * d:
        d *= 2
    return d


def coarsen_kernels(weights: Tensor, factor: int) -> Tensor:
    """The same per-pixel blur on a pixel grid ``factor`` times coarser (for kernels predicted on a shrunk image).

    Each K x K kernel, whose taps are pixels of the finer grid, is zero-padded symmetrically to ``factor * K'``
    (``K'`` the smallest odd size with ``factor * K' >= K``) and sum-pooled over ``factor`` x ``factor`` blocks, so
    the weights still sum to what they summed to and the blur extent in fine pixels is kept up to the block size
    (an even ``factor`` shifts the kernel centre by half a fine pixel). ``factor`` 1 returns ``weights``.

    Args:
        weights: [B, K*K, H, W] (row-major kernel index).
        factor: integer >= 1.
    Returns:
        [B, K'*K', H, W]
    """
    if factor < 1:
        raise ValueError(f"factor must be >= 1, got {factor}")
    if weights.dim() != 4:
        raise ValueError(f"weights: expected shape [B, K*K, H, W], got {list(weights.shape)}")
    K = pixel_kernel_size(weights.shape[1])
    if factor == 1:
        return weights
    B, _, H, W = weights.shape
    coarse = -(-K // factor)
    coarse += 1 - coarse % 2  # odd
    pad = coarse * factor - K
    before, after = pad // 2, pad - pad // 2
    k = weights.permute(0, 2, 3, 1).reshape(B * H * W, 1, K, K)
    k = F.pad(k, (before, after, before, after))
    k = F.avg_pool2d(k, factor) * (factor * factor)
    return k.reshape(B, H, W, coarse * coarse).permute(0, 3, 1, 2)
