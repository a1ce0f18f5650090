"""`estimate_degradations`: label each image of a set sharp / motion / defocus / mixres / unknown, with evidence.

The evidence (:mod:`.evidence`) compares every image with the set's sharpest ones; this module decides:

* **mixres**: an upsampling grid at factor f much stronger than in the reference images (a camera's own periodic
  artefacts do not count), f snapped to the project's groups.
* **sharp / between / blurred**: by the image's sharpness relative to the reference images (``sharp_threshold``,
  ``blurred_threshold``). A sharp image is left unknown when the references are not sharp themselves or its
  softest step edges are much wider than the set's narrowest (a lens focused on one depth).
* **sharp, confirmed** (``sharp_from="model"``): the degraded-image ensemble (:mod:`.ensemble`) judges every image
  the thresholds call sharp; one it flags counts as between sharp and blurred.
* **motion / defocus**: the kind-of-blur ensemble's probability of motion names the kind of every blurred image
  and every image between (``kind_in_between``), or leaves it unknown near 0.5.

Both ensembles read all the evidence together; they were fitted on generated scenes and degraded real photos whose
records hold the truth (``tools/estimate/fit_ensembles.py``, results in docs/results/estimate/results.md).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Optional, Sequence

import numpy as np
from torch import Tensor

from .config import EstimateConfig
from .ensemble import KIND_FEATURES, TreeEnsemble, evidence_matrix, load_degraded_model, load_kind_model, probability
from .evidence import SetEvidence, measure_images, set_evidence
from .features import ImageFeatures

LABELS = ("sharp", "motion", "defocus", "mixres", "unknown")
METHOD_VERSION = 7
"""Raised whenever the same images and config get other labels (cached estimates and benchmark runs that trained
on them are then computed again). 2: the detail-tensor second opinion on the kind of blur. 3: the kind of blur
from the image alone (region in focus, directional loss). 4: the region in focus only after the set rules. 5: the
blur's shape (detail spread over tiles, edge rise) names the kind the other rules leave unknown. 6: a fitted
ensemble over all that evidence names the kind. 7: a second ensemble flags degraded images among those the
thresholds call sharp (``sharp_from="model"``). (The hand-set rule chain of versions 1-5 is gone; the evidence
it read is what the ensembles read.) Whether a fitted ensemble reads the numbers it was fitted on is checked by its
provenance (:func:`~.ensemble.check_provenance`), not by this number."""

THRESHOLD_STAGES = ("mixres", "unknown", "sharp", "between", "blurred")
"""What the thresholds alone make of an image (:func:`threshold_stages`), before either ensemble."""


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
    images it did not judge (sharp, mixres, a set too small)."""
    degraded_probability: Optional[float] = None
    """The degraded-image ensemble's probability that an image the thresholds call sharp is degraded; None for the
    images it was not asked about (not sharp by the thresholds, smaller than ``degraded_min_size``, or
    ``sharp_from="rules"``)."""

    def evidence(self) -> dict:
        """The numbers as a JSON-ready dict (rounded)."""
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}


def _confidence(value: float, threshold: float, scale: float) -> float:
    """0 at the threshold, towards 1 as |log(value / threshold)| reaches log(scale)."""
    if value <= 0 or threshold <= 0:
        return 1.0
    return float(min(1.0, abs(math.log(value / threshold)) / math.log(scale)))


def _number(value: float) -> Optional[float]:
    """A measured number as a float; None when it is not (NaN, inf)."""
    return float(value) if math.isfinite(value) else None


def threshold_stages(ev: SetEvidence, config: Optional[EstimateConfig] = None) -> list[str]:
    """Per image of the set, one of :data:`THRESHOLD_STAGES`: mixres (an upsampling grid); unknown (a set smaller
    than ``min_set_size``, or sharp by its sharpness but the references untrusted or its own edges soft); sharp;
    between (sharpness between the two thresholds); blurred."""
    cfg = config or EstimateConfig()
    n = len(ev.sharpness)
    out = []
    for i in range(n):
        if ev.grid[i][0] > 1:
            out.append("mixres")
        elif n < cfg.min_set_size:
            out.append("unknown")
        elif ev.sharpness[i] >= cfg.sharp_threshold:
            trusted = ev.trusted_reference and not ev.soft[i]  # sharpest edges as sharp as the references', softest not
            out.append("sharp" if trusted else "unknown")
        else:
            out.append("between" if ev.sharpness[i] >= cfg.blurred_threshold else "blurred")
    return out


def ensemble_probability(ev: SetEvidence, model: TreeEnsemble, which: str) -> np.ndarray:
    """[n] the ensemble's probability for every image of the set; ValueError when it reads a number the estimate
    does not measure (``which`` names the model in that message)."""
    unknown = sorted(set(model.features) - set(KIND_FEATURES))
    if unknown:
        raise ValueError(f"{which} reads {unknown}, which the estimate does not measure (it measures "
                         f"{', '.join(KIND_FEATURES)}); refit it")  # fmt: skip
    return probability(model, evidence_matrix(ev.columns(), model.features))


def _kind_from_probability(p: float, cfg: EstimateConfig) -> tuple[str, float]:
    """(motion / defocus / unknown, confidence) from the kind-of-blur ensemble's probability of motion p."""
    label = "motion" if p >= cfg.kind_probability else "defocus" if p <= 1.0 - cfg.kind_probability else "unknown"
    if label == "unknown":
        return label, 0.0
    return label, float(min(1.0, (max(p, 1.0 - p) - cfg.kind_probability) / max(1.0 - cfg.kind_probability, 1e-6)))


