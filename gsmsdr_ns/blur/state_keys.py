"""Checkpoint keys of the degradation model that moved or appeared over time (pure functions on state dicts, no
nerfstudio import): :func:`remap_legacy_keys` moves an older checkpoint's keys to where
:class:`~gsmsdr_ns.blur.degradation_model.DegradationModel` keeps them, :func:`with_fallback_state` reconciles the
fallback gate's keys between a checkpoint and the model it loads into."""

from __future__ import annotations

from collections import OrderedDict
from typing import Any, Mapping

__all__ = ["LEGACY_KEY_PREFIXES", "LEGACY_LENS_PREFIX", "remap_legacy_keys", "with_fallback_state"]

LEGACY_KEY_PREFIXES = ("blur_field.", "resolution_model.", "train_camera_centres")
"""State-dict keys the degradation modules had when they were attributes of the nerfstudio model itself."""
LEGACY_LENS_PREFIX = "blur_field.thin_lens."
"""Where the thin lens's keys were while it was a child of the blur field (now ``thin_lens.``)."""


def remap_legacy_keys(state_dict: Mapping[str, Any], prefix: str) -> Mapping[str, Any]:
    """An older checkpoint with its degradation keys where ``DegradationModel`` keeps them (``prefix``, e.g.
    ``"degradation."``): keys written before :class:`DegradationModel` existed (``blur_field.*``,
    ``resolution_model.*``, ``train_camera_centres`` one level up) move under ``prefix``, and the thin lens's keys
    under the field (``<prefix>blur_field.thin_lens.*``) become ``<prefix>thin_lens.*``. ``state_dict`` itself when
    it has neither. The new dict keeps torch's ``_metadata`` (module versions), remapped."""
    legacy = tuple(p.rstrip(".") for p in LEGACY_KEY_PREFIXES)
    old_lens = prefix + LEGACY_LENS_PREFIX.rstrip(".")
    if not any(key.startswith(legacy) or key.startswith(old_lens) for key in state_dict):
        return state_dict

    def moved(key: str) -> str:
        key = prefix + key if key.startswith(legacy) else key
        return prefix + "thin_lens" + key[len(old_lens) :] if key.startswith(old_lens) else key

    out: Any = OrderedDict((moved(key), value) for key, value in state_dict.items())
    metadata = getattr(state_dict, "_metadata", None)
    if metadata is not None:
        out._metadata = OrderedDict((moved(key), value) for key, value in metadata.items())
    return out


def with_fallback_state(state_dict: Mapping[str, Any], own: Mapping[str, Any], prefix: str) -> Mapping[str, Any]:
    """A checkpoint's ``state_dict`` with the fallback gate's running errors (keys under ``prefix``) as this model
    has them: the model's own (unmeasured) values where the checkpoint has none, none where the model has no
    gate. ``state_dict`` itself when both agree; torch's ``_metadata`` is kept."""
    theirs = {key for key in state_dict if key.startswith(prefix)}
    ours = {key for key in own if key.startswith(prefix)}
    if theirs == ours:
        return state_dict
    out: Any = OrderedDict((key, value) for key, value in state_dict.items() if key in ours or key not in theirs)
    for key in ours - theirs:
        out[key] = own[key]
    metadata = getattr(state_dict, "_metadata", None)
    if metadata is not None:
        out._metadata = metadata
    return out
