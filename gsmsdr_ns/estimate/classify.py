"""`estimate_degradations`: label each image of a set sharp / motion / defocus / mixres / unknown, with evidence.

Sharpness means little on its own (a view of smooth walls is less detailed than a view of foliage, sharp or not),
so every decision is relative to the SET: its reference images are the ones with the steepest edges, and an
image is compared with them.

* **mixres**: an image upsampled from a lower resolution keeps the grid of its low-resolution samples
  (:func:`~gsmsdr_ns.estimate.grid.grid_scores`); a grid at factor f (much stronger than in the reference
  images, so a camera's own periodic artefacts do not count) gives mixres with f snapped to the project's groups.
* **sharp / blurred**: edge steepness and Laplacian variance relative to the reference images, combined. An
  image that passes as sharp but whose softest step edges are much wider than those of the set's narrowest-edged
  images is left unknown: a blur of only part of the view (a lens focused on one depth) leaves the strongest
  edges sharp, and so does a view whose content is simply softer.
* **sharp, confirmed by a fitted ensemble** (the default, ``sharp_from="model"``): the thresholds miss mild blur
  (a lens focused on one depth, on small images), so every image they call sharp is also judged by gradient-boosted
  trees over all the evidence below (:mod:`.ensemble`, fitted by ``tools/estimate/fit_ensembles.py`` on generated scenes and
  degraded real photos whose records hold the truth). An image it calls degraded is treated as one between sharp
  and blurred: the kind ensemble names its blur, or it stays unknown.
* **motion / defocus, by the fitted ensemble** (the default, ``kind_from="model"``): every number the rules below
  read (and the sharpness) is one input of another ensemble, fitted the same way. Its probability of motion names
  the kind of every blurred image and of every image between sharp and blurred, or leaves it unknown near 0.5.
  Each rule alone sees one trait of the blur; the ensemble weighs them together and names more kinds, with fewer
  wrong ones, on sets it was not fitted on (docs/results/estimate/results.md). With ``kind_from="rules"`` the
  rules decide in turn, as in version 5:
* **motion / defocus**: motion blur is directional, so the edges lose their steepness only across the motion;
  defocus flattens every orientation alike. The spread over orientations of the steepness (relative to the
  reference images, orientation by orientation) separates them, and the spread of the image's step-edge widths
  must agree (a defocus of the whole view narrows it; a blur of part of the view widens it, and the orientations
  then show where the blur is, not its direction). The kind of blur is left unknown when they disagree, when
  the sharp images of the set themselves spread over orientations that much (content that differs from view to
  view), or when fewer than two sharp images leave that spread unmeasured.
* **motion / defocus, second opinion**: where that rule leaves the kind unknown, the image's detail tensor
  (:func:`~gsmsdr_ns.estimate.direction.detail_tensor`, relative to the reference images') decides: defocus
  shrinks it alike along every orientation, motion blur mostly along one. It sums over the whole image instead of
  comparing orientations bin by bin (on small photos, sharp views of one scene disagree bin by bin), but it is
  trusted only when the set's other sharp images match the references' tensor closely (views of one scene), and
  the edge widths must agree with the kind as above.
* **motion / defocus, from the image alone**: where those rules leave the kind unknown, a blurred image whose
  sharpest region has step edges as narrow as the sharp images' is defocused (a lens focused on one depth; a shake
  blurs every region) unless its detail loss is directional, and otherwise the image's own directional loss
  decides (:attr:`DegradationEstimate.directional_loss`: how consistently its regions lost detail along one
  orientation, and how anisotropic its spectrum's fall-off is): above ``motion_direction`` motion, below
  ``defocus_direction`` defocus. It needs no other image, so it also names the kind in sets whose views show
  different content, and in images between sharp and blurred when it says motion. It comes after the set rules
  because a strong shake leaves measurable only the step edges along it, which are sharp: the sharpest region of
  a shaken photo can look in focus.
* **motion / defocus, from the blur's shape**: where every rule above leaves the kind unknown (curved shakes,
  views defocused everywhere), a blurred image whose fine detail is still spread over its tiles as unevenly as in
  the set's sharp images is defocused (a lens focused on one depth kept some tiles detailed; a shake takes detail
  from every tile). Otherwise the profile across its blurred step edges decides
  (:attr:`DegradationEstimate.edge_rise`): a peaked line spread with a tail (a shake that dwells at one place and
  moves briefly) is motion, a rounded one (a disk) defocus.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass
from typing import Literal, Optional, Sequence

import numpy as np
from torch import Tensor

from .direction import inverse_sqrt
from .features import MIXRES_GROUPS, ImageFeatures, image_features
from .ensemble import KIND_FEATURES, TreeEnsemble, evidence_matrix, load_degraded_model, load_kind_model, probability

LABELS = ("sharp", "motion", "defocus", "mixres", "unknown")
METHOD_VERSION = 7
"""Raised whenever the same images and config get other labels (cached estimates and benchmark runs that trained
on them are then computed again). 2: the detail-tensor second opinion on the kind of blur. 3: the kind of blur
from the image alone (region in focus, directional loss). 4: the region in focus only after the set rules. 5: the
blur's shape (detail spread over tiles, edge rise) names the kind the other rules leave unknown. 6: a fitted
ensemble over all that evidence names the kind (``kind_from="model"``). 7: a second ensemble flags degraded images
among those the thresholds call sharp (``sharp_from="model"``)."""


@dataclass
class EstimateConfig:
    """Knobs of the per-image degradation estimate (thresholds are relative to the set, see the module doc)."""

    reference_fraction: float = 0.1
    """Share of the set (at least `min_reference` images) with the steepest edges that serves as the sharp
    reference."""
    min_reference: int = 2
    """Fewest reference images."""
    min_set_size: int = 3
    """Below this many images, sharpness cannot be judged relative to the set: only an upsampling grid is
    reported, everything else is unknown."""
    sharp_threshold: float = 0.6
    """An image whose combined sharpness is at least this fraction of the reference's is sharp."""
    blurred_threshold: float = 0.45
    """Below this fraction it is blurred; in between the estimate is unknown."""
    min_reference_edge_ratio: float = 1.25
    """Edge steepness (full-resolution over blurred gradient, ~2.5 for a step edge, 1 for a flat ramp) the
    reference images must reach to be trusted as sharp; below it the whole set may be blurred and no image is
    called sharp."""
    anisotropy_threshold: float = 0.15
    """Spread over edge orientations of the relative steepness above which a blurred image is motion-blurred."""
    max_content_anisotropy: float = 0.3
    """When the sharp images, each against the others, spread over orientations by more than this (median), view
    content alone moves the measure too much and the kind of blur is left unknown."""
    grid_threshold: float = 10.0
    """Periodicity score (about 1 without a grid) from which an upsampling grid counts."""
    grid_reference_ratio: float = 5.0
    """... and how many times stronger than in the reference images it must be."""
    soft_width_ratio: float = 1.5
    """An image sharp by the measures above is left unknown when its softest step edges (90th percentile width)
    are more than this many times wider than those of the set's narrowest-edged images."""
    max_defocus_width_spread: float = 0.85
    """A blurred image is called defocused only when the spread of its step-edge widths (90th percentile over
    median, relative to the narrowest-edged images) is at most this: a defocus of the whole view narrows it."""
    max_motion_width_spread: float = 1.1
    """... and motion-blurred only when it is at most this: above it part of the view is blurred more than the
    rest (a lens focused on one depth), and the orientation spread then shows where the blur is, not its
    direction. Otherwise the kind is left unknown."""
    max_detail_spread: float = 0.07
    """The detail tensors decide a kind only when the set's sharp images other than the references differ from the
    references' tensor by at most this (median of the largest |log eigenvalue| of the relative tensor); more, and
    view content alone moves them."""
    motion_isotropy: float = 0.8
    """A blurred image whose detail isotropy (see `DegradationEstimate.isotropy`) is below this is motion-blurred
    (when the orientation rule leaves the kind unknown) ..."""
    defocus_isotropy: float = 0.87
    """... and above this, defocused; in between the kind stays unknown."""
    motion_direction: float = 0.4
    """Where both rules above leave the kind unknown, a blurred image whose directional loss (see
    `DegradationEstimate.directional_loss`, measured on the image alone) is above this is motion-blurred ..."""
    defocus_direction: float = 0.2
    """... and below this, defocused; in between the kind stays unknown."""
    focused_region_width: float = 1.15
    """A blurred image whose sharpest region's step edges are at most this many times as wide as the set's
    narrowest-edged images' is defocused (a lens focused on one depth) unless its loss of detail is directional."""
    focused_detail_spread: float = 0.84
    """Where every rule above leaves the kind of a blurred image unknown, one whose fine detail is spread over its
    tiles at least this unevenly, relative to the set's sharp images (see `DegradationEstimate.detail_spread`), is
    defocused: a lens focused on one depth kept some tiles detailed ..."""
    motion_edge_rise: float = 1.13
    """... and otherwise (every tile lost detail) the shape of the blur across its step edges decides: a 10-90 %
    rise over width (`DegradationEstimate.edge_rise`) above this (a peaked line spread with a tail: a shake that
    dwells and moves) is motion-blurred, at most this (rounded: a disk) defocused."""
    kind_from_blur_shape: bool = True
    """Apply the two rules above (off: those images stay of unknown kind)."""
    kind_from: Literal["model", "rules"] = "model"
    """What names the kind of a blurred image: "model", the fitted ensemble over the evidence of all the rules
    (:mod:`.ensemble`); "rules", the rules above in turn (version 5)."""
    kind_model: str = ""
    """The ensemble's JSON file ("": the one shipped with the package)."""
    kind_probability: float = 0.65
    """The ensemble names a kind when its probability is at least this; otherwise the kind stays unknown."""
    sharp_from: Literal["model", "rules"] = "model"
    """What confirms an image the thresholds above call sharp: "model", the fitted degraded-image ensemble over the
    same evidence (:mod:`.ensemble`; an image it flags is treated as one between sharp and blurred); "rules", the
    thresholds alone (version 6)."""
    degraded_model: str = ""
    """The degraded-image ensemble's JSON file ("": the one shipped with the package)."""
    degraded_probability: float = 0.7
    """The ensemble flags an image the thresholds call sharp when its probability of degraded is at least this."""
    degraded_min_size: int = 200
    """... and only on images whose longer side is at least this many px: the ensemble was fitted on images 200-600
    px wide, and on tiny ones it flags sharp views (a 64x48 generated scene: 3 of 10)."""
    kind_in_between: bool = True
    """An image neither sharp nor clearly blurred (sharpness between the two thresholds) gets the kind of blur the
    ensemble names (with ``kind_from="rules"``: motion when its directional loss names motion), else unknown: it
    pays for that model alone instead of both. Sharp views of soft content land here too, and are then simulated
    with one blur instead of both."""
    max_size: int = 1024
    """Blur is judged on a copy whose longer side is at most this many px (0: full resolution)."""
    coarse_sigma: float = 2.0
    """Gaussian blur (px at the analysis size) of the coarse scale that edge steepness is measured against."""


