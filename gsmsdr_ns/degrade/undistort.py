"""Undistorting a sharp input scene before it is degraded: the blur and resolution models work on pinhole images.

A COLMAP scene whose cameras carry distortion, or a transforms.json capture with non-zero ``k1 k2 k3 k4 p1 p2``,
is undistorted with pycolmap's image undistorter (what ``gsmsdr-process`` uses): the images are resampled to
pinhole cameras (cropped to the valid region) and the model is written as ``images/`` + ``sparse/0``, the
layout :func:`gsmsdr_ns.degrade.source.load_source` reads. Output names stay those the distorted input would
have had.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..io.colmap import quiet_pycolmap, read_colmap, write_colmap_model
from ..io.errors import InputError
from .source import read_transforms_frames

_OPENCV_PARAMS = ("k1", "k2", "p1", "p2")
"""Distortion parameters of COLMAP's OPENCV model (FULL_OPENCV adds k3..k6)."""


def describe_distortion(root: str | Path) -> str | None:
    """One line naming the input scene's lens distortion (largest coefficients), or None when it has none."""
    root = Path(root)
    model_dir = root / "sparse" / "0"
    if model_dir.is_dir():
        model = read_colmap(model_dir, skip_unposed=True)
        distorted = np.any(model.distortion != 0, axis=1)
        if not distorted.any():
            return None
        v = int(np.argmax(distorted))
        return (f"{int(distorted.sum())} of {len(model.names)} images with {model.camera_models[v]} cameras "
                f"(k1 k2 k3 k4 p1 p2 = {_format(model.distortion[v])})")  # fmt: skip
    if (root / "transforms.json").is_file():
        frames = read_transforms_frames(root, root / "transforms.json")
        distorted = [f for f in frames if any(d != 0 for d in f.distortion)]
        if not distorted:
            return None
        return (f"{len(distorted)} of {len(frames)} transforms.json frames (k1 k2 k3 k4 p1 p2 = "
                f"{_format(distorted[0].distortion)})")  # fmt: skip
    return None


def _format(values) -> str:
    return " ".join(f"{float(v):.4g}" for v in values)


def _write_transforms_model(root: Path, flat: Path, model_dir: Path) -> None:
    """Write the transforms.json capture at ``root`` as a COLMAP model with its distorted cameras (OPENCV /
    FULL_OPENCV) and no points into ``model_dir``; its image names are the frames' output names, linked in
    ``flat``."""
    frames = read_transforms_frames(root, root / "transforms.json")
    names = []
    for frame in frames:
        name = Path(frame.name).stem + frame.path.suffix  # the undistorter keeps the file format
        os.symlink(frame.path.absolute(), flat / name)
        names.append(name)
    write_colmap_model(
        model_dir,
        names,
        np.stack([frame.K for frame in frames]),
        [frame.size for frame in frames],
        np.stack([frame.w2c for frame in frames]),
        distortion=[frame.distortion for frame in frames],
    )


def undistort_scene(root: str | Path, work: str | Path) -> Path:
    """Undistort the scene at ``root`` into ``work/undistorted`` (``images/`` + ``sparse/0`` with PINHOLE cameras)
    and return that folder; ``work`` is an empty scratch folder the caller removes."""
    import pycolmap

    root, work = Path(root), Path(work)
    model_dir = root / "sparse" / "0"
    if model_dir.is_dir():
        images, distorted = root / "images", model_dir
    elif (root / "transforms.json").is_file():
        images, distorted = work / "frames", work / "distorted"
        images.mkdir()
        distorted.mkdir()
        _write_transforms_model(root, images, distorted)
    else:
        raise InputError(f"{root} has no COLMAP model (sparse/0/) and no transforms.json: nothing to undistort")
    undistorted = work / "undistorted"
    with quiet_pycolmap():
        pycolmap.undistort_images(undistorted, distorted, images, output_type="COLMAP", num_threads=1)
    os.rename(undistorted / "sparse", undistorted / "sparse-0")
    (undistorted / "sparse").mkdir()
    os.rename(undistorted / "sparse-0", undistorted / "sparse" / "0")
    return undistorted


__all__ = ["describe_distortion", "undistort_scene"]
