"""Checks on camera poses read from disk: the rotation part of every camera-to-world must be a proper rotation.

A rotation scaled by 2 trains silently into a wrong scene, an all-zero one fails at the first rasterizer step with
``linalg.inv: input matrix is singular``; both are rejected while the scene is parsed, with the file and the row or
image named. The tolerance holds for poses stored in float32 and for every pose COLMAP or LLFF writes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence, Tuple, Union

import numpy as np

from gsmsdr_ns.io.errors import InputError

ROTATION_TOLERANCE = 1e-3
"""Largest accepted ``max |R^T R - I|`` (element-wise) and ``|det(R) - 1|`` of a camera rotation."""


def rotation_defects(rotations: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(orthonormality error ``max |R^T R - I|`` [N], determinant [N]) of rotations [N, 3, 3]."""
    rotations = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    gram = np.einsum("nji,njk->nik", rotations, rotations)  # R^T R
    error = np.abs(gram - np.eye(3)).max(axis=(1, 2))
    return error, np.linalg.det(rotations)


def check_rotations(rotations: np.ndarray, source: Union[str, Path], labels: Sequence[str], fix: str) -> None:
    """Raise :class:`InputError` for the first rotation [N, 3, 3] that is not orthonormal with det +1.

    A rotation passes when ``max |R^T R - I| <= ROTATION_TOLERANCE`` and ``|det(R) - 1| <= ROTATION_TOLERANCE``
    (non-finite values fail). ``source`` is the pose file, ``labels[i]`` names row i in it (``"row 3 (image
    'a.png')"``), ``fix`` says how to repair the file.
    """
    rotations = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    error, det = rotation_defects(rotations)
    bad = ~(np.isfinite(error) & np.isfinite(det) & (error <= ROTATION_TOLERANCE)) | ~(
        np.abs(det - 1.0) <= ROTATION_TOLERANCE
    )
    if not bad.any():
        return
    i = int(np.flatnonzero(bad)[0])
    matrix = np.array2string(rotations[i] + 0.0, precision=4, separator=", ", suppress_small=True).replace("\n", "")
    more = int(bad.sum()) - 1
    raise InputError(
        f"gsmsdr: '{source}' {labels[i]} has a camera rotation that is not a rotation matrix: R = {matrix}, "
        f"max |R^T R - I| = {error[i]:.3g}, det(R) = {det[i]:.4g} (allowed: max |R^T R - I| <= {ROTATION_TOLERANCE:g} "
        f"and det(R) = 1 within {ROTATION_TOLERANCE:g}; a scale, shear, reflection or zero matrix is not a pose)"
        f"{f'; {more} more row(s) are bad too' if more else ''}. {fix}"
    )
