"""What a run record's numbers depend on: :func:`fingerprint` (a record whose fingerprint differs is rerun) and
:func:`training_identity` (runs with equal identities train the same model, so one trains and the others copy its
record)."""

from __future__ import annotations

import copy
import hashlib
import json
import re
from pathlib import Path
from typing import Any, Dict

from gsmsdr_ns.bench.methods import METHODS, MethodSpec
from gsmsdr_ns.bench.suite_config import RunKey, Suite, schedule_settings

RECORD_VERSION = 1
"""Bumped when a record's meaning changes: older records are then rerun instead of reused."""


ADDED_AT_NEUTRAL: Dict[str, Any] = {
    "feature_grid_cells": 0,
    "shake_translation": False,
    "deconvolved_loss_on_shake": False,
    "shake_translation_start": "warmup",
    "shake_parallax": False,
    "shake_occlusion": False,
}
"""Config fields added after records were made, each with the value that trains exactly as before: left out of
:func:`preset_fingerprint` at that value, so adding them does not rerun every record (another value changes it)."""


NETWORK_ONLY = frozenset({"feature_grid_cells"})
"""Fields of :data:`ADDED_AT_NEUTRAL` read only by the field's feature network: left out of the fingerprint of a
mode ``view`` field (no network) at any value."""


SHAKE_ONLY = frozenset({"deconvolved_loss_on_shake", "shake_translation_start", "shake_parallax", "shake_occlusion"})
"""Fields of :data:`ADDED_AT_NEUTRAL` read only with camera shake paths: left out of the fingerprint of a model
without them at any value."""


def preset_fingerprint(method: MethodSpec) -> str:
    """The resolved model and optimizer settings of ``method`` (its preset with its changes applied), so a record
    made before a preset default changed is rerun. Paths are left out, and so are the blur field's and degradation
    models' settings for methods that never build them (plain, sharp)."""
    config = method.make_config(Path("data"), Path("outputs"))
    model, optimizers = config.pipeline.model, dict(config.optimizers)
    if not method.has_blur_field:
        model = copy.copy(model)
        model.blur_field = model.degradation_model = None
        optimizers = {k: v for k, v in optimizers.items() if not k.startswith("blur_")}
    text = repr(model) + repr(sorted(optimizers.items()))
    without_network = model.blur_field is not None and model.blur_field.mode == "view"
    without_shake = model.degradation_model is None or not model.degradation_model.camera_shake
    for name, value in ADDED_AT_NEUTRAL.items():
        if (without_network and name in NETWORK_ONLY) or (without_shake and name in SHAKE_ONLY):
            # any value trains the same: drop it whatever it is
            text = re.sub(rf"\b{name}=[^,]*, ", "", text)
        text = text.replace(f"{name}={value!r}, ", "")
    return text


def fingerprint(suite: Suite, key: RunKey, estimate: bool = True) -> str:
    """What a record's numbers depend on; a record whose fingerprint differs is rerun. ``estimate=False`` leaves
    out the estimate's fingerprint (the part :func:`gsmsdr_ns.bench.ledger.rekey_unchanged_estimates` may forgive)."""
    method = METHODS[key.method]
    payload = {
        "version": RECORD_VERSION,
        "scene": suite.scene(key.scene).fingerprint(),
        "method": {"base": method.base, "blur_field": method.overrides, "sharp_data": method.sharp_data},
        **_training_settings(suite, key, estimate),
    }
    if suite.align_poses:  # only then, so records of suites without alignment keep their fingerprint
        payload["align_poses"] = True
    if method.degraded_poses:  # only then: the other methods' records keep their fingerprint
        payload["method"]["degraded_poses"] = True
    return digest(payload)


def training_identity(suite: Suite, key: RunKey) -> str:
    """What run ``key`` trains, whatever its scene and method are called: the images it reads
    (:meth:`SceneEntry.data_key`), the resolved model and optimizer settings, steps, seed, schedule and evaluation.
    Runs of a suite with equal identities would train the same model on the same data: one trains, the others copy
    its record (e.g. the sharp upper bound of every scene degraded from the same sharp photos, or plain Gaussians
    on a scene whose records say every image is sharp next to that upper bound)."""
    payload = {
        "version": RECORD_VERSION,
        "data": suite.scene(key.scene).data_key(METHODS[key.method]),
        **_training_settings(suite, key),
        "align_poses": suite.align_poses,
    }
    return digest(payload)


def _training_settings(suite: Suite, key: RunKey, estimate: bool = True) -> Dict[str, Any]:
    """The settings of run ``key`` both keys above share: resolved preset, steps, seed, schedule, evaluation steps,
    LPIPS, and (``estimate``) the estimate's fingerprint when the run trains on estimated records."""
    method = METHODS[key.method]
    settings = {
        "preset": preset_fingerprint(method),
        "steps": key.steps,
        "seed": key.seed,
        "schedule": schedule_settings(suite.schedule_for(key.steps)),
        "eval_steps": suite.eval_steps(key.steps),
        "lpips": suite.lpips,
    }
    if estimate and suite.scene(key.scene).trains_on_estimated_records(method):
        from gsmsdr_ns.estimate.records import estimate_fingerprint

        settings["estimate"] = estimate_fingerprint()  # a real-photo scene trains on the records estimated for it
    return settings


def digest(payload: Dict[str, Any]) -> str:
    """A short hex digest of ``payload`` as sorted JSON (values JSON cannot hold as their ``str``)."""
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]
