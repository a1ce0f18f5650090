"""The ``gsmsdr`` nerfstudio model: splatfacto's Gaussians, densification and losses, rendered by ``gsmsdr_ns.render``.

Differences from ``SplatfactoModel``, each kept as a small override that extends ``super()``:

* device-agnostic: no ``.cuda()`` (``get_outputs`` is rewritten for it: splatfacto's moves the intrinsics with
  ``.cuda()``); seed colours are written after ``super()`` built the parameters, and ``plugin/gaussians.py``
  rasterizes CUDA tensors with gsplat and CPU tensors with our own rasterizer;
* works offline: LPIPS only when its backbone is in the torch hub cache (else one warning, no metric); a point
  cloud that is empty or too small falls back to random initialisation with a warning;
* a non-finite loss or Gaussian parameter stops training with :class:`NonFiniteLossError` naming the step (found
  on the device every step, read every ``finite_check_every`` steps: a step does not wait for the device);
* checkpoints resize the existing Gaussian parameters in place when loaded, so optimizers built before loading
  (``ns-train --load-dir``) keep updating the model's parameters;
* GS-MSDR's degradation models live in ``degradation`` (:class:`~gsmsdr_ns.blur.degradation_model.DegradationModel`),
  built only for the effects the scene calls for (one ``DegradationProfile`` per training image, from the
  dataparser's ``metadata["degradations"]`` or the ``degradation`` mode): the blur field (MAAN + HPKO, thin lens)
  for blurred images, the resolution-loss model for images of known lower resolution, nothing for sharp ones. A
  training render enters it once (plan, then forward) and its loss once (``losses``). While training, ``rgb`` is
  the degraded render (what the loss compares with the photo) and ``rgb_sharp`` the render; at evaluation ``rgb``
  is the sharp render, and the viewer can also show ``degraded``, ``kernel_size`` and ``blur_mask``;
* the stages of a step are marked for ``gsmsdr_ns.timing_hooks`` (no-ops unless a timing recorder is attached).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Dict, List, Literal, Optional, Tuple, Type, Union

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes
from nerfstudio.models.splatfacto import SplatfactoModel, SplatfactoModelConfig
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from gsmsdr_ns.blur.degradation_config import DegradationConfig, with_degradation_config
from gsmsdr_ns.blur.degradation_model import (
    DegradationModel,
    DegradationPlan,
    crop_margin,
    remap_legacy_keys,
    with_fallback_state,
)
from gsmsdr_ns.blur.field import BlurFieldConfig
from gsmsdr_ns.blur.profile import motion_records, training_profiles
from gsmsdr_ns.data.effects import DegradationMode
from gsmsdr_ns.ops.ssim import SSIM
from gsmsdr_ns.plugin.cameras import TrainImageSizes, intrinsics_at_scale, viewmats_from_camera_to_worlds
from gsmsdr_ns.plugin.checkpoint_compat import (
    check_camera_shake,
    check_state_dict_shapes,
    check_thin_lens,
    checkpoint_layout,
)
from gsmsdr_ns.plugin.finite_check import FiniteCheckMixin, NonFiniteRecorder
from gsmsdr_ns.plugin.gaussians import (
    colours_and_sh_degree,
    expected_depth,
    gaussians_in_crop,
    rasterize_gaussians,
    usable_seed_points,
    write_seed_colours,
)
from gsmsdr_ns.plugin.lpips import (
    LPIPSUnavailable,
    lpips_backbone_cache_path,
    lpips_disabled,
    warn_lpips_disabled,
)
from gsmsdr_ns.render.gsplat_backend import require_gsplat_cuda
from gsmsdr_ns.timing_hooks import stage, timed


class GSMSDRWarning(UserWarning):
    """Degraded but working set-up (no LPIPS, random initialisation)."""


@dataclass
class GSMSDRModelConfig(SplatfactoModelConfig):
    """GS-MSDR model: splatfacto's Gaussian parameters and densification, rendered on CPU or GPU."""

    _target: Type = field(default_factory=lambda: GSMSDRModel)
    degradation: DegradationMode = "auto"
    """What degraded the training images. auto: per image, from the dataparser's records (degradation.json);
    images nothing is known about get the blur field (any blur, any resolution loss). motion / defocus / mixres /
    sharp: that for every training image the records do not call undegraded (sharp: plain splatfacto)."""
    blur_field: BlurFieldConfig = field(default_factory=BlurFieldConfig)
    """The blur field's architecture (MAAN + HPKO); the field is built only when some image needs it."""
    degradation_model: DegradationConfig = field(default_factory=DegradationConfig)
    """Everything else about simulating a training image's degradation: lens, shake, schedule, losses."""
    viewer_blur_outputs: bool = True
    """At evaluation, also output degraded (the blur simulated for the nearest training view), kernel_size (blur
    extent in pixels) and blur_mask, for the viewer; rgb stays the sharp render. Needs a blur field."""
    viewer_blur_max_side: int = 128
    """The viewer blur outputs are computed on the render shrunk by a power of two until its longer side is at most
    this (0: full resolution), then enlarged back, so their cost does not grow with the viewer's resolution."""
    camera_optimizer_views: Literal["degraded", "all"] = "degraded"
    """Training views whose pose the camera optimizer refines when it is on (``--pipeline.model.camera-optimizer.mode
    SO3xR3``; off by default, as in splatfacto). degraded: the images with a degradation model (blur makes their
    structure-from-motion poses uncertain; sharp images keep theirs, anchor the scene and train as plain splatfacto
    steps); all: every training view (splatfacto)."""
    degraded_densify_grad_scale: float = 1.0
    """Densification gradient of a training view rendered through its degradation model, times this (1: as
    splatfacto): a blur spreads and partly cancels the gradient reaching each Gaussian's 2D mean, so blurred views
    split fewer Gaussians; above 1 they split as many as sharp views would, at the cost of more Gaussians."""
    finite_check_every: Optional[int] = None
    """Steps between reads of the non-finite check: each step's loss terms and Gaussian parameters are checked on the
    device without waiting for it, and every N steps (and before every checkpoint) training stops with
    NonFiniteLossError naming the first bad step. 1: stop at the bad step itself, before its update; 0: no check;
    None: 1 on the CPU (reading costs no wait there), 10 on a GPU."""

    def __setstate__(self, state: Dict) -> None:
        """Loading a config.yml; one written before ``degradation_model`` existed loads too."""
        self.__dict__.update(with_degradation_config(state))


