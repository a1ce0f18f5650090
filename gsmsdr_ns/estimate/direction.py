"""Along which orientations, and where, an image lost fine detail: the detail tensor (fine-scale gradient tensor
whitened by the coarse-scale one), its coherence and its spread over tiles, and the anisotropy of the spectrum's
fall-off.

Pure functions on grey images ``gray: [H, W]`` (float, values in [0, 1]).
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np
import torch
from torch import Tensor

from .image_ops import scale_gradients


def _structure_tensor(grad: Tensor) -> np.ndarray:
    """grad: [2, H, W] (d/dx, d/dy) -> [2, 2] mean outer product of the gradient."""
    gx, gy = grad[0].to(torch.float64), grad[1].to(torch.float64)
    xy = float((gx * gy).mean())
    return np.array([[float((gx * gx).mean()), xy], [xy, float((gy * gy).mean())]])


def inverse_sqrt(matrix: np.ndarray) -> Optional[np.ndarray]:
    """matrix^-1/2 of a symmetric matrix [2, 2]; None unless it is finite and positive definite (its smallest
    eigenvalue above 1e-12 of its largest)."""
    values, vectors = np.linalg.eigh(matrix)
    if not np.all(np.isfinite(values)) or values.min() <= 1e-12 * max(values.max(), 1e-300):
        return None
    return vectors @ np.diag(values**-0.5) @ vectors.T


def detail_tensor(gray: Tensor, sigma: float = 2.0) -> np.ndarray:
    """Fine detail per orientation, relative to the coarse structure. gray: [H, W] -> [2, 2].

    The structure tensor J_f of the image's gradient, whitened by J_c, that of the image blurred by `sigma`:
    J_c^-1/2 J_f J_c^-1/2. The view's content shapes both tensors alike, so what is left is how much detail
    each orientation lost: a blur of every orientation alike (defocus) scales the tensor, a blur along one
    direction (motion) shrinks it along that direction only. NaN [2, 2] for a flat image.
    """
    return _detail_tensor(scale_gradients(gray, sigma))


def _detail_tensor(grads: Tensor) -> np.ndarray:
    """:func:`detail_tensor` from ``grads`` [2, 2, h, w] of :func:`scale_gradients`."""
    whiten = inverse_sqrt(_structure_tensor(grads[1]))
    if whiten is None:
        return np.full((2, 2), np.nan)
    return whiten @ _structure_tensor(grads[0]) @ whiten


def tile_detail_coherence(gray: Tensor, sigma: float = 2.0, tiles: int = 4) -> float:
    """How consistently the tiles of gray [H, W] lost fine detail along one orientation (no reference needed).

    Per tile of a ``tiles`` x ``tiles`` grid, the detail tensor (:func:`detail_tensor` of the tile) gives a
    double-angle vector: length log(larger / smaller eigenvalue), angle twice the orientation that kept the least
    detail. Content orients each tile's detail its own way, so those vectors point anywhere and mostly cancel; a
    camera shake takes detail from every tile along (nearly) the same direction. -> |mean vector| over the tiles
    with structure (0: none aligned; NaN: fewer than 4 such tiles).
    """
    return _tile_detail_coherence(scale_gradients(gray, sigma), tiles)


def _tile_detail_coherence(grads: Tensor, tiles: int = 4) -> float:
    """:func:`tile_detail_coherence` from ``grads`` [2, 2, h, w] of :func:`scale_gradients`."""
    h, w = grads.shape[-2:]
    cells = [grads[..., i * h // tiles : (i + 1) * h // tiles, j * w // tiles : (j + 1) * w // tiles]
             for i in range(tiles) for j in range(tiles)]  # fmt: skip
    strength = np.array([np.trace(_structure_tensor(cell[1])) for cell in cells])  # coarse gradient energy
    vectors = []
    for cell, s in zip(cells, strength):
        if s < 1e-3 * strength.max():  # a flat tile says nothing about direction
            continue
        tensor = _detail_tensor(cell)
        if not np.all(np.isfinite(tensor)):
            continue
        values, vecs = np.linalg.eigh(tensor)
        if values[0] <= 0:
            continue
        angle = math.atan2(vecs[1, 0], vecs[0, 0])  # the orientation that kept the least detail
        vectors.append(math.log(values[1] / values[0]) * complex(math.cos(2 * angle), math.sin(2 * angle)))
    return abs(sum(vectors) / len(vectors)) if len(vectors) >= 4 else float("nan")


def tile_detail_spread(gray: Tensor, sigma: float = 1.0, tiles: int = 10) -> float:
    """How unevenly the fine detail of gray [H, W] is spread over its tiles (no reference needed).

    Per tile of a ``tiles`` x ``tiles`` grid with structure, the mean log eigenvalue of its detail tensor
    (:func:`detail_tensor` of the tile at scale `sigma`): how much fine detail the tile holds for its coarse
    structure. -> the spread (90th minus 10th percentile) over the tiles; NaN with fewer than 4 such tiles.
    Content alone spreads it (fine texture here, smooth shading there); a blur of the whole view (a shake, a lens
    far from focus everywhere) narrows it, as every tile loses its detail, while a lens focused on one depth keeps
    the tiles at that depth detailed and blurs the others: the spread stays as wide as a sharp view's, or widens.
    """
    return _tile_detail_spread(scale_gradients(gray, sigma), tiles)


def _tile_detail_spread(grads: Tensor, tiles: int = 10) -> float:
    """:func:`tile_detail_spread` from ``grads`` [2, 2, h, w] of :func:`scale_gradients`.

    A tile's mean log eigenvalue of J_c^-1/2 J_f J_c^-1/2 is half the log of det(J_f) / det(J_c), so the tiles'
    structure tensors (means of the gradient products over each tile) are all it needs.
    """
    h, w = grads.shape[-2:]
    g = grads.to(torch.float64)
    products = torch.stack(
        [g[:, 0] * g[:, 0], g[:, 1] * g[:, 1], g[:, 0] * g[:, 1]], dim=1
    )  # [2, 3 (xx, yy, xy), h, w]
    rows = [i * h // tiles for i in range(tiles + 1)]
    cols = [j * w // tiles for j in range(tiles + 1)]
    bands = torch.stack([products[..., rows[i] : rows[i + 1], :].sum(-2) for i in range(tiles)], dim=-2)
    sums = torch.stack([bands[..., cols[j] : cols[j + 1]].sum(-1) for j in range(tiles)], dim=-1)  # [2, 3, t, t]
    heights = torch.tensor(np.diff(rows), dtype=torch.float64)
    widths = torch.tensor(np.diff(cols), dtype=torch.float64)
    (fxx, fyy, fxy), (cxx, cyy, cxy) = (sums / torch.outer(heights, widths)).flatten(2).numpy()  # [tiles^2] each
    strength = cxx + cyy  # coarse gradient energy
    half_gap = np.hypot((cxx - cyy) / 2, cxy)
    coarse_max, coarse_min = strength / 2 + half_gap, strength / 2 - half_gap
    det_fine, det_coarse = fxx * fyy - fxy**2, cxx * cyy - cxy**2
    usable = (
        (strength >= 1e-2 * strength.max())  # a flat tile has no detail to lose
        & (coarse_min > 1e-12 * np.maximum(coarse_max, 1e-300))  # the coarse tensor can be whitened
        & (det_fine > 0)
    )
    if usable.sum() < 4:
        return float("nan")
    detail = 0.5 * np.log(det_fine[usable] / det_coarse[usable])
    return float(np.percentile(detail, 90) - np.percentile(detail, 10))


SPECTRUM_BANDS = ((0.04, 0.1), (0.1, 0.2), (0.2, 0.3), (0.3, 0.45))
"""Radial frequency bands (cycles per px) of :func:`spectral_anisotropy`: the first is the reference, the others
are where a blur of a few px takes its share."""


def spectral_anisotropy(gray: Tensor, bins: int = 12) -> float:
    """How much more the image's fine detail fell off along one orientation than along the others. gray: [H, W].

    The power spectrum of the windowed image (Hann), averaged per orientation bin over [0, pi) and per radial band
    (:data:`SPECTRUM_BANDS`): the log power of each higher band over the lowest one is the image's fall-off per
    orientation, which view content sets alike for every band (edges fall off as 1/f^2 whatever their
    orientation) while a blur steepens it where it acts. -> the largest, over the higher bands, amplitude of the
    fall-off's cos(2 theta) component (0 for a blur of every orientation alike).
    """
    x = gray.to(torch.float64)
    H, W = x.shape
    hann = [torch.hann_window(n, periodic=False, dtype=x.dtype) for n in (H, W)]
    window = torch.outer(hann[0], hann[1])
    power = torch.fft.rfft2((x - x.mean()) * window).abs().square()  # [H, W // 2 + 1]
    fy = torch.fft.fftfreq(H, dtype=x.dtype)[:, None]
    fx = torch.fft.rfftfreq(W, dtype=x.dtype)[None, :]
    radius = torch.hypot(fx, fy)
    angle = torch.atan2(fy, fx).remainder(math.pi)
    which = torch.clamp((angle / math.pi * bins).long(), max=bins - 1)
    logs = []
    for lo, hi in SPECTRUM_BANDS:
        band = (radius >= lo) & (radius < hi)
        total = torch.bincount(which[band], power[band], minlength=bins)
        count = torch.bincount(which[band], minlength=bins).clamp(min=1)
        logs.append(torch.log(total / count + 1e-20).numpy())
    theta = (np.arange(bins) + 0.5) * math.pi / bins
    fit = np.linalg.pinv(np.stack([np.ones(bins), np.cos(2 * theta), np.sin(2 * theta)], 1))  # [3, bins]
    return float(max(math.hypot(*(fit @ (band - logs[0]))[1:]) for band in logs[1:]))


__all__ = [
    "inverse_sqrt",
    "detail_tensor",
    "tile_detail_coherence",
    "tile_detail_spread",
    "SPECTRUM_BANDS",
    "spectral_anisotropy",
]
