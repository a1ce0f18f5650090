"""Grey-image operations the estimate's measurements share: conversion, smoothing, gradients, the analysis size.

Pure functions on grey images ``gray: [H, W]`` (float, values in [0, 1]).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from kornia.color import rgb_to_grayscale
from kornia.filters import gaussian_blur2d, laplacian
from kornia.geometry.transform import resize
from torch import Tensor


def to_gray(rgb: np.ndarray | Tensor) -> Tensor:
    """rgb: [H, W, 3] uint8 or float in [0, 1] (an alpha channel is dropped) -> gray: [H, W] float64."""
    x = torch.as_tensor(np.asarray(rgb))
    if x.ndim != 3 or x.shape[-1] not in (3, 4):
        raise ValueError(f"expected an [H, W, 3] RGB image, got shape {tuple(x.shape)}")
    x = x[..., :3]
    x = x.to(torch.float64) / 255.0 if x.dtype == torch.uint8 else x.to(torch.float64)
    return rgb_to_grayscale(x.permute(2, 0, 1)[None])[0, 0]


def laplacian_variance(gray: Tensor) -> float:
    """Variance of the Laplacian (3x3, reflect border) of gray [H, W]."""
    return float(laplacian(gray[None, None], 3, normalized=False).var())


def gaussian_smooth(gray: Tensor, sigma: float) -> Tensor:
    """gray [H, W] blurred by a Gaussian of ``sigma`` px (window +-3 sigma, reflected border) -> [H, W]."""
    k = 2 * int(math.ceil(3 * sigma)) + 1
    return gaussian_blur2d(gray[None, None], (k, k), (sigma, sigma), border_type="reflect", separable=True)[0, 0]


def sobel_gradient(gray: Tensor) -> Tensor:
    """Normalised Sobel gradient of gray [H, W] (replicated border) -> [2, H, W] (d/dx, d/dy).

    The same numbers as kornia's ``spatial_gradient(mode="sobel", normalized=True)``, computed as two separable
    passes of slices: a 2-output 3x3 convolution on the CPU costs several times more.
    """
    p = F.pad(gray[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]  # [H + 2, W + 2]
    dx = p[:, 2:] - p[:, :-2]  # [H + 2, W]
    dy = p[2:, :] - p[:-2, :]  # [H, W + 2]
    gx = (dx[:-2] + 2 * dx[1:-1] + dx[2:]) / 8
    gy = (dy[:, :-2] + 2 * dy[:, 1:-1] + dy[:, 2:]) / 8
    return torch.stack([gx, gy])


def scale_gradients(gray: Tensor, sigma: float) -> Tensor:
    """Sobel gradients of gray [H, W] at full resolution and after a Gaussian blur of `sigma` px, without the
    border rows the blur's reach biases -> [2 (fine, coarse), 2 (d/dx, d/dy), H - 2m, W - 2m], m = ceil(3 sigma)."""
    x = gray.to(torch.float32)  # float32: the filters cost a fraction of float64's
    m = int(math.ceil(3 * sigma))
    return torch.stack([sobel_gradient(x), sobel_gradient(gaussian_smooth(x, sigma))])[:, :, m:-m, m:-m]


def analysis_view(gray: Tensor, max_size: int) -> Tensor:
    """gray [H, W] shrunk (antialiased) so its longer side is at most `max_size` px (0: unchanged) -> [h, w].

    Blur is judged at this size: large photos are often soft at the pixel level (demosaicing, optics) while
    sharp at any size a reconstruction is trained at, and the measurements get cheaper.
    """
    H, W = gray.shape
    scale = max_size / max(H, W) if max_size > 0 else 1.0
    if scale >= 1.0:
        return gray
    size = (max(16, round(H * scale)), max(16, round(W * scale)))
    return resize(gray[None, None], size, interpolation="area")[0, 0]


__all__ = ["to_gray", "laplacian_variance", "gaussian_smooth", "sobel_gradient", "scale_gradients", "analysis_view"]
