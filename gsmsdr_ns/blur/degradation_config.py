"""How a training image's degradation is simulated from the sharp render: :class:`DegradationConfig`.

The blur field's own architecture (widths, modules, kernel sizes, initialisation) is
:class:`~gsmsdr_ns.blur.field.BlurFieldConfig`; everything around it is here: which models run before it (camera
shake, thin lens) and when (warm-up, HPKO switch steps), how blur is applied (linear light, a render margin), the
resolution-loss model, and the weights of the degradation loss terms. Plain dataclass, no nerfstudio import; tyro
turns it into ``--pipeline.model.degradation-model.*`` options.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Dict, Literal, Mapping, Optional, Tuple

from gsmsdr_ns.blur.losses import DegradationLossWeights

__all__ = ["DegradationConfig", "with_degradation_config"]


@dataclass
class DegradationConfig:
    """Everything about simulating a training image's degradation except the blur field's architecture."""

    warmup: int = 250
    """The blur field (and the lens and shake before it) are skipped for the first ``warmup`` steps (BAGS: 250)."""
    fallback: bool = False
    """Per image, train a plain step (the Gaussians on the sharp render) until its degradation model explains the
    photo better than the sharp render does (running means of both errors, :class:`~gsmsdr_ns.blur.fallback.
    ExplanationGate`); meanwhile the model keeps learning on the detached render. Off by default: from random
    points it let the lens over-blur (docs/design.md). False: every blurred image trains through its model from the
    end of the warm-up."""
    fallback_decay: float = 0.5
    """Weight of an image's previous running errors at each of its steps (0: its last step alone decides)."""
    fallback_margin: float = 0.0
    """The model is used once its error is below (1 - margin) times the sharp render's."""
    fallback_sigma: float = 0.0
    """Both errors are measured after a Gaussian blur of this standard deviation (pixels of the training render) of
    the photo and both images: the pixel-scale noise of a render still being formed is not taken for blur the photo
    has. 0: as they are."""
    switch_steps: Optional[Tuple[int, ...]] = None
    """Steps where HPKO goes one scale finer; None: follow the model's resolution schedule (recommended)."""
    linear_light: bool = True
    """Apply every blur (shake, lens, field) to linear light (the sRGB-encoded render decoded, blurred, re-encoded): a
    sensor integrates irradiance over the exposure and the aperture before the camera's tone curve. False: blur the
    encoded values (BAGS)."""
    thin_lens: bool = True
    """Images known to be defocused are first blurred by a learnt thin lens: per-pixel disk kernels whose radius
    follows the rendered depth, ``aperture * |1/d - 1/d_focus|``, with one aperture and focus per view
    (:class:`~gsmsdr_ns.blur.defocus.ThinLensDefocus`, optimizer group ``blur_defocus``). Motion-blurred and
    mixed-resolution images never pay for it."""
    thin_lens_start: Literal["warmup", "densify_end"] = "densify_end"
    """When the thin lens starts: when the Gaussians stop densifying (the model's ``stop_split_at``, never before
    ``warmup``), or with the field after ``warmup``. Until then images the lens models alone train plain steps, and
    images with the field train through the field alone: a lens learnt on a render still being densified (from
    random points above all) grows to hide the render's errors, and the defocused scene ends below plain Gaussians
    (docs/design.md)."""
    thin_lens_for_unknown_kind: bool = False
    """Also put the thin lens before the field on images blurred by an unknown kind of blur (no record, or an
    estimate that could not tell motion from defocus). Off: the field alone models their blur, whatever it is."""
    defocus_field: bool = False
    """Also run the field (per-pixel and per-view kernels, mask) after the thin lens on images known to be defocused
    only. False: the lens alone models them (the field would compete with it for the same blur); images with motion
    blur, or nothing known, always run the field. Ignored without ``thin_lens``."""
    thin_lens_occlusion: bool = True
    """Each neighbour spreads its own disk and an in-focus foreground hides the blurred background behind it
    (:func:`~gsmsdr_ns.ops.disk_kernels.occluding_disk_kernels`); False: every pixel gathers its own disk whatever
    the neighbours' depth (:func:`~gsmsdr_ns.ops.disk_kernels.soft_disk_kernels`)."""
    thin_lens_initial_aperture: float = 1.0
    """Starting aperture: CoC radius in pixels per scene unit of inverse depth (small: the untrained lens barely
    blurs)."""
    camera_shake: bool = False
    """Images that may be motion-blurred (records name motion, or the kind of blur is unknown) are first blurred
    along a learnt camera rotation path (:class:`~gsmsdr_ns.blur.shake.CameraShake`, optimizer group
    ``blur_shake``), then by the field: a turning camera blurs every pixel along its own path, which roll makes
    vary across the image. Off by default (on the real-photo suite's 117x86 shaken fern it did not beat the field
    alone); on in ``gsmsdr-cpu``, where it gained 0.7 dB at 458-600 px (docs/design.md)."""
    shake_samples: int = 9
    """Time samples of the exposure the render is warped to along the rotation path."""
    shake_translation: bool = False
    """With ``camera_shake``, also learn a camera translation path per view: a moving camera blurs near points more
    than far ones, so the warp reads the render's depth (rendered for these steps, not differentiated through). On
    in ``gsmsdr-cpu``, with ``shake_parallax``: alone it lost 0.2 dB to the rotation path on the generated 600x400
    strong shake, with it gained 0.44 dB there at 6000 steps (docs/design.md)."""
    shake_translation_start: Literal["warmup", "densify_end"] = "warmup"
    """When the translation paths start: with the rotation paths after ``warmup``, or once the Gaussians stop
    densifying (the model's ``stop_split_at``, never before ``warmup``), when the render's depth they read has
    formed. Until then the paths rotate only."""
    shake_parallax: bool = False
    """With ``shake_translation``, a translation moves the image relative to the view's median depth only: the
    rotation path is offset by the rotation that moves a point at the render's median depth on the optical axis as
    far as the translation does, so the rotation path carries the blur at that depth and the translation only
    what differs with depth (near points one way, far points the other). False: both paths move every pixel and
    trade off against each other through the render's depth. On in ``gsmsdr-cpu``."""
    shake_occlusion: bool = False
    """With ``shake_translation``, each time sample reads the render along the depth its own camera sees (a z-buffer
    of the render's points projected into that sample; :func:`~gsmsdr_ns.blur.shake.apply_camera_shake_occluding`),
    so a near surface smears outward over the background as in a photo; pixels no point reaches keep the render's
    depth. False: every pixel reads the render along the render's depth at that pixel. Off in every preset."""
    shake_paths: Literal["learnt", "records"] = "learnt"
    """``records``: each shaken view's path is the cubic closest to the true path its record gives (generated and
    ``gsmsdr-degrade`` scenes record it; the pose must be the exact mid-exposure one) and is not trained: a
    diagnostic of what learning the paths costs. Needs ``camera_shake``, not ``shake_parallax`` (the records give
    the rotations themselves); with ``shake_translation`` the recorded translations too. On the generated 600x400
    strong shake at 6000 steps the true paths reach 22.89 dB where the preset's learnt ones reach 22.27."""
    render_margin: bool = False
    """Render the current kernel's half-width beyond every border of a blurred image and crop after blurring: a
    photo's border pixels are blurred with what lay just outside the frame, which replicate padding cannot know.
    Off by default (on the real-photo suite's shaken fern it moved PSNR within the seed noise); on in ``gsmsdr-cpu``,
    with ``camera_shake`` (docs/design.md)."""
    resolution_kernel_size: int = 3
    """Size of the learned residual kernel of the resolution-loss model (images of known lower resolution)."""
    mask_reg_weight: float = 0.001
    """Weight of the blur field's mask regulariser mean(m) (BAGS: 0.001)."""
    kernel_centre_weight: float = 1.0
    """Weight of the kernel-centre regulariser: mean squared distance (pixels) of each kernel's centre of mass from
    its pixel, on images whose pose was estimated from the photo (structure-from-motion puts a blurred photo's pose
    near the centre of its blur; a kernel free to shift lets the sharp scene drift off that pose by a different
    amount in every view). Images whose records give the exact mid-exposure pose of a simulated shake (generated
    and ``gsmsdr-degrade`` scenes) are not centred. 0: off."""
    kernel_centre_after_shake: bool = False
    """Also centre the field's kernels on images a shake path blurs first whose pose is the exact mid-exposure one:
    the path, which passes through that pose, carries the blur's shift, so the kernel after it is left only what
    the path does not explain, and is not free to shift the view's image against the other views. Off in every
    preset: on the generated 600x400 strong shake at 6000 steps 22.25 dB against the preset's 22.27
    (docs/results/real-size/shake-fit)."""
    deconvolved_loss_weight: float = 10.0
    """Weight of the deconvolved residual loss (``ops/deconvolved_loss.py``) on images the field (or, with
    ``deconvolved_loss_on_lens``, the thin lens) blurs: the mean squared residual weighted by the inverse of the
    image's mean kernel (loss ``blur_deconvolved``), so the detail the blur attenuates reaches the Gaussians at about
    full strength instead of attenuated twice. 0: off (the paper's loss alone)."""
    deconvolved_loss_on_lens: bool = True
    """Also take the deconvolved residual loss on images the thin lens blurs, weighted by the inverse of the lens's
    mean disk over the image (composed with the field's mean kernel when the field runs after the lens). False: on
    images the field blurs only."""
    deconvolved_loss_on_shake: bool = False
    """With ``camera_shake``, compose the rotation path's image-mean kernel (:func:`~gsmsdr_ns.blur.shake.
    shake_mean_kernel`) into the kernel the deconvolved residual loss weighs by (the path carries much of a shaken
    view's blur). Off in every preset: at 3000 steps it gained 0.5 dB on the shaken fern and lost 0.5 dB on the
    generated 600x400 strong shake, where its stronger gradients split 2.5x the Gaussians (docs/design.md)."""
    deconvolved_loss_eps: float = 0.01
    """Wiener regulariser of that weight: frequencies the blur keeps below sqrt(eps) are amplified at most
    eps^-1/2 times (10x), so noise and frequencies the blur removed are not blown up."""
    sharp_anchor_weight: float = 0.0
    """On steps that train the Gaussians through the thin lens, also this times splatfacto's loss of the sharp render
    against the photo (loss ``sharp_anchor``): the Gaussians cannot hide their own errors behind a lens blur that
    grows to cover them. 0: off."""

    def __post_init__(self) -> None:
        if self.warmup < 0:
            raise ValueError(f"warmup must be >= 0, got {self.warmup}")
        if not 0.0 <= self.fallback_decay < 1.0:
            raise ValueError(f"fallback_decay must be in [0, 1), got {self.fallback_decay}")
        if not 0.0 <= self.fallback_margin < 1.0:
            raise ValueError(f"fallback_margin must be in [0, 1), got {self.fallback_margin}")
        if not self.fallback_sigma >= 0:
            raise ValueError(f"fallback_sigma must be >= 0, got {self.fallback_sigma}")
        for name in ("thin_lens_start", "shake_translation_start"):
            if getattr(self, name) not in ("warmup", "densify_end"):
                raise ValueError(f"{name} must be 'warmup' or 'densify_end', got {getattr(self, name)!r}")
        if not self.thin_lens_initial_aperture > 0:
            raise ValueError(f"thin_lens_initial_aperture must be > 0, got {self.thin_lens_initial_aperture}")
        if not self.deconvolved_loss_weight >= 0:
            raise ValueError(f"deconvolved_loss_weight must be >= 0, got {self.deconvolved_loss_weight}")
        if not self.deconvolved_loss_eps > 0:
            raise ValueError(f"deconvolved_loss_eps must be > 0, got {self.deconvolved_loss_eps}")
        if not self.sharp_anchor_weight >= 0:
            raise ValueError(f"sharp_anchor_weight must be >= 0, got {self.sharp_anchor_weight}")
        if not self.kernel_centre_weight >= 0:
            raise ValueError(f"kernel_centre_weight must be >= 0, got {self.kernel_centre_weight}")
        if not self.mask_reg_weight >= 0:
            raise ValueError(f"mask_reg_weight must be >= 0, got {self.mask_reg_weight}")
        if self.shake_paths not in ("learnt", "records"):
            raise ValueError(f"shake_paths must be 'learnt' or 'records', got {self.shake_paths!r}")
        if self.shake_paths == "records" and (not self.camera_shake or self.shake_parallax):
            raise ValueError(
                "shake_paths 'records' needs camera_shake on and shake_parallax off (the records give the rotations "
                f"themselves); got camera_shake={self.camera_shake}, shake_parallax={self.shake_parallax}"
            )
        if self.shake_samples < 1:
            raise ValueError(f"shake_samples must be >= 1, got {self.shake_samples}")
        if self.resolution_kernel_size < 1 or self.resolution_kernel_size % 2 == 0:
            raise ValueError(
                f"resolution_kernel_size must be a positive odd integer, got {self.resolution_kernel_size}"
            )

    def start_step(self, start: str, densify_until: Optional[int]) -> int:
        """First step of a model part that starts at ``"warmup"`` or ``"densify_end"`` (``thin_lens_start``,
        ``shake_translation_start``): never before ``warmup``; at ``warmup`` when ``densify_until`` is unknown."""
        if start == "densify_end" and densify_until is not None:
            return max(self.warmup, int(densify_until))
        return self.warmup

    @property
    def loss_weights(self) -> DegradationLossWeights:
        return DegradationLossWeights(
            self.mask_reg_weight, self.kernel_centre_weight, self.deconvolved_loss_weight, self.deconvolved_loss_eps
        )


DEGRADATION_FIELDS = tuple(f.name for f in fields(DegradationConfig))


def with_degradation_config(model_state: Mapping[str, Any]) -> Dict[str, Any]:
    """A model config's attributes (as a config.yml holds them) with a ``degradation_model``: one written before
    :class:`DegradationConfig` existed had its options in ``blur_field`` (a ``BlurFieldConfig`` loaded with them as
    attributes) and ``resolution_kernel_size``; they move into a new ``DegradationConfig``, the rest stays."""
    state = dict(model_state)
    if "degradation_model" in state:
        return state
    moved: Dict[str, Any] = {}
    blur = state.get("blur_field")
    if blur is not None:
        attributes = vars(blur)
        moved = {k: attributes.pop(k) for k in list(attributes) if k in DEGRADATION_FIELDS}
    if "resolution_kernel_size" in state:
        moved["resolution_kernel_size"] = state.pop("resolution_kernel_size")
    state["degradation_model"] = DegradationConfig(**moved)
    return state
