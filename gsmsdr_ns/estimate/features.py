"""Per-image measurements behind the degradation estimate: sharpness (Laplacian variance, edge steepness, per
edge orientation, step-edge width) and the grid periodicity an upsampled image carries.

Pure functions on grey images ``gray: [H, W]`` (float, values in [0, 1]); none of them knows about the other
images of a set (the set-relative decisions live in :mod:`gsmsdr_ns.estimate.classify`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
from kornia.color import rgb_to_grayscale
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d, laplacian
from kornia.geometry.transform import resize
from torch import Tensor

MIXRES_GROUPS = (1, 2, 3, 4)
"""Resolution-loss factors of the project's mixed-resolution groups (``MixresConfig.factors``)."""


@dataclass
class ImageFeatures:
    """Measurements of one image (no decision yet)."""

    width: int
    height: int
    laplacian_variance: float
    """Variance of the 3x3 Laplacian of the grey image: large for fine detail, small after any blur."""
    edge_ratio: float
    """Median steepness of the strongest edges (:func:`edge_sharpness`): about 2.5 for step edges, towards 1 when
    blurred; independent of edge contrast and of how many edges the view shows."""
    edge_ratio_by_angle: np.ndarray
    """[bins] the same per orientation of the edge normal over [0, pi) (NaN: no edges in that bin)."""
    edge_width: float
    """Median width in px of the image's isolated step edges (:func:`edge_width`): about 1.5-2 on a sharp image,
    the blur's extent across the edge when blurred; NaN when the image has too few isolated step edges."""
    soft_edge_width: float
    """The same at the 90th percentile (the image's softest step edges): a blur of part of the view (a lens
    focused on one depth) widens these while the sharpest edges stay sharp."""
    sharpest_region_width: float
    """Median step-edge width of the image's sharpest region (:func:`sharpest_region_width`): about a sharp
    view's edge width when part of the view is in focus; NaN with too few step edges."""
    detail_tensor: np.ndarray
    """[2, 2] the fine-scale gradient structure tensor whitened by the coarse-scale one (:func:`detail_tensor`):
    how much fine detail each orientation holds for its coarse structure; NaN for a flat image."""
    tile_coherence: float
    """How consistently the image's tiles lost fine detail along one orientation (:func:`tile_detail_coherence`):
    large under camera shake, small for defocus and for sharp views whatever their content; NaN: too flat."""
    spectral_anisotropy: float
    """Largest cos(2 theta) amplitude of the spectrum's fall-off over orientations (:func:`spectral_anisotropy`)."""
    grid_scores: dict[int, float]
    """Per factor f in 2..4: periodicity of the grey image's second (third) differences at the knot spacing of an
    upsampling from 1/f of the size (:func:`grid_scores`); about 1 for images that were not upsampled."""


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
    tensors = []
    for i in range(tiles):
        for j in range(tiles):
            cell = grads[..., i * h // tiles : (i + 1) * h // tiles, j * w // tiles : (j + 1) * w // tiles]
            tensors.append((_structure_tensor(cell[0]), _structure_tensor(cell[1])))
    strength = np.array([np.trace(c) for _, c in tensors])
    vectors = []
    for (fine, coarse), s in zip(tensors, strength):
        whiten = inverse_sqrt(coarse)
        if whiten is None or s < 1e-3 * strength.max():  # a flat tile says nothing about direction
            continue
        values, vecs = np.linalg.eigh(whiten @ fine @ whiten)
        if values[0] <= 0:
            continue
        angle = math.atan2(vecs[1, 0], vecs[0, 0])  # the orientation that kept the least detail
        vectors.append(math.log(values[1] / values[0]) * complex(math.cos(2 * angle), math.sin(2 * angle)))
    return abs(sum(vectors) / len(vectors)) if len(vectors) >= 4 else float("nan")


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
    x = gray.to(torch.float32)
    H, W = x.shape
    margin = reach + 1  # every profile stays inside the image
    if H <= 2 * margin or W <= 2 * margin:
        return torch.zeros(0), torch.zeros(0), torch.zeros(0)
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
    return xs[step], ys[step], rise[step] / peak[step]


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
    medians = [float(width[cell == k].median()) for k in range(regions * regions) if int((cell == k).sum()) >= min_edges]
    return min(medians) if len(medians) >= 2 else float("nan")


def _line_periodicity(profile: Tensor, freq: float) -> float:
    """Power of profile [L] at `freq` cycles per sample, over its mean power per frequency (noise: about 1)."""
    p = profile - profile.mean()
    total = float((p**2).sum())
    if total <= 0:
        return 0.0
    x = torch.arange(len(p), dtype=p.dtype)
    phase = 2 * math.pi * freq * x
    re, im = float((p * torch.cos(phase)).sum()), float((p * torch.sin(phase)).sum())
    return (re * re + im * im) / total


def grid_scores(gray: Tensor, factors: tuple[int, ...] = (2, 3, 4)) -> dict[int, float]:
    """Periodicity of |second| and |third differences| at the knot spacing of an upsampling by f, per f in `factors`.

    An image interpolated from a low-resolution grid (bilinear, bicubic) bends only at (or changes its curvature
    pattern at) the low-resolution samples, so the column (row) profile of its |d2/dx2| (|d2/dy2|) repeats every
    W / w_low (H / h_low) pixels. The low size may have been rounded either way, so both roundings are tried.
    -> {f: min over the two axes of the best score}; an image without such a grid scores about 1. A grid every
    4 px also repeats every 2 px (it scores at f = 2 as well); a 2 px grid does not score at f = 4.
    """
    H, W = gray.shape
    # Second differences vanish inside a bilinear segment; with f = 2 every output pixel sits at the same
    # distance from a knot, and only the third differences (zero between the two pixels of a segment) show it.
    profiles = {
        "x": [torch.diff(gray, n, dim=1).abs().mean(0) for n in (2, 3)],  # [W - n]
        "y": [torch.diff(gray, n, dim=0).abs().mean(1) for n in (2, 3)],  # [H - n]
    }
    scores = {}
    for f in factors:
        axis_scores = []
        for axis, size in (("x", W), ("y", H)):
            lows = {max(1, math.floor(size / f)), max(1, math.ceil(size / f))}
            axis_scores.append(max(_line_periodicity(p, low / size) for low in lows for p in profiles[axis]))
        scores[f] = min(axis_scores)
    return scores


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


def image_features(rgb: np.ndarray | Tensor, coarse_sigma: float = 2.0, max_size: int = 1024) -> ImageFeatures:
    """All measurements of one image. rgb: [H, W, 3] uint8 or float in [0, 1].

    The upsampling grid is looked for at full resolution, everything else on :func:`analysis_view`.
    """
    full = to_gray(rgb)
    H, W = full.shape
    if H < 16 or W < 16:
        raise ValueError(f"image of {W}x{H} px is too small to estimate its degradation (need >= 16x16)")
    gray = analysis_view(full, max_size)
    grads = scale_gradients(gray, coarse_sigma)  # shared by the edge steepness and the detail tensor
    edge = _edge_sharpness(grads)
    xs, ys, widths = step_edges(gray)
    width = _width_quantiles(widths)
    return ImageFeatures(
        width=W,
        height=H,
        laplacian_variance=laplacian_variance(gray),
        edge_ratio=edge[0],
        edge_ratio_by_angle=edge[1],
        edge_width=width[0],
        soft_edge_width=width[1],
        sharpest_region_width=sharpest_region_width(xs, ys, widths, tuple(gray.shape)),
        detail_tensor=_detail_tensor(grads),
        tile_coherence=_tile_detail_coherence(grads),
        spectral_anisotropy=spectral_anisotropy(gray),
        grid_scores=grid_scores(full),
    )


__all__ = [
    "MIXRES_GROUPS",
    "ImageFeatures",
    "to_gray",
    "laplacian_variance",
    "gaussian_smooth",
    "sobel_gradient",
    "grid_scores",
    "edge_sharpness",
    "edge_width",
    "step_edges",
    "sharpest_region_width",
    "detail_tensor",
    "tile_detail_coherence",
    "spectral_anisotropy",
    "SPECTRUM_BANDS",
    "inverse_sqrt",
    "scale_gradients",
    "analysis_view",
    "image_features",
]
