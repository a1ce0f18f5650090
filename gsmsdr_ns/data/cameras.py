"""Scene cameras in file-name order, from a COLMAP model (read by ``gsmsdr_ns.io.colmap``) or an LLFF
``poses_bounds.npy``; intrinsics rescaled to the image files they are paired with.

``SceneCameras`` is the common result: one row per image, sorted by image name, camera-to-world in OpenCV axes
and the world frame of the source (COLMAP's: ``poses_bounds.npy`` is written from the same model, only with its
camera axes reordered), and intrinsics for the image size the source describes.

LLFF stores each camera as a 3x5 matrix ``[R | t | hwf]`` whose rotation columns are the camera's
(down, right, backwards) axes, i.e. OpenCV's ``[y, x, -z]``; ``hwf`` is (height, width, focal) in pixels, the
principal point is the image centre. Rows are in sorted-file-name order, followed by near / far depth bounds.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np

from gsmsdr_ns.data.poses import check_rotations
from gsmsdr_ns.io.atomic import write_file_atomic
from gsmsdr_ns.io.colmap import ColmapModel
from gsmsdr_ns.io.errors import InputError


@dataclass
class SceneCameras:
    """Cameras of a scene, one row per image, sorted by image name."""

    names: List[str]
    """Image names as the source lists them (COLMAP image names, or the file names for poses_bounds.npy)."""
    c2w: np.ndarray
    """[N, 4, 4] float64 camera-to-world, OpenCV camera axes (x right, y down, z forward)."""
    intrinsics: np.ndarray
    """[N, 4] float64 fx, fy, cx, cy in pixels of ``sizes``."""
    sizes: np.ndarray
    """[N, 2] int64 (width, height) that the intrinsics refer to."""
    distortion: np.ndarray
    """[N, 6] float64 k1, k2, k3, k4, p1, p2 (nerfstudio's order); zeros for pinhole cameras."""
    source: str
    """Where the cameras came from, for messages ("sparse/0", "poses_bounds.npy")."""
    bounds: Optional[np.ndarray] = None
    """[N, 2] near / far depths (poses_bounds.npy only)."""
    colmap_ids: Optional[List[int]] = field(default=None)
    """COLMAP image ids (COLMAP models only); the order of the rows is by name, never by id."""

    def __len__(self) -> int:
        return len(self.names)


def cameras_from_colmap(model: ColmapModel) -> SceneCameras:
    """The :class:`SceneCameras` of a COLMAP model read by :func:`gsmsdr_ns.io.colmap.read_colmap` (same rows).

    pycolmap builds each rotation from the quaternion as written, so a quaternion that is not a unit quaternion
    gives a scaled rotation: every rotation must pass :func:`~gsmsdr_ns.data.poses.check_rotations` (1e-3).
    """
    check_rotations(
        model.c2w[:, :3, :3],
        model.path,
        [f"image '{name}'" for name in model.names],
        "Re-run COLMAP's mapper (or re-export the model); a pose's quaternion must be a unit quaternion.",
    )
    return SceneCameras(
        names=list(model.names),
        c2w=model.c2w,
        intrinsics=model.intrinsics,
        sizes=model.sizes,
        distortion=model.distortion,
        source=str(model.path),
        colmap_ids=list(model.image_ids),
    )


def fit_intrinsics(
    intrinsics: Sequence[float], model_size: Tuple[int, int], image_size: Tuple[int, int], what: str
) -> np.ndarray:
    """Rescale ``fx, fy, cx, cy`` given for ``model_size`` (w, h) to an image of ``image_size`` (w, h).

    A downscaled copy may round its size either way, so the two axes may scale by slightly different amounts; a
    different aspect ratio (beyond that rounding) means the image is not a rescaled copy of what the cameras
    describe, and is an error naming ``what``.
    """
    (w0, h0), (w, h) = model_size, image_size
    sx, sy = w / w0, h / h0
    # Rounding a downscaled size moves it by < 1 px on each axis.
    if abs(sx - sy) > 1.0 / w0 + 1.0 / h0 + 1.0 / max(min(w, h), 1):
        raise InputError(
            f"gsmsdr: {what} is {w}x{h} px but its camera is {w0}x{h0} px, and {w}x{h} is not a rescaled copy of "
            f"{w0}x{h0} (aspect ratios {w / h:.4f} vs {w0 / h0:.4f}). Use images of the size the camera poses were "
            "computed on (or a downscaled copy of them), or re-run COLMAP on these images."
        )
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    return np.array([fx * sx, fy * sy, cx * sx, cy * sy], dtype=np.float64)


def check_same_scale(
    files: Sequence[Path], model_sizes: np.ndarray, image_sizes: Sequence[Tuple[int, int]], source: str
) -> None:
    """Every image of one folder must be the same rescaled copy of its camera (all full size, or all ``images_N``).

    ``model_sizes`` [N, 2] are the cameras' (width, height), ``image_sizes`` the files' (same order). The folder's
    scale is the most common ``image / camera`` ratio (ties: the first file in order); a file more than 1 px
    (rounding) away from its camera size times that scale is an :class:`InputError` naming the file, its size and
    the expected size. A half-size view among full-size ones would otherwise train with rescaled intrinsics at
    another resolution than the rest of its folder.
    """
    if len(files) < 2:
        return
    model = np.asarray(model_sizes, dtype=np.float64).reshape(-1, 2)
    image = np.asarray(image_sizes, dtype=np.float64).reshape(-1, 2)
    ratios = image / model  # [N, 2]
    # the folder's scale: the file ratio that the most files match within rounding (a small scale such as 1/16 of a
    # 4032 px camera must not be rounded itself: 0.062 instead of 0.0625 is 2 px off)
    candidates = [np.asarray(r) for r, _ in Counter(map(tuple, np.round(ratios, 6))).most_common(20)]
    fits = [int(np.all(np.abs(image - model * r) <= 1.0, axis=1).sum()) for r in candidates]
    scale = candidates[int(np.argmax(fits))]
    expected = model * scale
    bad = np.flatnonzero(np.any(np.abs(image - expected) > 1.0, axis=1))
    if bad.size == 0:
        return
    i = int(bad[0])
    (w, h), (ew, eh), (w0, h0) = image[i].astype(int), np.round(expected[i]).astype(int), model[i].astype(int)
    others = "the size of their cameras" if np.allclose(scale, 1.0) else f"{scale[0]:.3g}x the size of their cameras"
    raise InputError(
        f"gsmsdr: image file '{files[i]}' is {w}x{h} px but the other images of '{Path(files[i]).parent}' are "
        f"{others}, so it should be {ew}x{eh} px (its camera in {source} is "
        f"{w0}x{h0} px). All images of a folder must have matching sizes: store a lower-resolution view upsampled "
        f"back to {ew}x{eh} (as gsmsdr-degrade does, with its mixres factor in degradation.json), or replace it."
    )


# --- LLFF poses_bounds.npy -----------------------------------------------------------------------------------


def llff_to_opencv(poses: np.ndarray) -> np.ndarray:
    """[N, 3, >=4] LLFF ``[down, right, back | t]`` -> [N, 4, 4] OpenCV camera-to-world."""
    c2w = np.tile(np.eye(4), (poses.shape[0], 1, 1))
    c2w[:, :3, 0] = poses[:, :, 1]
    c2w[:, :3, 1] = poses[:, :, 0]
    c2w[:, :3, 2] = -poses[:, :, 2]
    c2w[:, :3, 3] = poses[:, :, 3]
    return c2w


def opencv_to_llff(c2w: np.ndarray) -> np.ndarray:
    """[N, 4, 4] (or [N, 3, 4]) OpenCV camera-to-world -> [N, 3, 4] LLFF ``[down, right, back | t]``."""
    c2w = np.asarray(c2w, dtype=np.float64)
    return np.stack([c2w[:, :3, 1], c2w[:, :3, 0], -c2w[:, :3, 2], c2w[:, :3, 3]], axis=2)


def read_poses_bounds(path: Path, names: Sequence[str]) -> SceneCameras:
    """Cameras from an LLFF ``poses_bounds.npy`` whose rows belong to ``names`` (sorted file names), in order.

    Every row's rotation must be orthonormal with det +1 within ``gsmsdr_ns.data.poses.ROTATION_TOLERANCE``
    (1e-3, see :func:`~gsmsdr_ns.data.poses.check_rotations`); :class:`InputError` naming the row and image if not.
    """
    path = Path(path)
    try:
        array = np.load(path, allow_pickle=False)
    except Exception as err:
        raise InputError(f"gsmsdr: cannot read '{path}': {err}. Expected an N x 17 float array (LLFF).") from err
    if array.ndim != 2 or array.shape[1] != 17:
        raise InputError(
            f"gsmsdr: '{path}' has shape {tuple(array.shape)}, expected N x 17 (LLFF: a flattened 3x5 pose "
            "[R | t | hwf] and near / far bounds per image)."
        )
    names = list(names)
    if array.shape[0] != len(names):
        raise InputError(
            f"gsmsdr: '{path}' has poses for {array.shape[0]} images but the image folder has {len(names)} images. "
            "Its rows belong to the images sorted by file name: add or remove images until the counts match, or "
            "use a COLMAP model (sparse/0) instead."
        )
    array = array.astype(np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(array), axis=1))
    if bad.size:
        raise InputError(f"gsmsdr: '{path}' row {int(bad[0])} (image '{names[bad[0]]}') contains non-finite values.")
    poses = array[:, :15].reshape(-1, 3, 5)
    height, width, focal = poses[:, 0, 4], poses[:, 1, 4], poses[:, 2, 4]
    bad = np.flatnonzero((height <= 0) | (width <= 0) | (focal <= 0))
    if bad.size:
        i = int(bad[0])
        raise InputError(
            f"gsmsdr: '{path}' row {i} (image '{names[i]}') has hwf = ({height[i]}, {width[i]}, {focal[i]}); "
            "height, width and focal length must be positive."
        )
    check_rotations(
        poses[:, :, :3],
        path,
        [f"row {i} (image '{name}')" for i, name in enumerate(names)],
        "Each row's first three columns must be a rotation (LLFF's [down, right, back] camera axes): re-create the "
        "file from the COLMAP model (gsmsdr-degrade writes one) or fix that row.",
    )
    intrinsics = np.stack([focal, focal, width / 2.0, height / 2.0], axis=1)
    sizes = np.stack([np.round(width), np.round(height)], axis=1).astype(np.int64)
    return SceneCameras(
        names=names,
        c2w=llff_to_opencv(poses),
        intrinsics=intrinsics,
        sizes=sizes,
        distortion=np.zeros((len(names), 6)),
        source=str(path),
        bounds=array[:, 15:17].copy(),
    )


