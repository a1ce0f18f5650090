"""Per-image degradation profiles and the resolution-loss operator for known mixed-resolution factors.

A :class:`DegradationProfile` says what happened to one training image (from the per-image entries of
``degradation.json`` or the dataparsers' records, see ``gsmsdr_ns.data.degradation``) and therefore which model
parts it needs (:func:`training_profiles` builds one per training image):

=====================  ==================  ===========  ========================================
profile                needs_blur_field    needs_depth  resolution model
=====================  ==================  ===========  ========================================
sharp / noise only     no                  no           no
motion                 yes                 yes          (factor > 1 if also mixres)
defocus                yes                 yes          (factor > 1 if also mixres)
mixres, factor f > 1   no                  no           yes: known down-up operator + residual
mixres, factor unknown yes (learns it)     no           no
=====================  ==================  ===========  ========================================

Depth decisions: defocus blur is a function of depth (circle of confusion ~ |1/d - 1/d_focus|), so depth is
needed. Camera motion blur depends on depth through parallax for the translational part of the shake (pixel
displacement ~ 1/d; the rotational part is depth independent); the paper's Table 8 shows the RGB-D input matters
most for motion, so motion also asks for depth. A resolution loss of known or unknown
factor is the same for every depth, so it does not.

:class:`ResolutionLossModel` applies the degrade tool's mixed-resolution operator
(:func:`gsmsdr_ns.ops.mixres.resolution_loss`: kornia antialiased bilinear downscale to round(H/f) x round(W/f),
bilinear (or bicubic) upscale back, clamp to [0, 1]) and adds a small learned residual
kernel, initialised to the identity, for any mismatch with how a real camera lost its resolution.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Any, List, Mapping, Optional, Sequence, Union

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gsmsdr_ns.data.degradation_schema import ESTIMATED_MODEL
from gsmsdr_ns.data.effects import DEGRADATION_MODES, KNOWN_EFFECTS, DegradationMode
from gsmsdr_ns.ops.mixres import resolution_loss

__all__ = [
    "DegradationProfile",
    "effective_factor",
    "ResolutionLossModel",
    "motion_records",
    "training_profiles",
    "describe_profiles",
]


@dataclass(frozen=True)
class DegradationProfile:
    """What degraded one training image. Default: sharp."""

    motion: bool = False
    """Camera motion blur."""
    defocus: bool = False
    """Defocus blur."""
    mixres_factor: Optional[int] = 1
    """Known resolution-loss factor (1: full resolution, f > 1: shrunk by f and enlarged back); None: the image may
    have lost resolution by an unknown factor (the blur field then learns it)."""
    noise: bool = False
    """Sensor noise (not modelled: the photometric loss averages it out)."""
    mixres_upsample: str = "bilinear"
    """Interpolation that enlarged a mixres image back to full size (``degradation.json``'s "upsample")."""
    exact_pose: bool = False
    """The records give the image's pose as the exact mid-exposure pose of a simulated shake (``gsmsdr-synth`` /
    ``gsmsdr-degrade`` write ``"reference": "mid_exposure"``). False: the pose was estimated from the photo itself
    (structure-from-motion puts it near the centre of the blur), or nothing is known."""

    blur_kind_known: bool = True
    """Whether the kind of blur is known. False for an image nothing is known about and for an estimated record
    that found the image blurred but could not tell motion from defocus (it names both, ``model: estimated``): the
    blur field alone then models the blur, the thin lens only with ``DegradationConfig.thin_lens_for_unknown_kind``."""

    def __post_init__(self) -> None:
        f = self.mixres_factor
        if f is not None and (not isinstance(f, int) or isinstance(f, bool) or f < 1):
            raise ValueError(f"mixres_factor must be None or an integer >= 1, got {f!r}")
        if self.mixres_upsample not in ("bilinear", "bicubic"):
            raise ValueError(f"mixres_upsample must be bilinear or bicubic, got {self.mixres_upsample!r}")

    @property
    def is_sharp(self) -> bool:
        """No blur, no resolution loss and no noise."""
        return not (self.motion or self.defocus or self.noise) and self.mixres_factor == 1

    @property
    def needs_resolution_model(self) -> bool:
        """A known resolution loss (factor > 1): model it with :class:`ResolutionLossModel`."""
        return self.mixres_factor is not None and self.mixres_factor > 1

    @property
    def needs_blur_field(self) -> bool:
        """Motion or defocus blur, or a resolution loss of unknown factor: the per-pixel kernel field is needed."""
        return self.motion or self.defocus or self.mixres_factor is None

    @property
    def defocus_only(self) -> bool:
        """Known to be blurred by defocus alone (no motion, no resolution loss of unknown factor)."""
        return self.defocus and not self.motion and self.mixres_factor is not None

    @property
    def needs_depth(self) -> bool:
        """Depth is an input of the blur field for this image (defocus: required; motion: helps, see module doc)."""
        return self.motion or self.defocus

    # ------------------------------------------------------------------------------------------ constructors

    @classmethod
    def unknown(cls) -> "DegradationProfile":
        """Profile of a training image nothing is known about: any blur, any resolution loss (blur field + depth)."""
        return cls(motion=True, defocus=True, mixres_factor=None, blur_kind_known=False)

    @staticmethod
    def is_known(metadata: Optional[Mapping[str, Any]]) -> bool:
        """Whether a per-image dict says what happened (``degraded`` is True/False, not None or missing)."""
        return metadata is not None and metadata.get("degraded", None) is not None

    @classmethod
    def from_metadata(cls, metadata: Optional[Mapping[str, Any]]) -> "DegradationProfile":
        """Profile from one image's dict: a ``degradation.json`` entry (``{"split", "degraded", "effects"}``) or a
        dataparser record (same keys plus ``"mixres_factor"``).

        Test views and ``degraded: false`` are sharp. Unknown metadata (None, ``degraded`` None or missing, or
        degraded with no effects listed) gives :meth:`unknown`.
        """
        if metadata is None:
            return cls.unknown()
        if metadata.get("split") == "test" or metadata.get("degraded", None) is False:
            return cls()
        effects = metadata.get("effects") or {}
        if not isinstance(effects, Mapping):
            raise ValueError(f"'effects' must be a dict, got {type(effects).__name__}")
        unknown_effects = set(effects) - set(KNOWN_EFFECTS)
        if unknown_effects:
            raise ValueError(f"unknown degradation effect(s) {sorted(unknown_effects)}")
        if metadata.get("degraded", None) is None or not effects:
            return cls.unknown()
        mixres = effects.get("mixres")
        factor = metadata.get("mixres_factor")
        if factor is None:
            factor = int(mixres.get("factor", 1)) if isinstance(mixres, Mapping) else 1
        upsample = mixres.get("upsample", "bilinear") if isinstance(mixres, Mapping) else "bilinear"
        motion = effects.get("motion")
        both_estimated = all(
            isinstance(effects.get(name), Mapping) and effects[name].get("model") == ESTIMATED_MODEL
            for name in ("motion", "defocus")
        )
        return cls(
            motion="motion" in effects,
            defocus="defocus" in effects,
            mixres_factor=int(factor),
            noise="noise" in effects,
            mixres_upsample=upsample,
            exact_pose=isinstance(motion, Mapping) and motion.get("reference") == "mid_exposure",
            blur_kind_known=not both_estimated,
        )

    @property
    def known_defocus(self) -> bool:
        """Defocus is known to be (part of) this image's blur: a record names it, not just an unknown kind of blur."""
        return self.defocus and self.blur_kind_known

    @classmethod
    def from_mode(cls, mode: DegradationMode, metadata: Optional[Mapping[str, Any]] = None) -> "DegradationProfile":
        """Profile of one image under the model's ``degradation_mode``.

        * ``auto``: what the metadata says (:meth:`from_metadata`; unknown images get :meth:`unknown`);
        * ``motion`` / ``defocus``: that blur only (a known mixres factor and noise in the metadata are kept);
        * ``mixres``: resolution loss only, factor from the metadata (None = unknown when it has none);
        * ``sharp``: no degradation (plain splatfacto).

        Test views (``split == "test"``) and images the metadata says are undegraded are sharp in every mode.
        """
        if mode not in DEGRADATION_MODES:
            raise ValueError(f"degradation mode must be one of {DEGRADATION_MODES}, got {mode!r}")
        if mode == "sharp":
            return cls()
        known = cls.is_known(metadata)
        meta = cls.from_metadata(metadata) if known else None
        if metadata is not None and (metadata.get("split") == "test" or metadata.get("degraded", None) is False):
            return cls()
        if mode == "auto":
            return meta if meta is not None else cls.unknown()
        factor = meta.mixres_factor if meta is not None else 1
        noise = meta.noise if meta is not None else False
        upsample = meta.mixres_upsample if meta is not None else "bilinear"
        exact = meta.exact_pose if meta is not None else False
        if mode == "mixres":
            factor = meta.mixres_factor if meta is not None else None
            return cls(mixres_factor=factor, noise=noise, mixres_upsample=upsample)
        return cls(motion=mode == "motion", defocus=mode == "defocus", mixres_factor=factor, noise=noise,
                   mixres_upsample=upsample, exact_pose=exact)  # fmt: skip


# ------------------------------------------------------------------------------------------------ resolution loss


def effective_factor(factor: float, downscale: float = 1.0) -> float:
    """Resolution-loss factor seen by a render at 1/``downscale`` of full resolution: ``factor / downscale``.

    An image shrunk by 4 and rendered (with its ground truth resized) at 1/2 resolution has lost a factor 2
    relative to that render; at 1/4 or coarser nothing is left to model (<= 1: identity). Approximate for
    non-power-of-two ratios (the ground truth is resized from the degraded full image, not re-degraded).
    """
    if factor < 1 or downscale <= 0:
        raise ValueError(f"factor must be >= 1 and downscale > 0, got {factor}, {downscale}")
    return factor / downscale


class ResolutionLossModel(nn.Module):
    """Known down-up operator plus a small learned residual kernel (identity at initialisation).

    ``out = R_v * resolution_loss(render, f_b)`` where ``*`` is a ``kernel_size`` x ``kernel_size`` convolution
    (replicate border) with ``R_v = delta + (W_v - mean(W_v))``: ``W_v`` is a learnable per-view table (or one
    global kernel with ``num_views=None``) initialised to zeros, so ``R_v`` always sums to 1 and starts as the exact
    identity. Images with an effective factor <= 1 pass through the residual only.

    Args:
        num_views: training views (one residual kernel each); None: one global kernel.
        kernel_size: odd residual kernel size (3 or 5).
        upsample: the degrade tool's upsampling ("bilinear" default, or "bicubic").
    ``forward(render [B,C,H,W], factors [B] (float; 1 = untouched), view_ids [B] or None) -> [B,C,H,W]``.
    """

    def __init__(self, num_views: Optional[int] = None, kernel_size: int = 3, upsample: str = "bilinear") -> None:
        super().__init__()
        if kernel_size < 1 or kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be odd and >= 1, got {kernel_size}")
        if upsample not in ("bilinear", "bicubic"):
            raise ValueError(f"upsample must be bilinear or bicubic, got {upsample!r}")
        self.kernel_size, self.upsample, self.num_views = kernel_size, upsample, num_views
        self.residual = nn.Parameter(torch.zeros(num_views or 1, kernel_size * kernel_size))

    def kernels(self, view_ids: Optional[Tensor], batch: int) -> Tensor:
        """Residual kernels ``delta + W - mean(W)``: [B, k*k], each summing to 1."""
        w: Tensor
        if self.num_views is None:
            w = self.residual
        else:
            assert view_ids is not None  # per-view residuals: forward checks that view_ids are given
            w = self.residual[view_ids.long()]
        w = w - w.mean(dim=1, keepdim=True)
        delta = torch.zeros_like(w)
        delta[:, (self.kernel_size * self.kernel_size) // 2] = 1.0
        return (delta + w).expand(batch, -1)

    def forward(
        self,
        render: Tensor,  # [B, C, H, W]
        factors: Union[Tensor, Sequence[float]],  # [B]
        view_ids: Optional[Tensor] = None,  # [B]
    ) -> Tensor:
        if render.dim() != 4:
            raise ValueError(f"render must be [B, C, H, W], got {list(render.shape)}")
        B, C, H, W = render.shape
        factors = [float(f) for f in (factors.tolist() if isinstance(factors, Tensor) else factors)]
        if len(factors) != B:
            raise ValueError(f"need one factor per image ({B}), got {len(factors)}")
        if self.num_views is not None and (view_ids is None or view_ids.shape != (B,)):
            raise ValueError(f"per-view residuals need view_ids of shape [{B}]")
        # one resize per distinct factor; images are gathered and put back by slicing (no index tensors: nothing
        # is copied between host and device per call)
        by_factor = {}
        for f in sorted(set(factors)):
            group = [render[i : i + 1] for i, g in enumerate(factors) if g == f]
            by_factor[f] = resolution_loss(torch.cat(group) if len(group) > 1 else group[0], f, self.upsample)
        if len(by_factor) == 1:
            low = by_factor[factors[0]]
        else:
            rank = [factors[:i].count(f) for i, f in enumerate(factors)]  # position of image i in its group
            low = torch.cat([by_factor[f][r : r + 1] for f, r in zip(factors, rank)])
        k = self.kernel_size
        kern = self.kernels(view_ids, B).to(render.dtype)  # [B, k*k]
        padded = F.pad(low.reshape(1, B * C, H, W), [k // 2] * 4, mode="replicate")
        weight = kern.repeat_interleave(C, dim=0).reshape(B * C, 1, k, k)
        return F.conv2d(padded, weight, groups=B * C).reshape(B, C, H, W)


# ------------------------------------------------------------------------------------------------ per training set


def training_profiles(
    mode: DegradationMode, metadata: Optional[Mapping[str, Any]], num_train: int
) -> List[DegradationProfile]:
    """One profile per training image.

    Args:
        mode: the model's ``degradation`` setting (``DegradationProfile.from_mode``): ``auto`` reads the records,
            an image without a usable record is unknown (any blur, any resolution loss); the others force that
            degradation on every training image the records do not call undegraded.
        metadata: the training dataset's metadata (``DataparserOutputs.metadata``); its ``"degradations"`` list,
            when present, must hold ``num_train`` records in the training split's order.
        num_train: number of training images.

    Raises:
        ValueError: the records do not match the training images.
    """
    records: Optional[Sequence[Optional[Mapping[str, Any]]]] = None
    if metadata is not None:
        records = metadata.get("degradations")
    if records is None:
        records = [None] * num_train
    if len(records) != num_train:
        raise ValueError(
            f"gsmsdr: the dataparser describes the degradation of {len(records)} training images, but there are "
            f"{num_train}: metadata['degradations'] must hold one record per training image, in the split's order."
        )
    return [DegradationProfile.from_mode(mode, record) for record in records]


def motion_records(
    records: Optional[Sequence[Optional[Mapping[str, Any]]]], num_train: int
) -> List[Optional[Mapping[str, Any]]]:
    """Each training image's ``motion`` effect record (None where it has none), from the dataparser's
    ``metadata["degradations"]`` (None: no records, all None)."""
    if records is None:
        return [None] * num_train
    found: List[Optional[Mapping[str, Any]]] = []
    for record in records:
        effects = (record or {}).get("effects") or {}
        motion = effects.get("motion") if isinstance(effects, Mapping) else None
        found.append(motion if isinstance(motion, Mapping) else None)
    return found


def _profile_kind(profile: DegradationProfile) -> str:
    if profile.is_sharp:
        return "sharp"
    if profile == DegradationProfile.unknown():
        return "unknown"
    if profile.blur_kind_known:
        parts = [name for name in ("motion", "defocus") if getattr(profile, name)]
    else:
        parts = ["blur of unknown kind"]
    if profile.mixres_factor is None:
        parts.append("mixres x?")
    elif profile.mixres_factor > 1:
        parts.append(f"mixres x{profile.mixres_factor}")
    if profile.noise:
        parts.append("noise")
    return "+".join(parts)


def describe_profiles(profiles: Sequence[DegradationProfile]) -> str:
    """Counts per kind, most common first, e.g. ``"6 motion, 2 sharp"``."""
    counts = Counter(_profile_kind(p) for p in profiles)
    return ", ".join(f"{n} {kind}" for kind, n in counts.most_common())
