"""How sharp an image's edges are: steepness against a blurred copy (overall and per orientation), the width of
its isolated step edges, and the width in its sharpest region.

Pure functions on grey images ``gray: [H, W]`` (float, values in [0, 1]).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .image_ops import gaussian_smooth, scale_gradients, sobel_gradient


def edge_sharpness(
    gray: Tensor, sigma: float = 2.0, top_fraction: float = 0.05, bins: int = 8
) -> tuple[float, np.ndarray]:
    """How steep the image's strongest edges are, overall and per edge orientation. gray: [H, W].

    At the pixels with the strongest gradients of the image blurred by `sigma` (the top `top_fraction`: edges
    and texture, wherever they are), the ratio of the full-resolution gradient magnitude to the blurred one does
    not depend on the edge's contrast: about 2.5 for a step edge, falling towards 1 as the edge gets blurred.
    -> (median ratio, [bins] median ratio of the edges whose normal lies in each orientation bin over [0, pi);
    NaN for a bin without edges). Motion blur lowers the ratio only for edges across its direction.
    """
    return _edge_sharpness(scale_gradients(gray, sigma), top_fraction, bins)


def _edge_sharpness(grads: Tensor, top_fraction: float = 0.05, bins: int = 8) -> tuple[float, np.ndarray]:
    """:func:`edge_sharpness` from ``grads`` [2, 2, h, w] of :func:`scale_gradients`."""
    g_fine, g_coarse = grads[0], grads[1]
    # hypot, not norm(dim=0): the vector norm over the leading axis of these slices is many times slower
    mag_coarse = torch.hypot(g_coarse[0], g_coarse[1]).flatten()
    mag_fine = torch.hypot(g_fine[0], g_fine[1]).flatten()
    n = max(16, int(top_fraction * mag_coarse.numel()))
    strong = torch.topk(mag_coarse, min(n, mag_coarse.numel())).indices
    if float(mag_coarse[strong].min()) <= 0:
        strong = strong[mag_coarse[strong] > 0]
    if strong.numel() == 0:
        return 0.0, np.full(bins, np.nan)
    ratio = (mag_fine[strong] / mag_coarse[strong]).numpy()
    angle = torch.atan2(g_coarse[1].flatten()[strong], g_coarse[0].flatten()[strong]).numpy() % math.pi
    which = np.minimum((angle / math.pi * bins).astype(int), bins - 1)
    per_bin = np.array([np.median(ratio[which == b]) if (which == b).sum() >= 8 else np.nan for b in range(bins)])
    return float(np.median(ratio)), per_bin


def step_edges(
    gray: Tensor, reach: int = 6, top_fraction: float = 0.05, sigma: float = 1.0
) -> tuple[Tensor, Tensor, Tensor]:
    """The isolated step edges of gray [H, W] and their widths in px -> (x [m], y [m], width [m]).

    At the pixels with the strongest gradients (found, with their normal, on the image smoothed by `sigma` px;
    the top `top_fraction`), the profile across the edge is sampled every px over +-`reach` px. A profile counts
    as a step when it rises by at least 0.8 of its total variation and is flat at both ends (lines, textures and
    edges with a neighbour within `reach` do not). Its width is the rise over the steepest 1 px slope: about 1.5
    for a sharp step, the width of the blur's line spread function when blurred (edges blurred much wider than
    `reach` px are not flat at the ends and do not count).
    """
    return _step_profiles(gray, reach, top_fraction, sigma)[:3]


def _step_profiles(
    gray: Tensor, reach: int, top_fraction: float, sigma: float
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`step_edges` -> (x [m], y [m], width [m], extent [m]); extent: how many px of the profile lie between
    10 % and 90 % of its rise."""
    x = gray.to(torch.float32)
    H, W = x.shape
    margin = reach + 1  # every profile stays inside the image
    if H <= 2 * margin or W <= 2 * margin:
        return torch.zeros(0), torch.zeros(0), torch.zeros(0), torch.zeros(0)
    g = sobel_gradient(gaussian_smooth(x, sigma))[:, margin:-margin, margin:-margin]  # [2, H - 2 margin, W - 2 margin]
    mag = torch.hypot(g[0], g[1]).flatten()
    n = min(max(16, int(top_fraction * mag.numel())), mag.numel())
    strong = torch.topk(mag, n, sorted=False).indices  # the order does not matter: only quantiles are taken
    strong = strong[mag[strong] > 0]
    inner_w = W - 2 * margin
    ys = (strong // inner_w + margin).to(torch.float32)
    xs = (strong % inner_w + margin).to(torch.float32)
    normal = g.flatten(1)[:, strong] / mag[strong]  # [2, n] unit (x, y)
    t = torch.arange(-reach, reach + 1, dtype=torch.float32)
    px = xs[:, None] + t * normal[0][:, None]  # [n, 2 reach + 1]
    py = ys[:, None] + t * normal[1][:, None]
    grid = torch.stack([px / (W - 1) * 2 - 1, py / (H - 1) * 2 - 1], dim=-1)[None]
    profile = F.grid_sample(x[None, None], grid, mode="bilinear", align_corners=True)[0, 0]
    slope = torch.diff(profile, dim=1)  # [n, 2 reach]
    rise, peak = slope.sum(1), slope.max(1).values
    ends = torch.maximum(slope[:, :2].abs().amax(1), slope[:, -2:].abs().amax(1))
    step = (rise > 0) & (rise >= 0.8 * slope.abs().sum(1)) & (ends < 0.2 * peak)
    up = slope[step].clamp(min=0)
    share = torch.cumsum(up, dim=1) / up.sum(1, keepdim=True).clamp(min=1e-12)  # share of the rise so far
    extent = ((share < 0.9).sum(1) - (share < 0.1).sum(1)).to(torch.float32)
    return xs[step], ys[step], rise[step] / peak[step], extent


def edge_rise_ratio(
    gray: Tensor, min_width: float = 2.0, min_edges: int = 8, reach: int = 8, top_fraction: float = 0.08
) -> float:
    """The shape of the blur across gray [H, W]'s blurred step edges: median, over the isolated step edges
    (:func:`step_edges`, here within +-`reach` px among the top `top_fraction` gradients) wider than `min_width`
    px, of the px between 10 % and 90 % of the rise over the edge's width (rise / steepest slope).

    A rounded or flat-topped line spread (a disk: defocus; a steady sweep) gives about 0.8-1.1; a peaked one with
    a long tail, as a shake that dwells at one place and moves briefly leaves, gives more (a Laplace-shaped spread
    about 1.6). NaN with fewer than `min_edges` such edges (a sharp image has few).
    """
    _, _, width, extent = _step_profiles(gray, reach, top_fraction, 1.0)
    wide = width > min_width
    if int(wide.sum()) < min_edges:
        return float("nan")
    return float(np.median((extent[wide] / width[wide]).numpy()))


def edge_width(
    gray: Tensor, reach: int = 6, top_fraction: float = 0.05, min_edges: int = 16, sigma: float = 1.0
) -> tuple[float, float]:
    """Width in px of the isolated step edges (:func:`step_edges`) of gray [H, W]: -> (median, 90th percentile)
    over those edges; NaN, NaN with fewer than `min_edges` steps."""
    return _width_quantiles(step_edges(gray, reach, top_fraction, sigma)[2], min_edges)


def _width_quantiles(width: Tensor, min_edges: int = 16) -> tuple[float, float]:
    if width.numel() < min_edges:
        return float("nan"), float("nan")
    return float(width.median()), float(torch.quantile(width, 0.9))


def sharpest_region_width(
    xs: Tensor, ys: Tensor, width: Tensor, size: tuple[int, int], regions: int = 3, min_edges: int = 8
) -> float:
    """Median step-edge width of the image's sharpest region: the smallest, over a ``regions`` x ``regions`` grid
    of an image of ``size`` (H, W), of the regions' median widths (:func:`step_edges` gives xs, ys, width [m]).

    A lens focused on one depth leaves some region as sharp as a sharp view; camera shake blurs every region.
    NaN unless at least two regions hold ``min_edges`` step edges.
    """
    H, W = size
    cell = (torch.clamp((ys * regions / H).long(), max=regions - 1) * regions
            + torch.clamp((xs * regions / W).long(), max=regions - 1))  # fmt: skip
    counts = torch.bincount(cell, minlength=regions * regions)
    medians = [float(width[cell == k].median()) for k in range(regions * regions) if int(counts[k]) >= min_edges]
    return min(medians) if len(medians) >= 2 else float("nan")


__all__ = ["edge_sharpness", "step_edges", "edge_width", "sharpest_region_width", "edge_rise_ratio"]
