"""Checks on a nerfstudio ``transforms.json`` before nerfstudio's own reader parses it.

nerfstudio's ``nerfstudio-data`` reader asserts on missing keys, opens the first image without naming the
transforms file, and accepts any 4x4 matrix as a pose. :func:`check_transforms_json` runs first and turns those
cases into :class:`~gsmsdr_ns.io.errors.InputError` messages naming the file and the frame.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict, Optional

import numpy as np

from gsmsdr_ns.data.poses import check_rotations
from gsmsdr_ns.io.errors import InputError


def transforms_file(data: Path) -> Path:
    """The transforms file of ``--data``: the path itself when it is a .json file, else ``<data>/transforms.json``."""
    data = Path(data)
    return data if data.suffix == ".json" else data / "transforms.json"


def check_transforms_json(data: Path, downscale_factor: Optional[int]) -> Dict[str, Any]:
    """Read and check the transforms file of ``data`` (see :func:`transforms_file`); returns the document.

    Checks: the file is a JSON object with a non-empty ``frames`` list; every frame has a ``file_path`` and a
    finite 4x4 (or 3x4) ``transform_matrix`` whose rotation is orthonormal with det +1 within
    ``gsmsdr_ns.data.poses.ROTATION_TOLERANCE`` (1e-3); at full resolution (``downscale_factor`` None or 1, where
    nerfstudio opens the files named in ``file_path``) every frame's image file exists. Whether the files decode
    is checked on the files nerfstudio resolved, after it has parsed (``check_image_files`` in the plugin).
    """
    path = transforms_file(data)
    try:
        doc = json.loads(path.read_text(encoding="utf8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(f"gsmsdr: cannot read '{path}': {err}. Re-create it (ns-process-data writes one).") from err
    frames = doc.get("frames") if isinstance(doc, dict) else None
    if not isinstance(frames, list) or not frames:
        raise InputError(f"gsmsdr: '{path}' has no \"frames\" list (one object per image with its file_path and pose).")
    rotations, labels = [], []
    for index, frame in enumerate(frames):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise InputError(f"gsmsdr: '{path}' frame {index} has no \"file_path\" string naming its image.")
        label = f"frame {index} ('{frame['file_path']}')"
        try:
            matrix = np.asarray(frame.get("transform_matrix"), dtype=np.float64)
        except (TypeError, ValueError):
            matrix = np.zeros(0)
        if matrix.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(matrix)):
            raise InputError(
                f"gsmsdr: '{path}' {label} has no finite 4x4 \"transform_matrix\" (camera-to-world, OpenGL axes). "
                "Fix that frame or re-create the file."
            )
        rotations.append(matrix[:3, :3])
        labels.append(label)
    check_rotations(
        np.stack(rotations),
        path,
        labels,
        "A transform_matrix is camera-to-world: its upper-left 3x3 must be a rotation (no scale). Fix that frame or "
        "re-create the file (ns-process-data).",
    )
    if downscale_factor is None or int(downscale_factor) == 1:
        base = path.parent
        for index, frame in enumerate(frames):
            image = base / frame["file_path"]
            if not image.is_file():
                raise InputError(
                    f"gsmsdr: image file '{image}' (frame {index} of '{path}') does not exist. Restore it, or remove "
                    "its frame from the transforms file."
                )
    return doc
