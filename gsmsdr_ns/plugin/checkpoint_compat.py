"""Whether a checkpoint's tensors fit the model this run's config builds, and what to say when they do not.

A checkpoint of another preset (``gsmsdr`` / ``gsmsdr-lite``), of another scene, or with or without an optional part
(thin lens, camera shake paths) raises :class:`CheckpointMismatchError` naming the widths of both and the method or
flag to load it with, instead of torch's list of mismatched tensors.

No state-dict key is written here. :func:`checkpoint_layout` finds where things sit from the model itself (its SH
coefficients) and from :func:`reference_degradation`, the degradation models its blur-field config builds with every
optional part on; :func:`width_locations` finds which tensors each width option sets by building that reference once
more with the option changed. Keys are matched by suffix, so the degradation models' place in the model does not
matter.

The presets a message can name are registered by the module that defines them (:func:`register_presets`): it imports
the model, whose checkpoint loading uses this module, so this module cannot import it.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple

import torch
from torch import nn

from gsmsdr_ns.blur.defocus import ThinLensDefocus
from gsmsdr_ns.blur.degradation_config import DegradationConfig
from gsmsdr_ns.blur.degradation_model import DegradationModel
from gsmsdr_ns.blur.field import BlurFieldConfig
from gsmsdr_ns.blur.profile import DegradationProfile
from gsmsdr_ns.blur.shake import CameraShake
from gsmsdr_ns.io.errors import InputError

State = Mapping[str, torch.Tensor]

WIDTH_OPTIONS = {"n": "feature_dim", "view": "view_dim", "mid": "mid_channels"}
"""The blur-field widths the presets differ in, by the name messages give them, and the config option setting each."""


class CheckpointMismatchError(InputError):
    """A checkpoint whose tensors do not fit the model this config builds (another preset or scene)."""

    def __init__(self, what: str, method: Optional[str] = None, path: Optional[Path] = None, scene: bool = False):
        self.what, self.method, self.path, self.scene = what, method, path, scene
        name = f"checkpoint '{path}'" if path is not None else "the checkpoint"
        load_with = f"`ns-train {method}`" if method else "the method and flags it was trained with"
        where = " on the scene it was trained on" if scene else ""
        super().__init__(f"gsmsdr: {name} {what}; load it with {load_with}{where}.")

    def for_file(self, path: Path, method: Optional[str] = None) -> "CheckpointMismatchError":
        """The same error naming the checkpoint file, and the method its run used when known (its config.yml)."""
        return CheckpointMismatchError(self.what, method or self.method, path, self.scene)


# -- where things sit in a state dict ----------------------------------------------------------------------------


class Location(NamedTuple):
    """A tensor holding a width: its key (a suffix of the full key) and the dimension whose size is the width."""

    key: str
    dim: int


class CheckpointLayout(NamedTuple):
    """Where a model's state dict keeps what the diagnosis reads (see :func:`checkpoint_layout`)."""

    sh_key: str
    """Full key of the Gaussians' SH coefficients above degree 0, ``[count, (degree + 1)^2 - 1, 3]``."""
    gaussians_prefix: str
    """Key prefix of the Gaussian parameters, which loading resizes to the checkpoint's count."""
    thin_lens_key: str
    """Key suffix of the thin lens's first tensor."""
    camera_shake_key: str
    """Key suffix of the camera shake paths' first tensor."""
    shake_translation_key: str
    """Key suffix of the camera shake paths' translation coefficients."""
    blur_field: BlurFieldConfig
    """The model's blur-field config, from which :func:`width_locations` finds the widths' tensors."""


def reference_degradation(blur_field: BlurFieldConfig) -> DegradationModel:
    """Degradation models of one motion-blurred and one defocused view with everything ``blur_field`` can build:
    thin lens, camera shake paths and every kernel scale. Its state dict has the keys (relative to the degradation
    models) of any checkpoint trained with this config."""
    everything = DegradationConfig(thin_lens=True, camera_shake=True, shake_translation=True)
    profiles = [DegradationProfile(motion=True), DegradationProfile(defocus=True)]
    return DegradationModel(profiles, blur_field, everything, num_downscales=len(blur_field.kernel_sizes))


