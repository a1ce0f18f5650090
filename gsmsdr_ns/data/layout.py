"""Scene layouts: the Deblur-NeRF ``hold=N`` rule, and recognising which reader a scene directory needs.

Layouts (checked in this order by :func:`detect_layout`):

* **Deblur-NeRF** (also what ``gsmsdr-degrade`` writes): a ``hold=N`` file, an ``images_test/`` folder or a
  ``degradation.json`` -> ``deblur-nerf-data``.
* **COLMAP / Mip-NeRF 360**: ``sparse/0`` with cameras + images -> the validating COLMAP reader (``colmap_path``
  ``sparse/0``).
* **nerfstudio**: ``transforms.json`` (or ``--data`` pointing at a .json file) -> ``nerfstudio-data``. It comes
  before ``colmap/sparse/0`` because ``ns-process-data`` writes both, and its transforms.json is the result.
* **COLMAP in ns-process-data's place**: ``colmap/sparse/0`` -> the COLMAP reader with that ``colmap_path``.
* **LLFF**: ``poses_bounds.npy`` and an image folder, no COLMAP model -> ``deblur-nerf-data`` (hold 8 unless a
  hold file says otherwise).
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np

from gsmsdr_ns.io.colmap import has_colmap_model
from gsmsdr_ns.io.errors import InputError, InputWarning, SceneFolderMissingError
from gsmsdr_ns.io.images import list_images

HOLD_PREFIX = "hold="
DEFAULT_HOLD = 8
DEGRADATION_FILE = "degradation.json"
TEST_IMAGES_DIR = "images_test"

LOOKED_FOR = (
    "a Deblur-NeRF scene (a 'hold=N' file, an images_test/ folder or degradation.json)",
    "a COLMAP / Mip-NeRF 360 scene (sparse/0 or colmap/sparse/0 with cameras + images .bin/.txt)",
    "a nerfstudio scene (transforms.json, or --data pointing at a .json file)",
    "an LLFF scene (poses_bounds.npy next to images/)",
)


def hold_files(data: Path) -> List[Path]:
    data = Path(data)
    if not data.is_dir():
        return []
    return sorted(p for p in data.iterdir() if p.name.startswith(HOLD_PREFIX))


def read_hold(data: Path, default: int = DEFAULT_HOLD) -> Tuple[int, str]:
    """The scene's holdout interval N from its ``hold=N`` file, and where it came from (for messages).

    No file: ``default`` with a :class:`InputWarning`. Several files, a value that is not an integer, or a
    value below 1: :class:`InputError`.
    """
    data = Path(data)
    files = hold_files(data)
    if not files:
        warnings.warn(
            f"gsmsdr: no 'hold=N' file in '{data}'; holding out every {default}th view (sorted by file name) as a "
            f"test view. Create an empty file named 'hold=N' in the scene to choose N.",
            InputWarning,
            stacklevel=2,
        )
        return default, f"default (no hold=N file in {data})"
    if len(files) > 1:
        raise InputError(
            f"gsmsdr: '{data}' has several hold files ({', '.join(p.name for p in files)}); keep exactly one "
            "'hold=N' file."
        )
    text = files[0].name[len(HOLD_PREFIX) :]
    if not re.fullmatch(r"[+-]?\d+", text.strip()):
        raise InputError(
            f"gsmsdr: cannot read the holdout interval from '{files[0]}': '{text}' is not an integer. Name the file "
            "'hold=N' with N >= 1 (every N-th view, sorted by file name, is a test view)."
        )
    hold = int(text)
    if hold < 1:
        raise InputError(
            f"gsmsdr: '{files[0]}' sets the holdout interval to {hold}; it must be >= 1 (views whose index in "
            "file-name order is divisible by N are the test views). Rename the file, e.g. to 'hold=8'."
        )
    return hold, str(files[0])


def holdout_split(num_images: int, hold: int) -> Tuple[np.ndarray, np.ndarray]:
    """(train, test) indices into a list sorted by file name: test = index % hold == 0, train = the rest."""
    if hold < 1:
        raise InputError(f"gsmsdr: holdout interval must be >= 1, got {hold}.")
    index = np.arange(num_images)
    test = index[index % hold == 0]
    train = index[index % hold != 0]
    return train, test


@dataclass(frozen=True)
class LayoutChoice:
    """Which reader a scene needs and why (one line, for the log)."""

    reader: str
    """"deblur-nerf-data", "colmap" or "nerfstudio-data"."""
    reason: str
    colmap_path: Optional[Path] = None
    """For "colmap": the model directory relative to the scene."""


def detect_layout(data: Path) -> LayoutChoice:
    """Recognise the layout of ``data`` (see the module docstring); :class:`InputError` if none fits."""
    data = Path(data)
    if data.is_file() and data.suffix.lower() == ".json":
        return LayoutChoice("nerfstudio-data", f"--data is the json file {data.name}")
    if not data.is_dir():
        raise SceneFolderMissingError(data)
    markers = [p.name for p in hold_files(data)]
    if (data / TEST_IMAGES_DIR).is_dir():
        markers.append(f"{TEST_IMAGES_DIR}/")
    if (data / DEGRADATION_FILE).is_file():
        markers.append(DEGRADATION_FILE)
    if markers:
        return LayoutChoice("deblur-nerf-data", f"Deblur-NeRF layout: found {', '.join(markers)}")
    if has_colmap_model(data / "sparse" / "0"):
        return LayoutChoice("colmap", "COLMAP / Mip-NeRF 360 layout: found sparse/0", Path("sparse/0"))
    if (data / "transforms.json").is_file():
        return LayoutChoice("nerfstudio-data", "nerfstudio layout: found transforms.json")
    if has_colmap_model(data / "colmap" / "sparse" / "0"):
        return LayoutChoice("colmap", "COLMAP layout: found colmap/sparse/0", Path("colmap/sparse/0"))
    if (data / "poses_bounds.npy").is_file():
        return LayoutChoice("deblur-nerf-data", "LLFF layout: found poses_bounds.npy and no COLMAP model")
    found = sorted(p.name + ("/" if p.is_dir() else "") for p in data.iterdir())
    shown = ", ".join(found[:12]) + (f", ... ({len(found)} entries)" if len(found) > 12 else "") if found else "nothing"
    photos = [data] + [data / sub for sub in ("images", "input") if (data / sub).is_dir()]
    for folder in photos:
        if len(list_images(folder)) >= 2:
            raise InputError(
                f"gsmsdr: '{data}' holds photos ({folder}) but no camera poses. Compute them with "
                f"`gsmsdr-process --images {folder} --out {data.parent / (data.name + '-scene')}` (structure-from-"
                "motion with pycolmap) and train on that scene."
            )
    raise InputError(
        f"gsmsdr: cannot tell what kind of scene '{data}' is. Looked for: {'; '.join(LOOKED_FOR)}. Found: {shown}. "
        "Fix the layout, or name a dataparser explicitly (e.g. `ns-train gsmsdr --data <dir> colmap`)."
    )
