"""GS-MSDR blur modelling: per-pixel blur kernels and the networks that predict them."""

from gsmsdr_ns.blur.kernels import ApplyPixelKernels, apply_pixel_kernels, apply_pixel_kernels_unfold, pixel_kernel_size
from gsmsdr_ns.blur.field import BlurField, BlurFieldConfig
from gsmsdr_ns.blur.hpko import HPKOHeads, HPKOScheduler, ScaleInfo
from gsmsdr_ns.blur.profile import DegradationProfile, ResolutionLossModel, down_up, effective_factor
from gsmsdr_ns.blur.defocus import ThinLensDefocus, occluding_disk_kernels, soft_disk_kernels, thin_lens_radius
