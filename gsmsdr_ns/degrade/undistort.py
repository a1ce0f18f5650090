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

from ..io.colmap import read_colmap
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


def _transforms_reconstruction(root: Path, flat: Path):
    """(pycolmap.Reconstruction with OPENCV / FULL_OPENCV cameras, one per frame, and no points) of the
    transforms.json capture at ``root``; its image names are the frames' output names, linked in ``flat``."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    for i, frame in enumerate(read_transforms_frames(root, root / "transforms.json")):
        k1, k2, k3, k4, p1, p2 = frame.distortion
        fx, fy, cx, cy = frame.K[0, 0], frame.K[1, 1], frame.K[0, 2], frame.K[1, 2]
        if k3 == 0 and k4 == 0:
            model, params = "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
        else:
            model, params = "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, 0.0, 0.0]
        width, height = frame.size
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(model=model, width=width, height=height, params=params, camera_id=i + 1)
        )
        name = Path(frame.name).stem + frame.path.suffix  # the undistorter keeps the file format
        os.symlink(frame.path.absolute(), flat / name)
        image = pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=i + 1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(frame.w2c[:3, :4]))
    return rec


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
        _transforms_reconstruction(root, images).write(distorted)
    else:
        raise InputError(f"{root} has no COLMAP model (sparse/0/) and no transforms.json: nothing to undistort")
    undistorted = work / "undistorted"
    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 1  # warnings and errors only
    try:
        pycolmap.undistort_images(undistorted, distorted, images, output_type="COLMAP", num_threads=1)
    finally:
        pycolmap.logging.minloglevel = previous
    os.rename(undistorted / "sparse", undistorted / "sparse-0")
    (undistorted / "sparse").mkdir()
    os.rename(undistorted / "sparse-0", undistorted / "sparse" / "0")
    return undistorted


__all__ = ["describe_distortion", "undistort_scene"]
