"""Which degradation model runs for which training image, and the small maths behind the blur viewer outputs.

Pure functions, no nerfstudio model state: ``GSMSDRModel`` asks them

* at construction: :func:`training_profiles` turns the dataparser's ``metadata["degradations"]`` (one record per
  training image, in the split's order; ``gsmsdr_ns.data.degradation``) and the model's ``degradation`` mode into
  one :class:`~gsmsdr_ns.blur.DegradationProfile` per training image; :func:`describe_profiles` makes the one-line
  summary it logs;
* per training step: :class:`DegradationPlan` says what to simulate for the image being trained;
* in the viewer: :func:`kernel_spread` (blur extent of per-pixel kernels), :func:`nearest_view` (training view
  closest to a viewer camera), :func:`preview_downscale` (resolution budget of the blur outputs) and
  :func:`coarsen_kernels` (the same blur expressed on a coarser pixel grid).
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Any, List, Mapping, NamedTuple, Optional, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from gsmsdr_ns.blur.hpko import ScaleInfo
from gsmsdr_ns.blur.kernels import pixel_kernel_size
from gsmsdr_ns.blur.profile import DegradationProfile, ProfileMode

__all__ = [
    "DegradationPlan",
    "training_profiles",
    "describe_profiles",
    "kernel_spread",
    "nearest_view",
    "preview_downscale",
    "coarsen_kernels",
]


class DegradationPlan(NamedTuple):
    """What one training step simulates on top of the sharp render (all empty: a plain splatfacto step)."""

    view_id: Optional[int] = None
    """Index of the training image (``camera.metadata["cam_idx"]``); None for cameras outside the training set."""
    blur_scale: Optional[ScaleInfo] = None
    """HPKO scale the blur field runs at; None: the field is not evaluated."""
    blur_uses_depth: bool = False
    """The blur field reads the rendered depth (the rasterizer must produce it)."""
    resolution_factor: float = 1.0
    """Effective resolution-loss factor at the current render downscale; > 1: the resolution model runs."""
    thin_lens: bool = False
    """The image may be defocused: the blur field's thin lens blurs the render first (needs depth)."""
    render_downscale: int = 1
    """The render's downscale factor (the thin lens's aperture is in full-resolution pixels)."""
    blur_field: bool = True
    """The field's kernels run (after the lens, if any); False: a defocused image is modelled by the thin lens
    alone."""

    @property
    def needs_depth(self) -> bool:
        return self.blur_scale is not None and ((self.blur_uses_depth and self.blur_field) or self.thin_lens)

    @property
    def is_plain(self) -> bool:
        """Nothing to simulate: outputs["rgb"] is the sharp render."""
        return self.blur_scale is None and self.resolution_factor <= 1.0


def training_profiles(
    mode: ProfileMode, metadata: Optional[Mapping[str, Any]], num_train: int
) -> List[DegradationProfile]:
    """One profile per training image.

    Args:
        mode: the model's ``degradation`` setting (``DegradationProfile.from_mode``): ``auto`` reads the records,
            an image without a usable record is unknown (any blur, any resolution loss); the others force that
            degradation on every training image the records do not call undegraded.
        metadata: the training dataset's metadata (``DataparserOutputs.metadata``); its ``"degradations"`` list,
            when present, must hold ``num_train`` records in the training split's order.
        num_train: number of training images.

    Raises:
        ValueError: the records do not match the training images.
    """
    records: Optional[Sequence[Optional[Mapping[str, Any]]]] = None
    if metadata is not None:
        records = metadata.get("degradations")
    if records is None:
        records = [None] * num_train
    if len(records) != num_train:
        raise ValueError(
            f"gsmsdr: the dataparser describes the degradation of {len(records)} training images, but there are "
            f"{num_train}: metadata['degradations'] must hold one record per training image, in the split's order."
        )
    return [DegradationProfile.from_mode(mode, record) for record in records]


def _profile_kind(profile: DegradationProfile) -> str:
    if profile.is_sharp:
        return "sharp"
    if profile == DegradationProfile.unknown():
        return "unknown"
    parts = [name for name in ("motion", "defocus") if getattr(profile, name)]
    if profile.mixres_factor is None:
        parts.append("mixres x?")
    elif profile.mixres_factor > 1:
        parts.append(f"mixres x{profile.mixres_factor}")
    if profile.noise:
        parts.append("noise")
    return "+".join(parts)


def describe_profiles(profiles: Sequence[DegradationProfile]) -> str:
    """Counts per kind, most common first, e.g. ``"6 motion, 2 sharp"``."""
    counts = Counter(_profile_kind(p) for p in profiles)
    return ", ".join(f"{n} {kind}" for kind, n in counts.most_common())


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
    K = pixel_kernel_size(weights.shape[1])
    offsets = torch.arange(K, device=weights.device, dtype=weights.dtype) - K // 2
    rows, cols = offsets.repeat_interleave(K), offsets.repeat(K)  # entry k = i * K + j: row i, column j
    moments = torch.stack([rows, cols, rows * rows + cols * cols])  # [3, K*K]
    mean_row, mean_col, second = torch.einsum("mk,bkhw->mbhw", moments, weights)
    variance = second - mean_row * mean_row - mean_col * mean_col
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
