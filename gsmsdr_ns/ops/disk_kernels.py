"""Per-pixel disk kernels of a thin lens: what a defocused pixel gathers from its window (pure functions).

:func:`soft_disk_kernels` (one disk per pixel) and :func:`occluding_disk_kernels` (each neighbour spreads its own
disk, an in-focus foreground hides the blurred background) return [B, K*K, H, W] weights in the row-major window
order of :func:`~gsmsdr_ns.ops.pixel_kernels.apply_pixel_kernels`. Training applies the same kernels fused, without
holding the weights (:mod:`gsmsdr_ns.ops.disk_defocus`); these are the reference and the viewer's blur size.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from gsmsdr_ns.ops.deconvolved_loss import mean_kernel

__all__ = ["soft_disk_kernels", "occluding_disk_kernels", "mean_soft_disk_kernel", "check_disk_window"]


def check_disk_window(kernel_size: int, softness: float) -> None:
    if kernel_size < 1 or kernel_size % 2 == 0:
        raise ValueError(f"kernel_size must be a positive odd integer, got {kernel_size}")
    if not softness > 0:
        raise ValueError(f"softness must be > 0, got {softness}")


def _disk_coverage(radius: Tensor, kernel_size: int, softness: float) -> Tensor:
    """Soft coverage of each window tap by a disk: radius [B, 1 or K*K, H, W] -> [B, K*K, H, W] (unnormalised;
    the centre tap 1; the other taps 0 at radius 0)."""
    half = kernel_size // 2
    offsets = torch.arange(kernel_size, device=radius.device, dtype=radius.dtype) - half
    tap_distance = torch.sqrt(offsets[:, None] ** 2 + offsets[None, :] ** 2).reshape(1, -1, 1, 1)
    coverage = torch.sigmoid((radius - tap_distance) / softness) - torch.sigmoid(-tap_distance / softness)
    return torch.where(tap_distance == 0, torch.ones_like(coverage), coverage)


def soft_disk_kernels(radius: Tensor, kernel_size: int, softness: float = 0.25) -> Tensor:
    """Per-pixel disk kernels with a soft edge.

    A tap at distance r_k > 0 from the centre gets weight ``s((radius - r_k) / softness) - s(-r_k / softness)``
    (s: the sigmoid), the centre tap 1, normalised to sum to 1: the pixel's area coverage by the disk (which ramps
    from 1 to 0 between r_k = radius - 0.5 and radius + 0.5, as the degradation simulator's ``disk_kernel``; the
    centre pixel is always covered), smoothed so that every weight is differentiable in the radius, and shifted so
    that radius 0 is exactly the identity (an in-focus pixel stays sharp) while its gradient there is not ~0. Radii
    beyond the window are truncated to it.

    Args:
        radius: [B, 1, H, W] disk radius in pixels, >= 0.
        kernel_size: odd window size K.
        softness: edge width in pixels (> 0).
    Returns:
        [B, K*K, H, W] weights (row-major window index, as ``apply_pixel_kernels``), summing to 1 over dim 1.
    """
    check_disk_window(kernel_size, softness)
    if radius.dim() != 4 or radius.shape[1] != 1:
        raise ValueError(f"radius must be [B, 1, H, W], got {list(radius.shape)}")
    weights = _disk_coverage(radius, kernel_size, softness)
    return weights / weights.sum(dim=1, keepdim=True)


def mean_soft_disk_kernel(radius: Tensor, kernel_size: int, softness: float = 0.25, max_pixels: int = 4096) -> Tensor:
    """The mean over an image of its pixels' :func:`soft_disk_kernels` (occlusion ignored): the image's mean blur.

    Larger images are averaged over an even grid of at most about ``max_pixels`` of their pixels (the mean over a
    smooth radius map changes little; holding every pixel's K*K weights would cost K*K times the image).

    Args:
        radius: [B, 1, H, W] disk radius in pixels, >= 0.
        kernel_size: odd window size K.
        softness: edge width in pixels (> 0).
        max_pixels: pixels averaged per image, at most about.
    Returns:
        [B, K, K], summing to 1.
    """
    check_disk_window(kernel_size, softness)
    if radius.dim() != 4 or radius.shape[1] != 1:
        raise ValueError(f"radius must be [B, 1, H, W], got {list(radius.shape)}")
    H, W = radius.shape[-2:]
    stride = max(1, math.ceil(math.sqrt(H * W / max_pixels)))
    sample = radius[..., stride // 2 :: stride, stride // 2 :: stride]  # an even grid of pixels, centred
    return mean_kernel(soft_disk_kernels(sample, kernel_size, softness))


def occluding_disk_kernels(radius: Tensor, inverse_depth: Tensor, kernel_size: int, softness: float = 0.25) -> Tensor:
    """Per-pixel defocus kernels that let each neighbour spread its own disk, with depth occlusion.

    A defocused photo is every scene point spread over its own circle of confusion, and a sharp object in front
    hides the blurred background behind it. Pixel p therefore gathers neighbour q (at distance r_k) with the soft
    coverage of :func:`soft_disk_kernels` at q's radius, divided by q's disk area ``1 + pi r_q^2`` (q's light is
    shared over its disk), except that a neighbour behind p (smaller inverse depth) reaches no further than p's
    own radius: an in-focus foreground pixel takes nothing from the blurred background, a blurred foreground
    spreads over what lies behind it. Weights are normalised per pixel. With one radius and one depth everywhere
    this is :func:`soft_disk_kernels`; radius 0 everywhere is the identity.

    Args:
        radius: [B, 1, H, W] disk radius in pixels, >= 0 (differentiable).
        inverse_depth: [B, 1, H, W] 1 / depth (only compared, never differentiated).
        kernel_size: odd window size K.
        softness: edge width in pixels (> 0).
    Returns:
        [B, K*K, H, W] weights (row-major window index, as ``apply_pixel_kernels``), summing to 1 over dim 1.
    """
    check_disk_window(kernel_size, softness)
    if radius.dim() != 4 or radius.shape[1] != 1 or inverse_depth.shape != radius.shape:
        raise ValueError(
            f"radius and inverse_depth must both be [B, 1, H, W], got {list(radius.shape)} and "
            f"{list(inverse_depth.shape)}"
        )
    B, _, H, W = radius.shape
    half = kernel_size // 2

    def neighbours(x: Tensor) -> Tensor:  # [B, 1, H, W] -> [B, K*K, H, W]: x at p + offset k
        return F.unfold(F.pad(x, (half,) * 4, mode="replicate"), kernel_size).view(B, kernel_size**2, H, W)

    radius_q = neighbours(radius)
    behind = neighbours(inverse_depth.detach().to(radius.dtype)) < inverse_depth.detach().to(radius.dtype)
    reach = torch.where(behind, torch.minimum(radius_q, radius), radius_q)
    weights = _disk_coverage(reach, kernel_size, softness) / (1.0 + math.pi * radius_q**2)
    return weights / weights.sum(dim=1, keepdim=True)
