"""The mixed-resolution protocol (GS-MSDR paper, section 4.2) and its on-disk cache.

Training views are split at random (uniformly, seed-controlled) into four equal groups; each group is downscaled
by 4x, 3x, 2x or 1x and upsampled back to the full size, so every training image has the full size but carries
the detail of its group's resolution. Test views stay untouched.

The degraded images are written once into ``<scene>/.gsmsdr_cache/mixres_seed<k>[_<images dir>]/`` together with
``manifest.json`` (a degradation.json-style description plus the key that produced it: protocol parameters and
the size / modification time of every source image). A cache whose key matches and whose files are all there is
reused; anything else is rebuilt in a temporary folder and renamed into place, so a crash never leaves a
half-written cache behind.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from gsmsdr_ns.io.atomic import replace_dir, temp_sibling_dir
from gsmsdr_ns.io.images import read_image, write_image

MIXRES_FACTORS = (4, 3, 2, 1)
"""Downscale factors of the four training groups (paper section 4.2)."""
CACHE_DIR = ".gsmsdr_cache"
MANIFEST = "manifest.json"
CACHE_FORMAT = 1


def mixres_factors(n: int, seed: int | Sequence[int], factors: Sequence[int] = (4, 3, 2, 1)) -> np.ndarray:
    """Split n views at random into len(factors) equal groups (sizes differ by at most one) -> factors [n] int.

    Which groups get the remainder is random too; the same (n, seed, factors) always gives the same split.
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    if len(factors) == 0:
        raise ValueError("factors must not be empty")
    rng = np.random.default_rng(seed)
    pattern = rng.permutation(np.asarray(factors, dtype=np.int64))
    return rng.permutation(np.resize(pattern, n)) if n else np.zeros(0, dtype=np.int64)


def assign_mixres_factors(num_images: int, seed: int, factors: Sequence[int] = MIXRES_FACTORS) -> np.ndarray:
    """Factor of each of ``num_images`` training images (in the given order, i.e. sorted by file name).

    The views are split at random into ``len(factors)`` equal groups (sizes differ by at most one; which groups get
    the remainder is random too), the same rule ``gsmsdr-degrade --effect mixres`` uses: both call
    :func:`mixres_factors`.
    """
    if any(int(f) < 1 for f in factors):
        raise ValueError(f"factors must be >= 1, got {list(factors)}")
    return np.asarray(mixres_factors(int(num_images), int(seed), [int(f) for f in factors]), dtype=np.int64)


def downscale_upscale(image: np.ndarray, factor: int) -> np.ndarray:
    """``[H, W, C]`` uint8 image shrunk by ``factor`` (antialiased bilinear, ``round(H / f) x round(W / f)``) and
    enlarged back to H x W (bilinear), via :func:`gsmsdr_ns.ops.mixres.apply_mixres`; factor 1 returns a copy."""
    from gsmsdr_ns.ops.mixres import apply_mixres  # kornia only for the images that need it

    if image.dtype != np.uint8 or image.ndim != 3:
        raise ValueError(f"expected [H, W, C] uint8, got {image.dtype} {image.shape}")
    if factor == 1:
        return image.copy()
    x = torch.tensor(image).permute(2, 0, 1)[None].to(torch.float32) / 255.0  # [1, C, H, W]; copied (may be read-only)
    full = apply_mixres(x, int(factor))
    return (full[0].permute(1, 2, 0).clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).numpy()


@dataclass
class MixresImages:
    """The training images of a mixed-resolution scene, aligned with the names passed to :func:`mixres_cache`."""

    files: List[Path]
    """Image file per training view: the degraded copy in the cache, or the source file for factor 1."""
    factors: List[int]
    """Downscale factor per training view."""
    cache_dir: Path
    reused: bool
    """True when an existing valid cache was used, False when it was (re)built now."""


def _fingerprint(path: Path) -> Dict[str, int]:
    stat = Path(path).stat()
    return {"bytes": int(stat.st_size), "mtime_ns": int(stat.st_mtime_ns)}


def _output_name(name: str) -> str:
    return name if name.lower().endswith(".png") else f"{name}.png"


def _cache_key(
    scene_dir: Path, names: Sequence[str], sources: Sequence[Path], factors: np.ndarray, params: Dict
) -> Dict:
    return {
        "format": CACHE_FORMAT,
        "params": params,
        "images": [
            {"name": n, "source": os.path.relpath(s, scene_dir), "factor": int(f), **_fingerprint(s)}
            for n, s, f in zip(names, sources, factors)
        ],
    }


