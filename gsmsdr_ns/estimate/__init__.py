"""Per-image degradation estimate for scenes without degradation records (no nerfstudio import).

* :func:`estimate_degradations` labels each image of a set sharp / motion / defocus / mixres / unknown, keeping
  the evidence (relative sharpness, orientation anisotropy, upsampling factor, confidence);
* :func:`estimate_scene_records` writes / reads the estimate of a scene as ``degradation.json`` records.
"""

from .classify import LABELS, DegradationEstimate, estimate_degradations, estimate_from_features
from .config import EstimateConfig
from .features import MIXRES_GROUPS, ImageFeatures, image_features
from .records import ESTIMATED, estimate_scene_records, write_scene_estimate

__all__ = [
    "ESTIMATED",
    "LABELS",
    "MIXRES_GROUPS",
    "DegradationEstimate",
    "EstimateConfig",
    "ImageFeatures",
    "estimate_degradations",
    "estimate_from_features",
    "image_features",
    "estimate_scene_records",
    "write_scene_estimate",
]
