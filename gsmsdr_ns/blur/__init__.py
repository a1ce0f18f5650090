"""GS-MSDR degradation modelling: the networks and learnt lens and shake that predict each training image's blur, and
the degradation model that turns a sharp render into that image's degraded photo. The operators they apply (pixel,
grid and disk kernels, the mixed-resolution down-up, the deconvolved loss) are in :mod:`gsmsdr_ns.ops`."""

from gsmsdr_ns.blur.defocus import ThinLensDefocus, thin_lens_radius
from gsmsdr_ns.blur.degradation_config import DegradationConfig
from gsmsdr_ns.blur.degradation_model import DegradationModel, DegradationPlan
from gsmsdr_ns.blur.field import BlurField, BlurFieldConfig
from gsmsdr_ns.blur.hpko import HPKOHeads, HPKOScheduler, ScaleInfo
from gsmsdr_ns.blur.profile import (
    DegradationProfile,
    ResolutionLossModel,
    describe_profiles,
    effective_factor,
    training_profiles,
)
from gsmsdr_ns.blur.shake import CameraShake, apply_camera_shake, rotation_homographies

__all__ = [
    "BlurField",
    "BlurFieldConfig",
    "CameraShake",
    "DegradationConfig",
    "DegradationModel",
    "DegradationPlan",
    "DegradationProfile",
    "HPKOHeads",
    "HPKOScheduler",
    "ResolutionLossModel",
    "ScaleInfo",
    "ThinLensDefocus",
    "apply_camera_shake",
    "describe_profiles",
    "effective_factor",
    "rotation_homographies",
    "thin_lens_radius",
    "training_profiles",
]
