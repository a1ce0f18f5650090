"""A residual weighted by the inverse of the blur: the loss term that lets the sharp render learn what the blur hides.

Through a blur k, the gradient that reaches the sharp render is ``k^T r`` (r: the residual of the blurred render):
the frequencies the blur attenuates reach the Gaussians attenuated twice, so detail the blur hides is learnt
slowly. Weighting the residual by ``W = (|k^|^2 + eps)^(-1/2)`` in the Fourier domain gives the render the gradient
``k^T W^2 r``, a Wiener deconvolution of the residual: every frequency the blur keeps above ``sqrt(eps)`` reaches the
Gaussians at about its full strength. The minimum (a blurred render equal to the photo) is unchanged.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from gsmsdr_ns.ops.fft_length import fast_fft_length


def mean_kernel(kernels: Tensor) -> Tensor:
    """The image's mean kernel.

    Args:
        kernels: [B, K*K, h, w] kernel weights (per pixel or per grid cell; rows sum to 1).
    Returns:
        [B, K, K], summing to 1.
    """
    B, KK = kernels.shape[:2]
    K = int(round(KK**0.5))
    return kernels.mean(dim=(-2, -1)).reshape(B, K, K)


def blend_with_identity(kernel: Tensor, mask: Tensor) -> Tensor:
    """``m * k + (1 - m) * identity``: the kernel of a blend of the blurred and the unblurred image.

    Args:
        kernel: [B, K, K]. mask: [B] blend weights.
    Returns:
        [B, K, K].
    """
    K = kernel.shape[-1]
    out = kernel * mask[:, None, None]
    out[:, K // 2, K // 2] += 1.0 - mask
    return out


def compose_kernels(first: Tensor, second: Tensor) -> Tensor:
    """The kernel of blurring by ``first``, then by ``second``: their full 2D convolution.

    Args:
        first: [B, K1, K1]. second: [B, K2, K2] (both odd sizes, centred).
    Returns:
        [B, K1 + K2 - 1, K1 + K2 - 1], centred; sums to the product of the two sums.
    """
    if first.dim() != 3 or second.dim() != 3 or first.shape[0] != second.shape[0]:
        raise ValueError(f"expected kernels [B, K1, K1] and [B, K2, K2], got {list(first.shape)}, {list(second.shape)}")
    B, K2 = first.shape[0], second.shape[-1]
    # conv2d correlates: the flipped second kernel makes it a convolution
    out = F.conv2d(F.pad(first[None], (K2 - 1,) * 4), second.flip(-2, -1)[:, None].to(first.dtype), groups=B)
    return out[0]


def deconvolved_residual(residual: Tensor, kernel: Tensor, eps: float) -> Tensor:
    """The residual weighted by the inverse of ``kernel``'s spectrum (module docstring).

    Args:
        residual: [B, C, H, W] blurred render minus photo.
        kernel: [B, K, K] the blur (centre tap at index K // 2), summing to 1; treated as a constant.
        eps: > 0; the weight is at most ``eps ** -0.5`` (at frequencies the blur removes).
    Returns:
        [B, C, H, W]: the residual convolved with the weight's impulse response (zero-padded by at least K on
        every side to a fast FFT size: no wrap-around inside the image).
    """
    if residual.dim() != 4 or kernel.dim() != 3 or kernel.shape[0] != residual.shape[0]:
        raise ValueError(f"expected residual [B, C, H, W] and kernel [B, K, K], got {list(residual.shape)}, "
                         f"{list(kernel.shape)}")  # fmt: skip
    if not eps > 0:
        raise ValueError(f"eps must be > 0, got {eps}")
    K = kernel.shape[-1]
    H, W = residual.shape[-2:]
    size = (fast_fft_length(H + 2 * K), fast_fft_length(W + 2 * K))
    padded = F.pad(residual, (K, size[1] - W - K, K, size[0] - H - K))
    taps = torch.zeros(kernel.shape[0], *size, dtype=residual.dtype, device=residual.device)
    taps[:, :K, :K] = kernel.detach().to(residual.dtype)
    taps = torch.roll(taps, shifts=(-(K // 2), -(K // 2)), dims=(-2, -1))  # the kernel's centre at the origin
    spectrum = torch.fft.rfft2(taps)
    weight = (spectrum.abs().square() + eps).rsqrt()[:, None]
    out = torch.fft.irfft2(torch.fft.rfft2(padded) * weight, s=size)
    return out[..., K : K + H, K : K + W]
