"""GS-MSDR blur modelling: per-pixel blur kernels, the networks that predict them, and the degradation model that
turns a sharp render into a training image's degraded photo."""

from gsmsdr_ns.blur.kernels import ApplyPixelKernels, apply_pixel_kernels, apply_pixel_kernels_unfold, pixel_kernel_size
from gsmsdr_ns.blur.field import BlurField, BlurFieldConfig
from gsmsdr_ns.blur.hpko import HPKOHeads, HPKOScheduler, ScaleInfo
from gsmsdr_ns.blur.profile import (
    DegradationProfile,
    ResolutionLossModel,
    describe_profiles,
    effective_factor,
    resolution_loss,
    training_profiles,
)
from gsmsdr_ns.blur.defocus import ThinLensDefocus, occluding_disk_kernels, soft_disk_kernels, thin_lens_radius
from gsmsdr_ns.blur.degradation_model import DegradationModel, DegradationPlan
from gsmsdr_ns.blur.shake import CameraShake, apply_camera_shake, rotation_homographies
