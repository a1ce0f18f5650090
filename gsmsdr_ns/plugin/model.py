"""The ``gsmsdr`` nerfstudio model: splatfacto's Gaussians, densification and losses, rendered by ``gsmsdr_ns.render``.

Differences from ``SplatfactoModel``, each kept as a small override that extends ``super()``:

* device-agnostic: no ``.cuda()``; seed colours are written into the SH coefficients after ``super()`` built the
  parameters, intrinsics follow the model's device, and ``gsmsdr_ns.render.rasterization`` sends CUDA tensors to
  gsplat and CPU tensors to our own rasterizer;
* works offline: LPIPS is built only when torchvision's AlexNet backbone is already in the torch hub cache,
  otherwise the metric is left out (one warning) instead of crashing on a download;
* a point cloud that is empty or too small falls back to random initialisation with a warning;
* a non-finite loss stops training with :class:`NonFiniteLossError` naming the step;
* checkpoints resize the existing Gaussian parameters in place when loaded, so optimizers built before loading
  (``ns-train --load-dir``) keep updating the model's parameters;
* GS-MSDR's degradation models, built only for the effects the scene calls for (one ``DegradationProfile`` per
  training image, from the dataparser's ``metadata["degradations"]`` or the ``degradation`` mode): the blur field
  (MAAN + HPKO) for blurred images, the resolution-loss model for images of known lower resolution, nothing for
  sharp ones. While training, ``rgb`` is the render passed through the image's degradation model (what the loss
  compares with the degraded photo) and ``rgb_sharp`` the render itself; at evaluation ``rgb`` is always the sharp
  render, and the viewer can also show ``degraded``, ``kernel_size`` and ``blur_mask``.
"""

from __future__ import annotations

import contextlib
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Iterator, List, Literal, Optional, Tuple, Type, Union
from urllib.parse import urlparse

import torch
import torch.nn.functional as F
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes
from nerfstudio.models.splatfacto import RGB2SH, SplatfactoModel, SplatfactoModelConfig
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from gsmsdr_ns.blur.field import BlurField, BlurFieldConfig
from gsmsdr_ns.blur.hpko import HPKOScheduler
from gsmsdr_ns.blur.profile import DegradationProfile, ResolutionLossModel, effective_factor
from gsmsdr_ns.plugin.degradation_plan import (
    DegradationPlan,
    coarsen_kernels,
    describe_profiles,
    kernel_spread,
    nearest_view,
    preview_downscale,
    training_profiles,
)

_lpips_warning_shown = False  # the "LPIPS disabled" warning is shown once per process, however many models are built

GAUSSIAN_PARAM_NAMES = ("means", "scales", "quats", "features_dc", "features_rest", "opacities")
MIN_SEED_POINTS = 4  # splatfacto sizes each Gaussian from its 3 nearest neighbours


class GSMSDRWarning(UserWarning):
    """Degraded but working set-up (no LPIPS, random initialisation)."""


class NonFiniteLossError(FloatingPointError):
    """A training loss became NaN or infinite."""


@dataclass
class GSMSDRModelConfig(SplatfactoModelConfig):
    """GS-MSDR model: splatfacto's Gaussian parameters and densification, rendered on CPU or GPU."""

    _target: Type = field(default_factory=lambda: GSMSDRModel)
    degradation: Literal["auto", "motion", "defocus", "mixres", "sharp"] = "auto"
    """What degraded the training images. auto: per image, from the dataparser's records (degradation.json);
    images nothing is known about get the blur field (any blur, any resolution loss). motion / defocus / mixres /
    sharp: that for every training image the records do not call undegraded (sharp: plain splatfacto)."""
    blur_field: BlurFieldConfig = field(default_factory=BlurFieldConfig)
    """The blur field (MAAN + HPKO) simulating blur on training views; built only when some image needs it."""
    resolution_kernel_size: int = 3
    """Size of the learned residual kernel of the resolution-loss model (images of known lower resolution)."""
    viewer_blur_outputs: bool = True
    """At evaluation, also output degraded (the blur simulated for the nearest training view), kernel_size (blur
    extent in pixels) and blur_mask, for the viewer; rgb stays the sharp render. Needs a blur field."""
    viewer_blur_max_side: int = 128
    """The viewer blur outputs are computed on the render shrunk by a power of two until its longer side is at most
    this (0: full resolution), then enlarged back, so their cost does not grow with the viewer's resolution."""


