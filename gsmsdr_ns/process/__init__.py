"""Structure-from-motion for ``gsmsdr-process``: a folder of photos -> an undistorted COLMAP scene (pycolmap)."""

from gsmsdr_ns.process.config import ProcessConfig
from gsmsdr_ns.process.sfm import ProcessResult, RegistrationError, choose_matching, process_photos
from gsmsdr_ns.process.sharpness import sharpness_scores, variance_of_laplacian

__all__ = [
    "ProcessConfig",
    "ProcessResult",
    "RegistrationError",
    "choose_matching",
    "process_photos",
    "sharpness_scores",
    "variance_of_laplacian",
]
