"""The degradation model's loss terms, computed in one place (pure functions).

Each term is added only when the step's degradation produced what it reads (:class:`DegradationAux`): the mask
regulariser when the field ran with a learnt mask, the kernel-centre regulariser when its kernels' centres were
taken, the deconvolved residual when the image's mean kernel was.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, NamedTuple, Optional, Union

import torch
from torch import Tensor

from gsmsdr_ns.ops.deconvolved_loss import blend_with_identity, deconvolved_residual, mean_kernel
from gsmsdr_ns.ops.grid_kernels import GridKernels
from gsmsdr_ns.ops.pixel_kernels import kernel_centroids

__all__ = [
    "DegradationAux",
    "DegradationLossWeights",
    "degradation_losses",
    "mask_regulariser",
    "kernel_centre_regulariser",
    "mean_blend_kernel",
    "kernel_centres",
]


class DegradationAux(NamedTuple):
    """What one degraded training render leaves beside the degraded image, for the losses, metrics and viewer."""

    sharp: Tensor
    """[H, W, 3] the sharp render (without the render margin)."""
    mask: Optional[Tensor] = None
    """[H, W, 1] the field's blend mask; None when the field did not run."""
    learnt_mask: bool = False
    """The mask is learnt (mode view's is the constant 1: no regulariser)."""
    kernel_mean: Optional[Tensor] = None
    """[1, K, K] detached mean over the image of the field's blend ``m * k + (1 - m) * identity``; None: no
    deconvolved loss on this step."""
    kernel_centroids: Optional[Tensor] = None
    """[1, 2, h, w] centres of mass (pixels) of the field's kernels; None: no kernel-centre regulariser."""
    kernel_size: Optional[int] = None
    """The HPKO kernel size the field ran at; None: the field did not run."""


@dataclass(frozen=True)
class DegradationLossWeights:
    """Weights of the degradation model's loss terms (0: the term is off), as ``DegradationConfig.loss_weights``
    gives them."""

    mask: float
    """Mask regulariser mean(m)."""
    kernel_centre: float
    """Kernel-centre regulariser mean(|c|^2)."""
    deconvolved: float
    """Deconvolved residual (:mod:`gsmsdr_ns.ops.deconvolved_loss`)."""
    deconvolved_eps: float
    """Wiener regulariser of the deconvolved residual's weight."""


def mean_blend_kernel(kernels: Union[Tensor, GridKernels], mask: Tensor) -> Tensor:
    """[B, K, K] detached mean over the image of the field's blend ``m * k + (1 - m) * identity`` (kernels
    [B, K*K, H, W], expanded over the pixels in mode view, or on the field's coarse grid; mask [B, 1, H, W])."""
    with torch.no_grad():
        if isinstance(kernels, GridKernels):
            weights = kernels.weights
        elif kernels.stride(-1) == 0 and kernels.stride(-2) == 0:
            weights = kernels[:, :, :1, :1]  # one kernel per image: no need to average H x W copies
        else:
            weights = kernels
        return blend_with_identity(mean_kernel(weights.float()), mask.float().mean(dim=(1, 2, 3)))


def kernel_centres(kernels: Union[Tensor, GridKernels]) -> Tensor:
    """[B, 2, h, w] centres of mass of the field's kernels, on its coarse grid when it predicts one (the dense
    kernels are that grid resampled bilinearly, and a centre of mass is linear in the weights)."""
    weights = kernels.weights if isinstance(kernels, GridKernels) else kernels
    if weights.stride(-1) == 0 and weights.stride(-2) == 0:  # one kernel per image, expanded over the pixels
        weights = weights[..., :1, :1]
    return kernel_centroids(weights)


def mask_regulariser(mask: Tensor, weight: float) -> Tensor:
    """``weight * mean(m)``: pushes blending the blur where it is not needed toward the sharp render."""
    return weight * mask.mean()


def kernel_centre_regulariser(centroids: Tensor, weight: float) -> Tensor:
    """``weight * mean(|c|^2)`` of the kernels' centres of mass (``centroids`` [B, 2, H, W] in pixels)."""
    return weight * centroids.square().sum(dim=1).mean()


def degradation_losses(
    aux: DegradationAux, degraded: Tensor, target: Optional[Tensor], weights: DegradationLossWeights
) -> Dict[str, Tensor]:
    """Every loss term of one degraded training step: ``blur_mask_reg``, ``blur_kernel_centre`` and, given the
    ``target`` [H, W, 3] the ``degraded`` render [H, W, 3] is compared with, ``blur_deconvolved``."""
    losses: Dict[str, Tensor] = {}
    if aux.mask is not None and aux.learnt_mask and weights.mask > 0:
        losses["blur_mask_reg"] = mask_regulariser(aux.mask, weights.mask)
    if aux.kernel_centroids is not None and weights.kernel_centre > 0:
        losses["blur_kernel_centre"] = kernel_centre_regulariser(aux.kernel_centroids, weights.kernel_centre)
    if aux.kernel_mean is not None and target is not None and weights.deconvolved > 0:
        residual = (degraded - target).permute(2, 0, 1)[None]
        weighted = deconvolved_residual(residual, aux.kernel_mean, weights.deconvolved_eps)
        losses["blur_deconvolved"] = weights.deconvolved * weighted.square().mean()
    return losses
