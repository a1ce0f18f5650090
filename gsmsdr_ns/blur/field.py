"""The GS-MSDR blur field: MAAN features -> HPKO heads -> per-pixel blur kernels and masks.

``BlurField.forward(render, depth, view_ids, scale)`` predicts, for each pixel of a training view rendered at the
resolution of HPKO scale s, a K_s x K_s kernel (softmax weights) and a blending mask; ``degrade`` applies them::

    degraded = m * apply_pixel_kernels(render, k) + (1 - m) * render

which is compared with the (blurry) training image. Test views are rendered without the field (sharp).

Modes (paper Table 7):

* ``full``     MAAN (SFE + 2 FANs of GAKA/SAFM) -> MCF -> MCA -> HPKO heads (3 scales);
* ``msd_only`` HPKO heads on BAGS' plain CNN features (MCF without FANs, no MCA): multi-scale deblurring only;
* ``re_only``  MAAN features with one full-resolution kernel scale (K_1) and no coarse-to-fine HPKO
  (= Table 6's "-HPKO" row);
* ``view``     (ours, not in the paper) one kernel per training view and scale (mask 1), no feature network:
  camera shake at the cost of a depthwise convolution (:class:`ViewKernels`).

The ablation switches ``gaka``, ``safm``, ``mca``, ``rgbd``, ``hpko`` (Table 6) remove their modules' parameters.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Dict, List, Literal, NamedTuple, Optional, Tuple, Union

from kornia.color import linear_rgb_to_rgb, rgb_to_linear_rgb
from torch import Tensor, nn

from gsmsdr_ns.ops.grid_kernels import GridKernels, apply_grid_kernels, pool_to_grid, upsample_grid
from gsmsdr_ns.ops.pixel_kernels import apply_image_kernels, apply_pixel_kernels

from .hpko import HPKOHeads, ViewKernels, check_kernel_sizes, hpko_scales, kernel_size_limit
from .maan import MCA, BAGSFeatures, ContextualFeatures, RGBDFeatures, check_bchw, check_view_ids

__all__ = ["BlurFieldConfig", "BlurField", "BlurFieldDims", "BlurFieldModules"]

_SIZE_PRESETS = {
    # feature_dim n, view_dim, pos_channels, mid_channels, num_fans
    "default": (32, 32, 16, 64, 2),
    "lite": (16, 16, 8, 32, 2),
}


class BlurFieldDims(NamedTuple):
    """Resolved widths of a blur field (config values, or the size preset where the config says None)."""

    feature_dim: int
    view_dim: int
    pos_channels: int
    mid_channels: int
    num_fans: int


class BlurFieldModules(NamedTuple):
    """Which modules a config builds, after the mode is applied (True = present)."""

    maan: bool  # FANs (GAKA / SAFM) as the RGB-D feature network; False: BAGS' plain CNN
    gaka: bool
    safm: bool
    mca: bool
    rgbd: bool  # depth is an input of the feature network
    hpko: bool  # coarse-to-fine scales; False: a single full-resolution scale


@dataclass
class BlurFieldConfig:
    """GS-MSDR blur field (MAAN + HPKO). Plain dataclass (no nerfstudio import); ``setup(**kwargs)`` builds it."""

    mode: Literal["full", "msd_only", "re_only", "view"] = "full"
    """full: MAAN + HPKO. msd_only: HPKO on BAGS' plain CNN (no GAKA/SAFM/MCA). re_only: MAAN with a single
    full-resolution kernel scale (no HPKO). view: one kernel per training view and HPKO scale, no feature
    network (fast; camera shake only). The mode overrides the module switches below."""
    size: Literal["default", "lite"] = "default"
    """Width preset for fields left at None: default (n=32, view 32, pos 16, mid 64: BAGS' 80-channel MCF) or
    lite (n=16, view 16, pos 8, mid 32) for CPU training."""
    feature_dim: Optional[int] = None
    """FAN width n (channels of the RGB-D features); None: from ``size``."""
    view_dim: Optional[int] = None
    """Width of the learnable per-training-view embedding l(i) (0: none); None: from ``size``."""
    pos_channels: Optional[int] = None
    """Channels of the 2D sinusoidal positional encoding p(x), a multiple of 4 (0: none); None: from ``size``."""
    mid_channels: Optional[int] = None
    """Width of the per-scale base heads M_base^s; None: from ``size``."""
    num_fans: Optional[int] = None
    """Number of Feature Attention Networks after the shallow 3x3 extractor (paper: 2); None: from ``size``."""
    feature_downsample: int = 4
    """The feature network, MCA and heads run on the render averaged over cells of this many pixels squared (1:
    every pixel, as in the paper); the kernels and masks they predict are resampled bilinearly to every pixel when
    they are applied. Blur varies smoothly across a photo, so the coarse grid predicts nearly the same kernels for
    a fraction of the network's time and memory."""
    feature_grid_cells: int = 4096
    """With ``feature_downsample`` > 1 and this > 0, larger cells on a render that would have more than this many:
    the factor becomes ``ceil(sqrt(H * W / feature_grid_cells))``, so the network costs about the same at any photo
    size (0: always ``feature_downsample``). 4096 changes nothing up to 256x256 px and keeps the field's cost flat
    above (7 px cells at 458x333, 8 at 600x400, 17 at 1297x866)."""
    kernel_sizes: Tuple[int, ...] = (5, 9, 17)
    """Blur kernel size per HPKO scale, coarse to fine (K_3, K_2, K_1); odd, non-decreasing."""
    gaka: bool = True
    """Global-Aware Kernel Attention inside each FAN (Table 6 ablation)."""
    safm: bool = True
    """Spatial Adaptive Fusion Module inside each FAN (Table 6 ablation)."""
    mca: bool = True
    """Multi-modal Context Adapter on the contextual features (Table 6 ablation)."""
    rgbd: bool = True
    """Feed the normalised rendered depth to the feature network (Table 6 "RGBD"); False: RGB only, no depth
    is read or normalised."""
    hpko: bool = True
    """Coarse-to-fine kernel scales (Table 6 "HPKO"); False: one full-resolution scale with the finest kernel."""
    progressive: bool = True
    """Each finer HPKO scale refines the coarser scale's kernel (its logits re-sampled on the finer grid, plus a
    residual head that starts near zero), so a scale switch keeps the blur learnt so far. False: independent heads
    (BAGS), each starting from the prior."""
    kernel_prior_sigma: float = 0.5
    """Width (pixels at the coarsest scale) of the centred Gaussian the kernels start from: the untrained field
    simulates almost no blur, instead of a near-uniform kernel that blurs everything."""
    mask_init: float = 0.9
    """Initial blending mask m (the coarsest head's bias), in (0, 1): high, since the field only runs on images
    believed blurred; the regulariser lowers it where blur does not matter. Mode view has no mask (m = 1)."""
    view_kernels: bool = True
    """Add a learnable per-view kernel (one K_s x K_s logit table per training view and scale) to the predicted
    per-pixel kernels: camera shake blurs a whole image along one path, which a per-view kernel captures with few
    parameters; the heads model how the blur varies across the image. Trained in the ``blur_view_kernels``
    optimizer group."""
    pixel_kernels: bool = True
    """Per-pixel kernel heads (M_blur^s). False: the kernel is the prior plus the per-view kernel only (needs
    ``view_kernels``); the mask heads stay."""
    mca_pool_size: int = 8
    """Output grid (P x P) of MCA's adaptive average pooling for the spatial context weights."""
    msd_hidden: int = 64
    """Hidden width of BAGS' plain CNN (msd_only mode)."""
    layer_scale_init: float = 0.1
    """Initial value of the learnable residual scales of GAKA and SAFM."""
    detach_inputs: bool = True
    """Feed detached render and depth to the feature network (BAGS); gradients reach the Gaussians through the
    kernel application only."""

    def __post_init__(self) -> None:
        if self.mode not in ("full", "msd_only", "re_only", "view"):
            raise ValueError(f"mode must be full, msd_only, re_only or view, got {self.mode!r}")
        if self.size not in _SIZE_PRESETS:
            raise ValueError(f"size must be one of {sorted(_SIZE_PRESETS)}, got {self.size!r}")
        check_kernel_sizes(self.kernel_sizes, self.max_kernel_size)
        dims = self.dims
        if dims.feature_dim < 2 or dims.mid_channels < 1 or dims.view_dim < 0 or dims.num_fans < 0:
            raise ValueError(f"invalid blur field widths {dims}")
        if not (self.view_kernels or self.pixel_kernels):
            raise ValueError("a blur field needs pixel_kernels, view_kernels or both")
        if not self.kernel_prior_sigma > 0:
            raise ValueError(f"kernel_prior_sigma must be > 0, got {self.kernel_prior_sigma}")
        if int(self.feature_downsample) != self.feature_downsample or self.feature_downsample < 1:
            raise ValueError(f"feature_downsample must be an integer >= 1, got {self.feature_downsample}")
        if int(self.feature_grid_cells) != self.feature_grid_cells or self.feature_grid_cells < 0:
            raise ValueError(f"feature_grid_cells must be an integer >= 0, got {self.feature_grid_cells}")
        if dims.pos_channels < 0 or dims.pos_channels % 4:
            raise ValueError(f"pos_channels must be a non-negative multiple of 4, got {dims.pos_channels}")

    @property
    def max_kernel_size(self) -> int:
        """Largest kernel size allowed (:func:`~gsmsdr_ns.blur.hpko.kernel_size_limit`): mode ``view`` has no
        per-pixel kernels."""
        return kernel_size_limit(self.mode != "view" and self.pixel_kernels)

    @property
    def dims(self) -> BlurFieldDims:
        preset = _SIZE_PRESETS[self.size]
        values = (self.feature_dim, self.view_dim, self.pos_channels, self.mid_channels, self.num_fans)
        return BlurFieldDims(*(p if v is None else int(v) for v, p in zip(values, preset)))

    @property
    def modules(self) -> BlurFieldModules:
        if self.mode == "msd_only":
            return BlurFieldModules(False, False, False, False, self.rgbd, self.hpko)
        if self.mode == "view":
            return BlurFieldModules(False, False, False, False, False, self.hpko)
        if self.mode == "re_only":
            return BlurFieldModules(True, self.gaka, self.safm, self.mca, self.rgbd, False)
        return BlurFieldModules(True, self.gaka, self.safm, self.mca, self.rgbd, self.hpko)

    def for_schedule(self, num_downscales: int, switch_steps: Optional[Tuple[int, ...]] = None) -> "BlurFieldConfig":
        """This config with only the HPKO scales a resolution schedule starting at 1 / 2^num_downscales visits.

        A scale coarser than the first training resolution would never be trained, yet with ``progressive`` heads
        its untrained kernel would be where the finer ones start; dropping it keeps every trained scale starting
        from the prior at its own resolution. Unchanged with explicit ``switch_steps`` or without HPKO.
        """
        if switch_steps is not None or not self.modules.hpko:
            return self
        keep = max(1, min(len(self.kernel_sizes), int(num_downscales) + 1))
        return dataclasses.replace(self, kernel_sizes=tuple(self.kernel_sizes)[-keep:])

    def __setstate__(self, state: Dict[str, Any]) -> None:
        """Loading a config.yml (or a pickle): fields added since it was written take their defaults."""
        defaults = {f.name: f.default for f in dataclasses.fields(self) if f.default is not dataclasses.MISSING}
        self.__dict__.update({**defaults, **state})

    def grid_factor(self, size: Tuple[int, int]) -> int:
        """The feature grid's cell size (pixels) on a render of ``size`` (H, W)."""
        factor = int(self.feature_downsample)
        if factor > 1 and self.feature_grid_cells > 0:
            factor = max(factor, math.ceil(math.sqrt(size[0] * size[1] / self.feature_grid_cells)))
        return factor

    def setup(self, **kwargs: Any) -> "BlurField":
        """Build the field; kwargs are run-time values (``num_train_views``, optional ``use_depth``)."""
        return BlurField(self, **kwargs)


def blend(mask: Tensor, blurred: Tensor, sharp: Tensor) -> Tensor:
    """``mask * blurred + (1 - mask) * sharp``: the field's mask chooses, per pixel, how much of the blur a photo
    shows. mask [B, 1, H, W], blurred and sharp [B, C, H, W] -> [B, C, H, W]."""
    return mask * blurred + (1.0 - mask) * sharp


class BlurField(nn.Module):
    """Per-pixel blur kernels and masks for training views (GS-MSDR).

    Args:
        config: the field's hyperparameters.
        num_train_views: rows of the view embedding; ``view_ids`` index training views in [0, num_train_views).
        use_depth: False forces an RGB-only feature network (e.g. the degradation profile says depth does not
            matter); None follows ``config.rgbd``. Depth is used only when both allow it.
    """

    def __init__(
        self,
        config: BlurFieldConfig,
        num_train_views: int,
        use_depth: Optional[bool] = None,
    ) -> None:
        super().__init__()
        self.config = config
        mods, dims = config.modules, config.dims
        self._num_train_views = int(num_train_views)
        self.uses_depth = mods.rgbd and (use_depth is None or bool(use_depth))
        self.scales: Tuple[int, ...] = hpko_scales(len(config.kernel_sizes), mods.hpko)
        self.mcf: Optional[ContextualFeatures] = None
        self.mca: Optional[MCA] = None
        self.heads: Union[HPKOHeads, ViewKernels]
        if config.mode == "view":
            self.heads = ViewKernels(
                num_train_views,
                config.kernel_sizes,
                self.scales,
                progressive=config.progressive,
                prior_sigma=config.kernel_prior_sigma,
            )
            return
        in_ch = 4 if self.uses_depth else 3
        if mods.maan:
            net: Union[RGBDFeatures, BAGSFeatures] = RGBDFeatures(
                in_ch, dims.feature_dim, dims.num_fans, mods.gaka, mods.safm, config.layer_scale_init
            )
        else:
            net = BAGSFeatures(in_ch, dims.feature_dim, config.msd_hidden)
        self.mcf = ContextualFeatures(num_train_views, dims.view_dim, dims.pos_channels, net, config.detach_inputs)
        channels = self.mcf.out_channels
        self.mca = MCA(channels, config.mca_pool_size) if mods.mca else None
        self.heads = HPKOHeads(
            channels,
            dims.mid_channels,
            config.kernel_sizes,
            self.scales,
            progressive=config.progressive,
            prior_sigma=config.kernel_prior_sigma,
            mask_init=config.mask_init,
            num_views=num_train_views if config.view_kernels else 0,
            pixel_kernels=config.pixel_kernels,
        )

    @property
    def num_train_views(self) -> int:
        return self._num_train_views

    def kernel_size(self, scale: int) -> int:
        """K_s of an active scale."""
        if scale not in self.scales:
            raise ValueError(f"scale {scale} is not one of this field's scales {self.scales}")
        return self.heads.kernel_sizes[scale]

    def features(self, render: Tensor, depth: Optional[Tensor], view_ids: Tensor) -> Tensor:
        """MCF (-> MCA) features. render [B,3,H,W], depth [B,1,H,W] or None, view_ids [B] -> [B, C, H, W]."""
        if self.mcf is None:
            raise ValueError("a blur field in mode 'view' has no feature network")
        f = self.mcf(render, depth if self.uses_depth else None, view_ids)
        return self.mca(f) if self.mca is not None else f

    def forward(
        self,
        render: Tensor,  # [B, 3, H, W]
        depth: Optional[Tensor],  # [B, 1, H, W] or None
        view_ids: Tensor,  # [B] int
        scale: int,
        dense: bool = True,
    ) -> Tuple[Union[Tensor, GridKernels], Tensor]:
        """Kernels and masks for ``render`` (already at scale ``scale``'s resolution).

        With a grid factor r > 1 (:meth:`BlurFieldConfig.grid_factor`) the feature network runs on the render
        averaged over r x r cells and the kernels are predicted on that grid; ``dense`` resamples them to every
        pixel, ``dense=False`` keeps them on the grid (:class:`GridKernels`, which :meth:`blur` applies without a
        full-resolution copy). The mask is always resampled to the render's pixels.

        Returns:
            kernel_weights: [B, K_s * K_s, H, W] (or :class:`GridKernels`), softmax over dim 1 (sums to 1),
                row-major window index.
            mask: [B, 1, H, W] in (0, 1).
        """
        factor = self.config.grid_factor((render.shape[-2], render.shape[-1]))
        if self.mcf is None and not dense:
            return self._predict_per_image(render, view_ids, scale)
        if self.mcf is None or factor == 1:
            return self._predict_per_pixel(render, depth, view_ids, scale)
        check_bchw(render, "render", 3)
        size = (render.shape[-2], render.shape[-1])
        grid_depth = pool_to_grid(depth, factor) if depth is not None and self.uses_depth else None
        features = self.features(pool_to_grid(render, factor), grid_depth, view_ids)
        kernels, mask = self.heads(features, scale, view_ids)
        grid_kernels = GridKernels(kernels, factor, size)
        return (grid_kernels.dense() if dense else grid_kernels), upsample_grid(mask, factor, size)

    def _predict_per_image(self, render: Tensor, view_ids: Tensor, scale: int) -> Tuple[GridKernels, Tensor]:
        """Mode view: each image's kernel as a grid of one cell (no [B, K*K, H, W] tensor, nor its gradient)."""
        check_bchw(render, "render", 3)
        check_view_ids(view_ids, render.shape[0], self.num_train_views)
        size = (render.shape[-2], render.shape[-1])
        kernels, mask = self.heads(view_ids, scale, 1, 1)
        return GridKernels(kernels, max(size), size), mask.expand(-1, -1, *size)

    def _predict_per_pixel(
        self, render: Tensor, depth: Optional[Tensor], view_ids: Tensor, scale: int
    ) -> Tuple[Tensor, Tensor]:
        """Kernels and masks from the feature network run at every pixel of ``render``."""
        if self.mcf is None:
            check_bchw(render, "render", 3)
            check_view_ids(view_ids, render.shape[0], self.num_train_views)
            return self.heads(view_ids, scale, render.shape[-2], render.shape[-1])
        return self.heads(self.features(render, depth, view_ids), scale, view_ids)

    @staticmethod
    def blur(render: Tensor, kernel_weights: Union[Tensor, GridKernels], linear_light: bool = False) -> Tensor:
        """``apply_pixel_kernels(render, k)``; with ``linear_light`` the kernels blur ``srgb_to_linear(render)`` and
        the result is re-encoded (``linear_to_srgb``).

        Args:
            render: [B, C, H, W]; sRGB-encoded in [0, 1] when ``linear_light``.
            kernel_weights: [B, K*K, H, W]; expanded with stride 0 over the pixels (mode "view"), applied as one
                convolution per image; or :class:`GridKernels` (``forward(..., dense=False)``), resampled on the fly
                (a grid of one cell, mode "view": one convolution per image).
            linear_light: blur linear light (a camera's blur) instead of the encoded values.
        Returns:
            [B, C, H, W], in the render's dtype (or wider). Kernels predicted in a lower precision (the heads under
            ``torch.autocast``) are applied in the render's dtype.
        """
        source = rgb_to_linear_rgb(render) if linear_light else render
        if isinstance(kernel_weights, GridKernels):
            blurred = apply_grid_kernels(source, kernel_weights.weights.to(source.dtype), kernel_weights.factor)
        elif kernel_weights.dim() == 4 and kernel_weights.stride(-1) == 0 and kernel_weights.stride(-2) == 0:
            # one kernel per image, expanded over the pixels (mode "view"): a depthwise convolution
            blurred = apply_image_kernels(source, kernel_weights[:, :, 0, 0])
        else:
            blurred = apply_pixel_kernels(source, kernel_weights.to(source.dtype))
        return linear_rgb_to_rgb(blurred) if linear_light else blurred

    @staticmethod
    def degrade(
        render: Tensor, kernel_weights: Union[Tensor, GridKernels], mask: Tensor, linear_light: bool = False
    ) -> Tensor:
        """``m * blur(render, k, linear_light) + (1 - m) * render`` (the blend is on the encoded values).

        Args:
            render: [B, C, H, W] (not detached: gradients reach the Gaussians); see :meth:`blur`.
            kernel_weights: [B, K*K, H, W].
            mask: [B, 1, H, W].
            linear_light: see :meth:`blur`.
        Returns:
            [B, C, H, W], in the render's dtype (or wider).
        """
        if mask.dim() != 4 or mask.shape[1] != 1 or mask.shape[-2:] != render.shape[-2:]:
            raise ValueError(f"mask must be [B, 1, H, W] matching render {list(render.shape)}, got {list(mask.shape)}")
        return blend(mask, BlurField.blur(render, kernel_weights, linear_light), render)

    # -------------------------------------------------------------------- optimizer groups

    def get_param_groups(self, param_groups: Dict[str, List[nn.Parameter]]) -> Dict[str, List[nn.Parameter]]:
        """Add the ``blur_field`` group (the feature network, MCA and per-pixel heads) and, with per-view kernels,
        ``blur_view_kernels`` (each view's table gets a gradient only when that view is drawn: it needs a higher
        learning rate)."""
        view = self.heads.per_view_parameters()
        own_group = {id(p) for p in view}
        shared = [p for p in self.parameters() if id(p) not in own_group]
        if shared:  # none in mode "view"
            param_groups["blur_field"] = shared
        if view:
            param_groups["blur_view_kernels"] = view
        return param_groups

    def parameters_for_scale(self, scale: int) -> List[nn.Parameter]:
        """Parameters that take part in ``forward(..., scale)`` (feature network, MCA and that scale's heads)."""
        shared = list(self.mcf.parameters()) if self.mcf is not None else []
        shared += list(self.mca.parameters()) if self.mca is not None else []
        return shared + list(self.heads.parameters_for_scale(scale))