def _first_key_of(module: nn.Module, part: type) -> str:
    """The state-dict key (relative to ``module``) of the first tensor of ``module``'s first submodule of type
    ``part``."""
    for name, sub in module.named_modules():
        if isinstance(sub, part):
            return f"{name}.{next(iter(sub.state_dict()))}"
    raise ValueError(f"{type(module).__name__} builds no {part.__name__}")


def _translation_coefficients(reference: DegradationModel) -> torch.Tensor:
    shake = reference.camera_shake
    assert shake is not None and shake.translation_coefficients is not None  # the reference builds every part
    return shake.translation_coefficients


def _key_of(model: nn.Module, tensor: torch.Tensor) -> str:
    """The key of ``tensor`` (a parameter or buffer of ``model``) in ``model``'s state dict."""
    for key, value in model.state_dict(keep_vars=True).items():
        if value is tensor:
            return key
    raise ValueError("the tensor is not in the model's state dict")


def checkpoint_layout(model: nn.Module, blur_field: BlurFieldConfig) -> CheckpointLayout:
    """Where ``model`` (a splatfacto model, whose ``features_rest`` are its SH coefficients) and the degradation
    models ``blur_field`` builds keep what the diagnosis reads."""
    sh_key = _key_of(model, model.features_rest)
    reference = reference_degradation(blur_field)
    return CheckpointLayout(
        sh_key=sh_key,
        gaussians_prefix=sh_key.rsplit(".", 1)[0] + ".",
        thin_lens_key=_first_key_of(reference, ThinLensDefocus),
        camera_shake_key=_first_key_of(reference, CameraShake),
        shake_translation_key=_key_of(reference, _translation_coefficients(reference)),
        blur_field=blur_field,
    )


def _shapes(module: nn.Module) -> Dict[str, Tuple[int, ...]]:
    return {key: tuple(value.shape) for key, value in module.state_dict().items()}


def _following(
    base: Mapping[str, Tuple[int, ...]], changed: Mapping[str, Tuple[int, ...]], before: int, after: int
) -> List[Location]:
    """The tensors (in state-dict order) with a dimension of size ``before`` in ``base`` that is ``after`` in
    ``changed``: those an option set from ``before`` to ``after`` sizes one for one."""
    found = []
    for key, shape in base.items():
        other = changed.get(key)
        if other is not None and len(other) == len(shape):
            found += [Location(key, d) for d in range(len(shape)) if shape[d] == before and other[d] == after]
    return found


def width_locations(blur_field: BlurFieldConfig) -> Dict[str, List[Location]]:
    """For each width of :data:`WIDTH_OPTIONS`, the tensors whose size is that width, in state-dict order: found by
    building :func:`reference_degradation` again with the option one larger. A width no tensor follows (no view
    embedding, no feature network) has none."""
    base = _shapes(reference_degradation(blur_field))
    locations = {}
    for name, option in WIDTH_OPTIONS.items():
        width = getattr(blur_field.dims, option)
        wider = _shapes(reference_degradation(dataclasses.replace(blur_field, **{option: width + 1})))
        locations[name] = _following(base, wider, width, width + 1)
    return locations


def kernel_locations(blur_field: BlurFieldConfig) -> List[Location]:
    """The per-scale tensors whose size is a scale's kernel size squared, as keys with ``{}`` for the scale number
    (so a checkpoint's other scales are found too): found by building :func:`reference_degradation` again with every
    kernel 2 smaller."""
    sizes = tuple(blur_field.kernel_sizes)
    smaller = tuple(k - 2 if k >= 3 else k for k in sizes)  # still odd and non-decreasing
    reference = reference_degradation(blur_field)
    base = _shapes(reference)
    changed = _shapes(reference_degradation(dataclasses.replace(blur_field, kernel_sizes=smaller)))
    templates: Optional[List[Location]] = None
    for scale in reference.blur_field.scales:
        size, less = sizes[len(sizes) - scale], smaller[len(sizes) - scale]  # scale 1 is the finest, listed last
        if size == less:
            continue
        found = [Location(_scale_template(key, scale), dim) for key, dim in _following(base, changed, size**2, less**2)]
        templates = found if templates is None else [t for t in templates if t in found]
    return templates or []


