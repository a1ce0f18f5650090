"""Thin-lens defocus from the rendered depth: per-pixel disk kernels with a learnt aperture and focus per view.

A thin lens focused at distance d_f images a point at depth d as a disk whose radius, in pixels, is proportional
to ``|1/d - 1/d_f|`` (``gsmsdr_ns.degrade.kernels.defocus_radius``). For a defocused training photo the blur of
every pixel therefore follows from the rendered depth and two numbers per photo: the aperture (the radius per
unit of inverse depth) and the focus (an inverse depth). Learning those two numbers from every pixel of the photo
is far better posed than learning a free kernel per pixel, which is what the feature network would have to do.

Pure functions first (shapes in the docstrings), then :class:`ThinLensDefocus`, the learnable per-view lens. The
kernels are for inspection (the viewer's blur size); training applies the lens with the fused ops of
:mod:`gsmsdr_ns.ops.disk_defocus`, which never hold the K*K weights (:meth:`ThinLensDefocus.blur`).
"""

from __future__ import annotations

import math
from typing import Optional

import torch
from kornia.color import linear_rgb_to_rgb, rgb_to_linear_rgb
from torch import Tensor, nn

from gsmsdr_ns.ops.disk_defocus import apply_occluding_defocus, apply_soft_disk_defocus
from gsmsdr_ns.ops.disk_kernels import mean_soft_disk_kernel, occluding_disk_kernels, soft_disk_kernels

from .hpko import MAX_KERNEL_SIZE
from .maan import check_bchw, check_view_ids

__all__ = ["thin_lens_radius", "lens_window", "ThinLensDefocus"]


def thin_lens_radius(inverse_depth: Tensor, aperture: Tensor, inverse_focus: Tensor) -> Tensor:
    """Circle-of-confusion radius of a thin lens: ``aperture * |1/d - 1/d_f|``.

    Args:
        inverse_depth: [B, 1, H, W] 1/d.
        aperture: [B] radius in pixels per unit of inverse depth (the lens's f_px * A / 2).
        inverse_focus: [B] 1/d_f.
    Returns:
        [B, 1, H, W] radius in pixels.
    """
    return aperture[:, None, None, None] * (inverse_depth - inverse_focus[:, None, None, None]).abs()


def lens_window(radius: Tensor, max_kernel_size: int, softness: float) -> int:
    """The odd window holding the largest disk of ``radius`` [B, 1, H, W] with its soft edge, at most
    ``max_kernel_size``: a lens that barely blurs costs a 5x5 window, not the scale's full one.

    Reading the largest radius is a host-device synchronisation, free on the CPU only: on any other device the
    window is ``max_kernel_size`` (the extra taps of a smaller disk weigh less than e^-24). A NaN radius (a NaN
    depth) also gets ``max_kernel_size``: it flows on into the loss, where training stops naming the step.
    """
    half = max_kernel_size // 2
    if radius.device.type == "cpu":
        largest = float(radius.detach().max())
        if not math.isnan(largest):
            half = min(half, math.ceil(largest + 6.0 * softness))
    return 2 * half + 1


