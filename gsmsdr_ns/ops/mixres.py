"""The mixed-resolution operator: an image shrunk by a factor and enlarged back, as the simulator makes a low-resolution
photo and as training models one (pure, differentiable functions on [B, C, H, W] tensors).

One down-up for both: kornia's antialiased bilinear shrink to ``max(1, round(H / f)) x max(1, round(W / f))``, an
enlargement back to H x W with ``upsample`` (bilinear or bicubic), clamped to [0, 1].
"""

from __future__ import annotations

from kornia.geometry.transform import resize
from torch import Tensor

from gsmsdr_ns.ops.checks import check_image

__all__ = ["apply_mixres", "resolution_loss"]


def _down_up(image: Tensor, factor: float, upsample: str) -> Tensor:
    """[B, C, H, W] shrunk by ``factor`` (> 1) and enlarged back to [B, C, H, W]."""
    height, width = image.shape[-2:]
    small = (max(1, round(height / factor)), max(1, round(width / factor)))
    low = resize(image, small, interpolation="bilinear", antialias=True)
    return resize(low, (height, width), interpolation=upsample, align_corners=False).clamp(0.0, 1.0)


def apply_mixres(image: Tensor, factor: int, upsample: str = "bilinear") -> Tensor:
    """A photo taken ``factor`` (an integer >= 1) times smaller and enlarged back. [B, C, H, W] -> [B, C, H, W]

    factor 1 returns the image unchanged; anything but an integer >= 1 raises ValueError.
    """
    check_image(image)
    if int(factor) != factor or factor < 1:
        raise ValueError(f"mixres factor must be an integer >= 1, got {factor}")
    return image if factor == 1 else _down_up(image, int(factor), upsample)


def resolution_loss(image: Tensor, factor: float, upsample: str = "bilinear") -> Tensor:
    """The same operator at any factor (a known factor seen by a coarser render, e.g. 3 at 1/2 resolution, is 1.5).
    [B, C, H, W] -> [B, C, H, W]; ``factor <= 1`` returns ``image``."""
    check_image(image)
    return image if factor <= 1 else _down_up(image, float(factor), upsample)
