"""Camera poses and intrinsics from a COLMAP model (pycolmap) or an LLFF ``poses_bounds.npy``, in file-name order.

``SceneCameras`` is the common result: one row per image, sorted by image name, camera-to-world in OpenCV axes
and the world frame of the source (COLMAP's: ``poses_bounds.npy`` is written from the same model, only with its
camera axes reordered), and intrinsics for the image size the source describes.

LLFF stores each camera as a 3x5 matrix ``[R | t | hwf]`` whose rotation columns are the camera's
(down, right, backwards) axes, i.e. OpenCV's ``[y, x, -z]``; ``hwf`` is (height, width, focal) in pixels, the
principal point is the image centre. Rows are in sorted-file-name order, followed by near / far depth bounds.
"""

from __future__ import annotations

import os
import shutil
import struct
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np

from gsmsdr_ns.data.errors import GSMSDRDataError

MODEL_FILES = ("cameras", "images", "points3D", "rigs", "frames")

# COLMAP camera model -> (fx, fy, cx, cy, k1, k2, k3, k4, p1, p2) from its parameter vector. Models with other
# distortion (fisheye, thin prism, ...) are refused: undistort the images with COLMAP first.
_PARAMS = {
    "SIMPLE_PINHOLE": lambda p: (p[0], p[0], p[1], p[2], 0, 0, 0, 0, 0, 0),
    "PINHOLE": lambda p: (p[0], p[1], p[2], p[3], 0, 0, 0, 0, 0, 0),
    "SIMPLE_RADIAL": lambda p: (p[0], p[0], p[1], p[2], p[3], 0, 0, 0, 0, 0),
    "RADIAL": lambda p: (p[0], p[0], p[1], p[2], p[3], p[4], 0, 0, 0, 0),
    "OPENCV": lambda p: (p[0], p[1], p[2], p[3], p[4], p[5], 0, 0, p[6], p[7]),
}


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

    def select(self, indices: Sequence[int]) -> "SceneCameras":
        idx = np.asarray(indices, dtype=np.int64)
        return SceneCameras(
            names=[self.names[i] for i in idx],
            c2w=self.c2w[idx],
            intrinsics=self.intrinsics[idx],
            sizes=self.sizes[idx],
            distortion=self.distortion[idx],
            source=self.source,
            bounds=None if self.bounds is None else self.bounds[idx],
            colmap_ids=None if self.colmap_ids is None else [self.colmap_ids[i] for i in idx],
        )


def has_colmap_model(recon_dir: Path) -> bool:
    recon_dir = Path(recon_dir)
    return any(
        (recon_dir / f"cameras{ext}").is_file() and (recon_dir / f"images{ext}").is_file() for ext in (".bin", ".txt")
    )


def _model_ext(recon_dir: Path) -> str:
    for ext in (".bin", ".txt"):
        if (recon_dir / f"cameras{ext}").is_file() and (recon_dir / f"images{ext}").is_file():
            return ext
    raise GSMSDRDataError(
        f"gsmsdr: no COLMAP model in '{recon_dir}' (expected cameras.bin + images.bin or cameras.txt + images.txt)."
    )


def _load_reconstruction(recon_dir: Path):
    """pycolmap.Reconstruction of ``recon_dir``; a missing points3D file counts as an empty point cloud.

    pycolmap refuses a model without a points3D file, which COLMAP exports and LLFF tools sometimes omit; such a
    model is read through a temporary folder that links the other files and adds an empty points3D file.
    """
    import pycolmap

    recon_dir = Path(recon_dir)
    ext = _model_ext(recon_dir)
    try:
        if (recon_dir / f"points3D{ext}").is_file():
            return pycolmap.Reconstruction(str(recon_dir))
        with tempfile.TemporaryDirectory(prefix="gsmsdr-colmap-") as tmp:
            for name in MODEL_FILES[:2] + MODEL_FILES[3:]:
                src = recon_dir / f"{name}{ext}"
                if src.is_file():
                    try:
                        os.symlink(src.resolve(), Path(tmp) / src.name)
                    except OSError:
                        shutil.copyfile(src, Path(tmp) / src.name)
            empty = Path(tmp) / f"points3D{ext}"
            empty.write_bytes(struct.pack("<Q", 0) if ext == ".bin" else b"")
            return pycolmap.Reconstruction(tmp)
    except GSMSDRDataError:
        raise
    except Exception as err:  # pycolmap raises ValueError / RuntimeError with its C++ check message
        raise GSMSDRDataError(
            f"gsmsdr: cannot read the COLMAP model in '{recon_dir}': {str(err).strip()[:400]}. The model files are "
            "truncated or malformed; re-export the model from COLMAP."
        ) from err


def _cam_from_world(image):
    cfw = image.cam_from_world  # a method in pycolmap >= 3.12 (the pose lives in the frame), an attribute before
    return cfw() if callable(cfw) else cfw


def read_colmap_model(recon_dir: Path) -> Tuple[SceneCameras, np.ndarray, np.ndarray]:
    """Cameras (see :func:`read_colmap_cameras`) and sparse points (see :func:`read_colmap_points`), one read."""
    recon_dir = Path(recon_dir)
    rec = _load_reconstruction(recon_dir)
    return (_cameras_of(rec, recon_dir), *_points_of(rec))


def read_colmap_cameras(recon_dir: Path) -> SceneCameras:
    """All posed images of a COLMAP model, sorted by image name, with validated intrinsics and poses."""
    return _cameras_of(_load_reconstruction(Path(recon_dir)), Path(recon_dir))


