"""The schema of a version-1 ``degradation.json`` entry and document: the type and range of every field.

Fields are those ``gsmsdr-degrade`` (``gsmsdr_ns.degrade``) and the estimate (``gsmsdr_ns.estimate.records``)
write. Every field is optional (hand-written files may hold only ``degraded`` and the effect names); a field that
is present must have its type and range. Effect names must be known. Fields the schema does not know (notes,
extra parameters of a newer generator) are kept as written and not checked. A violation is an
:class:`~gsmsdr_ns.io.errors.InputError` naming the file, the image and the field, and saying what is allowed.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Tuple

from gsmsdr_ns.data.effects import KNOWN_EFFECTS
from gsmsdr_ns.io.errors import InputError

ESTIMATED_MODEL = "estimated"
"""``model`` of an effect the estimate wrote (no parameters are known)."""


@dataclass(frozen=True)
class Field:
    """One field's allowed values."""

    kind: str
    """"number", "int", "bool", "str", "list", "dict" or "size" (a [width, height] pair of integers >= 1)."""
    minimum: Optional[float] = None
    """Smallest allowed value (numbers and integers)."""
    maximum: Optional[float] = None
    """Largest allowed value (numbers and integers)."""
    choices: Tuple[Any, ...] = ()
    """Allowed values, when only a few are."""
    nullable: bool = False
    """Whether JSON null is allowed."""

    def allowed(self) -> str:
        """What the field may hold, as a phrase for messages."""
        if self.choices:
            text = "one of " + ", ".join(json.dumps(c) for c in self.choices)
        elif self.kind in ("number", "int"):
            text = "a finite number" if self.kind == "number" else "an integer"
            bounds = []
            if self.minimum is not None:
                bounds.append(f">= {self.minimum:g}")
            if self.maximum is not None:
                bounds.append(f"<= {self.maximum:g}")
            if bounds:
                text += " " + " and ".join(bounds)
        else:
            text = {
                "bool": "true or false (a JSON boolean, not a string)",
                "str": "a string",
                "list": "a list",
                "dict": "an object",
                "size": "[width, height], two integers >= 1",
            }[self.kind]
        return text + (" or null" if self.nullable else "")

    def accepts(self, value: Any) -> bool:
        if value is None:
            return self.nullable
        if self.choices:
            return isinstance(value, (str, int)) and not isinstance(value, bool) and value in self.choices
        if self.kind == "bool":
            return isinstance(value, bool)
        if self.kind in ("number", "int"):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                return False
            if self.kind == "int" and not isinstance(value, int):
                return False
            if not math.isfinite(value):
                return False
            return (self.minimum is None or value >= self.minimum) and (self.maximum is None or value <= self.maximum)
        if self.kind == "size":
            return (
                isinstance(value, list)
                and len(value) == 2
                and all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in value)
            )
        return isinstance(value, {"str": str, "list": list, "dict": dict}[self.kind])


NON_NEGATIVE = Field("number", minimum=0)
POSITIVE_INT = Field("int", minimum=1)
BOOL = Field("bool")
TEXT = Field("str")
LIST = Field("list")

EFFECT_FIELDS: Dict[str, Dict[str, Field]] = {
    "motion": {
        "model": Field("str", choices=("trajectory", "rotational_shake", "kernel", ESTIMATED_MODEL)),
        "blur_px": NON_NEGATIVE,
        "max_displacement_px": NON_NEGATIVE,
        "border_reach_px": NON_NEGATIVE,
        "samples": POSITIVE_INT,
        "kernel_size": POSITIVE_INT,
        "keyframes": POSITIVE_INT,
        "render_supersample": POSITIVE_INT,
        "linear_light": BOOL,
        "reference": TEXT,
        "pose": TEXT,
        "trajectory_px": LIST,
        "times": LIST,
        "rotvecs": LIST,
    },
    "defocus": {
        "model": Field("str", choices=("thin_lens", "disk", ESTIMATED_MODEL)),
        "radius_px": NON_NEGATIVE,
        "border_reach_px": NON_NEGATIVE,
        "max_coc_px": NON_NEGATIVE,
        "focus_distance": Field("number", minimum=0),
        "focus_quantile": Field("number", minimum=0, maximum=1),
        "aperture": NON_NEGATIVE,
        "focal_px": Field("number", minimum=0),
        "radius_step_px": NON_NEGATIVE,
        "radius_levels": Field("int", minimum=0),
        "linear_light": BOOL,
    },
    "mixres": {
        "model": Field("str", choices=(ESTIMATED_MODEL,)),
        "factor": POSITIVE_INT,
        "size": Field("size"),
        "downsample": TEXT,
        "upsample": Field("str", choices=("bilinear", "bicubic")),
    },
    "noise": {
        "model": Field("str", choices=("poisson_gaussian", "gaussian", ESTIMATED_MODEL)),
        "sigma": NON_NEGATIVE,
        "gain": NON_NEGATIVE,
        "clipped": BOOL,
        "seed": Field("int", minimum=0),
    },
}
"""Fields of each effect's record (``entry["effects"][<effect>]``)."""