def _load_valid(cache_dir: Path, key: Dict) -> Optional[Dict]:
    """The manifest of ``cache_dir`` if it was built for ``key`` and all its files are intact, else None."""
    try:
        manifest = json.loads((cache_dir / MANIFEST).read_text(encoding="utf8"))
    except (OSError, ValueError):
        return None
    if not isinstance(manifest, dict) or manifest.get("key") != key:
        return None
    for name, entry in manifest.get("images", {}).items():
        file = entry.get("file")
        if file is not None:
            path = cache_dir / file
            if not path.is_file() or path.stat().st_size != entry.get("bytes"):
                return None
    return manifest


def mixres_cache(
    scene_dir: Path,
    cache_dir: Path,
    names: Sequence[str],
    sources: Sequence[Path],
    seed: int,
    factors: Sequence[int] = MIXRES_FACTORS,
    params: Optional[Dict] = None,
    log: Optional[Callable[[str], None]] = None,
) -> MixresImages:
    """Degraded training images for ``names`` (sorted file names) read from ``sources``; built or reused.

    ``params`` are extra protocol parameters (hold interval, image folder, ...) that must match for a cache to be
    reused. ``cache_dir`` is the final folder, e.g. ``<scene>/.gsmsdr_cache/mixres_seed0``.
    """
    log = log or (lambda _msg: None)
    scene_dir, cache_dir = Path(scene_dir), Path(cache_dir)
    sources = [Path(s) for s in sources]
    if len(names) != len(sources):
        raise ValueError("names and sources must have the same length")
    assigned = assign_mixres_factors(len(names), seed, factors)
    key = _cache_key(scene_dir, names, sources, assigned, {"seed": int(seed), "factors": [int(f) for f in factors],
                                                           **(params or {})})  # fmt: skip
    manifest = _load_valid(cache_dir, key)
    reused = manifest is not None
    if manifest is None:
        log(f"building the mixed-resolution cache {cache_dir} ({len(names)} training images, seed {seed})")
        manifest = _build(scene_dir, cache_dir, names, sources, assigned, key, seed)
    else:
        log(f"reusing the mixed-resolution cache {cache_dir}")
    files = []
    for name, source in zip(names, sources):
        entry = manifest["images"][name]
        files.append(cache_dir / entry["file"] if entry.get("file") is not None else source)
    return MixresImages(files=files, factors=[int(f) for f in assigned], cache_dir=cache_dir, reused=reused)


def _build(
    scene_dir: Path,
    cache_dir: Path,
    names: Sequence[str],
    sources: Sequence[Path],
    assigned: np.ndarray,
    key: Dict,
    seed: int,
) -> Dict:
    tmp = temp_sibling_dir(cache_dir)
    try:
        images = {}
        for name, source, factor in zip(names, sources, assigned):
            entry = {"split": "train", "degraded": bool(factor > 1), "effects": {"mixres": {"factor": int(factor)}}}
            if factor > 1:
                out = _output_name(name)
                write_image(tmp / out, downscale_upscale(read_image(source), int(factor)))
                entry.update(file=out, bytes=(tmp / out).stat().st_size)
            else:
                entry.update(file=None, source=os.path.relpath(source, scene_dir))
            images[name] = entry
        manifest = {
            "version": 1,
            "generator": "gsmsdr mixres-data",
            "source": str(scene_dir),
            "seed": int(seed),
            "effects": ["mixres"],
            "key": key,
            "images": images,
        }
        with open(tmp / MANIFEST, "w", encoding="utf8") as f:
            json.dump(manifest, f, indent=1)
        try:
            replace_dir(tmp, cache_dir)
        except OSError:
            # Another process may have finished the same cache first: use it if it is valid.
            other = _load_valid(cache_dir, key)
            if other is None:
                raise
            shutil.rmtree(tmp, ignore_errors=True)
            return other
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return manifest


def cache_dir_for(scene_dir: Path, seed: int, images_dir: str = "images") -> Path:
    """``<scene>/.gsmsdr_cache/mixres_seed<seed>`` (plus ``_<images_dir>`` when not reading ``images/``)."""
    suffix = "" if images_dir == "images" else f"_{images_dir.replace('/', '_')}"
    return Path(scene_dir) / CACHE_DIR / f"mixres_seed{int(seed)}{suffix}"


def group_sizes(factors: Sequence[int], choices: Sequence[int] = MIXRES_FACTORS) -> Tuple[int, ...]:
    """How many images got each factor of ``choices`` (for logs and tests)."""
    return tuple(int(sum(1 for f in factors if f == c)) for c in choices)
