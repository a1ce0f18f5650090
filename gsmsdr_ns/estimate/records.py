"""Estimated degradation records: ``degradation.json`` entries from :func:`estimate_degradations`, merged with
the true records a scene may already have, written atomically; and a cached estimate for the dataparsers.

An estimated entry is a valid version-1 entry for ``gsmsdr_ns.data.degradation`` (``degraded`` + ``effects``)
with two extra keys the reader ignores: ``"source": "estimated"`` and ``"estimate"`` (the evidence)::

    sharp             {"degraded": false, "effects": {}}
    motion / defocus  {"degraded": true, "effects": {"motion": {"model": "estimated"}}}
    mixres            {"degraded": true, "effects": {"mixres": {"factor": 2, "upsample": "bilinear", ...}}}
    blurred, kind unknown   both blur effects (the model simulates both, at full resolution)
    unknown           {"degraded": true, "effects": {}} (the model treats it as unknown: every degradation)

Users may edit them; an entry without ``"source": "estimated"`` is a true record and is kept unless asked.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

from .. import __version__
from ..data.degradation import load_degradation_json
from ..data.degradation_schema import check_entry
from ..io.atomic import write_json_atomic
from ..io.errors import InputError
from ..io.images import list_images, read_image
from .classify import METHOD_VERSION, DegradationEstimate, estimate_degradations
from .config import EstimateConfig
from .ensemble import load_degraded_model, load_kind_model

ESTIMATED = "estimated"
"""Value of an entry's ``"source"`` key that marks it as estimated (not a true record)."""
GENERATOR = f"gsmsdr-estimate {__version__}"
DEGRADATION_FILE = "degradation.json"
CACHE_FILE = "degradation.estimated.json"
"""The dataparsers' cache of a scene's estimate (same format as degradation.json, plus file fingerprints)."""
FORMAT_VERSION = 1


def entry_from_estimate(est: DegradationEstimate) -> Dict[str, Any]:
    """The degradation.json entry of one estimate (see the module doc)."""
    mark = {"model": ESTIMATED}
    if est.label == "sharp":
        degraded, effects = False, {}
    elif est.label in ("motion", "defocus"):
        degraded, effects = True, {est.label: dict(mark)}
    elif est.label == "mixres":
        degraded = True
        effects = {"mixres": {"factor": int(est.mixres_factor), "upsample": "bilinear", **mark}}
    elif est.blurred:
        degraded, effects = True, {"motion": dict(mark), "defocus": dict(mark)}
    else:
        degraded, effects = True, {}
    return {"degraded": degraded, "effects": effects, "source": ESTIMATED, "estimate": est.evidence()}


def is_estimated(entry: Any) -> bool:
    """Whether a degradation.json entry was written by the estimate (not a true record)."""
    return isinstance(entry, dict) and entry.get("source") == ESTIMATED


def read_folder(folder: Path, names: Optional[Sequence[str]] = None) -> tuple[List[str], list]:
    """(names, images [H, W, C] uint8) of the image files of folder (all of them, sorted, if names is None).

    An empty folder or an unreadable image is a :class:`InputError` naming the folder or file.
    """
    folder = Path(folder)
    names = list(names) if names is not None else list_images(folder)
    if not names:
        raise InputError(
            f"gsmsdr: no images in '{folder}' (looked for .png, .jpg, .jpeg, .bmp, .tif, .tiff, .webp). Point "
            "--images at the folder that holds the photos, or --scene at the scene that has an images/ folder."
        )
    return names, [read_image(folder / n) for n in names]


def estimate_entries(
    folder: Path, config: Optional[EstimateConfig] = None, names: Optional[Sequence[str]] = None
) -> Dict[str, Dict[str, Any]]:
    """Estimate every image of folder (as one set) -> {name: degradation.json entry}, in name order."""
    names, images = read_folder(folder, names)
    estimates = estimate_degradations(images, config)
    return {n: entry_from_estimate(e) for n, e in zip(names, estimates)}


def merge_entries(
    doc: Optional[Dict[str, Any]],
    estimated: Dict[str, Dict[str, Any]],
    source: str,
    config: EstimateConfig,
    replace_records: bool = False,
) -> tuple[Dict[str, Any], List[str]]:
    """The document with the estimated entries merged in -> (document, names whose true record was kept).

    doc: the current degradation.json (None: none yet). True records are kept unless replace_records; earlier
    estimates are replaced; entries of other images are left as they are.
    """
    if doc is None:
        doc = {"version": FORMAT_VERSION, "generator": GENERATOR, "source": source, "images": {}}
    doc = dict(doc)
    images = dict(doc.get("images", {}))
    kept = []
    for name, entry in estimated.items():
        current = images.get(name)
        if current is not None and not is_estimated(current) and not replace_records:
            kept.append(name)
            continue
        images[name] = entry
    doc["images"] = dict(sorted(images.items()))
    doc["estimate"] = {"generator": GENERATOR, "images": source, "config": estimate_fingerprint(config)}
    return doc, kept