ENTRY_FIELDS: Dict[str, Field] = {
    "split": Field("str", choices=("train", "test")),
    "degraded": BOOL,
    "effects": Field("dict"),
    "source": TEXT,
    "estimate": Field("dict"),
}
"""Fields of an image's entry (``images[<name>]``)."""

DOCUMENT_FIELDS: Dict[str, Field] = {
    "hold": Field("int", minimum=1, nullable=True),
    "seed": Field("int", nullable=True),
    "effects": LIST,
    "preset": Field("str", nullable=True),
    "generator": TEXT,
    "source": TEXT,
    "assignment": TEXT,
    "config": Field("dict"),
    "estimate": Field("dict"),
    "border_crop_px": Field("int", minimum=0),
}
"""Top-level fields other than ``version`` and ``images`` (checked by the reader itself)."""


def _check(path: Path, where: str, name: str, value: Any, spec: Field, fix: str) -> None:
    if not spec.accepts(value):
        raise InputError(
            f"gsmsdr: '{path}': {where}, field \"{name}\" is {_show(value)}; it must be {spec.allowed()}. {fix}"
        )


def _show(value: Any) -> str:
    """The value as it is written in the file (JSON), shortened; lists and objects by their kind."""
    text = {dict: "an object", list: "a list"}.get(type(value)) or json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _unknown_effects(path: Path, where: str, names: Any, fix: str) -> None:
    unknown = [n for n in names if n not in KNOWN_EFFECTS]
    if unknown:
        raise InputError(
            f"gsmsdr: '{path}': {where} names unknown degradation effect(s) {unknown}; the known effects are "
            f"{', '.join(KNOWN_EFFECTS)}. {fix}"
        )


def check_entry(path: Path, name: str, entry: Any, fix: str) -> None:
    """Check image ``name``'s entry of the file ``path`` against the schema; ``fix`` ends each message."""
    where = f"image '{name}'"
    if not isinstance(entry, Mapping):
        raise InputError(f"gsmsdr: '{path}': the entry of {where} is {_show(entry)}, not an object. {fix}")
    for key, spec in ENTRY_FIELDS.items():
        if key in entry:
            _check(path, where, key, entry[key], spec, fix)
    effects = entry.get("effects", {})
    _unknown_effects(path, f'{where}, field "effects"', list(effects), fix)
    for effect, record in effects.items():
        field_name = f"effects.{effect}"
        if not isinstance(record, Mapping):
            raise InputError(
                f"gsmsdr: '{path}': {where}, field \"{field_name}\" is {_show(record)}; it must be an object of the "
                f"effect's parameters ({{}} when none are known). {fix}"
            )
        for key, spec in EFFECT_FIELDS[effect].items():
            if key in record:
                _check(path, where, f"{field_name}.{key}", record[key], spec, fix)


def check_document(path: Path, doc: Mapping[str, Any], fix: str) -> None:
    """Check the top-level fields (not ``version`` / ``images``) and every entry of a degradation.json."""
    where = "the top level"
    for key, spec in DOCUMENT_FIELDS.items():
        if key in doc:
            _check(path, where, key, doc[key], spec, fix)
    if isinstance(doc.get("effects"), list):
        _unknown_effects(path, 'the top-level field "effects"', doc["effects"], fix)
    for name, entry in doc["images"].items():
        check_entry(path, name, entry, fix)
