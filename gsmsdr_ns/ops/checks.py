"""Argument checks the operators share: errors that name the argument and the shape it must have."""

from __future__ import annotations

from torch import Tensor

__all__ = ["check_image"]


def check_image(image: Tensor, name: str = "image") -> None:
    """Raise a ValueError naming ``name`` unless ``image`` is a tensor [B, C, H, W]."""
    if not isinstance(image, Tensor) or image.dim() != 4:
        shape = tuple(image.shape) if isinstance(image, Tensor) else type(image).__name__
        raise ValueError(f"{name} must be a tensor [B, C, H, W], got {shape}")
