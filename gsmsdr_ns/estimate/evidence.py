"""The evidence of the degradation estimate: every image of a set measured (:func:`~.features.image_features`) and
then compared with the set's references -> :class:`SetEvidence`, the numbers :mod:`.classify` decides on.

Sharpness means little on its own (a view of smooth walls is less detailed than a view of foliage, sharp or not),
so the numbers are relative to the SET: its reference images are the ones with the steepest edges (for sharpness
and the detail tensor), the ones with the narrowest step edges (for edge widths), and the images sharp by the
threshold (for the detail spread over tiles). The 13 arrays the fitted ensembles read are
:data:`~.ensemble.KIND_FEATURES`; the settings they depend on are :data:`~.config.EVIDENCE_SETTINGS`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
from torch import Tensor

from .config import EstimateConfig
from .direction import inverse_sqrt
from .ensemble import KIND_FEATURES
from .features import MIXRES_GROUPS, ImageFeatures, image_features


def measure_images(
    images: Sequence[np.ndarray | Tensor], config: Optional[EstimateConfig] = None
) -> list[ImageFeatures]:
    """:func:`~.features.image_features` of every image, at the config's analysis size and coarse scale.

    images: each [H, W, 3] (or [H, W, 4]) uint8, or float in [0, 1]; sizes may differ. -> one per image, in order.
    """
    cfg = config or EstimateConfig()
    return [image_features(img, coarse_sigma=cfg.coarse_sigma, max_size=cfg.max_size) for img in images]


def _reference_count(n: int, cfg: EstimateConfig) -> int:
    """How many of ``n`` images serve as the set's reference: ``reference_fraction`` of them, at least
    ``min_reference``, at most ``n``."""
    return min(n, max(cfg.min_reference, int(math.ceil(cfg.reference_fraction * n))))


def _combined(edge: float, lap: float) -> float:
    # Geometric mean: the Laplacian reacts strongly to any blur, the edge steepness hardly depends on content.
    return math.sqrt(max(edge, 0.0) * max(lap, 0.0))


def _reference(values: np.ndarray, idx: np.ndarray) -> float:
    # The median: one blurred image among the references (few sharp photos in a shaky capture) does not move it.
    return float(np.median(values[idx])) if len(idx) else float("nan")


def _column_nanmedian(values: np.ndarray) -> np.ndarray:
    """Median of values [n, bins] over n, NaN ignored -> [bins]; NaN where a bin has no value (an orientation with
    no measured edge in any of the images is expected, so numpy's all-NaN warning is not passed on)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(values, axis=0)


def _orientation_spread(by_angle: np.ndarray, baseline: np.ndarray) -> float:
    """Spread (max - min) over edge orientations of by_angle [bins] relative to baseline [bins], both edge ratios
    (1: flat ramp): 0 when every orientation lost the same share of its steepness, as under defocus."""
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = (by_angle - 1.0) / np.maximum(baseline - 1.0, 1e-6)
    rel = rel[np.isfinite(rel)]
    return float(np.ptp(rel)) if rel.size >= 2 else 0.0


def _width_evidence(feats: Sequence[ImageFeatures], cfg: EstimateConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step-edge widths against the set's narrowest-edged images -> (soft width [n], width spread [n], sharpest
    region [n]); NaN unknown.

    soft width: the image's 90th-percentile width over the references'. width spread: the image's 90th
    percentile over its median, over the same ratio of the references. A blur of the whole view widens every edge
    towards the blur's own width, so defocus narrows the spread (below 1); motion widens only the edges across
    it (about 1); a blur of part of the view widens the soft tail only (above 1). The references are the images
    with the narrowest median edge (as many as the sharpness references): edge steepness picks views for their
    content as much as for their focus, edge width much less.
    """
    median = np.array([f.edge_width for f in feats])
    soft = np.array([f.soft_edge_width for f in feats])
    known = np.isfinite(median) & np.isfinite(soft)
    if known.sum() < cfg.min_set_size:
        return np.full(len(feats), np.nan), np.full(len(feats), np.nan), np.full(len(feats), np.nan)
    ref = np.argsort(np.where(known, median, np.inf), kind="stable")[: _reference_count(int(known.sum()), cfg)]
    soft_width = soft / max(float(np.median(soft[ref])), 1e-6)
    spread = (soft / median) / max(float(np.median(soft[ref] / median[ref])), 1e-6)
    region = np.array([f.sharpest_region_width for f in feats]) / max(float(np.median(median[ref])), 1e-6)
    return np.where(known, soft_width, np.nan), np.where(known, spread, np.nan), region


def _detail_isotropy(feats: Sequence[ImageFeatures], ref: np.ndarray) -> np.ndarray:
    """Detail tensors relative to the reference images' -> isotropy [n], NaN where undefined.

    Each image's tensor is whitened by the element-wise median of the references' tensors; its eigenvalues are
    then the shares of fine detail kept along its two principal orientations. isotropy = log(larger) /
    log(smaller): 1 when both lost the same share, 0 when one lost none.
    """
    tensors = np.stack([f.detail_tensor for f in feats])  # [n, 2, 2]
    base = np.median(tensors[ref], axis=0)
    n = len(feats)
    whiten = inverse_sqrt(base) if np.all(np.isfinite(base)) else None
    if whiten is None:
        return np.full(n, np.nan)
    log_eig = np.full((n, 2), np.nan)
    for i, t in enumerate(tensors):
        if np.all(np.isfinite(t)):
            log_eig[i] = np.log(np.maximum(np.linalg.eigvalsh(whiten @ t @ whiten), 1e-12))  # ascending
    with np.errstate(invalid="ignore", divide="ignore"):
        # 0 when the least-blurred orientation kept all its detail (or more, by content); NaN when none lost any
        return np.where(log_eig[:, 0] < 0, np.maximum(log_eig[:, 1] / log_eig[:, 0], 0.0), np.nan)


def _directional_loss(feat: ImageFeatures) -> float:
    """Geometric mean of the tile coherence and the spectral anisotropy of one image (NaN when either is)."""
    return math.sqrt(max(feat.tile_coherence, 0.0) * max(feat.spectral_anisotropy, 0.0))


def _relative_detail_spread(feats: Sequence[ImageFeatures], sharp_idx: list[int]) -> np.ndarray:
    """[n] each image's tile detail spread over the median of the set's sharp images' (NaN without any)."""
    spread = np.array([f.tile_detail_spread for f in feats])
    base = spread[sharp_idx] if sharp_idx else np.zeros(0)
    base = base[np.isfinite(base)]
    if not len(base) or float(np.median(base)) <= 0:
        return np.full(len(feats), np.nan)
    return spread / float(np.median(base))


def _grid_factor(feats: Sequence[ImageFeatures], ref: np.ndarray, cfg: EstimateConfig) -> list[tuple[int, float]]:
    """(factor snapped to MIXRES_GROUPS, score) per image; factor 1 without a grid.

    A grid counts when it is strong and much stronger than in the reference images (each image is compared with
    the references other than itself): a periodic pattern every photo of the camera has is not a resolution loss.
    """
    factors = [f for f in MIXRES_GROUPS if f > 1]
    ref_list = ref.tolist()
    out = []
    for i, ft in enumerate(feats):
        others = [j for j in ref_list if j != i]
        passing = []
        for f in factors:
            base = float(np.median([feats[j].grid_scores[f] for j in others])) if others else 1.0
            score = ft.grid_scores[f]
            if score >= cfg.grid_threshold and score >= cfg.grid_reference_ratio * max(base, 1.0):
                passing.append((f, score))
        if passing:
            # the largest: a grid every 4 px also repeats every 2 px (its harmonic), never the other way round
            out.append(max(passing))
        else:
            out.append((1, max(ft.grid_scores[f] for f in factors)))
    return out


@dataclass
class SetEvidence:
    """Every number the decision reads, for a set of n images: arrays [n] (NaN: not measured) and the set's own
    facts. The names of the 13 arrays the ensembles read are :data:`~.ensemble.KIND_FEATURES`."""

    sharpness: np.ndarray
    """Combined sharpness relative to the reference images."""
    edge_sharpness: np.ndarray
    """Edge steepness above a flat ramp relative to the reference images."""
    laplacian_variance: np.ndarray
    """Variance of the Laplacian relative to the reference images."""
    anisotropy: np.ndarray
    """Orientation spread of the relative edge steepness."""
    soft_width: np.ndarray
    """Softest step edges' width relative to the narrowest-edged images."""
    width_spread: np.ndarray
    """Spread of the step-edge widths relative to those images'."""
    sharpest_region: np.ndarray
    """Median step-edge width of the sharpest region relative to those images."""
    isotropy: np.ndarray
    """Detail isotropy relative to the reference images' detail tensor."""
    directional_loss: np.ndarray
    """Directional loss of detail, from the image alone."""
    detail_spread: np.ndarray
    """Tile detail spread relative to the set's sharp images."""
    edge_rise: np.ndarray
    """10-90 % rise over width of the blurred step edges."""
    tile_coherence: np.ndarray
    """Tiles' coherence of detail loss (one part of the directional loss)."""
    spectral_anisotropy: np.ndarray
    """Anisotropy of the spectrum's fall-off (the other part)."""
    size: np.ndarray
    """Longer side of each image in px."""
    grid: list
    """(mixres factor snapped to the groups, periodicity score) per image."""
    reference: np.ndarray
    """Indices of the reference images."""
    soft: np.ndarray
    """[n] bool: softest step edges much wider than the narrowest-edged images'."""
    trusted_reference: bool
    """The reference images are sharp enough (and the set large enough) to call any image sharp."""

    def columns(self) -> dict:
        """The arrays the ensembles may read, by name."""
        return {name: getattr(self, name) for name in KIND_FEATURES}


def set_evidence(feats: Sequence[ImageFeatures], config: Optional[EstimateConfig] = None) -> SetEvidence:
    """The evidence of a set from its images' measurements (:func:`measure_images`) -> its :class:`SetEvidence`."""
    cfg = config or EstimateConfig()
    n = len(feats)
    if n == 0:
        raise ValueError("estimate_degradations needs at least one image")
    edge = np.array([f.edge_ratio for f in feats])
    lap = np.array([f.laplacian_variance for f in feats])
    ref = np.argsort(-edge, kind="stable")[: _reference_count(n, cfg)]
    ref_edge = _reference(edge, ref)
    edge_rel = (edge - 1.0) / max(ref_edge - 1.0, 1e-6)
    lap_rel = lap / max(_reference(lap, ref), 1e-12)
    sharp = np.array([_combined(e, v) for e, v in zip(edge_rel, lap_rel)])
    sharp = sharp / max(_reference(sharp, ref), 1e-12)
    soft_width, width_spread, region_width = _width_evidence(feats, cfg)
    with np.errstate(invalid="ignore"):
        soft = soft_width > cfg.soft_width_ratio  # NaN: no evidence either way
    by_angle = np.stack([f.edge_ratio_by_angle for f in feats])  # [n, bins]
    ref_angle = _column_nanmedian(by_angle[ref])
    sharp_idx = [i for i in range(n) if sharp[i] >= cfg.sharp_threshold and not soft[i]]
    return SetEvidence(
        sharpness=sharp,
        edge_sharpness=edge_rel,
        laplacian_variance=lap_rel,
        anisotropy=np.array([_orientation_spread(b, ref_angle) for b in by_angle]),
        soft_width=soft_width,
        width_spread=width_spread,
        sharpest_region=region_width,
        isotropy=_detail_isotropy(feats, ref),
        directional_loss=np.array([_directional_loss(f) for f in feats]),
        detail_spread=_relative_detail_spread(feats, sharp_idx),
        edge_rise=np.array([f.edge_rise_ratio for f in feats]),
        tile_coherence=np.array([f.tile_coherence for f in feats]),
        spectral_anisotropy=np.array([f.spectral_anisotropy for f in feats]),
        size=np.array([max(f.width, f.height) for f in feats]),
        grid=_grid_factor(feats, ref, cfg),
        reference=ref,
        soft=soft,
        trusted_reference=bool(ref_edge >= cfg.min_reference_edge_ratio and n >= cfg.min_set_size),
    )


__all__ = ["SetEvidence", "set_evidence", "measure_images"]
