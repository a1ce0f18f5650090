"""Thin-lens defocus from the rendered depth: per-pixel disk kernels with a learnt aperture and focus per view.

A thin lens focused at distance d_f images a point at depth d as a disk whose radius, in pixels, is proportional
to ``|1/d - 1/d_f|`` (``gsmsdr_ns.degrade.kernels.defocus_radius``). For a defocused training photo the blur of
every pixel therefore follows from the rendered depth and two numbers per photo: the aperture (the radius per
unit of inverse depth) and the focus (an inverse depth). Learning those two numbers from every pixel of the photo
is far better posed than learning a free kernel per pixel, which is what the feature network would have to do.

Pure functions first (shapes in the docstrings), then :class:`ThinLensDefocus`, the learnable per-view lens. The
kernels are for inspection (the viewer's blur size); training applies the lens with the fused ops of
:mod:`gsmsdr_ns.blur.defocus_op`, which never hold the K*K weights (:meth:`ThinLensDefocus.blur`).
"""

from __future__ import annotations

import math
from typing import Optional

import torch
import torch.nn.functional as F
from kornia.color import linear_rgb_to_rgb, rgb_to_linear_rgb
from torch import Tensor, nn

from .defocus_op import apply_occluding_defocus, apply_soft_disk_defocus
from .maan import check_bchw, check_view_ids

__all__ = [
    "soft_disk_kernels",
    "occluding_disk_kernels",
    "thin_lens_radius",
    "lens_window",
    "ThinLensDefocus",
    "apply_occluding_defocus",
    "apply_soft_disk_defocus",
]


def _check_window(kernel_size: int, softness: float) -> None:
    if kernel_size < 1 or kernel_size % 2 == 0:
        raise ValueError(f"kernel_size must be a positive odd integer, got {kernel_size}")
    if not softness > 0:
        raise ValueError(f"softness must be > 0, got {softness}")


def _disk_coverage(radius: Tensor, kernel_size: int, softness: float) -> Tensor:
    """Soft coverage of each window tap by a disk: radius [B, 1 or K*K, H, W] -> [B, K*K, H, W] (unnormalised;
    the centre tap 1; the other taps 0 at radius 0)."""
    half = kernel_size // 2
    offsets = torch.arange(kernel_size, device=radius.device, dtype=radius.dtype) - half
    tap_distance = torch.sqrt(offsets[:, None] ** 2 + offsets[None, :] ** 2).reshape(1, -1, 1, 1)
    coverage = torch.sigmoid((radius - tap_distance) / softness) - torch.sigmoid(-tap_distance / softness)
    return torch.where(tap_distance == 0, torch.ones_like(coverage), coverage)


def soft_disk_kernels(radius: Tensor, kernel_size: int, softness: float = 0.25) -> Tensor:
    """Per-pixel disk kernels with a soft edge.

    A tap at distance r_k > 0 from the centre gets weight ``s((radius - r_k) / softness) - s(-r_k / softness)``
    (s: the sigmoid), the centre tap 1, normalised to sum to 1: the pixel's area coverage by the disk (which ramps
    from 1 to 0 between r_k = radius - 0.5 and radius + 0.5, as the degradation simulator's ``disk_kernel``; the
    centre pixel is always covered), smoothed so that every weight is differentiable in the radius, and shifted so
    that radius 0 is exactly the identity (an in-focus pixel stays sharp) while its gradient there is not ~0. Radii
    beyond the window are truncated to it.

    Args:
        radius: [B, 1, H, W] disk radius in pixels, >= 0.
        kernel_size: odd window size K.
        softness: edge width in pixels (> 0).
    Returns:
        [B, K*K, H, W] weights (row-major window index, as ``apply_pixel_kernels``), summing to 1 over dim 1.
    """
    _check_window(kernel_size, softness)
    if radius.dim() != 4 or radius.shape[1] != 1:
        raise ValueError(f"radius must be [B, 1, H, W], got {list(radius.shape)}")
    weights = _disk_coverage(radius, kernel_size, softness)
    return weights / weights.sum(dim=1, keepdim=True)


def occluding_disk_kernels(radius: Tensor, inverse_depth: Tensor, kernel_size: int, softness: float = 0.25) -> Tensor:
    """Per-pixel defocus kernels that let each neighbour spread its own disk, with depth occlusion.

    A defocused photo is every scene point spread over its own circle of confusion, and a sharp object in front
    hides the blurred background behind it. Pixel p therefore gathers neighbour q (at distance r_k) with the soft
    coverage of :func:`soft_disk_kernels` at q's radius, divided by q's disk area ``1 + pi r_q^2`` (q's light is
    shared over its disk), except that a neighbour behind p (smaller inverse depth) reaches no further than p's
    own radius: an in-focus foreground pixel takes nothing from the blurred background, a blurred foreground
    spreads over what lies behind it. Weights are normalised per pixel. With one radius and one depth everywhere
    this is :func:`soft_disk_kernels`; radius 0 everywhere is the identity.

    Args:
        radius: [B, 1, H, W] disk radius in pixels, >= 0 (differentiable).
        inverse_depth: [B, 1, H, W] 1 / depth (only compared, never differentiated).
        kernel_size: odd window size K.
        softness: edge width in pixels (> 0).
    Returns:
        [B, K*K, H, W] weights (row-major window index, as ``apply_pixel_kernels``), summing to 1 over dim 1.
    """
    _check_window(kernel_size, softness)
    if radius.dim() != 4 or radius.shape[1] != 1 or inverse_depth.shape != radius.shape:
        raise ValueError(
            f"radius and inverse_depth must both be [B, 1, H, W], got {list(radius.shape)} and "
            f"{list(inverse_depth.shape)}"
        )
    B, _, H, W = radius.shape
    half = kernel_size // 2

    def neighbours(x: Tensor) -> Tensor:  # [B, 1, H, W] -> [B, K*K, H, W]: x at p + offset k
        return F.unfold(F.pad(x, (half,) * 4, mode="replicate"), kernel_size).view(B, kernel_size**2, H, W)

    radius_q = neighbours(radius)
    behind = neighbours(inverse_depth.detach().to(radius.dtype)) < inverse_depth.detach().to(radius.dtype)
    reach = torch.where(behind, torch.minimum(radius_q, radius), radius_q)
    weights = _disk_coverage(reach, kernel_size, softness) / (1.0 + math.pi * radius_q**2)
    return weights / weights.sum(dim=1, keepdim=True)


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
        most ``max_kernel_size`` (radii beyond it are truncated).
        """
        radius, inverse_depth, K = self._lens(depth, view_ids, max_kernel_size, pixel_scale)
        if image is not None:
            return self._blur(image, radius, inverse_depth, K, linear_light)
        if not self.occlusion:
            return soft_disk_kernels(radius, K, self.softness)
        return occluding_disk_kernels(radius, inverse_depth, K, self.softness)

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