@dataclass
class DegradationEstimate:
    """The estimate for one image and the numbers it rests on."""

    label: str
    """sharp, motion, defocus, mixres or unknown (inconclusive)."""
    confidence: float
    """0 (a guess at the decision boundary) to 1 (far from it)."""
    sharpness: float
    """Combined sharpness relative to the set's reference images (1: as sharp as they are)."""
    edge_sharpness: float
    """Edge steepness above a flat ramp, relative to the reference images."""
    laplacian_variance: float
    """Variance of the Laplacian relative to the reference images."""
    anisotropy: float
    """Spread over edge orientations of the relative edge steepness (motion blur: large; defocus: small)."""
    mixres_factor: Optional[int]
    """Resolution-loss factor snapped to the mixres groups (1: full resolution); None when unknown."""
    grid_score: float
    """Periodicity score of the upsampling grid at mixres_factor (at the best factor when none is found)."""
    blurred: Optional[bool] = None
    """Whether the image is blurred (None: undecided)."""
    reference: bool = False
    """The image is one of the set's sharp reference images."""
    soft_width: Optional[float] = None
    """Width of the image's softest step edges relative to the set's narrowest-edged images (1: as narrow);
    None when the image or the set has too few isolated step edges."""
    width_spread: Optional[float] = None
    """Spread of the image's step-edge widths relative to those images' (defocus: below 1; motion: about 1; a
    blur of part of the view: above 1); None as above."""
    isotropy: Optional[float] = None
    """How alike the orientations lost their fine detail: log of the detail tensor's larger eigenvalue over log of
    its smaller, relative to the reference images' tensor (defocus: near 1; motion: lower); None for an image that
    lost none or a flat image."""

    sharpest_region: Optional[float] = None
    """Median step-edge width of the image's sharpest region relative to the set's narrowest-edged images (near 1:
    part of the view is in focus); None with too few step edges."""
    directional_loss: Optional[float] = None
    """How much more fine detail the image lost along one orientation than along the others, from the image alone:
    the geometric mean of its tiles' coherence of detail loss and of its spectrum's anisotropy of fall-off (camera
    shake: large; defocus and sharp views: small); None for a flat image."""
    detail_spread: Optional[float] = None
    """How unevenly fine detail is spread over the image's tiles, relative to the set's sharp images (1: as unevenly;
    below: every tile lost detail, as under a shake or a lens far from focus everywhere); None when unmeasured or
    the set has no sharp image."""
    edge_rise: Optional[float] = None
    """10-90 % rise over width of the image's blurred step edges (a disk, i.e. defocus: about 0.8-1.1; a shake that
    dwells at one place and moves briefly: more); None with too few blurred step edges."""
    motion_probability: Optional[float] = None
    """The fitted ensemble's probability that a blurred image is motion- rather than defocus-blurred; None for
    images it did not judge (sharp, mixres, a set too small, or ``kind_from="rules"``)."""
    degraded_probability: Optional[float] = None
    """The degraded-image ensemble's probability that an image the thresholds call sharp is degraded; None for the
    images it was not asked about (not sharp by the thresholds, smaller than ``degraded_min_size``, or
    ``sharp_from="rules"``)."""

    def evidence(self) -> dict:
        """The numbers as a JSON-ready dict (rounded)."""
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}


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


