"""Where real photo sets live: ``$GSMSDR_DATA_DIR``, else ``shared/data/`` in a parent folder of an anchor (the
project keeps its photo sets, e.g. ``llff-fern``, in ``shared/data/`` beside the repository)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import List, Optional, Sequence

DATA_DIR_ENV = "GSMSDR_DATA_DIR"
"""Environment variable naming a folder that holds photo sets (``$GSMSDR_DATA_DIR/llff-fern``)."""
PACKAGE_DIR = Path(__file__).resolve().parents[1]
"""The installed ``gsmsdr_ns`` package: from an editable install, ``shared/data`` beside the repository is found
from here."""


def photo_set_roots(anchors: Sequence[Path] = ()) -> List[Path]:
    """Folders that may hold photo sets, in the order they are searched: ``$GSMSDR_DATA_DIR``, then ``shared/data``
    in each anchor (and the package folder) and each of their parents."""
    roots: List[Path] = []
    env = os.environ.get(DATA_DIR_ENV)
    if env:
        roots.append(Path(env).expanduser())
    for anchor in [*anchors, PACKAGE_DIR]:
        for folder in [Path(anchor).absolute(), *Path(anchor).absolute().parents]:
            candidate = folder / "shared" / "data"
            if candidate not in roots:
                roots.append(candidate)
    return roots


def find_photo_set(name: str, anchors: Sequence[Path] = (), subfolder: str = "") -> Optional[Path]:
    """The first ``<root>/<name>`` of :func:`photo_set_roots` whose ``subfolder`` (e.g. ``images_16``) is a folder;
    None when no root has it."""
    for root in photo_set_roots(anchors):
        if (root / name / subfolder).is_dir():
            return root / name
    return None


__all__ = ["DATA_DIR_ENV", "find_photo_set", "photo_set_roots"]