class ThinLensDefocus(nn.Module):
    """A learnable thin lens per training view: ``blur(image, depth, view_ids, kernel_size, pixel_scale)`` -> the
    image through the lens; ``forward(depth, view_ids, kernel_size, pixel_scale)`` -> its kernels.

    Parameters: ``log_aperture`` (one, shared: a capture is usually shot with one lens setting, so every photo's
    gradient trains it), ``view_log_aperture`` [V] (each photo's deviation from it, starts at 0) and
    ``inverse_focus`` [V]. A view's focus starts, the first time the view is seen, at the median inverse depth of
    its render in training mode (focus somewhere inside the scene), recorded in the ``focus_initialised`` buffer so
    a checkpoint keeps it. The aperture starts at ``initial_aperture`` (small: an untrained lens barely blurs).

    With ``occlusion`` (default) the kernels are :func:`occluding_disk_kernels` (each neighbour spreads its own
    disk, an in-focus foreground hides the background), else :func:`soft_disk_kernels` (each pixel's own disk).

    Depth units are the scene's (nerfstudio rescales poses), so the aperture is learnt in pixels at the full
    training resolution per scene unit of inverse depth; ``pixel_scale`` (render width / full width) converts.
    """

    focus_initialised: Tensor  # buffer (register_buffer in __init__)

    def __init__(
        self, num_views: int, initial_aperture: float = 1.0, softness: float = 0.25, occlusion: bool = True
    ) -> None:
        super().__init__()
        self.occlusion = bool(occlusion)
        if num_views < 1:
            raise ValueError(f"num_views must be >= 1, got {num_views}")
        if not initial_aperture > 0:
            raise ValueError(f"initial_aperture must be > 0, got {initial_aperture}")
        self.softness = float(softness)
        self.log_aperture = nn.Parameter(torch.tensor(math.log(initial_aperture)))
        self.view_log_aperture = nn.Parameter(torch.zeros(num_views))
        self.inverse_focus = nn.Parameter(torch.zeros(num_views))
        self.register_buffer("focus_initialised", torch.zeros(num_views, dtype=torch.bool))

    @property
    def num_views(self) -> int:
        return self.view_log_aperture.shape[0]

    def aperture(self, view_ids: Tensor) -> Tensor:
        """[B] aperture (pixels at full resolution per unit of inverse depth) of ``view_ids`` [B]."""
        return torch.exp(self.log_aperture + self.view_log_aperture[view_ids.long()])

    def radius(self, depth: Tensor, view_ids: Tensor, pixel_scale: float = 1.0) -> Tensor:
        """[B, 1, H, W] circle-of-confusion radius in render pixels for rendered ``depth`` [B, 1, H, W] (detached:
        the lens learns from the depth, the depth is not moved to explain the blur)."""
        return self._radius(self._inverse_depth(depth, view_ids), view_ids.long(), pixel_scale)

    def _inverse_depth(self, depth: Tensor, view_ids: Tensor) -> Tensor:
        """Checked, detached ``1 / depth`` [B, 1, H, W] (float)."""
        check_bchw(depth, "depth", 1)
        check_view_ids(view_ids, depth.shape[0], self.num_views)
        return 1.0 / depth.detach().float().clamp_min(1e-6)

    def _radius(self, inverse_depth: Tensor, ids: Tensor, pixel_scale: float) -> Tensor:
        # a viewer preview (eval mode) must not pick a training view's focus; seen views need no median
        if self.training:
            if inverse_depth.device.type != "cpu":  # reading focus_initialised would wait for the device
                self._initialise_focus_on_device(ids, inverse_depth)
            elif not bool(self.focus_initialised[ids].all()):
                self._initialise_focus(ids, inverse_depth)
        radius = thin_lens_radius(inverse_depth, self.aperture(ids), self.inverse_focus[ids])
        return radius * float(pixel_scale)

    @torch.no_grad()
    def _initialise_focus(self, ids: Tensor, inverse_depth: Tensor) -> None:
        """Focus of the views in ``ids`` [B] not seen yet: the median of their ``inverse_depth`` [B, 1, H, W]."""
        medians = inverse_depth.flatten(1).nanmedian(dim=1).values
        new = ~self.focus_initialised[ids] & torch.isfinite(medians)  # a non-finite render teaches nothing
        if new.any():
            self.inverse_focus[ids[new]] = medians[new].to(self.inverse_focus.dtype)
            self.focus_initialised[ids[new]] = True

    @torch.no_grad()
    def _initialise_focus_on_device(self, ids: Tensor, inverse_depth: Tensor) -> None:
        """:meth:`_initialise_focus` without a host round trip: the medians are computed every time and written
        only where a view is new (``torch.where`` on the parameter's data)."""
        medians = inverse_depth.flatten(1).nanmedian(dim=1).values.to(self.inverse_focus.dtype)
        seen = self.focus_initialised[ids]
        new = ~seen & torch.isfinite(medians)
        self.inverse_focus[ids] = torch.where(new, medians, self.inverse_focus[ids])
        self.focus_initialised[ids] = seen | new

    def _lens(self, depth: Tensor, view_ids: Tensor, max_kernel_size: int, pixel_scale: float):
        """(radius [B, 1, H, W] clamped to the window, inverse depth [B, 1, H, W], window K)."""
        if max_kernel_size < 1 or max_kernel_size % 2 == 0:
            raise ValueError(f"max_kernel_size must be a positive odd integer, got {max_kernel_size}")
        # the disks are per-pixel kernels: a per-view field's larger kernel size does not widen them
        max_kernel_size = min(max_kernel_size, MAX_KERNEL_SIZE)
        inverse_depth = self._inverse_depth(depth, view_ids)
        radius = self._radius(inverse_depth, view_ids.long(), pixel_scale).clamp(max=max_kernel_size // 2)
        return radius, inverse_depth, lens_window(radius, max_kernel_size, self.softness)

    def forward(
        self,
        depth: Tensor,
        view_ids: Tensor,
        max_kernel_size: int,
        pixel_scale: float = 1.0,
        image: Optional[Tensor] = None,
        linear_light: bool = False,
    ) -> Tensor:
        """The lens of ``view_ids`` [B] for rendered ``depth`` [B, 1, H, W]: its [B, K*K, H, W] defocus kernels (sum
        to 1), or with ``image`` [B, C, H, W] the image through it (:meth:`blur`).

        K is :func:`lens_window` of the radii (the smallest odd window holding the largest disk on the CPU), at
        most ``max_kernel_size`` and the per-pixel limit ``MAX_KERNEL_SIZE`` (radii beyond it are truncated).
        """
        radius, inverse_depth, K = self._lens(depth, view_ids, max_kernel_size, pixel_scale)
        if image is not None:
            return self._blur(image, radius, inverse_depth, K, linear_light)
        if not self.occlusion:
            return soft_disk_kernels(radius, K, self.softness)
        return occluding_disk_kernels(radius, inverse_depth, K, self.softness)

    @torch.no_grad()
    def mean_kernel(self, depth: Tensor, view_ids: Tensor, max_kernel_size: int, pixel_scale: float = 1.0) -> Tensor:
        """[B, K, K] detached mean over the image of the lens's disks for rendered ``depth`` [B, 1, H, W]
        (:func:`~gsmsdr_ns.ops.disk_kernels.mean_soft_disk_kernel`; occlusion ignored), K as :meth:`forward`."""
        radius, _, K = self._lens(depth, view_ids, max_kernel_size, pixel_scale)
        return mean_soft_disk_kernel(radius.float(), K, self.softness)

    def blur(
        self,
        image: Tensor,
        depth: Tensor,
        view_ids: Tensor,
        max_kernel_size: int,
        pixel_scale: float = 1.0,
        linear_light: bool = False,
    ) -> Tensor:
        """``image`` [B, C, H, W] through the lens: ``BlurField.blur(image, self(depth, ...), linear_light)``
        computed by the fused ops (:func:`apply_occluding_defocus`, :func:`apply_soft_disk_defocus`), which never
        hold the [B, K*K, H, W] kernels. Returns [B, C, H, W] in the wider of the image's and the radius's dtype.
        Same as ``self(depth, view_ids, max_kernel_size, pixel_scale, image, linear_light)`` (a module call: hooks
        see it)."""
        return self(depth, view_ids, max_kernel_size, pixel_scale, image, linear_light)

    def _blur(self, image: Tensor, radius: Tensor, inverse_depth: Tensor, K: int, linear_light: bool) -> Tensor:
        dtype = torch.promote_types(image.dtype, radius.dtype)
        source = rgb_to_linear_rgb(image) if linear_light else image
        source, radius = source.to(dtype), radius.to(dtype)
        if self.occlusion:
            blurred = apply_occluding_defocus(source, radius, inverse_depth.to(dtype), K, self.softness)
        else:
            blurred = apply_soft_disk_defocus(source, radius, K, self.softness)
        return linear_rgb_to_rgb(blurred) if linear_light else blurred
