"""Per-image fallback to a plain step: :class:`ExplanationGate`.

A degradation model that does not yet explain its photo (a lens learning from a random start, a field before the
geometry has formed) teaches the Gaussians its own mistakes when they train through it. The gate keeps, per
training image, a running mean of two photometric errors measured on the steps that image ran its model: the
simulated degradation's against the photo, and the sharp render's. Until the first is the smaller one, the image
trains as a plain step (the Gaussians on the sharp render) while its degradation model keeps learning on the
detached render, so it can start explaining the photo later. No nerfstudio import.
"""

from __future__ import annotations

import math

import torch
from kornia.filters import gaussian_blur2d
from torch import Tensor, nn

__all__ = ["ExplanationGate", "photo_errors"]


def photo_errors(degraded: Tensor, sharp: Tensor, target: Tensor, sigma: float = 0.0) -> Tensor:
    """[2] detached mean absolute errors of ``degraded`` and ``sharp`` against ``target`` (all [H, W, 3]), measured
    after a Gaussian blur of standard deviation ``sigma`` pixels of all three (0: as they are). The blur keeps what a
    photo's own blur changes and removes the pixel-scale noise of a render still being formed, which any blur would
    otherwise seem to explain."""
    with torch.no_grad():
        images = torch.stack([degraded, sharp, target]).permute(0, 3, 1, 2).float()  # [3, 3, H, W]
        if sigma > 0:
            size = 2 * math.ceil(3 * sigma) + 1
            images = gaussian_blur2d(images, (size, size), (sigma, sigma), border_type="replicate")
        return (images[:2] - images[2:]).abs().mean(dim=(1, 2, 3))


class ExplanationGate(nn.Module):
    """Whether each training image's degradation model explains its photo better than the sharp render.

    Buffers (persistent, so a resumed run decides as the uninterrupted one would): ``errors`` [N, 2], the running
    means of (degraded, sharp) errors per image, NaN until the image's first measured step.

    Args:
        num_views: training images.
        decay: weight of the previous running mean at each new measurement of an image (0: the last step alone).
        margin: the model is used once its error is below ``(1 - margin)`` times the sharp render's.
    """

    errors: Tensor

    def __init__(self, num_views: int, decay: float = 0.5, margin: float = 0.0) -> None:
        super().__init__()
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"fallback decay must be in [0, 1), got {decay}")
        if not 0.0 <= margin < 1.0:
            raise ValueError(f"fallback margin must be in [0, 1), got {margin}")
        self.decay = float(decay)
        self.margin = float(margin)
        self.register_buffer("errors", torch.full((num_views, 2), float("nan")))

    def views_using_model(self) -> Tensor:
        """[N] bool: the images that train through their degradation model (False until measured and found to
        explain the photo better than the sharp render; a NaN comparison is False)."""
        return self.errors[:, 0] < (1.0 - self.margin) * self.errors[:, 1]

    def views_measured(self) -> Tensor:
        """[N] bool: the images whose errors have been measured at least once."""
        return ~torch.isnan(self.errors[:, 0])

    def uses_model(self, view_id: int) -> bool:
        """Whether image ``view_id`` trains through its degradation model (:meth:`views_using_model`)."""
        return bool(self.views_using_model()[view_id])

    @torch.no_grad()
    def update(self, view_id: int, errors: Tensor) -> None:
        """Fold one step's ``errors`` [2] (:func:`photo_errors`) into image ``view_id``'s running means."""
        row = self.errors[view_id]
        fresh = errors.to(row)
        row.copy_(torch.where(torch.isnan(row), fresh, self.decay * row + (1.0 - self.decay) * fresh))

    def fraction_using_model(self) -> Tensor:
        """Scalar: the share of measured images whose model is in use (0 when none is measured)."""
        measured = self.views_measured().float().sum().clamp(min=1.0)
        return self.views_using_model().float().sum() / measured
