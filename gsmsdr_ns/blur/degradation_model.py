"""Everything that turns a sharp render into the degraded photo a training image is: :class:`DegradationModel`.

It owns one :class:`~gsmsdr_ns.blur.profile.DegradationProfile` per training image and, as siblings, only the parts
those profiles need: the camera-shake paths (``DegradationConfig.camera_shake``), the thin lens for defocus, the
blur field (MAAN + HPKO) with its HPKO scheduler, and the resolution-loss model. A sharp scene builds none of
them. The field's architecture is its :class:`~gsmsdr_ns.blur.field.BlurFieldConfig`; everything else is the
:class:`~gsmsdr_ns.blur.degradation_config.DegradationConfig`. One training step enters it three times, each a
function of its arguments (no state carried between them): :meth:`DegradationModel.plan` says what the image needs
at this step and resolution, :meth:`DegradationModel.forward` passes the render through it and returns the degraded
image with one :class:`~gsmsdr_ns.blur.losses.DegradationAux`, and :meth:`DegradationModel.losses` turns that into
every degradation loss term. The viewer's blur outputs come from
:meth:`DegradationModel.preview`; it and ``forward`` run "the thin lens, then the field" through one method,
:meth:`DegradationModel._lens_then_field`.

Checkpoint keys: ``blur_field.*``, ``thin_lens.*``, ``camera_shake.*``, ``resolution_model.*``, ``fallback.*`` and
``train_camera_centres`` under this module's prefix; :mod:`gsmsdr_ns.blur.state_keys` moves the keys of older
checkpoints to them.
"""

from __future__ import annotations

from collections import Counter
from typing import Any, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gsmsdr_ns.blur.defocus import ThinLensDefocus
from gsmsdr_ns.blur.degradation_config import DegradationConfig
from gsmsdr_ns.blur.fallback import ExplanationGate, photo_errors
from gsmsdr_ns.blur.field import BlurField, BlurFieldConfig, blend
from gsmsdr_ns.blur.hpko import HPKOScheduler
from gsmsdr_ns.blur.losses import DegradationAux, degradation_losses, kernel_centres, mean_blend_kernel
from gsmsdr_ns.blur.maan import host_checked_view_ids
from gsmsdr_ns.blur.plan import DegradationPlan, crop_margin
from gsmsdr_ns.blur.preview import coarsen_kernels, kernel_spread, nearest_view, preview_downscale
from gsmsdr_ns.blur.profile import DegradationProfile, ResolutionLossModel, describe_profiles, effective_factor
from gsmsdr_ns.blur.recorded_shake import set_recorded_paths
from gsmsdr_ns.blur.shake import CameraShake
from gsmsdr_ns.blur.state_keys import LEGACY_KEY_PREFIXES, remap_legacy_keys, with_fallback_state
from gsmsdr_ns.ops.deconvolved_loss import compose_kernels
from gsmsdr_ns.ops.grid_kernels import GridKernels, as_dense
from gsmsdr_ns.timing_hooks import timed

__all__ = [
    "DegradationModel",
    "DegradationPlan",
    "crop_margin",
    "LEGACY_KEY_PREFIXES",
    "remap_legacy_keys",
    "with_fallback_state",
]


def _lens_for(profile: DegradationProfile, config: DegradationConfig) -> bool:
    """Whether the thin lens blurs this image before the field: known defocus, or (when the config asks) a blur of
    unknown kind."""
    return profile.known_defocus or (profile.defocus and config.thin_lens_for_unknown_kind)


class LensThenField(NamedTuple):
    """The blur stages of one image: the lens's kernels (None: no lens), the image after the lens, and the field's
    kernels (per pixel, or on the field's coarse grid) and mask for that image (None: the field did not run)."""

    lens_kernels: Optional[Tensor]
    image: Tensor
    kernels: Optional[Union[Tensor, GridKernels]]
    mask: Optional[Tensor]


def _bchw(x: Tensor) -> Tensor:
    """[H, W, C] -> [1, C, H, W]"""
    return x.permute(2, 0, 1)[None]


def _hwc(x: Tensor) -> Tensor:
    """[1, C, H, W] -> [H, W, C]"""
    return x[0].permute(1, 2, 0)