def read_colmap_points(recon_dir: Path) -> Tuple[np.ndarray, np.ndarray]:
    """Sparse points of a COLMAP model: xyz [P, 3] float64 (model world frame) and rgb [P, 3] uint8 (P may be 0)."""
    return _points_of(_load_reconstruction(Path(recon_dir)))


def _cameras_of(rec, recon_dir: Path) -> SceneCameras:
    rows = []
    for image_id, image in rec.images.items():
        if hasattr(image, "has_pose") and not image.has_pose:
            raise GSMSDRDataError(
                f"gsmsdr: image '{image.name}' (COLMAP image id {image_id} in '{recon_dir}') has no camera pose "
                "(not registered). Remove it from the model and the image folder, or re-run COLMAP's mapper."
            )
        pose = _cam_from_world(image)
        quat = np.asarray(pose.rotation.quat, dtype=np.float64)
        w2c = np.eye(4)
        w2c[:3, :4] = pose.matrix()
        if not np.all(np.isfinite(w2c)) or not np.all(np.isfinite(quat)) or np.linalg.norm(quat) < 1e-8:
            raise GSMSDRDataError(
                f"gsmsdr: image '{image.name}' (COLMAP image id {image_id} in '{recon_dir}') has a non-finite or "
                f"degenerate camera pose (quaternion {quat.tolist()}, translation {w2c[:3, 3].tolist()}). Remove the "
                "image from the reconstruction or re-run COLMAP's mapper."
            )
        cam = rec.cameras[image.camera_id]
        model = cam.model.name
        params = np.asarray(cam.params, dtype=np.float64)
        if model not in _PARAMS:
            raise GSMSDRDataError(
                f"gsmsdr: COLMAP camera {image.camera_id} in '{recon_dir}' uses the {model} model; supported are "
                f"{', '.join(_PARAMS)}. Undistort the images first (colmap image_undistorter)."
            )
        values = np.asarray(_PARAMS[model](params), dtype=np.float64)
        if not np.all(np.isfinite(values)) or values[0] <= 0 or values[1] <= 0 or cam.width <= 0 or cam.height <= 0:
            raise GSMSDRDataError(
                f"gsmsdr: COLMAP camera {image.camera_id} in '{recon_dir}' has invalid intrinsics (model {model}, "
                f"{cam.width}x{cam.height}, params {params.tolist()}): the focal length must be finite and positive."
            )
        rows.append((image.name, image_id, np.linalg.inv(w2c), values, (cam.width, cam.height)))
    if not rows:
        raise GSMSDRDataError(f"gsmsdr: the COLMAP model in '{recon_dir}' contains no images.")
    names = [r[0] for r in rows]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise GSMSDRDataError(f"gsmsdr: the COLMAP model in '{recon_dir}' lists image names twice: {dup[:5]}.")
    rows.sort(key=lambda r: r[0])
    values = np.stack([r[3] for r in rows])
    return SceneCameras(
        names=[r[0] for r in rows],
        c2w=np.stack([r[2] for r in rows]),
        intrinsics=values[:, :4].copy(),
        sizes=np.array([r[4] for r in rows], dtype=np.int64),
        distortion=values[:, 4:].copy(),
        source=str(recon_dir),
        colmap_ids=[int(r[1]) for r in rows],
    )


def _points_of(rec) -> Tuple[np.ndarray, np.ndarray]:
    points = rec.points3D
    if len(points) == 0:
        return np.zeros((0, 3), np.float64), np.zeros((0, 3), np.uint8)
    ids = sorted(points.keys())
    xyz = np.array([points[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([points[i].color for i in ids], dtype=np.uint8).reshape(-1, 3)
    finite = np.all(np.isfinite(xyz), axis=1)
    return xyz[finite], rgb[finite]


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
    """Cameras from an LLFF ``poses_bounds.npy`` whose rows belong to ``names`` (sorted file names), in order."""
    path = Path(path)
    try:
        array = np.load(path, allow_pickle=False)
    except Exception as err:
        raise GSMSDRDataError(f"gsmsdr: cannot read '{path}': {err}. Expected an N x 17 float array (LLFF).") from err
    if array.ndim != 2 or array.shape[1] != 17:
        raise GSMSDRDataError(
            f"gsmsdr: '{path}' has shape {tuple(array.shape)}, expected N x 17 (LLFF: a flattened 3x5 pose "
            "[R | t | hwf] and near / far bounds per image)."
        )
    names = list(names)
    if array.shape[0] != len(names):
        raise GSMSDRDataError(
            f"gsmsdr: '{path}' has poses for {array.shape[0]} images but the image folder has {len(names)} images. "
            "Its rows belong to the images sorted by file name: add or remove images until the counts match, or "
            "use a COLMAP model (sparse/0) instead."
        )
    array = array.astype(np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(array), axis=1))
    if bad.size:
        raise GSMSDRDataError(
            f"gsmsdr: '{path}' row {int(bad[0])} (image '{names[bad[0]]}') contains non-finite values."
        )
    poses = array[:, :15].reshape(-1, 3, 5)
    height, width, focal = poses[:, 0, 4], poses[:, 1, 4], poses[:, 2, 4]
    bad = np.flatnonzero((height <= 0) | (width <= 0) | (focal <= 0))
    if bad.size:
        i = int(bad[0])
        raise GSMSDRDataError(
            f"gsmsdr: '{path}' row {i} (image '{names[i]}') has hwf = ({height[i]}, {width[i]}, {focal[i]}); "
            "height, width and focal length must be positive."
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
    np.save(Path(path), poses_bounds_array(cameras, bounds))

