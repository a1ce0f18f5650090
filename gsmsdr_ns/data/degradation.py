"""``degradation.json`` (version 1): which images of a degraded scene are degraded, and how.

The file is written by ``gsmsdr-degrade`` / ``gsmsdr-synth`` (``gsmsdr_ns.degrade.pipeline`` writes it)::

    {"version": 1, "generator": ..., "source": ..., "seed": 0, "hold": 8, "effects": [...], "preset": ...,
     "images": {"<name>": {"split": "train" | "test", "degraded": bool, "effects": {"motion": {...}, ...}}}}

Each image becomes one *record*, a plain dict that the dataparsers put into ``metadata["degradations"]`` (one
per image of a split, in the split's order) and from which the model builds its per-image degradation profile::

    {"name": str, "split": "train" | "test", "degraded": True | False | None, "effects": {...},
     "mixres_factor": int | None}

``degraded`` is None when nothing is known (no degradation.json, or the image is missing from it);
``mixres_factor`` is the ``mixres`` effect's factor, 1 for images known to be at full resolution, None if unknown.

The file is checked against its schema when it is read (``gsmsdr_ns.data.degradation_schema``: the type and range
of every field, known effect names), so a bad entry fails while the scene is parsed, naming the image and field.
"""

from __future__ import annotations

import copy
import json
import warnings
from pathlib import Path
from typing import Any, Dict, Iterable, Optional

from gsmsdr_ns.data.degradation_schema import check_document
from gsmsdr_ns.io.errors import InputError, InputWarning

SUPPORTED_VERSIONS = (1,)
RECREATE = "Fix the entry, or re-create the file with gsmsdr-degrade (or gsmsdr-estimate)."
"""How to fix a bad degradation.json (the end of every message about one)."""


def load_degradation_json(path: Path, fix: str = RECREATE) -> Dict[str, Any]:
    """Parse a degradation.json and check it against the schema; returns the document (``images``: name -> entry).

    Every field's type and range and every effect name are checked (``gsmsdr_ns.data.degradation_schema``); a
    violation is an :class:`InputError` naming the file, the image and the field, ended by ``fix``.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(f"gsmsdr: cannot read '{path}': {err}. Re-create it with gsmsdr-degrade.") from err
    if not isinstance(doc, dict):
        raise InputError(f"gsmsdr: '{path}' must hold a JSON object, got {type(doc).__name__}.")
    version = doc.get("version")
    if version not in SUPPORTED_VERSIONS:
        raise InputError(
            f"gsmsdr: '{path}' has version {version!r}; this gsmsdr reads version(s) {list(SUPPORTED_VERSIONS)}."
        )
    images = doc.get("images")
    if not isinstance(images, dict):
        raise InputError(f"gsmsdr: '{path}' has no \"images\" object mapping image names to their entries.")
    check_document(path, doc, fix)
    return doc


def unknown_record(name: str, split: str) -> Dict[str, Any]:
    """Record for an image whose degradation is unknown (train) or that is a sharp evaluation view (test)."""
    if split == "train":
        return {"name": name, "split": split, "degraded": None, "effects": {}, "mixres_factor": None}
    return sharp_record(name, split)


def sharp_record(name: str, split: str) -> Dict[str, Any]:
    return {"name": name, "split": split, "degraded": False, "effects": {}, "mixres_factor": 1}


def record_from_entry(name: str, split: str, entry: Optional[Dict[str, Any]]) -> Dict[str, Any]:
    """The record of image ``name`` in ``split`` from its degradation.json entry (None: not listed)."""
    if entry is None:
        return unknown_record(name, split)
    effects = copy.deepcopy(entry.get("effects", {}))
    degraded = entry.get("degraded", bool(effects))
    mixres = effects.get("mixres")
    factor = int(mixres["factor"]) if isinstance(mixres, dict) and "factor" in mixres else 1
    return {"name": name, "split": split, "degraded": bool(degraded), "effects": effects, "mixres_factor": factor}


def match_entries(doc: Dict[str, Any], names: Iterable[str], path: Path) -> Dict[str, Optional[Dict[str, Any]]]:
    """Map each scene image name to its degradation.json entry (None when missing, with one warning).

    Entries may be keyed by the exact name or by a name with the same stem (downscaled copies are often PNG). An
    entry that matches no image means the file belongs to another scene: :class:`InputError`.
    """
    names = list(names)
    entries: Dict[str, Dict[str, Any]] = doc["images"]
    by_stem = {Path(key).stem: key for key in entries}
    matched: Dict[str, Optional[Dict[str, Any]]] = {}
    used = set()
    for name in names:
        key = name if name in entries else by_stem.get(Path(name).stem)
        matched[name] = entries.get(key) if key is not None else None
        if key is not None:
            used.add(key)
    stray = sorted(set(entries) - used)
    if stray:
        raise InputError(
            f"gsmsdr: '{path}' describes {len(stray)} image(s) that are not in the scene, e.g. {stray[:3]}: the file "
            "belongs to another scene or the images were renamed. Re-create it with gsmsdr-degrade."
        )
    missing = [name for name, entry in matched.items() if entry is None]
    if missing:
        warnings.warn(
            f"gsmsdr: '{path}' does not describe {len(missing)} image(s) (e.g. {missing[:3]}); their degradation is "
            "treated as unknown.",
            InputWarning,
            stacklevel=2,
        )
    return matched