def _scale_template(key: str, scale: int) -> str:
    return ".".join("{}" if part == str(scale) else part for part in key.split("."))


# -- reading widths ----------------------------------------------------------------------------------------------


def _find(state: State, suffix: str) -> Optional[torch.Tensor]:
    for key, value in state.items():
        if (key == suffix or key.endswith("." + suffix)) and isinstance(value, torch.Tensor):
            return value
    return None


def _size_at(state: State, locations: Sequence[Location]) -> Optional[int]:
    """The size at the first of ``locations`` that ``state`` has."""
    for key, dim in locations:
        value = _find(state, key)
        if value is not None and value.dim() > dim:
            return int(value.shape[dim])
    return None


def _kernel_sizes(state: State, templates: Sequence[Location]) -> Optional[str]:
    """``state``'s kernel sizes coarse to fine (``5/9/17``) from the first template it has tensors of."""
    for template, dim in templates:
        before, after = template.split("{}", 1)
        pattern = re.compile(r"(?:^|\.)" + re.escape(before) + r"(\d+)" + re.escape(after) + "$")
        sizes = {int(m.group(1)): v for k, v in state.items() if (m := pattern.search(k)) and v.dim() > dim}
        if sizes:  # scale 1 is the finest; listed coarse to fine like BlurFieldConfig.kernel_sizes
            return "/".join(str(round(math.sqrt(sizes[s].shape[dim]))) for s in sorted(sizes, reverse=True))
    return None


def sh_degree(state: State, layout: CheckpointLayout) -> Optional[int]:
    """The SH degree of the Gaussians in ``state``, from the count of their SH coefficients."""
    value = state.get(layout.sh_key)
    if not isinstance(value, torch.Tensor) or value.dim() < 2:
        return None
    return round(math.sqrt(value.shape[1] + 1)) - 1


def model_widths(
    state: State, layout: CheckpointLayout, widths: Mapping[str, Sequence[Location]], kernels: Sequence[Location]
) -> Dict[str, Any]:
    """The blur-field widths (``n``, ``view``, ``mid``, ``kernels``) and ``sh_degree`` a state dict was built with;
    those it has no tensor of are left out."""
    found: Dict[str, Any] = {name: _size_at(state, locations) for name, locations in widths.items()}
    found["kernels"] = _kernel_sizes(state, kernels)
    found["sh_degree"] = sh_degree(state, layout)
    return {name: value for name, value in found.items() if value is not None}


def describe_widths(widths: Mapping[str, Any]) -> str:
    """:func:`model_widths` as text (``blur field n=32, view 32, mid 64, kernels 5/9/17; SH degree 3``): what differs
    between the ``gsmsdr`` and ``gsmsdr-lite`` presets."""
    field = [f"{k}={v}" if k == "n" else f"{k} {v}" for k, v in widths.items() if k != "sh_degree"]
    parts = ["blur field " + ", ".join(field)] if field else []
    if "sh_degree" in widths:
        parts.append(f"SH degree {widths['sh_degree']}")
    return "; ".join(parts) or "no blur field"


# -- the presets a message can name -------------------------------------------------------------------------------

_PRESETS: List[Callable[[], Any]] = []


def register_presets(*make_configs: Callable[[], Any]) -> None:
    """Let mismatch messages name these presets: functions returning a fresh nerfstudio trainer config of a gsmsdr
    method. Called by the module defining them; registering one again changes nothing."""
    _PRESETS.extend(make for make in make_configs if make not in _PRESETS)


def preset_of(widths: Mapping[str, Any], make_configs: Sequence[Callable[[], Any]]) -> Optional[str]:
    """The method name of the first preset (of ``make_configs``) with the SH degree and blur-field width ``n`` of
    ``widths`` (:func:`model_widths`; no blur field fits any width), or None."""
    for make in make_configs:
        config = make()
        model = config.pipeline.model
        if widths.get("sh_degree") == model.sh_degree and widths.get("n") in (None, model.blur_field.dims.feature_dim):
            return config.method_name
    return None


# -- the checks ---------------------------------------------------------------------------------------------------