# ---------------------------------------------------------------------------------------------------------------
# camera helpers (pure functions)


def viewmats_from_camera_to_worlds(camera_to_worlds: Tensor) -> Tensor:
    """World-to-camera matrices in gsplat's OpenCV convention from nerfstudio camera-to-world poses.

    Args:
        camera_to_worlds: [C, 3, 4] (or [C, 4, 4]) poses, OpenGL axes (x right, y up, z backwards).

    Returns:
        [C, 4, 4] world-to-camera matrices with OpenCV axes (x right, y down, z forwards).
    """
    if camera_to_worlds.ndim != 3 or camera_to_worlds.shape[-2] not in (3, 4) or camera_to_worlds.shape[-1] != 4:
        raise ValueError(f"expected camera_to_worlds of shape [C, 3, 4], got {tuple(camera_to_worlds.shape)}")
    flip_yz = camera_to_worlds.new_tensor([1.0, -1.0, -1.0])
    rotation = camera_to_worlds[:, :3, :3] * flip_yz  # negate the y and z camera axes
    translation = camera_to_worlds[:, :3, 3:4]
    rotation_inv = rotation.transpose(1, 2)
    translation_inv = -rotation_inv @ translation
    bottom = camera_to_worlds.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(camera_to_worlds.shape[0], 1, 4)
    return torch.cat([torch.cat([rotation_inv, translation_inv], dim=2), bottom], dim=1)


def intrinsics_at_scale(camera: Cameras, downscale: int, device: torch.device) -> Tuple[Tensor, int, int]:
    """Pinhole intrinsics and image size of a single camera rendered ``downscale`` times smaller.

    Matches ``Cameras.rescale_output_resolution(1 / downscale)`` (floor rounding) without mutating the camera.

    Returns:
        K: [1, 3, 3] on ``device``; width; height.
    """
    K = camera.get_intrinsics_matrices().reshape(-1, 3, 3).to(device)
    if downscale > 1:
        K = torch.cat([K[:, :2] / downscale, K[:, 2:]], dim=1)
    width = int(camera.width.reshape(-1)[0].item()) // downscale
    height = int(camera.height.reshape(-1)[0].item()) // downscale
    return K, width, height


# ---------------------------------------------------------------------------------------------------------------
# LPIPS without downloads


def lpips_backbone_cache_path() -> Path:
    """Where torchvision keeps the AlexNet weights that torchmetrics' default LPIPS needs."""
    from torchvision.models import AlexNet_Weights

    filename = Path(urlparse(AlexNet_Weights.DEFAULT.url).path).name
    return Path(torch.hub.get_dir()) / "checkpoints" / filename


class LPIPSUnavailable(torch.nn.Module):
    """Stands in for LPIPS when its backbone weights are not cached; returns NaN, which the model drops."""

    def forward(self, *_args, **_kwargs) -> Tensor:
        return torch.tensor(float("nan"))


@contextlib.contextmanager
def lpips_disabled() -> Iterator[None]:
    """While active, torchmetrics' LPIPS class builds an :class:`LPIPSUnavailable` instead of downloading AlexNet.

    splatfacto's ``populate_modules`` imports ``LearnedPerceptualImagePatchSimilarity`` from
    ``torchmetrics.image.lpip`` when it runs, so swapping the module attribute for the duration of that call is
    enough; it is restored afterwards.
    """
    import torchmetrics.image.lpip as lpip_module

    original = lpip_module.LearnedPerceptualImagePatchSimilarity
    lpip_module.LearnedPerceptualImagePatchSimilarity = lambda *args, **kwargs: LPIPSUnavailable()  # type: ignore
    try:
        yield
    finally:
        lpip_module.LearnedPerceptualImagePatchSimilarity = original


# ---------------------------------------------------------------------------------------------------------------