def decide(ev: SetEvidence, config: Optional[EstimateConfig] = None) -> list[DegradationEstimate]:
    """Label every image of a set from its evidence -> one :class:`DegradationEstimate` per image."""
    cfg = config or EstimateConfig()
    n = len(ev.sharpness)
    sharp = ev.sharpness
    p_motion = ensemble_probability(ev, load_kind_model(cfg.kind_model, cfg),
                                    f"kind-of-blur model {cfg.kind_model or 'built-in'}")  # fmt: skip
    p_degraded = np.full(n, np.nan)
    if cfg.sharp_from == "model":
        p_degraded = ensemble_probability(ev, load_degraded_model(cfg.degraded_model, cfg),
                                          f"degraded-image model {cfg.degraded_model or 'built-in'}")  # fmt: skip

    def kind_in_between(i: int, sure: float) -> tuple[str, float]:
        """(kind, confidence) of image i that is neither sharp nor clearly blurred; ``sure``: how sure it is not
        sharp (the confidence is at most that; 0 when the kind is unknown)."""
        if not cfg.kind_in_between:
            return "unknown", 0.0
        judged.add(i)
        label, conf_kind = _kind_from_probability(float(p_motion[i]), cfg)
        return label, min(conf_kind, sure)

    out = []
    ref_set = set(ev.reference.tolist())
    judged: set[int] = set()  # images whose kind of blur was asked for
    flag_asked: set[int] = set()  # images the degraded-image ensemble was asked about
    for i, stage in enumerate(threshold_stages(ev, cfg)):
        factor, gscore = ev.grid[i]
        blurred: Optional[bool] = None
        label, conf = "unknown", 0.0
        if stage == "mixres":
            label = "mixres"
            conf = float(min(1.0, math.log(gscore / cfg.grid_threshold + 1.0) / math.log(10.0)))
        elif stage == "sharp":
            label, blurred = "sharp", False
            conf = _confidence(sharp[i], cfg.sharp_threshold, 2.0)
            if cfg.sharp_from == "model" and ev.size[i] >= cfg.degraded_min_size:
                flag_asked.add(i)
                if p_degraded[i] >= cfg.degraded_probability:
                    # sharp by the two thresholds, degraded by all the evidence together (mild defocus, mostly)
                    sure = (p_degraded[i] - cfg.degraded_probability) / max(1.0 - cfg.degraded_probability, 1e-6)
                    blurred = None
                    label, conf = kind_in_between(i, float(sure))
        elif stage == "between":
            # neither sharp nor clearly blurred: the kind of blur may still show (and saves simulating both)
            label, conf = kind_in_between(i, _confidence(sharp[i], cfg.sharp_threshold, 2.0))
        elif stage == "blurred":
            blurred = True
            judged.add(i)
            label, conf_kind = _kind_from_probability(float(p_motion[i]), cfg)
            conf = min(_confidence(sharp[i], cfg.blurred_threshold, 2.0), conf_kind)
        out.append(
            DegradationEstimate(
                label=label,
                confidence=round(float(conf), 4),
                sharpness=float(sharp[i]),
                edge_sharpness=float(ev.edge_sharpness[i]),
                laplacian_variance=float(ev.laplacian_variance[i]),
                anisotropy=float(ev.anisotropy[i]),
                mixres_factor=factor if (factor > 1 or blurred is not None) else (1 if label == "sharp" else None),
                grid_score=float(gscore),
                blurred=blurred,
                reference=i in ref_set,
                soft_width=_number(ev.soft_width[i]),
                width_spread=_number(ev.width_spread[i]),
                isotropy=_number(ev.isotropy[i]),
                sharpest_region=_number(ev.sharpest_region[i]),
                directional_loss=_number(ev.directional_loss[i]),
                detail_spread=_number(ev.detail_spread[i]),
                edge_rise=_number(ev.edge_rise[i]),
                motion_probability=_number(p_motion[i]) if i in judged else None,
                degraded_probability=_number(p_degraded[i]) if i in flag_asked else None,
            )
        )
    return out


def estimate_from_features(
    feats: Sequence[ImageFeatures], config: Optional[EstimateConfig] = None
) -> list[DegradationEstimate]:
    """Decide the labels of a set from its measurements (:func:`~.evidence.measure_images`). -> one per image."""
    return decide(set_evidence(feats, config), config)


def estimate_degradations(
    images: Sequence[np.ndarray | Tensor], config: Optional[EstimateConfig] = None
) -> list[DegradationEstimate]:
    """Estimate the degradation of every image of a set (one capture: sharpness is judged relative to it).

    images: each [H, W, 3] (or [H, W, 4]) uint8, or float in [0, 1]; sizes may differ. -> one
    :class:`DegradationEstimate` per image, in order.
    """
    return estimate_from_features(measure_images(images, config), config)


__all__ = [
    "LABELS",
    "METHOD_VERSION",
    "THRESHOLD_STAGES",
    "EstimateConfig",
    "DegradationEstimate",
    "estimate_degradations",
    "estimate_from_features",
    "SetEvidence",
    "set_evidence",
    "threshold_stages",
    "decide",
    "ensemble_probability",
]
