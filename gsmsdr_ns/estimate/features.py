"""Per-image measurements behind the degradation estimate, gathered by :func:`image_features` into
:class:`ImageFeatures`: sharpness and the blur's profile across edges (:mod:`.edges`, Laplacian variance), the
orientations and the places that lost detail (:mod:`.direction`) and the grid an upsampled image carries
(:mod:`.grid`).

None of them knows about the other images of a set (the set-relative evidence is :mod:`.evidence`, the decision
:mod:`.classify`). The measurement functions are re-exported here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from torch import Tensor

from .direction import (
    SPECTRUM_BANDS,
    _detail_tensor,
    _tile_detail_coherence,
    _tile_detail_spread,
    detail_tensor,
    inverse_sqrt,
    spectral_anisotropy,
    tile_detail_coherence,
    tile_detail_spread,
)
from .edges import (
    _edge_sharpness,
    _width_quantiles,
    edge_rise_ratio,
    edge_sharpness,
    edge_width,
    sharpest_region_width,
    step_edges,
)
from .grid import grid_scores
from .image_ops import analysis_view, gaussian_smooth, laplacian_variance, scale_gradients, sobel_gradient, to_gray

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
    tile_detail_spread: float
    """How unevenly fine detail is spread over the image's 10x10 tiles (:func:`tile_detail_spread`): a blur of the
    whole view narrows it, a lens focused on one depth does not; NaN: too flat."""
    edge_rise_ratio: float
    """10-90 % rise over width of the blurred step edges (:func:`edge_rise_ratio`): about 0.8-1.1 for a disk,
    more for a shake that dwells at one place; NaN with too few blurred step edges."""
    grid_scores: dict[int, float]
    """Per factor f in 2..4: periodicity of the grey image's second (third) differences at the knot spacing of an
    upsampling from 1/f of the size (:func:`grid_scores`); about 1 for images that were not upsampled."""


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
        tile_detail_spread=_tile_detail_spread(scale_gradients(gray, 1.0)),
        edge_rise_ratio=edge_rise_ratio(gray),
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
    "tile_detail_spread",
    "edge_rise_ratio",
    "spectral_anisotropy",
    "SPECTRUM_BANDS",
    "inverse_sqrt",
    "scale_gradients",
    "analysis_view",
    "image_features",
]