class GSMSDRModel(SplatfactoModel):
    """Gaussian splatting model of the ``gsmsdr`` method (see the module docstring)."""

    config: GSMSDRModelConfig

    # -- construction ---------------------------------------------------------------------------------------

    def populate_modules(self) -> None:
        seed = self._usable_seed_points()
        original_seed = self.seed_points
        # Colourless seed: super() then skips its `.cuda()` colour branch; colours are written below.
        self.seed_points = None if seed is None else (seed[0], seed[1][:0])
        lpips_path = lpips_backbone_cache_path()
        with contextlib.nullcontext() if lpips_path.is_file() else lpips_disabled():
            super().populate_modules()
        self.seed_points = original_seed
        if seed is not None:
            self._init_colours(seed[1])
        if not self.has_lpips:
            self._warn_lpips_disabled(lpips_path)
        self._populate_degradation_modules()

    def _populate_degradation_modules(self) -> None:
        """One profile per training image, and only the degradation models those profiles need.

        * ``blur_field`` (:class:`BlurField`, ``num_train_views`` rows of view embedding, depth input when some
          image's blur depends on depth), its HPKO scheduler ``hpko`` with its running state ``hpko_state`` (a plain
          dict, like ``strategy_state``) and ``train_camera_centres`` (persistent [N, 3] buffer: the viewer's
          blur outputs use the view embedding of the nearest training camera): when some image is blurred or lost
          resolution by an unknown factor;
        * ``resolution_model`` (:class:`ResolutionLossModel`): when some image has a known resolution-loss factor > 1.

        A sharp scene builds none of them and trains as plain splatfacto. They are initialised under
        ``torch.random.fork_rng``: building them leaves the random stream that training draws from (random
        backgrounds, densification) exactly as it would be without them.
        """
        metadata = self.kwargs.get("metadata")
        self.profiles: List[DegradationProfile] = training_profiles(
            self.config.degradation, metadata, self.num_train_data
        )
        self.blur_field: Optional[BlurField] = None
        self.hpko: Optional[HPKOScheduler] = None
        self.hpko_state: Optional[Dict] = None
        self.resolution_model: Optional[ResolutionLossModel] = None
        if any(p.needs_blur_field for p in self.profiles):
            use_depth = any(p.needs_depth for p in self.profiles)
            field_config = self.config.blur_field.for_schedule(self.config.num_downscales)
            with torch.random.fork_rng(devices=[]):
                self.blur_field = field_config.setup(
                    num_train_views=self.num_train_data,
                    use_depth=use_depth,
                    use_thin_lens=any(p.defocus for p in self.profiles),
                )
            self.hpko = field_config.make_scheduler(
                num_downscales=self.config.num_downscales, resolution_schedule=self.config.resolution_schedule
            )
            self.hpko_state = self.hpko.initialize_state()
            self.register_buffer("train_camera_centres", torch.full((self.num_train_data, 3), float("nan")))
        mixres = [p for p in self.profiles if p.needs_resolution_model]
        if mixres:
            upsample = Counter(p.mixres_upsample for p in mixres).most_common(1)[0][0]
            self.resolution_model = ResolutionLossModel(
                num_views=self.num_train_data, kernel_size=self.config.resolution_kernel_size, upsample=upsample
            )
        if self.num_train_data > 0:
            CONSOLE.log(f"gsmsdr: training views: {describe_profiles(self.profiles)} -> {self._describe_modules()}")

    def _describe_modules(self) -> str:
        parts = []
        if self.blur_field is not None:
            depth = "RGB-D" if self.blur_field.uses_depth else "RGB"
            lens = ", thin lens for defocus" if self.blur_field.thin_lens is not None else ""
            parts.append(f"blur field ({self.config.blur_field.mode}, {depth}, kernels {self.hpko.kernel_sizes}{lens})")
        if self.resolution_model is not None:
            parts.append("resolution-loss model")
        return " + ".join(parts) or "plain splatfacto (no degradation model)"

    @staticmethod
    def _warn_lpips_disabled(lpips_path: Path) -> None:
        global _lpips_warning_shown
        if _lpips_warning_shown:
            return
        _lpips_warning_shown = True
        warnings.warn(
            f"gsmsdr: LPIPS is disabled because its AlexNet backbone is not in the torch hub cache ({lpips_path}) "
            "and nothing is downloaded at run time. Metrics (ns-eval) report psnr and ssim only. To enable LPIPS, "
            "place alexnet weights at that path (or set TORCH_HOME to a cache that has them).",
            GSMSDRWarning,
            stacklevel=4,
        )

    def _usable_seed_points(self) -> Optional[Tuple[Tensor, Tensor]]:
        """The seed point cloud without non-finite points, or None (random initialisation, with a warning)."""
        if self.config.random_init:
            return None
        if self.seed_points is None:
            problem = "no point cloud was provided"
        else:
            xyz, rgb = self.seed_points
            finite = torch.isfinite(xyz).all(dim=-1)
            if rgb.shape[0] == xyz.shape[0]:
                rgb = rgb[finite]
            else:
                rgb = rgb[:0]
            xyz = xyz[finite]
            if xyz.shape[0] >= MIN_SEED_POINTS:
                return xyz, rgb
            problem = f"the point cloud has {xyz.shape[0]} usable points (need at least {MIN_SEED_POINTS})"
        warnings.warn(
            f"gsmsdr: {problem}; initialising {self.config.num_random} random Gaussians in a cube of side "
            f"{self.config.random_scale} instead. Training will converge more slowly; set "
            "--pipeline.model.num-random / --pipeline.model.random-scale to tune it.",
            GSMSDRWarning,
            stacklevel=3,
        )
        return None

    @torch.no_grad()
    def _init_colours(self, rgb: Tensor) -> None:
        """Set the base colour of each Gaussian from its seed point's 0-255 RGB (no-op without colours)."""
        features_dc = self.gauss_params["features_dc"]
        if rgb.shape[0] != features_dc.shape[0]:
            return
        rgb = rgb.to(device=features_dc.device, dtype=features_dc.dtype) / 255.0
        features_dc.copy_(RGB2SH(rgb) if self.config.sh_degree > 0 else torch.logit(rgb, eps=1e-10))

    @property
    def has_lpips(self) -> bool:
        return not isinstance(self.lpips, LPIPSUnavailable)

    # -- checkpoints ----------------------------------------------------------------------------------------

    def update_to_step(self, step: int) -> None:
        """Loading a checkpoint of step ``step``: render with the SH degree training had reached."""
        self.step = step

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):  # type: ignore[override]
        """Resize the Gaussian parameters to the checkpoint's count *in place*, then load.

        splatfacto replaces the parameter objects here, which detaches them from optimizers created before loading
        (trainer resume): those would keep stepping the stale tensors. Keeping the objects avoids that.
        """
        count = state_dict["gauss_params.means"].shape[0]
        for param in self.gauss_params.values():
            param.data = param.data.new_zeros((count, *param.shape[1:]))
        return torch.nn.Module.load_state_dict(self, state_dict, strict=strict, assign=assign)

    # -- rendering ------------------------------------------------------------------------------------------

    def get_outputs(self, camera: Cameras) -> Dict[str, Union[Tensor, List]]:
        """Render one camera: ``rgb`` [H, W, 3], ``depth`` [H, W, 1] (eval only), ``accumulation``, ``background``.

        Training a degraded image adds ``rgb_sharp`` (the render; ``rgb`` is then its simulated degradation) and
        ``blur_mask`` [H, W, 1] when the blur field ran. Evaluation adds the viewer's blur outputs (see
        ``viewer_blur_outputs``); ``rgb`` is the sharp render.
        """
        if not isinstance(camera, Cameras):
            raise TypeError(f"gsmsdr renders a nerfstudio Cameras object, got {type(camera).__name__}")
        if camera.shape[0] != 1:
            raise ValueError(f"gsmsdr renders one camera at a time, got {camera.shape[0]}")

        downscale = self._get_downscale_factor()
        K, width, height = intrinsics_at_scale(camera, downscale, self.device)
        gaussians = self._gaussians_in_crop()
        if gaussians is None:
            full_width, full_height = int(camera.width.item()), int(camera.height.item())
            return self.get_empty_outputs(full_width, full_height, self.background_color.to(self.device))

        plan = self._degradation_plan(camera, downscale)
        viewmats = viewmats_from_camera_to_worlds(self._camera_to_worlds(camera))
        with_depth = self.config.output_depth_during_training or not self.training or plan.needs_depth
        render, alpha, self.info = self._rasterize(gaussians, viewmats, K, width, height, with_depth)
        if self.training:
            self.strategy.step_pre_backward(
                self.gauss_params, self.optimizers, self.strategy_state, self.step, self.info
            )

        background = self._get_background_color()
        rgb = torch.clamp(render[..., :3] + (1.0 - alpha) * background, 0.0, 1.0)
        if self.config.use_bilateral_grid and self.training and camera.metadata and "cam_idx" in camera.metadata:
            rgb = self._apply_bilateral_grid(rgb, camera.metadata["cam_idx"], height, width)
        if not self.training:
            background = background.expand(height, width, 3)
        depth = self._expected_depth(render, alpha) if with_depth else None
        outputs = {
            "rgb": rgb.squeeze(0),
            "depth": depth,
            "accumulation": alpha.squeeze(0),
            "background": background,
        }
        if not plan.is_plain:
            outputs.update(self._simulate_degradation(outputs["rgb"], depth, plan))
        elif not self.training and self.config.viewer_blur_outputs and self.blur_field is not None:
            outputs.update(self._blur_preview(camera, outputs["rgb"], depth))
        return outputs

    # -- degradation (training) -----------------------------------------------------------------------------

    def _degradation_plan(self, camera: Cameras, downscale: int) -> DegradationPlan:
        """What to simulate for this training camera, by the profile of ``camera.metadata["cam_idx"]``.

        Nothing at evaluation, for cameras outside the training set (no ``cam_idx``) and for sharp images. The
        blur field runs once the HPKO scheduler is past its warm-up, at the scale of the *current* render downscale
        (so it follows the resolution schedule; explicit ``blur_field.switch_steps`` take over when set); the
        resolution model runs while the image's factor, relative to the current downscale, is still > 1.
        """
        if not self.training or not camera.metadata or "cam_idx" not in camera.metadata:
            return DegradationPlan()
        view_id = int(camera.metadata["cam_idx"])
        profile = self.profiles[view_id]
        if profile.is_sharp:
            return DegradationPlan(view_id)
        blur_scale = None
        if profile.needs_blur_field and self.hpko is not None:
            follow = None if self.hpko.switch_steps is not None else downscale
            blur_scale = self.hpko.update(self.hpko_state, self.step, downscale=follow)
        factor = 1.0
        if profile.needs_resolution_model and self.resolution_model is not None:
            factor = effective_factor(profile.mixres_factor, downscale)
        thin_lens = profile.defocus and self.blur_field is not None and self.blur_field.thin_lens is not None
        runs_field = not self._lens_alone(profile)
        uses_depth = self.blur_field is not None and self.blur_field.uses_depth
        return DegradationPlan(view_id, blur_scale, uses_depth, factor, thin_lens, downscale, runs_field)

    def _lens_alone(self, profile: DegradationProfile) -> bool:
        """Whether the thin lens alone models this image's blur (defocus only, a lens is built, and the config does
        not ask for the field on defocus)."""
        field = self.blur_field
        return (
            field is not None
            and field.thin_lens is not None
            and profile.defocus_only
            and not field.config.defocus_field
        )

    def _simulate_degradation(
        self, rgb: Tensor, depth: Optional[Tensor], plan: DegradationPlan
    ) -> Dict[str, Tensor]:
        """Pass the sharp render [H, W, 3] (and depth [H, W, 1]) through this image's degradation models, in the
        order a camera degrades a photo: blur (blur field), then resolution loss (resolution model).

        Returns ``rgb`` (the simulated degraded image), ``rgb_sharp`` and, when the blur field ran, ``blur_mask``.
        """
        image = rgb.permute(2, 0, 1)[None]  # [1, 3, H, W]
        view_ids = torch.tensor([plan.view_id], device=image.device)
        outputs: Dict[str, Tensor] = {"rgb_sharp": rgb}
        if plan.blur_scale is not None:
            assert self.blur_field is not None
            linear_light = self.blur_field.config.linear_light
            if plan.thin_lens:
                assert self.blur_field.thin_lens is not None and depth is not None
                lens = self.blur_field.thin_lens(
                    depth.permute(2, 0, 1)[None], view_ids, plan.blur_scale.kernel_size, 1.0 / plan.render_downscale
                )
                image = BlurField.blur(image, lens, linear_light)
            if plan.blur_field:
                depth_in = depth.permute(2, 0, 1)[None] if plan.blur_uses_depth else None
                kernels, mask = self.blur_field(image, depth_in, view_ids, plan.blur_scale.scale)
                image = BlurField.degrade(image, kernels, mask, linear_light)
                outputs["blur_mask"] = mask[0].permute(1, 2, 0)
        if plan.resolution_factor > 1.0:
            assert self.resolution_model is not None
            image = self.resolution_model(image, [plan.resolution_factor], view_ids)
        outputs["rgb"] = image[0].permute(1, 2, 0)
        return outputs

    # -- degradation (viewer) -------------------------------------------------------------------------------

    def _blur_preview(self, camera: Cameras, rgb: Tensor, depth: Tensor) -> Dict[str, Tensor]:
        """Viewer outputs of the blur field for an evaluation camera, as for the nearest training view (its
        embedding and per-view kernels).

        The field runs at the HPKO scale training uses at the model's step (``hpko.scale_for_step``), on the render
        shrunk to that scale's resolution, or further (powers of two) until its longer side is at most
        ``viewer_blur_max_side``; in that case the kernels are re-expressed on the coarser grid
        (:func:`coarsen_kernels`) so the simulated blur keeps its extent. Results are enlarged back to the render's
        size. ``degraded`` [H, W, 3] = mask * blurred + (1 - mask) * render; ``kernel_size`` [H, W, 1] = the
        kernels' RMS blur radius in pixels of the render, times the mask (0 where the field keeps the render
        sharp); ``blur_mask`` [H, W, 1]. When that training view is defocused, its thin lens blurs the render
        first (``render`` above is then the lens's blur) and its RMS radius is added in quadrature; a view the lens
        models alone (defocus only, see ``BlurFieldConfig.defocus_field``) shows the lens's blur, its RMS radius and
        a mask of 1.
        """
        assert self.blur_field is not None and self.hpko is not None
        height, width = rgb.shape[:2]
        info = self.hpko.scale_for_step(self.step)
        d = preview_downscale(height, width, self.config.viewer_blur_max_side, at_least=info.downsample)
        small = (max(1, height // d), max(1, width // d))
        image = rgb.permute(2, 0, 1)[None]  # [1, 3, H, W]
        low = image if d == 1 else F.interpolate(image, size=small, mode="area")
        centre = camera.camera_to_worlds.reshape(-1, 3, 4)[0, :3, 3]
        view_id = nearest_view(self.train_camera_centres, centre)
        view_ids = torch.tensor([view_id], device=image.device)
        lens = self.blur_field.thin_lens if self.profiles[view_id].defocus else None
        lens_alone = self._lens_alone(self.profiles[view_id])
        field_depth = self.blur_field.uses_depth and not lens_alone
        low_depth = None
        if field_depth or lens is not None:
            depth_in = depth.permute(2, 0, 1)[None]
            low_depth = depth_in if d == 1 else F.interpolate(depth_in, size=small, mode="area")
        linear_light = self.blur_field.config.linear_light

        def enlarge(x: Tensor) -> Tensor:
            return x if d == 1 else F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False)

        if lens is not None:  # as in training: the lens first, then the field
            window = (info.kernel_size * info.downsample // d) | 1  # the scale's window at the preview's grid, odd
            lens_kernels = lens(low_depth, view_ids, window, 1.0 / d)
            low = BlurField.blur(low, lens_kernels, linear_light)
            if lens_alone:  # as in training: a defocus-only view is the lens's blur in full
                return {
                    "degraded": enlarge(low).clamp(0.0, 1.0)[0].permute(1, 2, 0),
                    "kernel_size": enlarge(kernel_spread(lens_kernels) * d)[0].permute(1, 2, 0),
                    "blur_mask": rgb.new_ones(height, width, 1),
                }
        kernels, mask = self.blur_field(low, low_depth if field_depth else None, view_ids, info.scale)
        extent = kernel_spread(kernels) * info.downsample * mask  # kernel taps are pixels at the scale's resolution
        if lens is not None:  # RMS radii of successive blurs add in quadrature
            extent = torch.sqrt(extent**2 + (kernel_spread(lens_kernels) * d) ** 2)
        coarse = coarsen_kernels(kernels, d // info.downsample)
        blurred = BlurField.blur(low, coarse, linear_light)
        mask_full = enlarge(mask)
        base = image if lens is None else enlarge(low)  # what the field blends with: the render, or its lens blur
        degraded = (mask_full * enlarge(blurred) + (1.0 - mask_full) * base).clamp(0.0, 1.0)
        return {
            "degraded": degraded[0].permute(1, 2, 0),
            "kernel_size": enlarge(extent)[0].permute(1, 2, 0),
            "blur_mask": mask_full[0].permute(1, 2, 0),
        }

    # -- training callbacks ---------------------------------------------------------------------------------

    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> List[TrainingCallback]:
        """splatfacto's callbacks; also records the training camera centres for the viewer's blur outputs."""
        pipeline = training_callback_attributes.pipeline
        datamanager = getattr(pipeline, "datamanager", None)
        dataset = getattr(datamanager, "train_dataset", None)
        if self.blur_field is not None and dataset is not None:
            self.set_train_camera_centres(dataset.cameras.camera_to_worlds)
        return super().get_training_callbacks(training_callback_attributes)

    @torch.no_grad()
    def set_train_camera_centres(self, camera_to_worlds: Tensor) -> None:
        """Store the centres of the training cameras ([N, 3, 4] poses, the training split's order)."""
        if self.blur_field is None:
            return
        centres = camera_to_worlds.reshape(-1, 3, 4)[:, :3, 3]
        if centres.shape != self.train_camera_centres.shape:
            raise ValueError(
                f"expected {self.train_camera_centres.shape[0]} training camera poses, got {centres.shape[0]}"
            )
        self.train_camera_centres.copy_(centres)

    def get_param_groups(self) -> Dict[str, List[torch.nn.Parameter]]:
        """splatfacto's groups, plus ``blur_field`` and ``resolution_model`` when those modules exist."""
        groups = super().get_param_groups()
        if self.blur_field is not None:
            self.blur_field.get_param_groups(groups)
        if self.resolution_model is not None:
            groups["resolution_model"] = list(self.resolution_model.parameters())
        return groups

    def _camera_to_worlds(self, camera: Cameras) -> Tensor:
        """[1, 3, 4] pose on the model's device, corrected by the camera optimizer while training."""
        if self.training:
            return self.camera_optimizer.apply_to_camera(camera).to(self.device)
        return camera.camera_to_worlds.to(self.device)

    def _gaussians_in_crop(self) -> Optional[Dict[str, Tensor]]:
        """The raw Gaussian parameters, restricted to the viewer's crop box at eval time; None if it is empty."""
        params = {name: self.gauss_params[name] for name in GAUSSIAN_PARAM_NAMES}
        if self.crop_box is None or self.training:
            return params
        inside = self.crop_box.within(self.means).reshape(-1)
        if not bool(inside.any()):
            return None
        return {name: value[inside] for name, value in params.items()}

    def _colours_and_sh_degree(self, gaussians: Dict[str, Tensor]) -> Tuple[Tensor, Optional[int]]:
        """SH coefficients [N, K, 3] and the degree unlocked so far, or plain RGB [N, 3] when sh_degree is 0."""
        coefficients = torch.cat([gaussians["features_dc"][:, None, :], gaussians["features_rest"]], dim=1)
        if self.config.sh_degree == 0:
            return torch.sigmoid(coefficients[:, 0, :]), None
        return coefficients, min(self.step // self.config.sh_degree_interval, self.config.sh_degree)

    def _rasterize(
        self, gaussians: Dict[str, Tensor], viewmats: Tensor, K: Tensor, width: int, height: int, with_depth: bool
    ) -> Tuple[Tensor, Tensor, Dict]:
        """Activate the parameters and rasterize: render [1, H, W, 3 or 4], alpha [1, H, W, 1], info."""
        from gsmsdr_ns.render import rasterization  # imported on first render: keeps method discovery light

        colours, sh_degree = self._colours_and_sh_degree(gaussians)
        return rasterization(
            means=gaussians["means"],
            quats=gaussians["quats"],  # normalised by the rasterizer
            scales=torch.exp(gaussians["scales"]),
            opacities=torch.sigmoid(gaussians["opacities"]).squeeze(-1),
            colors=colours,
            viewmats=viewmats,
            Ks=K,
            width=width,
            height=height,
            near_plane=0.01,
            far_plane=1e10,
            sh_degree=sh_degree,
            packed=False,
            render_mode="RGB+ED" if with_depth else "RGB",
            sparse_grad=False,
            absgrad=self.strategy.absgrad,
            rasterize_mode=self.config.rasterize_mode,
        )

    @staticmethod
    def _expected_depth(render: Tensor, alpha: Tensor) -> Tensor:
        """[H, W, 1] expected depth; empty pixels get the farthest rendered depth."""
        depth = render[..., 3:4]
        return torch.where(alpha > 0, depth, depth.detach().max()).squeeze(0)

    # -- losses and metrics ---------------------------------------------------------------------------------

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        """splatfacto's loss on ``rgb`` (the simulated degradation while training) plus the blur mask regulariser."""
        loss_dict = super().get_loss_dict(outputs, batch, metrics_dict)
        if self.training:
            if self.blur_field is not None:
                self.blur_field.get_loss_dict(loss_dict, outputs.get("blur_mask"))
            self._check_finite(loss_dict)
        return loss_dict

    def get_metrics_dict(self, outputs, batch) -> Dict[str, Tensor]:
        """splatfacto's metrics; ``blur_kernel_size`` (the HPKO kernel size) on steps where the blur field ran."""
        metrics_dict = super().get_metrics_dict(outputs, batch)
        if self.training and "blur_mask" in outputs and self.hpko_state is not None:
            metrics_dict["blur_kernel_size"] = self.hpko_state["kernel_size"]
        return metrics_dict

    def _check_finite(self, loss_dict: Dict[str, Tensor]) -> None:
        """Raise :class:`NonFiniteLossError` if a loss term or a Gaussian parameter is NaN or infinite.

        Parameters are checked too: a NaN position, scale or rotation only culls its Gaussian, so the loss would
        stay finite while the scene silently decays.
        """
        values = torch.stack([torch.as_tensor(v).detach().float().sum().cpu() for v in loss_dict.values()])
        params_ok = torch.stack([torch.isfinite(p.detach()).all() for p in self.gauss_params.values()])
        if bool(torch.isfinite(values).all()) and bool(params_ok.all()):
            return
        terms = ", ".join(f"{name}={value:.4g}" for name, value in zip(loss_dict, values.tolist()))
        bad = [name for name, ok in zip(self.gauss_params.keys(), params_ok.tolist()) if not ok]
        raise NonFiniteLossError(
            f"gsmsdr: non-finite training loss or parameters at step {self.step} ({terms}); non-finite Gaussian "
            f"parameters: {', '.join(bad) or 'none'}; {self.num_points} Gaussians. Lower the learning rates in "
            "--optimizers, check the input images and poses, or resume from an earlier checkpoint."
        )

    def get_image_metrics_and_images(
        self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
        metrics, images = super().get_image_metrics_and_images(outputs, batch)
        if not self.has_lpips:
            for name in ("lpips", "cc_lpips"):
                metrics.pop(name, None)
        return metrics, images


__all__ = [
    "GSMSDRModel",
    "GSMSDRModelConfig",
    "GSMSDRWarning",
    "NonFiniteLossError",
    "intrinsics_at_scale",
    "viewmats_from_camera_to_worlds",
]