def llff_poses_bounds_rows(c2w: np.ndarray, sizes: np.ndarray, focal: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """The N x 17 LLFF ``poses_bounds`` array: per camera a flattened 3x5 ``[down, right, back | t | hwf]``, then
    near, far (the inverse of `read_poses_bounds`).

    As in LLFF's imgs2poses: columns (x, y, z) of the OpenCV camera-to-world become (y, x, -z) (`opencv_to_llff`)
    and hwf = (height, width, focal).

    Args:
        c2w: [N, 4, 4] (or [N, 3, 4]) OpenCV camera-to-world. sizes: [N, 2] (width, height) in pixels.
        focal: [N] focal length in pixels (fx). bounds: [N, 2] near / far depths.
    """
    llff = opencv_to_llff(c2w)
    sizes = np.asarray(sizes).reshape(-1, 2)
    hwf = np.stack([sizes[:, 1], sizes[:, 0], np.asarray(focal).reshape(-1)], axis=1).astype(np.float64)
    poses = np.concatenate([llff, hwf[:, :, None]], axis=2)
    return np.concatenate([poses.reshape(-1, 15), np.asarray(bounds, dtype=np.float64).reshape(-1, 2)], axis=1)


def poses_bounds_array(cameras: SceneCameras, bounds: np.ndarray) -> np.ndarray:
    """The N x 17 LLFF array for ``cameras`` (rows in their order; focal = fx) with [N, 2] near / far ``bounds``."""
    return llff_poses_bounds_rows(cameras.c2w, cameras.sizes, cameras.intrinsics[:, 0], bounds)


def depth_bounds(cameras: SceneCameras, xyz: np.ndarray, default: Tuple[float, float] = (0.1, 100.0)) -> np.ndarray:
    """LLFF-style near / far per camera: 0.1 and 99.9 percentiles of the depths of the points in front of it."""
    bounds = np.tile(np.asarray(default, dtype=np.float64), (len(cameras), 1))
    if xyz.shape[0] == 0:
        return bounds
    for i, c2w in enumerate(cameras.c2w):
        depth = (xyz - c2w[:3, 3]) @ c2w[:3, 2]
        depth = depth[depth > 0]
        if depth.size:
            bounds[i] = np.percentile(depth, 0.1), np.percentile(depth, 99.9)
    return bounds


def write_poses_bounds(path: Path, cameras: SceneCameras, bounds: Optional[np.ndarray] = None) -> None:
    """Write ``poses_bounds.npy`` for ``cameras`` (which must already be in sorted-file-name order)."""
    if list(cameras.names) != sorted(cameras.names):
        raise ValueError("poses_bounds.npy rows must be in sorted-file-name order")
    if bounds is None:
        bounds = cameras.bounds if cameras.bounds is not None else depth_bounds(cameras, np.zeros((0, 3)))
    array = poses_bounds_array(cameras, bounds)
    write_file_atomic(Path(path), lambda tmp: np.save(tmp, array))
