"""`EstimateConfig`: the settings of the per-image degradation estimate, and which of them the evidence depends on.

A leaf module (no other import of the estimate's) so that the evidence (:mod:`.evidence`), the fitted ensembles'
loader (:mod:`.ensemble`) and the decision (:mod:`.classify`) all read the same settings.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, Literal, Optional


@dataclass
class EstimateConfig:
    """Settings of the per-image degradation estimate (thresholds are relative to the set, see :mod:`.classify`)."""

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
    grid_threshold: float = 10.0
    """Periodicity score (about 1 without a grid) from which an upsampling grid counts."""
    grid_reference_ratio: float = 5.0
    """... and how many times stronger than in the reference images it must be."""
    soft_width_ratio: float = 1.5
    """An image sharp by the measures above is left unknown when its softest step edges (90th percentile width)
    are more than this many times wider than those of the set's narrowest-edged images."""
    kind_model: str = ""
    """The kind-of-blur ensemble's JSON file ("": the one shipped with the package)."""
    kind_probability: float = 0.65
    """The ensemble names a kind when its probability is at least this; otherwise the kind stays unknown."""
    sharp_from: Literal["model", "rules"] = "model"
    """What confirms an image the thresholds above call sharp: "model", the fitted degraded-image ensemble over the
    evidence (:mod:`.ensemble`; an image it flags is treated as one between sharp and blurred); "rules", the
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
    ensemble names, else unknown: it pays for that model alone instead of both. Sharp views of soft content land
    here too, and are then simulated with one blur instead of both."""
    max_size: int = 1024
    """Blur is judged on a copy whose longer side is at most this many px (0: full resolution)."""
    coarse_sigma: float = 2.0
    """Gaussian blur (px at the analysis size) of the coarse scale that edge steepness is measured against."""


EVIDENCE_SETTINGS = (
    "max_size",
    "coarse_sigma",
    "reference_fraction",
    "min_reference",
    "min_set_size",
    "sharp_threshold",
    "soft_width_ratio",
)
"""The :class:`EstimateConfig` fields the ensembles' input numbers depend on: the analysis copy and scale of each
image's measurements, the set's references they are relative to, and the sharp images (sharp by
``sharp_threshold`` and not soft-edged) the detail spread is relative to. A fitted ensemble records their values
(its provenance); the loader refuses it under other values."""


def evidence_settings(config: Optional[EstimateConfig] = None) -> Dict[str, Any]:
    """{name: value} of :data:`EVIDENCE_SETTINGS` in ``config`` (default: the default config)."""
    cfg = config or EstimateConfig()
    return {name: getattr(cfg, name) for name in EVIDENCE_SETTINGS}


__all__ = ["EstimateConfig", "EVIDENCE_SETTINGS", "evidence_settings"]
