"""Configuration of scene degradation: one dataclass per effect, nested in `DegradeConfig`, loadable from YAML.

Pixel-valued parameters (blur extent, circle of confusion) are given for an image `px_reference_width` pixels
wide and scaled by width / px_reference_width, so one preset means the same relative blur at 64, 200 or 600 px.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Tuple

import tyro
from typing_extensions import Annotated

from ..data.effects import KNOWN_EFFECTS, SHARP_ALIASES
from ..io.config import load_dataclass, read_yaml_mapping


@dataclass
class MotionConfig:
    """Camera shake during the exposure."""

    model: Literal["auto", "trajectory", "rotational_shake", "kernel"] = "auto"
    """auto: 'trajectory' (re-render sub-frames along a 6-DoF path) for generated scenes (scene.json), else
    'rotational_shake' (homography warps K R(t) K^-1 of the photo); 'kernel' is one spatially uniform kernel."""
    min_blur_px: float = 6.0
    """Smallest blur extent per view: the largest distance between two positions of one scene point during
    the exposure, over the image, at the reference width. Each training view draws its extent uniformly from
    [min_blur_px, max_blur_px]."""
    max_blur_px: float = 12.0
    """Largest blur extent per view (see min_blur_px)."""
    curvature: float = 0.5
    """Shape of the shake path: 0 is a straight line, 1 a cubic Bezier through random control points."""
    roll_fraction: float = 0.3
    """Amplitude of roll (rotation about the optical axis) relative to pan/tilt, as an angle ratio."""
    translation_fraction: float = 0.25
    """(trajectory model) share of the blur at the median scene depth caused by camera translation."""
    sample_spacing_px: float = 1.0
    """Largest pixel motion between consecutive exposure samples (one homography warp per sample)."""
    keyframe_spacing_px: float = 6.0
    """(trajectory model) largest pixel motion between re-rendered sub-frames; the motion between them is
    interpolated with homographies induced by the plane at the sub-frame's median depth."""
    max_samples: int = 64
    """Cap on exposure samples per view (long paths are sampled more coarsely rather than slower)."""
    render_supersample: int = 0
    """(trajectory model) supersampling of each re-rendered sub-frame; 0: the scene's own (scene.json), so the
    blurred view is the blur of the same anti-aliased image as its sharp twin. A lower value is faster but adds
    aliasing that no blur kernel can explain."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_blur_px <= self.max_blur_px:
            raise ValueError(
                f"motion: need 0 <= min_blur_px <= max_blur_px, got {self.min_blur_px}, {self.max_blur_px}"
            )
        if not 0.0 <= self.curvature <= 1.0:
            raise ValueError(f"motion.curvature must be in [0, 1], got {self.curvature}")
        if not 0.0 <= self.translation_fraction < 1.0:
            raise ValueError(f"motion.translation_fraction must be in [0, 1), got {self.translation_fraction}")
        if self.roll_fraction < 0:
            raise ValueError(f"motion.roll_fraction must be >= 0, got {self.roll_fraction}")
        if self.sample_spacing_px <= 0 or self.keyframe_spacing_px <= 0:
            raise ValueError("motion.sample_spacing_px and motion.keyframe_spacing_px must be > 0")
        if self.render_supersample < 0:
            raise ValueError(f"motion.render_supersample must be >= 0 (0: the scene's), got {self.render_supersample}")
        if self.max_samples < 2:
            raise ValueError(f"motion.max_samples must be >= 2, got {self.max_samples}")


@dataclass
class DefocusConfig:
    """Out-of-focus blur of a thin lens (depth known) or a uniform disk (no depth)."""

    model: Literal["auto", "thin_lens", "disk"] = "auto"
    """auto: 'thin_lens' where depth/<stem>.npy exists (circle of confusion from depth, layered so that blurred
    foreground spreads over the background), else 'disk' (one uniform disk PSF per view)."""
    min_coc_px: float = 8.0
    """Smallest largest-circle-of-confusion DIAMETER per view, in pixels at the reference width; each view draws
    its maximum CoC uniformly from [min_coc_px, max_coc_px] (thin lens: the aperture is set so the largest CoC
    in the view equals it; disk: the disk diameter)."""
    max_coc_px: float = 14.0
    """Largest maximum-CoC diameter per view (see min_coc_px)."""
    focus_quantile_min: float = 0.2
    """(thin lens) the focus distance is the q-quantile of the view's depth, q uniform in [min, max]."""
    focus_quantile_max: float = 0.6
    """(thin lens) upper bound of the focus-distance quantile."""
    radius_step_px: float = 0.5
    """(thin lens) depth layers are blurred with radii quantised to this step (finer costs more layers)."""
    radius_rel_step: float = 0.15
    """(thin lens) above radius_step_px / radius_rel_step the quantisation step grows to this fraction of r."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_coc_px <= self.max_coc_px:
            raise ValueError(f"defocus: need 0 <= min_coc_px <= max_coc_px, got {self.min_coc_px}, {self.max_coc_px}")
        if not 0.0 <= self.focus_quantile_min <= self.focus_quantile_max <= 1.0:
            raise ValueError("defocus: need 0 <= focus_quantile_min <= focus_quantile_max <= 1")
        if self.radius_step_px <= 0 or self.radius_rel_step <= 0:
            raise ValueError("defocus.radius_step_px and defocus.radius_rel_step must be > 0")


@dataclass
class MixresConfig:
    """Mixed resolution: training views split into equal groups, downscaled and upsampled back."""

    factors: Tuple[int, ...] = (4, 3, 2, 1)
    """Downscale factors of the groups (equal group sizes up to one view); 1 leaves a view untouched."""
    upsample: Literal["bilinear", "bicubic"] = "bilinear"
    """Interpolation used to bring the downscaled view back to full size (downscaling is antialiased bilinear)."""

    def __post_init__(self) -> None:
        self.factors = tuple(int(f) for f in self.factors)
        if not self.factors or any(f < 1 for f in self.factors):
            raise ValueError(f"mixres.factors must be a non-empty list of integers >= 1, got {list(self.factors)}")


@dataclass
class NoiseConfig:
    """Sensor noise added last, on the stored (display) values, then clipped to [0, 1]."""

    sigma: Annotated[float, tyro.conf.arg(aliases=("--noise-sigma",))] = 0.0
    """Standard deviation of the signal-independent Gaussian read noise (image values in [0, 1]); > 0 turns the
    noise effect on."""
    gain: float = 0.0
    """Shot-noise gain: variance gain * x + sigma^2 (Poisson-Gaussian model when > 0)."""

    def __post_init__(self) -> None:
        if self.sigma < 0 or self.gain < 0:
            raise ValueError(f"noise: sigma and gain must be >= 0, got {self.sigma}, {self.gain}")

    @property
    def active(self) -> bool:
        return self.sigma > 0 or self.gain > 0


@dataclass
class DegradeConfig:
    """Everything that determines a degraded scene besides the input; same config + input -> same output."""

    effects: Annotated[Tuple[str, ...], tyro.conf.UseAppendAction, tyro.conf.arg(name="effect")] = ()
    """Effects to apply to the training views: motion, defocus, mixres, noise (repeat the flag or give a comma
    list; 'sharp' means none). They are applied in the order motion, defocus, mixres, noise."""
    seed: int = 0
    """Seed of every random choice (per view and effect streams, so adding an effect leaves the others unchanged)."""
    hold: int = 8
    """Views whose sorted index % hold == 0 are sharp held-out test views (Deblur-NeRF's hold=N)."""
    assignment: Literal["all", "one_per_image"] = "all"
    """all: every training view gets every listed effect; one_per_image: each training view gets ONE of the listed
    blur effects (motion / defocus / mixres, equal shares, seed-controlled); noise still applies to all."""
    px_reference_width: int = 600
    """Image width at which pixel-valued parameters are given; they scale with width / px_reference_width
    (0: use them as absolute pixels)."""
    linear_light: bool = True
    """Blur (motion, defocus) in linear light: sRGB-decode before and encode after, as a sensor integrates light."""
    workers: int = 0
    """Processes degrading views in parallel; 0 picks one per CPU core when there are enough views."""
    crop_border: bool = True
    """Photos (a scene that cannot be re-rendered): crop every image, sharp twins included, by the widest border
    band any view's blur filled from outside the photo (reflected pixels no camera records; the records'
    ``border_reach_px``); the principal point moves with the crop. Generated scenes re-render their margins and
    are never cropped."""
    motion: MotionConfig = field(default_factory=MotionConfig)
    """Motion blur parameters."""
    defocus: DefocusConfig = field(default_factory=DefocusConfig)
    """Defocus blur parameters."""
    mixres: MixresConfig = field(default_factory=MixresConfig)
    """Mixed-resolution parameters."""
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    """Sensor noise parameters."""

    def __post_init__(self) -> None:
        if isinstance(self.effects, str):
            self.effects = (self.effects,)
        self.effects = tuple(self.effects)
        if self.hold < 2:
            raise ValueError(
                f"hold must be >= 2 (every hold-th view is a sharp test view; hold={self.hold} leaves "
                f"{'no valid split' if self.hold < 1 else 'no training views'})"
            )
        if self.px_reference_width < 0:
            raise ValueError(f"px_reference_width must be >= 0, got {self.px_reference_width}")
        if self.workers < 0:
            raise ValueError(f"workers must be >= 0, got {self.workers}")
        normalize_effects(self.effects)  # unknown names fail here, at config time

    def resolved_effects(self) -> tuple[str, ...]:
        """Effects in application order, with 'noise' added when noise.sigma / noise.gain are > 0."""
        effects = set(normalize_effects(self.effects))
        if self.noise.active:
            effects.add("noise")
        if "noise" in effects and not self.noise.active:
            raise ValueError("the noise effect needs noise.sigma > 0 or noise.gain > 0 (CLI: --noise-sigma 0.01)")
        return tuple(e for e in KNOWN_EFFECTS if e in effects)


def normalize_effects(effects: Iterable[str]) -> tuple[str, ...]:
    """Split comma lists, lower-case, drop 'sharp'/'none', check names. -> effects in application order."""
    names: list[str] = []
    for item in effects:
        names += [n.strip().lower() for n in str(item).split(",") if n.strip()]
    unknown = sorted({n for n in names if n not in KNOWN_EFFECTS and n not in SHARP_ALIASES})
    if unknown:
        raise ValueError(f"unknown effect(s) {unknown}; valid effects: {list(KNOWN_EFFECTS)} (or 'sharp' for none)")
    if any(n in SHARP_ALIASES for n in names) and any(n in KNOWN_EFFECTS for n in names):
        raise ValueError(f"'sharp' cannot be combined with other effects, got {names}")
    return tuple(e for e in KNOWN_EFFECTS if e in names)


def config_from_dict(
    values: Mapping[str, Any], base: DegradeConfig | None = None, source: str | Path | None = None
) -> DegradeConfig:
    """Overlay a (nested) mapping on `base` (default config); unknown keys and wrong types are an InputError naming
    `source` and the key, not silently ignored. `effects` may be one comma-separated string."""
    values = dict(values)
    if "effects" in values:
        effects = values["effects"]
        values["effects"] = (effects,) if isinstance(effects, str) else tuple(effects or ())
    return load_dataclass(DegradeConfig, values, source, base if base is not None else DegradeConfig())


def load_preset(path: str | Path) -> DegradeConfig:
    """Read a YAML preset (mapping of DegradeConfig fields, effect sections nested; omitted keys keep defaults)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"degradation preset {path} not found")
    return config_from_dict(read_yaml_mapping(path), source=path)