class GSMSDRModel(FiniteCheckMixin, SplatfactoModel):
    """Gaussian splatting model of the ``gsmsdr`` method (see the module docstring)."""

    config: GSMSDRModelConfig

    # -- construction ---------------------------------------------------------------------------------------

    def populate_modules(self) -> None:
        seed = None
        if not self.config.random_init:
            seed = usable_seed_points(self.seed_points, self.config.num_random, self.config.random_scale, GSMSDRWarning)
        original_seed = self.seed_points
        # Colourless seed: super() then skips its `.cuda()` colour branch; colours are written below.
        self.seed_points = None if seed is None else (seed[0], seed[1][:0])
        lpips_path = lpips_backbone_cache_path()
        with contextlib.nullcontext() if lpips_path.is_file() else lpips_disabled():
            super().populate_modules()
        self.ssim = SSIM()  # splatfacto's SSIM, its five filtered maps in two convolutions instead of ten
        self.seed_points = original_seed
        if seed is not None:
            write_seed_colours(self.gauss_params["features_dc"], seed[1], self.config.sh_degree)
        if not self.has_lpips:
            warn_lpips_disabled(lpips_path, GSMSDRWarning)
        self._populate_degradation_modules()
        self._nonfinite = NonFiniteRecorder()
        self._train_image_sizes = TrainImageSizes()

    def _populate_degradation_modules(self) -> None:
        """``degradation``: the :class:`DegradationModel` of the training images (one profile each, from the
        dataparser's ``metadata["degradations"]`` and the ``degradation`` mode); a sharp scene gets one that builds
        nothing and trains as plain splatfacto."""
        metadata = self.kwargs.get("metadata") or {}
        profiles = training_profiles(self.config.degradation, metadata, self.num_train_data)
        self.degradation = DegradationModel(
            profiles,
            self.config.blur_field,
            self.config.degradation_model,
            num_downscales=self.config.num_downscales,
            resolution_schedule=self.config.resolution_schedule,
            preview_max_side=self.config.viewer_blur_max_side,
            densify_until=self.config.stop_split_at,
            shake_records=motion_records(metadata.get("degradations"), self.num_train_data),
            pose_scale=metadata.get("pose_scale"),
        )
        if self.num_train_data > 0:
            CONSOLE.log(f"gsmsdr: training views: {self.degradation.describe_training_views()}")

    @property
    def has_lpips(self) -> bool:
        return not isinstance(self.lpips, LPIPSUnavailable)

    # -- checkpoints ----------------------------------------------------------------------------------------

    def update_to_step(self, step: int) -> None:
        """Loading a checkpoint of step ``step``: render with the SH degree and blur scale training had reached."""
        self.step = step

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):  # type: ignore[override]
        """Resize the Gaussian parameters to the checkpoint's count *in place*, then load.

        splatfacto replaces the parameter objects here, which detaches them from optimizers created before loading
        (trainer resume): those would keep stepping the stale tensors. Keeping the objects avoids that. Checkpoints
        written before the degradation models moved into ``degradation`` load too (:func:`remap_legacy_keys`), and
        so do checkpoints written before the per-image fallback or with it switched off (:func:`with_fallback_state`).
        A checkpoint of another preset (other widths) raises ``CheckpointMismatchError`` naming both.
        """
        state_dict = remap_legacy_keys(state_dict, "degradation.")
        state_dict = with_fallback_state(state_dict, self.state_dict(), "degradation.fallback.")
        layout = checkpoint_layout(self, self.config.blur_field)
        check_thin_lens(layout, self.state_dict(), state_dict)
        check_camera_shake(layout, self.state_dict(), state_dict)
        check_state_dict_shapes(layout, self.state_dict(), state_dict)
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
        full_size = self._train_image_sizes.get(camera) if self.training else None
        K, width, height = intrinsics_at_scale(camera, downscale, self.device, full_size)
        gaussians = gaussians_in_crop(self.gauss_params, self.crop_box, self.training)
        if gaussians is None:
            full_width, full_height = int(camera.width.item()), int(camera.height.item())
            return self.get_empty_outputs(full_width, full_height, self.background_color.to(self.device))

        plan = self.degradation.with_fallback(self._degradation_plan(camera, downscale))
        if plan.margin:  # the blur reads what lies just outside the frame: render it, crop after blurring
            K = K.clone()
            K[:, :2, 2] += plan.margin
            width, height = width + 2 * plan.margin, height + 2 * plan.margin
        viewmats = viewmats_from_camera_to_worlds(self._camera_to_worlds(camera, plan))
        with_depth = self.config.output_depth_during_training or not self.training or plan.needs_depth
        render, alpha, self.info = timed(
            "rasterization", self._rasterize, gaussians, viewmats, K, width, height, with_depth
        )
        self.info["degraded"] = not (plan.is_plain or plan.fallback)  # read by step_post_backward
        if self.training:
            with stage("densification"):
                self.strategy.step_pre_backward(
                    self.gauss_params, self.optimizers, self.strategy_state, self.step, self.info
                )

        background = self._get_background_color()
        rgb = torch.clamp(render[..., :3] + (1.0 - alpha) * background, 0.0, 1.0)
        if self.config.use_bilateral_grid and self.training and camera.metadata and "cam_idx" in camera.metadata:
            rgb = self._apply_bilateral_grid(rgb, camera.metadata["cam_idx"], height, width)
        if not self.training:
            background = background.expand(height, width, 3)
        depth = expected_depth(render, alpha) if with_depth else None
        outputs = {"rgb": rgb.squeeze(0), "depth": depth, "accumulation": alpha.squeeze(0), "background": background}
        if not plan.is_plain:
            degraded, aux = self.degradation(outputs["rgb"], depth, plan, K[0])
            outputs["rgb"] = aux.sharp if plan.fallback else degraded  # what the Gaussians' loss compares
            outputs["rgb_sharp"], outputs["rgb_degraded"], outputs["degradation"] = aux.sharp, degraded, aux
            outputs["degradation_plan"] = plan
            if aux.mask is not None:
                outputs["blur_mask"] = aux.mask
            if plan.margin:
                for key in ("accumulation", "depth"):
                    if outputs[key] is not None:
                        outputs[key] = crop_margin(outputs[key], plan.margin, dims=(0, 1))
        elif not self.training and self.config.viewer_blur_outputs and self.degradation.blur_field is not None:
            centre = camera.camera_to_worlds.reshape(-1, 3, 4)[0, :3, 3]
            outputs.update(self.degradation.preview(outputs["rgb"], depth, centre, self.step))
        return outputs

    def _degradation_plan(self, camera: Cameras, downscale: int) -> DegradationPlan:
        """What to simulate for this camera (:meth:`DegradationModel.plan`): nothing at evaluation or for cameras
        outside the training set (no ``cam_idx``)."""
        if not self.training or not camera.metadata or "cam_idx" not in camera.metadata:
            return DegradationPlan()
        return self.degradation.plan(int(camera.metadata["cam_idx"]), downscale, self.step)

    # -- training callbacks ---------------------------------------------------------------------------------

    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> List[TrainingCallback]:
        """splatfacto's callbacks; also records the training camera centres for the viewer's blur outputs."""
        pipeline = training_callback_attributes.pipeline
        datamanager = getattr(pipeline, "datamanager", None)
        dataset = getattr(datamanager, "train_dataset", None)
        if self.degradation.blur_field is not None and dataset is not None:
            self.degradation.set_train_camera_centres(dataset.cameras.camera_to_worlds)
        if self.device.type == "cuda":
            require_gsplat_cuda()  # at set-up, not at the first render: a clear error naming what is missing
        return super().get_training_callbacks(training_callback_attributes)

    def step_post_backward(self, step: int) -> None:
        """splatfacto's densification after the backward pass, marked as the ``densification`` timing stage."""
        with stage("densification"):
            scale = self.config.degraded_densify_grad_scale
            if scale != 1.0 and self.info.get("degraded", False):
                means2d = self.info["means2d"]
                for grad in (means2d.grad, getattr(means2d, "absgrad", None)):
                    if grad is not None:
                        grad.mul_(scale)
            super().step_post_backward(step)

    def get_param_groups(self) -> Dict[str, List[torch.nn.Parameter]]:
        """splatfacto's groups, plus the degradation model's (``blur_field``, ``blur_view_kernels``,
        ``blur_defocus``, ``resolution_model``) for the modules that exist."""
        return self.degradation.get_param_groups(super().get_param_groups())

    def _camera_to_worlds(self, camera: Cameras, plan: DegradationPlan) -> Tensor:
        """[1, 3, 4] pose on the model's device, corrected by the camera optimizer while training the views it
        refines (``camera_optimizer_views``)."""
        refine = self.config.camera_optimizer.mode != "off"
        if self.training and refine and (self.config.camera_optimizer_views == "all" or plan.has_model):
            return self.camera_optimizer.apply_to_camera(camera).to(self.device)
        return camera.camera_to_worlds.to(self.device)

    def _rasterize(
        self, gaussians: Dict[str, Tensor], viewmats: Tensor, K: Tensor, width: int, height: int, with_depth: bool
    ) -> Tuple[Tensor, Tensor, Dict]:
        """:func:`~gsmsdr_ns.plugin.gaussians.rasterize_gaussians` with the SH degree unlocked at this step."""
        config = self.config
        colours, sh_degree = colours_and_sh_degree(gaussians, config.sh_degree, self.step, config.sh_degree_interval)
        return rasterize_gaussians(
            gaussians, colours, sh_degree, viewmats, K, width, height, with_depth, self.strategy.absgrad,
            config.rasterize_mode,
        )  # fmt: skip

    # -- losses and metrics ---------------------------------------------------------------------------------

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        """splatfacto's loss on ``rgb`` (the simulated degradation while training) plus the degradation model's
        terms (:meth:`DegradationModel.losses`) on steps that ran it."""
        loss_dict = super().get_loss_dict(outputs, batch, metrics_dict)
        if self.training:
            aux = outputs.get("degradation")
            if aux is not None:
                plan, degraded = outputs["degradation_plan"], outputs["rgb_degraded"]
                target = None  # the training image, built only for the gate or the deconvolved loss
                if self.degradation.fallback is not None or aux.kernel_mean is not None:
                    target = self._training_target(outputs, batch)
                if self.degradation.fallback is not None:
                    self.degradation.record_errors(plan, degraded, aux.sharp, target)
                anchor = self.config.degradation_model.sharp_anchor_weight
                if plan.fallback:  # a plain step for the Gaussians; the degradation models fit the photo alone
                    loss_dict["degradation_fit"] = self._photometric_loss(degraded, batch, outputs["background"])
                elif anchor > 0 and plan.thin_lens and plan.blur_scale is not None:
                    sharp_loss = self._photometric_loss(aux.sharp, batch, outputs["background"])
                    loss_dict["sharp_anchor"] = anchor * sharp_loss
                loss_dict.update(self.degradation.losses(aux, degraded, target))
            self._check_finite(loss_dict)
        return loss_dict

    def _photometric_loss(self, pred: Tensor, batch, background: Tensor) -> Tensor:
        """splatfacto's main loss, (1 - ssim_lambda) * L1 + ssim_lambda * (1 - SSIM), of ``pred`` [H, W, 3]
        against the training image (masked pixels black in both, as splatfacto does)."""
        gt = self.composite_with_background(self.get_gt_img(batch["image"]), background)[..., :3]
        if "mask" in batch:
            mask = self._downscale_if_required(batch["mask"]).to(self.device)
            gt, pred = gt * mask, pred * mask
        l1 = torch.abs(gt - pred).mean()
        ssim = self.ssim(gt.permute(2, 0, 1)[None], pred.permute(2, 0, 1)[None])
        return (1 - self.config.ssim_lambda) * l1 + self.config.ssim_lambda * (1 - ssim)

    def _training_target(self, outputs, batch) -> Tensor:
        """[H, W, 3] the training image composited on the render's background, its masked pixels replaced by the
        (detached) render so they add no residual."""
        gt = self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])[..., :3]
        if "mask" in batch:
            mask = self._downscale_if_required(batch["mask"]).to(self.device)
            return gt * mask + outputs["rgb"].detach() * (1.0 - mask.float())
        return gt

    def get_metrics_dict(self, outputs, batch) -> Dict[str, Tensor]:
        """splatfacto's metrics; ``blur_kernel_size`` (the HPKO kernel size) on steps where the blur field ran."""
        metrics_dict = super().get_metrics_dict(outputs, batch)
        aux = outputs.get("degradation") if self.training else None
        if aux is not None and aux.kernel_size is not None:
            metrics_dict["blur_kernel_size"] = aux.kernel_size
        if self.training and self.degradation.fallback is not None:
            metrics_dict["blur_model_in_use"] = self.degradation.fallback.fraction_using_model()
        return metrics_dict

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
]