class DegradationModel(nn.Module):
    """The degradation models of a set of training images, built only for the effects their profiles call for.

    Args:
        profiles: one per training image, in the training split's order.
        field_config: the blur field's architecture (restricted to the scales ``num_downscales`` visits).
        config: everything else: lens, shake, schedule, margin, resolution model, loss weights.
        num_downscales: splatfacto's ``num_downscales`` (training starts at 1 / 2^num_downscales).
        resolution_schedule: splatfacto's ``resolution_schedule`` (steps between resolution doublings).
        preview_max_side: the viewer outputs' working resolution (see :meth:`preview`; 0: full resolution).
        densify_until: the step the Gaussians stop densifying (splatfacto's ``stop_split_at``), where the thin lens
            starts when the config's ``thin_lens_start`` is ``"densify_end"`` (and the shake paths' translations
            when ``shake_translation_start`` is); None: unknown, both start with the field.
        shake_records, pose_scale: with the config's ``shake_paths`` ``"records"``, each training image's ``motion``
            record (None: none) and the dataparser's pose scale (:func:`~.recorded_shake.set_recorded_paths`).

    Attributes (None when no image needs them): ``camera_shake`` (:class:`CameraShake`), ``thin_lens``
    (:class:`ThinLensDefocus`), ``blur_field`` (:class:`BlurField`), ``hpko`` (:class:`HPKOScheduler`),
    ``train_camera_centres`` (persistent [N, 3] buffer, NaN until :meth:`set_train_camera_centres`: the viewer
    outputs use the nearest training view), ``resolution_model`` (:class:`ResolutionLossModel`), ``fallback``
    (:class:`~gsmsdr_ns.blur.fallback.ExplanationGate`, with the blur field when the config's ``fallback`` is on).
    The blur field is initialised under ``torch.random.fork_rng``: building it leaves the random stream training
    draws from as it would be without it.
    """

    train_camera_centres: Tensor  # buffer, registered in __init__ when there is a blur field

    def __init__(
        self,
        profiles: Sequence[DegradationProfile],
        field_config: BlurFieldConfig,
        config: Optional[DegradationConfig] = None,
        num_downscales: int = 2,
        resolution_schedule: int = 3000,
        preview_max_side: int = 128,
        densify_until: Optional[int] = None,
        shake_records: Optional[Sequence[Optional[Mapping[str, Any]]]] = None,
        pose_scale: Optional[float] = None,
    ) -> None:
        super().__init__()
        self.profiles: List[DegradationProfile] = list(profiles)
        self.config = config = DegradationConfig() if config is None else config
        self.lens_start = config.start_step(config.thin_lens_start, densify_until)
        """First step the thin lens runs (:attr:`DegradationConfig.thin_lens_start`)."""
        self.shake_translation_start = config.start_step(config.shake_translation_start, densify_until)
        """First step the shake paths translate (:attr:`DegradationConfig.shake_translation_start`)."""
        self.preview_max_side = int(preview_max_side)
        self.blur_field: Optional[BlurField] = None
        self.thin_lens: Optional[ThinLensDefocus] = None
        self.hpko: Optional[HPKOScheduler] = None
        self.resolution_model: Optional[ResolutionLossModel] = None
        self.fallback: Optional[ExplanationGate] = None
        self._view_id_tensors: Dict[Tuple[int, torch.device], Tensor] = {}
        num_views = len(self.profiles)
        if any(p.needs_blur_field for p in self.profiles):
            field_config = field_config.for_schedule(num_downscales, config.switch_steps)
            with torch.random.fork_rng(devices=[]):
                self.blur_field = field_config.setup(
                    num_train_views=num_views, use_depth=any(p.needs_depth for p in self.profiles)
                )
            if config.thin_lens and any(_lens_for(p, config) for p in self.profiles):
                self.thin_lens = ThinLensDefocus(
                    num_views, config.thin_lens_initial_aperture, occlusion=config.thin_lens_occlusion
                )
            self.hpko = HPKOScheduler(
                kernel_sizes=tuple(field_config.kernel_sizes),
                num_downscales=num_downscales,
                resolution_schedule=resolution_schedule,
                switch_steps=config.switch_steps,
                warmup=config.warmup,
                enabled=field_config.modules.hpko,
            )
            self.register_buffer("train_camera_centres", torch.full((num_views, 3), float("nan")))
            if config.fallback:
                self.fallback = ExplanationGate(num_views, config.fallback_decay, config.fallback_margin)
        self.camera_shake: Optional[CameraShake] = None
        if self.blur_field is not None and config.camera_shake and any(p.motion for p in self.profiles):
            self.camera_shake = CameraShake(
                num_views,
                config.shake_samples,
                translation=config.shake_translation,
                parallax=config.shake_parallax,
                occlusion=config.shake_occlusion,
            )
        if self.camera_shake is not None and config.shake_paths == "records":
            set_recorded_paths(self.camera_shake, self.profiles, shake_records, pose_scale)
        mixres = [p for p in self.profiles if p.needs_resolution_model]
        if mixres:
            upsample = Counter(p.mixres_upsample for p in mixres).most_common(1)[0][0]
            self.resolution_model = ResolutionLossModel(
                num_views=num_views, kernel_size=config.resolution_kernel_size, upsample=upsample
            )

    # -- description and state ------------------------------------------------------------------------------

    def describe(self) -> str:
        """One line for the log: what the training images are and which models that builds."""
        parts = []
        if self.blur_field is not None:
            assert self.hpko is not None
            depth = "RGB-D" if self.blur_field.uses_depth else "RGB"
            lens = f", thin lens for defocus from step {self.lens_start}" if self.thin_lens is not None else ""
            parts.append(f"blur field ({self.blur_field.config.mode}, {depth}, kernels {self.hpko.kernel_sizes}{lens})")
        if self.resolution_model is not None:
            parts.append("resolution-loss model")
        return " + ".join(parts) or "plain splatfacto (no degradation model)"

    def describe_training_views(self) -> str:
        """``"<profile counts> -> <models>"``, e.g. ``"6 motion, 2 sharp -> blur field (...)"``."""
        return f"{describe_profiles(self.profiles)} -> {self.describe()}"

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

    # -- nerfstudio-style shared-dict hooks -----------------------------------------------------------------

    def get_param_groups(self, groups: Dict[str, List[nn.Parameter]]) -> Dict[str, List[nn.Parameter]]:
        """Add ``blur_field`` / ``blur_view_kernels`` / ``blur_defocus`` (see ``BlurField.get_param_groups``) and
        ``resolution_model`` for the modules that exist."""
        if self.blur_field is not None:
            self.blur_field.get_param_groups(groups)
        if self.thin_lens is not None:
            groups["blur_defocus"] = list(self.thin_lens.parameters())
        if self.camera_shake is not None:
            groups["blur_shake"] = list(self.camera_shake.parameters())
        if self.resolution_model is not None:
            groups["resolution_model"] = list(self.resolution_model.parameters())
        return groups

    def losses(self, aux: DegradationAux, degraded: Tensor, target: Optional[Tensor]) -> Dict[str, Tensor]:
        """Every degradation loss term of a step (:func:`~gsmsdr_ns.blur.losses.degradation_losses`): ``aux`` and
        ``degraded`` [H, W, 3] from :meth:`forward`, ``target`` [H, W, 3] the training image (needed only when
        ``aux.kernel_mean`` is set)."""
        return degradation_losses(aux, degraded, target, self.config.loss_weights)

    # -- training -------------------------------------------------------------------------------------------

    def view_ids(self, view_id: int, device: torch.device) -> Tensor:
        """[1] tensor of training image ``view_id`` on ``device``, made (and range-checked on the host) once per
        view and device, then reused: no host-to-device copy per step, and the modules need not read it back
        (:func:`~gsmsdr_ns.blur.maan.host_checked_view_ids`)."""
        key = (int(view_id), torch.device(device))
        tensor = self._view_id_tensors.get(key)
        if tensor is None:
            tensor = host_checked_view_ids([key[0]], len(self.profiles), key[1])
            self._view_id_tensors[key] = tensor
        return tensor

    def lens_alone(self, view_id: int) -> bool:
        """Whether the thin lens alone models this image's blur (defocus only, a lens is built, and the field's
        config does not ask for the field on defocus)."""
        field = self.blur_field
        return (
            field is not None
            and self.thin_lens is not None
            and self.profiles[view_id].defocus_only
            and not self.config.defocus_field
        )

    def plan(self, view_id: Optional[int], render_downscale: int, step: int) -> DegradationPlan:
        """What to simulate for training image ``view_id`` (None: a camera outside the training set) rendered at
        1 / ``render_downscale`` on training step ``step``; a function of its arguments alone.

        Nothing for sharp images. The blur field runs once the HPKO scheduler is past its warm-up, at the scale of
        ``render_downscale`` (so it follows the resolution schedule; explicit ``switch_steps`` take over when set);
        the resolution model runs while the image's factor, relative to ``render_downscale``, is still > 1. The thin
        lens runs from :attr:`lens_start`; before it an image the lens models alone is a plain step.
        """
        if view_id is None:
            return DegradationPlan()
        profile = self.profiles[view_id]
        if profile.is_sharp:
            return DegradationPlan(view_id)
        field = self.blur_field
        blur_scale = None
        if profile.needs_blur_field and self.hpko is not None:
            blur_scale = self.hpko.scale_at(step, render_downscale)
        factor = 1.0
        if profile.needs_resolution_model and self.resolution_model is not None:
            assert profile.mixres_factor is not None  # needs_resolution_model: a known factor > 1
            factor = effective_factor(profile.mixres_factor, render_downscale)
        config = self.config
        lens = self.thin_lens is not None and _lens_for(profile, config)
        runs_field = not self.lens_alone(view_id)
        if lens and step < self.lens_start:
            lens = False
            blur_scale = blur_scale if runs_field else None  # an image the lens models alone waits for it
        if field is None or blur_scale is None:
            return DegradationPlan(view_id, resolution_factor=factor, render_downscale=render_downscale, has_model=True)
        shake = self.camera_shake is not None and profile.motion
        return DegradationPlan(
            view_id=view_id,
            blur_scale=blur_scale,
            blur_uses_depth=field.uses_depth,
            resolution_factor=factor,
            thin_lens=lens,
            render_downscale=render_downscale,
            blur_field=runs_field,
            shake=shake,
            shake_depth=shake and config.shake_translation and step >= self.shake_translation_start,
            margin=blur_scale.kernel_size // 2 if config.render_margin else 0,
            deconvolved_loss=(runs_field or (lens and config.deconvolved_loss_on_lens))
            and config.deconvolved_loss_weight > 0,
            kernel_centre_loss=runs_field
            and config.kernel_centre_weight > 0
            and (not profile.exact_pose or (shake and config.kernel_centre_after_shake)),
            has_model=True,
        )

    def with_fallback(self, plan: DegradationPlan) -> DegradationPlan:
        """``plan`` with ``fallback`` set when its image's blur model runs but does not yet explain the photo better
        than the sharp render (:class:`~gsmsdr_ns.blur.fallback.ExplanationGate`); reads the gate's state."""
        if self.fallback is None or plan.blur_scale is None or plan.view_id is None:
            return plan
        return plan if self.fallback.uses_model(plan.view_id) else plan._replace(fallback=True)

    @torch.no_grad()
    def record_errors(self, plan: DegradationPlan, degraded: Tensor, sharp: Tensor, target: Tensor) -> None:
        """After a step that ran ``plan``'s blur model: fold how well ``degraded`` and ``sharp`` (the render) explain
        ``target`` (all [H, W, 3]) into the gate."""
        if self.fallback is not None and plan.blur_scale is not None and plan.view_id is not None:
            self.fallback.update(plan.view_id, photo_errors(degraded, sharp, target, self.config.fallback_sigma))

    def forward(
        self, rgb: Tensor, depth: Optional[Tensor], plan: DegradationPlan, K: Optional[Tensor] = None
    ) -> Tuple[Tensor, DegradationAux]:
        """Pass the sharp render through this image's degradation models, in the order a camera degrades a photo:
        camera shake, thin lens, blur field, then resolution loss.

        Args:
            rgb: [H + 2 m, W + 2 m, 3] sharp render, m = ``plan.margin``.
            depth: [H + 2 m, W + 2 m, 1] expected depth, or None when the plan does not need it.
            plan: from :meth:`plan`.
            K: [3, 3] intrinsics of the render (margin included); needed when ``plan.shake``.
        Returns:
            The simulated degraded image [H, W, 3], and what the losses, metrics and viewer read of the step
            (:class:`~gsmsdr_ns.blur.losses.DegradationAux`). With ``plan.fallback`` the models run on the detached
            render: the degraded image's gradient reaches them alone (``aux.sharp`` keeps the render's).
        """
        sharp = crop_margin(rgb, plan.margin, dims=(0, 1))
        if plan.fallback:
            rgb = rgb.detach()
            depth = None if depth is None else depth.detach()
        image = _bchw(rgb)
        assert plan.view_id is not None
        view_ids = self.view_ids(plan.view_id, image.device)
        aux = DegradationAux(sharp)
        shake_mean = None
        if plan.shake:
            assert self.camera_shake is not None and self.blur_field is not None and K is not None
            centred = not self.profiles[plan.view_id].exact_pose
            linear_light = self.config.linear_light
            shake_depth = None if depth is None or not plan.shake_depth else depth[..., 0]
            image = timed(
                "kernels", self.camera_shake, image, K, view_ids, centred, linear_light, shake_depth, plan.shake_depth
            )
            if plan.deconvolved_loss and self.config.deconvolved_loss_on_shake and plan.blur_scale is not None:
                height, width = image.shape[-2:]
                max_size = 2 * plan.blur_scale.kernel_size + 1
                shake_mean = self.camera_shake.mean_kernel(K, view_ids, centred, height, width, max_size)
        if plan.blur_scale is not None:
            assert self.blur_field is not None
            stages = self._lens_then_field(
                image,
                None if depth is None else _bchw(depth),
                view_ids,
                plan.blur_scale.scale,
                lens_window=plan.blur_scale.kernel_size,
                lens_pixel_scale=1.0 / plan.render_downscale,
                lens=plan.thin_lens,
                field=plan.blur_field,
                field_depth=plan.blur_uses_depth,
            )
            image = stages.image
            lens_mean = None
            if plan.thin_lens and plan.deconvolved_loss and self.config.deconvolved_loss_on_lens:
                assert self.thin_lens is not None and depth is not None
                lens_args = (view_ids, plan.blur_scale.kernel_size, 1.0 / plan.render_downscale)
                lens_mean = self.thin_lens.mean_kernel(_bchw(depth), *lens_args)
            if stages.kernels is not None:
                assert stages.mask is not None
                blurred = timed("kernels", BlurField.blur, image, stages.kernels, self.config.linear_light)
                image = blend(stages.mask, blurred, image)
                kernel_mean = None
                if plan.deconvolved_loss:
                    kernel_mean = mean_blend_kernel(stages.kernels, stages.mask)
                    kernel_mean = kernel_mean if lens_mean is None else compose_kernels(lens_mean, kernel_mean)
                    kernel_mean = kernel_mean if shake_mean is None else compose_kernels(shake_mean, kernel_mean)
                aux = DegradationAux(
                    sharp,
                    mask=_hwc(crop_margin(stages.mask, plan.margin)),
                    learnt_mask=self.blur_field.config.mode != "view",
                    kernel_mean=kernel_mean,
                    kernel_centroids=(
                        timed("blur_field", kernel_centres, stages.kernels) if plan.kernel_centre_loss else None
                    ),
                    kernel_size=plan.blur_scale.kernel_size,
                )
            elif lens_mean is not None:
                aux = DegradationAux(sharp, kernel_mean=lens_mean)
        image = crop_margin(image, plan.margin)
        if plan.resolution_factor > 1.0:
            assert self.resolution_model is not None
            image = timed("kernels", self.resolution_model, image, [plan.resolution_factor], view_ids)
        return _hwc(image), aux

    def _lens_then_field(
        self,
        image: Tensor,
        depth: Optional[Tensor],
        view_ids: Tensor,
        scale: int,
        lens_window: int,
        lens_pixel_scale: float,
        lens: bool,
        field: bool,
        field_depth: bool,
        keep_lens_kernels: bool = False,
    ) -> LensThenField:
        """The blur of a training view as a camera makes it: its thin lens first (``lens``: disk kernels from
        ``depth`` in a ``lens_window`` window, aperture scaled by ``lens_pixel_scale`` from full-resolution pixels),
        then the field's kernels and mask on the lens's result (``field``; it reads ``depth`` when
        ``field_depth``). The lens's kernels are returned with ``keep_lens_kernels`` only: the fused lens never
        holds them. image [1, 3, H, W], depth [1, 1, H, W] or None, view_ids [1]."""
        assert self.blur_field is not None
        lens_kernels = None
        if lens:
            assert self.thin_lens is not None and depth is not None
            thin_lens = self.thin_lens
            linear_light = self.config.linear_light
            if keep_lens_kernels:
                lens_kernels = timed("blur_field", thin_lens, depth, view_ids, lens_window, lens_pixel_scale)
                image = timed("kernels", BlurField.blur, image, lens_kernels, linear_light)
            else:  # the image through the lens (ThinLensDefocus.blur)
                args = (depth, view_ids, lens_window, lens_pixel_scale, image, linear_light)
                image = timed("kernels", thin_lens, *args)
        kernels = mask = None
        if field:
            field_depth_in = depth if field_depth else None
            kernels, mask = timed("blur_field", self.blur_field, image, field_depth_in, view_ids, scale, dense=False)
        return LensThenField(lens_kernels, image, kernels, mask)

    # -- viewer ---------------------------------------------------------------------------------------------

    def preview(self, rgb: Tensor, depth: Optional[Tensor], camera_centre: Tensor, step: int) -> Dict[str, Tensor]:
        """Viewer outputs of the blur field for an evaluation camera, as for the nearest training view (its
        embedding and per-view kernels).

        The field runs at the HPKO scale training uses at ``step`` (``hpko.scale_for_step``), on the
        render shrunk to that scale's resolution, or further (powers of two) until its longer side is at most
        ``preview_max_side``; in that case the kernels are re-expressed on the coarser grid (:func:`coarsen_kernels`)
        so the simulated blur keeps its extent. Results are enlarged back to the render's size. ``degraded``
        [H, W, 3] = mask * blurred + (1 - mask) * render; ``kernel_size`` [H, W, 1] = the kernels' RMS blur radius
        in pixels of the render, times the mask (0 where the field keeps the render sharp); ``blur_mask``
        [H, W, 1]. When that training view is defocused, its thin lens blurs the render first (``render`` above is
        then the lens's blur) and its RMS radius is added in quadrature; a view the lens models alone shows the
        lens's blur, its RMS radius and a mask of 1.

        Args:
            rgb: [H, W, 3] sharp render.
            depth: [H, W, 1] expected depth (read when the field or the lens needs it).
            camera_centre: [3] position of the evaluation camera.
            step: the training step whose kernels to show.
        """
        assert self.blur_field is not None and self.hpko is not None
        height, width = rgb.shape[:2]
        info = self.hpko.scale_for_step(step)
        d = preview_downscale(height, width, self.preview_max_side, at_least=info.downsample)
        small = (max(1, height // d), max(1, width // d))
        image = _bchw(rgb)
        low = image if d == 1 else F.interpolate(image, size=small, mode="area")
        view_id = nearest_view(self.train_camera_centres, camera_centre)
        view_ids = self.view_ids(view_id, image.device)
        lens = self.thin_lens is not None and _lens_for(self.profiles[view_id], self.config)
        lens_alone = self.lens_alone(view_id)
        field_depth = self.blur_field.uses_depth and not lens_alone
        low_depth = None
        if field_depth or lens:
            assert depth is not None
            depth_in = _bchw(depth)
            low_depth = depth_in if d == 1 else F.interpolate(depth_in, size=small, mode="area")

        def enlarge(x: Tensor) -> Tensor:
            return x if d == 1 else F.interpolate(x, size=(height, width), mode="bilinear", align_corners=False)

        window = (info.kernel_size * info.downsample // d) | 1  # the scale's window at the preview's grid, odd
        stages = self._lens_then_field(
            low, low_depth, view_ids, info.scale, window, 1.0 / d, lens=lens, field=not lens_alone,
            field_depth=field_depth, keep_lens_kernels=True,
        )  # fmt: skip
        lens_extent = None if stages.lens_kernels is None else kernel_spread(stages.lens_kernels) * d
        if stages.kernels is None:  # as in training: a defocus-only view is the lens's blur in full
            assert lens_extent is not None
            return {
                "degraded": _hwc(enlarge(stages.image).clamp(0.0, 1.0)),
                "kernel_size": _hwc(enlarge(lens_extent)),
                "blur_mask": rgb.new_ones(height, width, 1),
            }
        assert stages.mask is not None
        kernels = as_dense(stages.kernels)
        extent = kernel_spread(kernels) * info.downsample * stages.mask  # taps are pixels at the scale's grid
        if lens_extent is not None:  # RMS radii of successive blurs add in quadrature
            extent = torch.sqrt(extent**2 + lens_extent**2)
        coarse = coarsen_kernels(kernels, d // info.downsample)
        blurred = BlurField.blur(stages.image, coarse, self.config.linear_light)
        mask_full = enlarge(stages.mask)
        base = image if not lens else enlarge(stages.image)  # what the field blends with: the render or its lens blur
        degraded = blend(mask_full, enlarge(blurred), base).clamp(0.0, 1.0)
        return {"degraded": _hwc(degraded), "kernel_size": _hwc(enlarge(extent)), "blur_mask": _hwc(mask_full)}