def _check_optional_part(
    model_state: State, checkpoint_state: State, key: str, only_in_checkpoint: str, only_in_model: str
) -> None:
    """Raise :class:`CheckpointMismatchError` with ``only_in_checkpoint`` when a tensor ``key`` (a key suffix) is in
    the checkpoint and not in this model, with ``only_in_model`` the other way round: an optional module one config
    builds and the other does not."""
    theirs, ours = _find(checkpoint_state, key) is not None, _find(model_state, key) is not None
    if theirs and not ours:
        raise CheckpointMismatchError(only_in_checkpoint)
    if ours and not theirs:
        raise CheckpointMismatchError(only_in_model)


def check_thin_lens(layout: CheckpointLayout, model_state: State, checkpoint_state: State) -> None:
    """Raise :class:`CheckpointMismatchError` naming the flag to load with when the checkpoint has a thin lens this
    model does not build, or the other way round."""
    _check_optional_part(
        model_state,
        checkpoint_state,
        layout.thin_lens_key,
        "has a thin lens that this run's config does not build: it was trained with the lens on images blurred by an "
        "unknown kind of blur, which is now optional (add "
        "--pipeline.model.degradation-model.thin-lens-for-unknown-kind True)",
        "has no thin lens, but this run's config builds one (add --pipeline.model.degradation-model.thin-lens False, "
        "or --pipeline.model.degradation-model.thin-lens-for-unknown-kind False if it was set)",
    )


def check_camera_shake(layout: CheckpointLayout, model_state: State, checkpoint_state: State) -> None:
    """Raise :class:`CheckpointMismatchError` naming the flag to load with when the checkpoint has learnt camera
    shake paths (or their translations) this model does not build, or the other way round."""
    _check_optional_part(
        model_state,
        checkpoint_state,
        layout.camera_shake_key,
        "has camera shake paths that this run's config does not build (add "
        "--pipeline.model.degradation-model.camera-shake True)",
        "has no camera shake paths, but this run's config builds them (add "
        "--pipeline.model.degradation-model.camera-shake False)",
    )
    _check_optional_part(
        model_state,
        checkpoint_state,
        layout.shake_translation_key,
        "has camera shake paths that move the camera, which this run's config does not build (add "
        "--pipeline.model.degradation-model.shake-translation True)",
        "has camera shake paths that only turn the camera, but this run's config also moves it (add "
        "--pipeline.model.degradation-model.shake-translation False)",
    )


def check_state_dict_shapes(layout: CheckpointLayout, model_state: State, checkpoint_state: State) -> None:
    """Raise :class:`CheckpointMismatchError` when a tensor of ``checkpoint_state`` has another shape than the
    model's (the Gaussian parameters, which loading resizes to the checkpoint's count: their other dimensions).

    The message names the widths of both (:func:`describe_widths`) and the registered preset the checkpoint matches,
    instead of torch's list of every mismatched tensor.
    """
    mismatched = []
    for key, value in checkpoint_state.items():
        own = model_state.get(key)
        if not isinstance(own, torch.Tensor) or not isinstance(value, torch.Tensor):
            continue
        theirs, ours = tuple(value.shape), tuple(own.shape)
        if key.startswith(layout.gaussians_prefix):
            theirs, ours = theirs[1:], ours[1:]
        if theirs != ours:
            mismatched.append((key, tuple(value.shape), tuple(own.shape)))
    if not mismatched:
        return
    widths, kernels = width_locations(layout.blur_field), kernel_locations(layout.blur_field)
    trained = model_widths(checkpoint_state, layout, widths, kernels)
    built = model_widths(model_state, layout, widths, kernels)
    method = preset_of(trained, _PRESETS)
    if describe_widths(trained) != describe_widths(built):
        raise CheckpointMismatchError(f"was trained with other widths ({describe_widths(trained)}) than this run's "
                                      f"config builds ({describe_widths(built)})", method)  # fmt: skip
    key, theirs, ours = mismatched[0]
    raise CheckpointMismatchError(
        f"does not fit this model: its '{key}' has shape {list(theirs)}, this model's {list(ours)} "
        f"({len(mismatched)} tensor(s) differ), so it was trained on another scene (another number of training "
        "views) or with other settings", method, scene=True,
    )  # fmt: skip
