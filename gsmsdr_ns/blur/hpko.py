"""HPKO: Hierarchical Progressive Kernel Optimization (paper section 3.3, Table 1, section 4.1).

Scales are numbered as in the paper: s = 3 (coarsest, images downsampled by 2^(s-1) = 4, kernel K_3 = 5),
s = 2 (1/2, K_2 = 9), s = 1 (full resolution, K_1 = 17). Kernel sizes are given coarse to fine, so
``kernel_sizes[num_scales - s]`` is K_s.

* :class:`HPKOHeads` holds the per-scale heads M_base^s, M_blur^s, M_mask^s (1x1 convs, i.e. per-pixel MLPs).
* :class:`HPKOScheduler` says which scale is active at a step: pure queries of its hyperparameters, no running
  state. The degradation model asks ``scale_at(step, d)`` with the downscale factor it is actually rendering at,
  so that the kernel scale can never drift from splatfacto's resolution schedule.
* :func:`hpko_scales` numbers the scales; the scheduler, the heads and the field all take them from it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Optional, Sequence, Tuple, cast

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gsmsdr_ns.io.errors import InputError

__all__ = [
    "ScaleInfo",
    "hpko_scales",
    "downsample_for_scale",
    "MAX_KERNEL_SIZE",
    "MAX_VIEW_KERNEL_SIZE",
    "kernel_size_limit",
    "check_kernel_sizes",
    "kernel_prior_logits",
    "kernel_upsample_matrix",
    "HPKOScheduler",
    "HPKOHeads",
    "ViewKernels",
]


class ScaleInfo(NamedTuple):
    """One HPKO scale: its index s, kernel size K_s and image downsample factor 2^(s-1)."""

    scale: int
    kernel_size: int
    downsample: int


def downsample_for_scale(scale: int) -> int:
    """Image downsample factor of scale s: 2^(s-1)."""
    if scale < 1:
        raise ValueError(f"HPKO scales start at 1, got {scale}")
    return 2 ** (scale - 1)


def hpko_scales(num_kernel_sizes: int, enabled: bool = True) -> Tuple[int, ...]:
    """Scale indices, coarse to fine: (S, ..., 2, 1) for S kernel sizes, or (1,) without HPKO."""
    return tuple(range(int(num_kernel_sizes), 0, -1)) if enabled else (1,)


MAX_KERNEL_SIZE = 33
"""Largest per-pixel blur kernel (pixels across): twice the paper's 17. At 33 a 600x400 image's per-pixel kernels
already hold 261M weights; larger sizes only exhaust memory (999 asked for terabytes)."""

MAX_VIEW_KERNEL_SIZE = 129
"""Largest per-view blur kernel (a field without per-pixel kernels: mode ``view``): one K x K kernel per image,
applied by an FFT, so its cost hardly grows with K; 129 px covers the shake of a 1300 px capture (about 2x the 33 px
of a 600 px one, doubled again for margin)."""


def kernel_size_limit(pixel_kernels: bool) -> int:
    """Largest kernel size allowed: ``MAX_KERNEL_SIZE`` where kernels are predicted per pixel (K^2 weights per
    pixel), ``MAX_VIEW_KERNEL_SIZE`` where there is one kernel per image."""
    return MAX_KERNEL_SIZE if pixel_kernels else MAX_VIEW_KERNEL_SIZE


def check_kernel_sizes(kernel_sizes: Sequence[int], max_size: int = MAX_KERNEL_SIZE) -> Tuple[int, ...]:
    """Validate coarse-to-fine kernel sizes: non-empty, odd, in [1, ``max_size``] and non-decreasing. Returns them
    as a tuple; InputError (a ValueError) naming the allowed range otherwise."""
    ks = tuple(int(k) for k in kernel_sizes)
    if not ks or any(k < 1 or k % 2 == 0 or k > max_size for k in ks):
        wider = max_size < MAX_VIEW_KERNEL_SIZE
        per_view = f"; per-view kernels (mode view) up to {MAX_VIEW_KERNEL_SIZE}" if wider else ""
        raise InputError(
            f"gsmsdr: blur kernel sizes must be odd integers from 1 to {max_size}{per_view} "
            f"(--pipeline.model.blur-field.kernel-sizes), got {list(kernel_sizes)}"
        )
    if any(b < a for a, b in zip(ks, ks[1:])):
        raise ValueError(f"kernel sizes are listed coarse to fine and must not decrease, got {list(ks)}")
    return ks


@dataclass
class HPKOScheduler:
    """Which HPKO scale is trained at a given step.

    Default: the scale follows splatfacto's resolution schedule (downscale ``2^max(num_downscales - step //
    resolution_schedule, 0)``), i.e. with the defaults s = 3 before step 3000, s = 2 before 6000, then s = 1.
    ``switch_steps`` overrides that with explicit steps. With ``enabled=False`` (no HPKO, RE-only) there is a
    single scale, s = 1 with the finest kernel, at every step.
    """

    kernel_sizes: Tuple[int, ...] = (5, 9, 17)
    """Kernel size per scale, coarse to fine (K_3, K_2, K_1)."""
    num_downscales: int = 2
    """splatfacto's ``num_downscales``: training starts at 1 / 2^num_downscales resolution."""
    resolution_schedule: int = 3000
    """splatfacto's ``resolution_schedule``: steps between resolution doublings."""
    switch_steps: Optional[Tuple[int, ...]] = None
    """Steps at which the scale goes one level finer (len = number of scales - 1, increasing); None: derived
    from the resolution schedule."""
    warmup: int = 250
    """The blur field is skipped for steps < warmup (BAGS: 250)."""
    enabled: bool = True
    """False: no coarse-to-fine HPKO, one full-resolution scale with the finest kernel size."""

    def __post_init__(self) -> None:
        # the field checks its own limit (per-pixel or per-view kernels)
        self.kernel_sizes = check_kernel_sizes(self.kernel_sizes, MAX_VIEW_KERNEL_SIZE)
        if self.switch_steps is not None:
            self.switch_steps = tuple(int(s) for s in self.switch_steps)
            if len(self.switch_steps) != len(self.kernel_sizes) - 1 or any(
                b <= a for a, b in zip(self.switch_steps, self.switch_steps[1:])
            ):
                raise ValueError(
                    f"switch_steps must hold {len(self.kernel_sizes) - 1} increasing steps (one per scale change), "
                    f"got {list(self.switch_steps)}"
                )
        if self.num_downscales < 0 or self.resolution_schedule < 1 or self.warmup < 0:
            raise ValueError("num_downscales and warmup must be >= 0 and resolution_schedule >= 1")

    # ------------------------------------------------------------------------------------------ pure queries

    @property
    def scales(self) -> Tuple[int, ...]:
        """Active scale indices, coarse to fine: (3, 2, 1) by default, (1,) without HPKO."""
        return hpko_scales(len(self.kernel_sizes), self.enabled)

    def info(self, scale: int) -> ScaleInfo:
        """ScaleInfo of scale s."""
        if scale not in self.scales:
            raise ValueError(f"scale {scale} is not one of the active scales {self.scales}")
        return ScaleInfo(scale, self.kernel_sizes[len(self.kernel_sizes) - scale], downsample_for_scale(scale))

    def downscale_for_step(self, step: int) -> int:
        """splatfacto's training downscale factor at ``step`` (``SplatfactoModel._get_downscale_factor``)."""
        return 2 ** max(self.num_downscales - step // self.resolution_schedule, 0)

    def scale_for_step(self, step: int) -> ScaleInfo:
        """The scale to train at ``step`` (pure: the same answer whatever happened before)."""
        if not self.enabled:
            return self.info(1)
        if self.switch_steps is None:
            return self.scale_for_downscale(self.downscale_for_step(step))
        finer = sum(1 for s in self.switch_steps if step >= s)
        return self.info(len(self.kernel_sizes) - finer)

    def scale_for_downscale(self, downscale: float) -> ScaleInfo:
        """The scale matching a render downscale factor d (a power of two): s = log2(d) + 1, clamped to the
        coarsest scale (a render coarser than 2^(S-1) still uses K_S). Always s = 1 without HPKO."""
        if not self.enabled:
            return self.info(1)
        level = math.log2(float(downscale)) if downscale > 0 else float("nan")
        if not (level >= 0 and abs(level - round(level)) < 1e-6):
            raise ValueError(f"downscale factor must be a power of two >= 1, got {downscale}")
        return self.info(min(int(round(level)) + 1, len(self.kernel_sizes)))

    def is_active(self, step: int) -> bool:
        """Whether the blur field runs at ``step`` (False during warm-up)."""
        return step >= self.warmup

    def scale_at(self, step: int, downscale: float) -> Optional[ScaleInfo]:
        """The scale the blur field runs at on ``step`` for a render at 1 / ``downscale``: None during warm-up; the
        render's own scale (:meth:`scale_for_downscale`), or the step's when ``switch_steps`` are set."""
        if not self.is_active(step):
            return None
        return self.scale_for_downscale(downscale) if self.switch_steps is None else self.scale_for_step(step)


def kernel_prior_logits(kernel_size: int, sigma: float, floor: float = -8.0) -> Tensor:
    """Logits of a centred isotropic Gaussian kernel: ``max(-r^2 / (2 sigma^2), floor)``, r in pixels.

    Returns [K * K] (row-major window index). The floor keeps the outer taps learnable: a softmax tap at logit -100
    would get no gradient, one at -8 still does (Adam normalises its small gradient).
    """
    if sigma <= 0:
        raise ValueError(f"kernel prior sigma must be > 0, got {sigma}")
    r = torch.arange(kernel_size, dtype=torch.float64) - (kernel_size - 1) / 2
    r2 = r[:, None] ** 2 + r[None, :] ** 2
    return (-r2 / (2.0 * sigma**2)).clamp_min(floor).reshape(-1).float()


def kernel_upsample_matrix(coarse_size: int, fine_size: int, factor: int = 2) -> Tensor:
    """Linear map taking a coarse kernel's logits (taps ``factor`` fine pixels apart) to a fine kernel's logits.

    Fine tap at offset u (fine pixels) reads the coarse logits bilinearly at u / factor; taps beyond the coarse
    window read its border (replicate). Returns [fine_size^2, coarse_size^2]; rows sum to 1.
    """
    cc, fc = (coarse_size - 1) / 2, (fine_size - 1) / 2

    def axis_weights() -> Tensor:
        w = torch.zeros(fine_size, coarse_size, dtype=torch.float64)
        for i in range(fine_size):
            x = min(max((i - fc) / factor + cc, 0.0), coarse_size - 1.0)
            lo = min(int(math.floor(x)), coarse_size - 1)
            hi = min(lo + 1, coarse_size - 1)
            t = x - lo
            w[i, lo] += 1.0 - t
            w[i, hi] += t
        return w

    a = axis_weights()
    return torch.einsum("ia,jb->ijab", a, a).reshape(fine_size**2, coarse_size**2).float()


class HPKOHeads(nn.Module):
    """Per-scale heads (paper eqs. 11-13), stacked coarse to fine as in BAGS.

    ``M_base^S`` maps the MCF/MCA features to ``mid`` channels (1x1 conv + ReLU); each finer scale's base takes the
    previous (coarser) base output: ``f_mid^s = M_base^s(f_mid^(s+1))``, so a finer scale starts from what the
    coarser one learnt. ``k^s = softmax_K(z^s)`` (K_s^2 channels) and ``m^s = sigmoid(y^s)`` where, with
    ``progressive`` (default), each finer scale refines the coarser one's prediction::

        z^s = U_s z^(s+1) + M_blur^s(f_mid^s),   y^s = y^(s+1) + M_mask^s(f_mid^s)

    (U_s: :func:`kernel_upsample_matrix`, the coarse kernel re-sampled on the 2x finer pixel grid). The finer heads
    start near zero, so when HPKO switches scale the kernel keeps the blur extent learnt so far instead of
    restarting from a random one. The coarsest head (every head without ``progressive``) starts from a narrow
    centred Gaussian (``prior_sigma`` pixels, :func:`kernel_prior_logits`): the simulated blur starts close to the
    render, so an untrained field does not blur everything and teach the mask to switch itself off.

    With ``num_views > 0`` each scale also holds a per-view logit table ``v^s`` [num_views, K_s^2] (zeros at
    start) added at every pixel of that view: ``z^s += v^s[view]``. Camera shake blurs a whole photo along one
    path; a per-view kernel learns that path from every pixel's gradient at once, and the per-pixel heads only
    model how the blur varies across the image. ``pixel_kernels=False`` keeps the kernel heads' bias (the prior)
    but drops their per-pixel part.

    ``forward(features [B, C, H, W], scale, view_ids [B] | None) -> (kernel_weights [B, K_s^2, H, W],
    mask [B, 1, H, W])`` (``view_ids`` required with per-view tables).
    Kernel index k = i * K + j is row i, column j of the K x K window (row-major, like ``F.unfold``).
    """

    def __init__(
        self,
        in_channels: int,
        mid_channels: int,
        kernel_sizes: Sequence[int],
        scales: Sequence[int],
        progressive: bool = True,
        prior_sigma: float = 0.5,
        mask_init: float = 0.5,
        head_init_scale: float = 0.1,
        num_views: int = 0,
        pixel_kernels: bool = True,
    ):
        super().__init__()
        ks = check_kernel_sizes(kernel_sizes, kernel_size_limit(pixel_kernels))
        if not 0.0 < mask_init < 1.0:
            raise ValueError(f"mask_init must be in (0, 1), got {mask_init}")
        self.scales = tuple(scales)  # coarse to fine
        self.kernel_sizes = {s: ks[len(ks) - s] for s in self.scales}
        self.progressive = bool(progressive)
        self.pixel_kernels = bool(pixel_kernels)
        if num_views < 0 or (num_views == 0 and not pixel_kernels):
            raise ValueError("HPKOHeads needs per-pixel kernel heads, per-view kernels (num_views > 0), or both")
        self.num_views = int(num_views)
        # per-view kernel logits (one K_s x K_s kernel per training view and scale), added to the heads' logits
        self.view_logits = nn.ParameterDict()
        self.base = nn.ModuleDict()
        self.blur = nn.ModuleDict()
        self.mask = nn.ModuleDict()
        c = in_channels
        previous = None
        for s in self.scales:
            k = self.kernel_sizes[s]
            self.base[str(s)] = nn.Sequential(nn.Conv2d(c, mid_channels, 1), nn.ReLU())
            blur = self.blur[str(s)] = nn.Conv2d(mid_channels, k * k, 1)
            mask = self.mask[str(s)] = nn.Conv2d(mid_channels, 1, 1)
            with torch.no_grad():
                # small per-pixel variation around the bias: the kernels start as the prior (or the coarser kernel)
                blur.weight.mul_(head_init_scale)
                mask.weight.mul_(head_init_scale)
                assert blur.bias is not None and mask.bias is not None  # built with a bias
                if previous is None or not self.progressive:
                    blur.bias.copy_(kernel_prior_logits(k, prior_sigma))
                    mask.bias.fill_(math.log(mask_init / (1.0 - mask_init)))
                else:
                    blur.bias.zero_()
                    mask.bias.zero_()
            if self.num_views:
                self.view_logits[str(s)] = nn.Parameter(torch.zeros(self.num_views, k * k))
            if previous is not None and self.progressive:
                matrix = kernel_upsample_matrix(self.kernel_sizes[previous], k)
                self.register_buffer(f"upsample_{s}", matrix[:, :, None, None], persistent=False)
            previous = s
            c = mid_channels

    def forward(self, features: Tensor, scale: int, view_ids: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
        if scale not in self.scales:
            raise ValueError(f"scale {scale} is not one of this field's scales {self.scales}")
        if self.num_views and (view_ids is None or view_ids.shape != features.shape[:1]):
            raise ValueError(f"per-view kernels need view_ids of shape [{features.shape[0]}]")
        f = features
        logits = mask_logits = None
        for s in self.scales:  # coarse to fine, stop at the requested scale
            f = self.base[str(s)](f)
            if self.progressive or s == scale:
                blur = cast(nn.Conv2d, self.blur[str(s)])
                z, y = blur(f), self.mask[str(s)](f)
                if not self.pixel_kernels:
                    assert blur.bias is not None  # the heads' convolutions are built with a bias
                    z = blur.bias[None, :, None, None].expand_as(z)
                if self.num_views:
                    assert view_ids is not None  # checked on entry when there are per-view kernels
                    z = z + self.view_logits[str(s)][view_ids.long()][:, :, None, None].to(z.dtype)
                if self.progressive and logits is not None:
                    upsample = getattr(self, f"upsample_{s}")
                    z = z + F.conv2d(logits, upsample.to(logits.dtype))
                    y = y + mask_logits
                logits, mask_logits = z, y
            if s == scale:
                break
        assert logits is not None and mask_logits is not None  # scale is one of self.scales: the loop set them
        return F.softmax(logits, dim=1), torch.sigmoid(mask_logits)

    def per_view_parameters(self):
        """The per-view logit tables (their own optimizer group)."""
        return list(self.view_logits.parameters())

    def parameters_for_scale(self, scale: int):
        """The head parameters that take part in ``forward(., scale)``."""
        for s in self.scales:
            yield from self.base[str(s)].parameters()
            if self.progressive or s == scale:
                yield from self.blur[str(s)].parameters()
                yield from self.mask[str(s)].parameters()
                if self.num_views:
                    yield self.view_logits[str(s)]
            if s == scale:
                break


class ViewKernels(nn.Module):
    """One kernel per training view and scale, no feature network (blur field mode ``view``).

    Camera shake moves the whole photo along one path: one K_s x K_s kernel per view explains most of it at the cost
    of a depthwise convolution. Kernel logits ``z^s`` [num_views, K_s^2] start as the narrow prior at the coarsest
    scale; with ``progressive`` each finer scale adds its table to the coarser kernel re-sampled on its grid
    (:func:`kernel_upsample_matrix`), as :class:`HPKOHeads` does. The mask is 1: a per-view blend
    ``m * k + (1 - m) * identity`` is itself a kernel, so a learnt mask adds nothing but, under the mask
    regulariser, a pull toward less blur.

    ``forward(view_ids [B], scale, height, width) -> (kernel_weights [B, K_s^2, H, W], mask [B, 1, H, W])``, both
    expanded (stride 0) over the pixels: ``BlurField.degrade`` applies such kernels as one convolution.
    """

    def __init__(
        self,
        num_views: int,
        kernel_sizes: Sequence[int],
        scales: Sequence[int],
        progressive: bool = True,
        prior_sigma: float = 0.5,
    ):
        super().__init__()
        ks = check_kernel_sizes(kernel_sizes, kernel_size_limit(pixel_kernels=False))
        if num_views < 1:
            raise ValueError(f"num_views must be >= 1, got {num_views}")
        self.num_views = int(num_views)
        self.scales = tuple(scales)  # coarse to fine
        self.kernel_sizes = {s: ks[len(ks) - s] for s in self.scales}
        self.progressive = bool(progressive)
        self.view_logits = nn.ParameterDict()
        previous = None
        for s in self.scales:
            k = self.kernel_sizes[s]
            if previous is None or not self.progressive:
                z = kernel_prior_logits(k, prior_sigma).expand(self.num_views, -1).clone()
            else:
                z = torch.zeros(self.num_views, k * k)
                matrix = kernel_upsample_matrix(self.kernel_sizes[previous], k)
                self.register_buffer(f"upsample_{s}", matrix, persistent=False)
            self.view_logits[str(s)] = nn.Parameter(z)
            previous = s

    def forward(self, view_ids: Tensor, scale: int, height: int, width: int) -> Tuple[Tensor, Tensor]:
        if scale not in self.scales:
            raise ValueError(f"scale {scale} is not one of this field's scales {self.scales}")
        ids = view_ids.long()
        logits = None
        for s in self.scales:
            if self.progressive or s == scale:
                z = self.view_logits[str(s)][ids]
                if self.progressive and logits is not None:
                    z = z + logits @ getattr(self, f"upsample_{s}").t()
                logits = z
            if s == scale:
                break
        assert logits is not None  # scale is one of self.scales: the loop set it
        kernels = F.softmax(logits, dim=1)[:, :, None, None].expand(-1, -1, height, width)
        mask = kernels.new_ones(1, 1, 1, 1).expand(len(ids), 1, height, width)
        return kernels, mask

    def per_view_parameters(self):
        return list(self.parameters())

    def parameters_for_scale(self, scale: int):
        """The tables that take part in ``forward(., scale)``."""
        for s in self.scales:
            if self.progressive or s == scale:
                yield self.view_logits[str(s)]
            if s == scale:
                break