def _confidence(value: float, threshold: float, scale: float) -> float:
    """0 at the threshold, towards 1 as |log(value / threshold)| reaches log(scale)."""
    if value <= 0 or threshold <= 0:
        return 1.0
    return float(min(1.0, abs(math.log(value / threshold)) / math.log(scale)))


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


def _content_anisotropy(by_angle: np.ndarray, sharp_idx: list[int]) -> float:
    """Orientation spread that view-to-view content alone causes: median over the sharp images of each one's
    spread against the others' per-orientation median (leave one out; of two images, each against the other).
    Infinite with fewer than two sharp images: the spread is then unmeasured, not zero."""
    if len(sharp_idx) < 2:
        return math.inf
    spreads = []
    for i in sharp_idx:
        others = [j for j in sharp_idx if j != i]
        spreads.append(_orientation_spread(by_angle[i], _column_nanmedian(by_angle[others])))
    return float(np.median(spreads))


def _width_evidence(
    feats: Sequence[ImageFeatures], cfg: EstimateConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def _detail_evidence(
    feats: Sequence[ImageFeatures], ref: np.ndarray, sharp_idx: list[int]
) -> tuple[np.ndarray, float]:
    """Detail tensors relative to the reference images' -> (isotropy [n], NaN where undefined; spread of the sharp
    images other than the references, inf when none is left to measure it).

    Each image's tensor is whitened by the element-wise median of the references' tensors; its eigenvalues are
    then the shares of fine detail kept along its two principal orientations. isotropy = log(larger) /
    log(smaller): 1 when both lost the same share, 0 when one lost none.
    """
    tensors = np.stack([f.detail_tensor for f in feats])  # [n, 2, 2]
    base = np.median(tensors[ref], axis=0)
    n = len(feats)
    whiten = inverse_sqrt(base) if np.all(np.isfinite(base)) else None
    if whiten is None:
        return np.full(n, np.nan), math.inf
    log_eig = np.full((n, 2), np.nan)
    for i, t in enumerate(tensors):
        if np.all(np.isfinite(t)):
            log_eig[i] = np.log(np.maximum(np.linalg.eigvalsh(whiten @ t @ whiten), 1e-12))  # ascending
    with np.errstate(invalid="ignore", divide="ignore"):
        # 0 when the least-blurred orientation kept all its detail (or more, by content); NaN when none lost any
        isotropy = np.where(log_eig[:, 0] < 0, np.maximum(log_eig[:, 1] / log_eig[:, 0], 0.0), np.nan)
    ref_set = set(ref.tolist())
    others = [i for i in sharp_idx if i not in ref_set and np.all(np.isfinite(log_eig[i]))]
    spread = float(np.median([np.abs(log_eig[i]).max() for i in others])) if others else math.inf
    return isotropy, spread


def _kind_from_isotropy(isotropy: float, width_spread: float, cfg: EstimateConfig) -> str:
    """motion, defocus or unknown from the detail isotropy; the edge-width spread must agree (NaN: no evidence)."""
    if not isotropy < cfg.defocus_isotropy:  # NaN included: only a measured isotropy names a kind
        label = "defocus" if isotropy > cfg.defocus_isotropy else "unknown"
    else:
        label = "motion" if isotropy < cfg.motion_isotropy else "unknown"
    limit = {"motion": cfg.max_motion_width_spread, "defocus": cfg.max_defocus_width_spread}.get(label)
    if limit is not None and width_spread > limit:
        return "unknown"
    return label


def _directional_loss(feat: ImageFeatures) -> float:
    """Geometric mean of the tile coherence and the spectral anisotropy of one image (NaN when either is)."""
    return math.sqrt(max(feat.tile_coherence, 0.0) * max(feat.spectral_anisotropy, 0.0))


def _kind_from_direction(directional: float, region: float, cfg: EstimateConfig) -> str:
    """motion, defocus or unknown from the directional loss and the sharpest region's edge width (relative to the
    set's narrowest-edged images; NaN: no evidence). The edge-width spread is not asked here: a lens focused on one
    depth widens it as a shake does."""
    in_focus = region <= cfg.focused_region_width  # part of the view as sharp as a sharp view: a lens
    if directional > cfg.motion_direction:
        return "unknown" if in_focus else "motion"  # a directional loss and a region in focus disagree
    if in_focus or directional < cfg.defocus_direction:
        return "defocus"
    return "unknown"  # NaN included


def _kind_from_blur_shape(spread: float, rise: float, directional: bool, cfg: EstimateConfig) -> tuple[str, float]:
    """(motion / defocus / unknown, confidence) from the detail spread over tiles (relative to the set's sharp
    images) and the edge rise ratio (NaN: no evidence). ``directional``: the image's loss of detail was directional
    while a region in focus contradicted it; the shape must then side with one of the two, and a rounded edge
    profile alone does not outvote the direction."""
    if spread > cfg.focused_detail_spread:  # some tiles kept their detail: a lens focused on one depth
        return "defocus", _confidence(spread, cfg.focused_detail_spread, 1.5)
    if not math.isfinite(rise):
        return "unknown", 0.0
    if rise > cfg.motion_edge_rise:
        return "motion", _confidence(rise, cfg.motion_edge_rise, 1.5)
    return ("unknown", 0.0) if directional else ("defocus", _confidence(rise, cfg.motion_edge_rise, 1.5))


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
    """Every number the decisions read, for a set of n images: arrays [n] (NaN: not measured) and the set's own
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
    sharp_idx: list
    """Indices of the images sharp by the thresholds and not soft-edged."""
    soft: np.ndarray
    """[n] bool: softest step edges much wider than the narrowest-edged images'."""
    trusted_reference: bool
    """The reference images are sharp enough (and the set large enough) to call any image sharp."""
    direction_ok: bool
    """The sharp images' orientation spread is small enough for the orientation rule."""
    detail_ok: bool
    """The sharp images' detail tensors agree closely enough for the isotropy rule."""

    def columns(self) -> dict:
        """The arrays the ensembles may read, by name."""
        return {name: getattr(self, name) for name in KIND_FEATURES}


def set_evidence(feats: Sequence[ImageFeatures], config: Optional[EstimateConfig] = None) -> SetEvidence:
    """Measure a set against itself (:func:`image_features` per image) -> its :class:`SetEvidence`."""
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
    isotropy, detail_spread = _detail_evidence(feats, ref, sharp_idx)
    return SetEvidence(
        sharpness=sharp,
        edge_sharpness=edge_rel,
        laplacian_variance=lap_rel,
        anisotropy=np.array([_orientation_spread(b, ref_angle) for b in by_angle]),
        soft_width=soft_width,
        width_spread=width_spread,
        sharpest_region=region_width,
        isotropy=isotropy,
        directional_loss=np.array([_directional_loss(f) for f in feats]),
        detail_spread=_relative_detail_spread(feats, sharp_idx),
        edge_rise=np.array([f.edge_rise_ratio for f in feats]),
        tile_coherence=np.array([f.tile_coherence for f in feats]),
        spectral_anisotropy=np.array([f.spectral_anisotropy for f in feats]),
        size=np.array([max(f.width, f.height) for f in feats]),
        grid=_grid_factor(feats, ref, cfg),
        reference=ref,
        sharp_idx=sharp_idx,
        soft=soft,
        trusted_reference=bool(ref_edge >= cfg.min_reference_edge_ratio and n >= cfg.min_set_size),
        direction_ok=bool(_content_anisotropy(by_angle, sharp_idx) < cfg.max_content_anisotropy),
        detail_ok=bool(detail_spread <= cfg.max_detail_spread),
    )


def ensemble_probability(ev: SetEvidence, model: TreeEnsemble, which: str) -> np.ndarray:
    """[n] the ensemble's probability for every image of the set; ValueError when it reads a number the estimate
    does not measure (``which`` names the model in that message)."""
    unknown = sorted(set(model.features) - set(KIND_FEATURES))
    if unknown:
        raise ValueError(f"{which} reads {unknown}, which the estimate does not measure (it measures "
                         f"{', '.join(KIND_FEATURES)}); refit it")  # fmt: skip
    return probability(model, evidence_matrix(ev.columns(), model.features))


def decide(ev: SetEvidence, config: Optional[EstimateConfig] = None) -> list[DegradationEstimate]:
    """Label every image of a set from its evidence -> one :class:`DegradationEstimate` per image."""
    cfg = config or EstimateConfig()
    n = len(ev.sharpness)
    sharp, aniso, width_spread, isotropy = ev.sharpness, ev.anisotropy, ev.width_spread, ev.isotropy
    directional, region_width = ev.directional_loss, ev.sharpest_region
    p_motion = np.full(n, np.nan)
    if cfg.kind_from == "model":
        p_motion = ensemble_probability(ev, load_kind_model(cfg.kind_model),
                                        f"kind-of-blur model {cfg.kind_model or 'built-in'}")  # fmt: skip
    p_degraded = np.full(n, np.nan)
    if cfg.sharp_from == "model":
        p_degraded = ensemble_probability(ev, load_degraded_model(cfg.degraded_model),
                                          f"degraded-image model {cfg.degraded_model or 'built-in'}")  # fmt: skip

    def kind_from_model(i: int) -> tuple[str, float]:
        """(motion / defocus / unknown, confidence) of blurred image i from the ensemble's probability."""
        p = float(p_motion[i])
        label = "motion" if p >= cfg.kind_probability else "defocus" if p <= 1.0 - cfg.kind_probability else "unknown"
        if label == "unknown":
            return label, 0.0
        return label, float(min(1.0, (max(p, 1.0 - p) - cfg.kind_probability) / max(1.0 - cfg.kind_probability, 1e-6)))

    def kind_of(i: int) -> tuple[str, float]:
        """(motion / defocus / unknown, confidence of the kind) of blurred image i: the ensemble, or the rules in
        turn."""
        if cfg.kind_from == "model":
            return kind_from_model(i)
        if ev.direction_ok:
            label = "motion" if aniso[i] >= cfg.anisotropy_threshold else "defocus"
            limit = cfg.max_motion_width_spread if label == "motion" else cfg.max_defocus_width_spread
            if not width_spread[i] > limit:  # the edge widths must not contradict that kind (NaN: no evidence)
                return label, _confidence(aniso[i] + 1e-3, cfg.anisotropy_threshold, 2.0)
        if ev.detail_ok:
            label = _kind_from_isotropy(isotropy[i], width_spread[i], cfg)
            if label != "unknown":
                threshold = cfg.motion_isotropy if label == "motion" else cfg.defocus_isotropy
                return label, _confidence(isotropy[i], threshold, 1.25)
        # the sharpest region is compared with the narrowest-edged images: only trusted when some images are sharp
        region = region_width[i] if len(ev.sharp_idx) >= 2 else math.nan
        label = _kind_from_direction(directional[i], region, cfg)
        if label != "unknown":
            threshold = cfg.motion_direction if label == "motion" else cfg.defocus_direction
            return label, _confidence(directional[i], threshold, 2.0)
        if cfg.kind_from_blur_shape:
            return _kind_from_blur_shape(ev.detail_spread[i], ev.edge_rise[i], directional[i] > cfg.motion_direction,
                                         cfg)  # fmt: skip
        return "unknown", 0.0

    def kind_in_between(i: int, sure: float) -> tuple[str, float]:
        """(kind, confidence) of image i that is neither sharp nor clearly blurred; ``sure``: how sure it is not
        sharp (the confidence is at most that; 0 when the kind is unknown)."""
        if cfg.kind_in_between and cfg.kind_from == "model":
            judged.add(i)
            label, conf_kind = kind_from_model(i)
            return label, min(conf_kind, sure)
        if cfg.kind_in_between and directional[i] > cfg.motion_direction:
            # only a directional loss of detail: a region in focus or a low directional loss is what a sharp view
            # of soft content shows as well
            return "motion", min(_confidence(directional[i], cfg.motion_direction, 2.0), sure)
        return "unknown", 0.0

    out = []
    ref_set = set(ev.reference.tolist())
    judged: set[int] = set()  # images whose kind of blur was asked for
    flag_asked: set[int] = set()  # images the degraded-image ensemble was asked about
    for i in range(n):
        factor, gscore = ev.grid[i]
        blurred: Optional[bool]
        if factor > 1:
            label, blurred = "mixres", None
            conf = float(min(1.0, math.log(gscore / cfg.grid_threshold + 1.0) / math.log(10.0)))
        elif n < cfg.min_set_size:
            label, blurred, conf = "unknown", None, 0.0
        elif sharp[i] >= cfg.sharp_threshold:
            trusted = ev.trusted_reference and not ev.soft[i]  # sharpest edges as sharp as the references', softest not
            label, blurred = ("sharp", False) if trusted else ("unknown", None)
            conf = _confidence(sharp[i], cfg.sharp_threshold, 2.0) if trusted else 0.0
            if trusted and cfg.sharp_from == "model" and ev.size[i] >= cfg.degraded_min_size:
                flag_asked.add(i)
                if p_degraded[i] >= cfg.degraded_probability:
                    # sharp by the two thresholds, degraded by all the evidence together (mild defocus, mostly)
                    sure = (p_degraded[i] - cfg.degraded_probability) / max(1.0 - cfg.degraded_probability, 1e-6)
                    blurred = None
                    label, conf = kind_in_between(i, float(sure))
        elif sharp[i] >= cfg.blurred_threshold:
            # neither sharp nor clearly blurred: the kind of blur may still show (and saves simulating both)
            blurred = None
            label, conf = kind_in_between(i, _confidence(sharp[i], cfg.sharp_threshold, 2.0))
        else:
            blurred = True
            judged.add(i)
            label, conf_kind = kind_of(i)
            conf = min(_confidence(sharp[i], cfg.blurred_threshold, 2.0), conf_kind)
        out.append(
            DegradationEstimate(
                label=label,
                confidence=round(float(conf), 4),
                sharpness=float(sharp[i]),
                edge_sharpness=float(ev.edge_sharpness[i]),
                laplacian_variance=float(ev.laplacian_variance[i]),
                anisotropy=float(aniso[i]),
                mixres_factor=factor if (factor > 1 or blurred is not None) else (1 if label == "sharp" else None),
                grid_score=float(gscore),
                blurred=blurred,
                reference=i in ref_set,
                soft_width=_number(ev.soft_width[i]),
                width_spread=_number(width_spread[i]),
                isotropy=_number(isotropy[i]),
                sharpest_region=_number(region_width[i]),
                directional_loss=_number(directional[i]),
                detail_spread=_number(ev.detail_spread[i]),
                edge_rise=_number(ev.edge_rise[i]),
                motion_probability=_number(p_motion[i]) if i in judged else None,
                degraded_probability=_number(p_degraded[i]) if i in flag_asked else None,
            )
        )
    return out


def _number(value: float) -> Optional[float]:
    """A measured number as a float; None when it is not (NaN, inf)."""
    return float(value) if math.isfinite(value) else None


def estimate_from_features(
    feats: Sequence[ImageFeatures], config: Optional[EstimateConfig] = None
) -> list[DegradationEstimate]:
    """Decide the labels of a set from its measurements (:func:`image_features` per image). -> one per image."""
    return decide(set_evidence(feats, config), config)


def estimate_degradations(
    images: Sequence[np.ndarray | Tensor], config: Optional[EstimateConfig] = None
) -> list[DegradationEstimate]:
    """Estimate the degradation of every image of a set (one capture: sharpness is judged relative to it).

    images: each [H, W, 3] (or [H, W, 4]) uint8, or float in [0, 1]; sizes may differ. -> one
    :class:`DegradationEstimate` per image, in order.
    """
    cfg = config or EstimateConfig()
    feats = [image_features(img, coarse_sigma=cfg.coarse_sigma, max_size=cfg.max_size) for img in images]
    return estimate_from_features(feats, cfg)


__all__ = [
    "LABELS",
    "METHOD_VERSION",
    "EstimateConfig",
    "DegradationEstimate",
    "estimate_degradations",
    "estimate_from_features",
    "SetEvidence",
    "set_evidence",
    "decide",
    "ensemble_probability",
]