def estimate_fingerprint(config: Optional[EstimateConfig] = None) -> Dict[str, Any]:
    """What an estimate depends on besides the images: the config, the method's version and the digests of the
    fitted ensembles it reads (JSON-ready)."""
    from dataclasses import asdict

    cfg = config or EstimateConfig()
    out = {**asdict(cfg), "method_version": METHOD_VERSION}
    out["kind_model_digest"] = load_kind_model(cfg.kind_model, cfg).digest
    if cfg.sharp_from == "model":
        out["degraded_model_digest"] = load_degraded_model(cfg.degraded_model, cfg).digest
    return out


def write_scene_estimate(
    scene_dir: Path,
    config: Optional[EstimateConfig] = None,
    images_dir: str = "images",
    out: Optional[Path] = None,
    replace_records: bool = False,
) -> tuple[Path, Dict[str, Any], List[str]]:
    """Estimate the images of scene_dir/images_dir and merge them into out (default scene_dir/degradation.json).

    -> (path written, document, names whose true record was kept). An existing file that cannot be read is an
    error (it is not overwritten). Everything is computed before anything is written.
    """
    cfg = config or EstimateConfig()
    scene_dir = Path(scene_dir)
    folder = scene_dir / images_dir
    out = Path(out) if out is not None else scene_dir / DEGRADATION_FILE
    doc = load_degradation_json(out) if out.exists() else None
    estimated = estimate_entries(folder, cfg)
    merged, kept = merge_entries(doc, estimated, str(folder), cfg, replace_records)
    if len(kept) < len(estimated):  # nothing to add when every image has a true record: leave the file alone
        write_json_atomic(out, merged)
    return out, merged, kept


def _fingerprints(folder: Path, names: Sequence[str]) -> Dict[str, List[int]]:
    out = {}
    for n in names:
        st = (folder / n).stat()
        out[n] = [st.st_size, st.st_mtime_ns]
    return out


def estimate_scene_records(
    scene_dir: Path,
    images_dir: str = "images",
    config: Optional[EstimateConfig] = None,
    cache: bool = True,
) -> Dict[str, Dict[str, Any]]:
    """Estimated degradation.json entries of every image of scene_dir/images_dir -> {name: entry}.

    For a dataparser whose scene has no degradation records: pass each entry to
    ``gsmsdr_ns.data.degradation.record_from_entry``. The result is cached in scene_dir/degradation.estimated.json
    (written atomically; reused while the image files - names, sizes, modification times - and the config are
    unchanged; a cache that cannot be written, e.g. a read-only scene, is skipped). Reused entries are checked
    against the degradation.json schema (the file is user-editable): InputError naming the cache, image and field.
    """
    cfg = config or EstimateConfig()
    scene_dir = Path(scene_dir)
    folder = scene_dir / images_dir
    names = list_images(folder)
    if not names:
        read_folder(folder, names)  # the clear "no images" error
    key = {"images": images_dir, "files": _fingerprints(folder, names), "config": estimate_fingerprint(cfg)}
    cache_path = scene_dir / CACHE_FILE
    if cache and cache_path.is_file():
        try:
            doc = json.loads(cache_path.read_text(encoding="utf8"))
            reuse = isinstance(doc, dict) and doc.get("cache_key") == key
            entries = doc["images"] if reuse else None
        except (OSError, ValueError, KeyError):
            entries = None  # a stale or broken cache is recomputed
        if entries is not None:
            fix = f"Fix the entry, or delete '{cache_path}' to estimate again."
            for name, entry in entries.items():  # the cache may have been edited by hand
                check_entry(cache_path, name, entry, fix)
            return entries
    entries = estimate_entries(folder, cfg, names)
    if cache:
        doc = {"version": FORMAT_VERSION, "generator": GENERATOR, "source": str(folder), "cache_key": key,
               "images": entries}  # fmt: skip
        try:
            write_json_atomic(cache_path, doc)
        except OSError:
            pass  # read-only scene: estimate again next time
    return entries


__all__ = [
    "ESTIMATED",
    "CACHE_FILE",
    "entry_from_estimate",
    "estimate_fingerprint",
    "is_estimated",
    "read_folder",
    "estimate_entries",
    "merge_entries",
    "write_scene_estimate",
    "estimate_scene_records",
]
