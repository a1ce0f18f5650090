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
"""

from __future__ import annotations

import copy
import json
import warnings
from pathlib import Path
from typing import Any, Dict, Iterable, Optional

from gsmsdr_ns.io.errors import InputError, InputWarning

SUPPORTED_VERSIONS = (1,)
KNOWN_EFFECTS = ("motion", "defocus", "mixres", "noise")


def load_degradation_json(path: Path) -> Dict[str, Any]:
    """Parse and check a degradation.json; returns the document with ``images`` as a name -> entry dict."""
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
    for name, entry in images.items():
        if not isinstance(entry, dict):
            raise InputError(f"gsmsdr: '{path}': the entry of image '{name}' is not an object.")
        effects = entry.get("effects", {})
        if not isinstance(effects, dict):
            raise InputError(f"gsmsdr: '{path}': \"effects\" of image '{name}' is not an object.")
        factor = effects.get("mixres", {}).get("factor", 1) if isinstance(effects.get("mixres"), dict) else 1
        if not isinstance(factor, int) or isinstance(factor, bool) or factor < 1:
            raise InputError(
                f"gsmsdr: '{path}': image '{name}' has mixres factor {factor!r}; it must be an integer >= 1."
            )
        if entry.get("split") not in (None, "train", "test"):
            raise InputError(
                f"gsmsdr: '{path}': image '{name}' has split {entry.get('split')!r}; expected \"train\" or \"test\"."
            )
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


def match_entries(
    doc: Dict[str, Any], names: Iterable[str], path: Path
) -> Dict[str, Optional[Dict[str, Any]]]:
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
