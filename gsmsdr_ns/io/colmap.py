"""The COLMAP model reader and writer (pycolmap), shared by the dataparsers, ``gsmsdr-degrade`` and ``gsmsdr-synth``.

:func:`read_colmap` returns a :class:`ColmapModel`: one row per posed image, sorted by image name, with
camera-to-world and world-to-camera matrices in OpenCV camera axes (x right, y down, z forward; COLMAP's world
frame), pinhole intrinsics ``fx, fy, cx, cy`` in pixels of the camera's size (pixel centres at +0.5), distortion in
nerfstudio's order, and the sparse points (optionally with their observations).

Before pycolmap parses a binary model its files are walked record by record, because pycolmap reports a
truncated file with a bare C++ message (or not at all, for ``cameras.bin``); an empty or truncated file is an
:class:`~gsmsdr_ns.io.errors.InputError` naming it.

:func:`write_colmap_model` writes a model (PINHOLE cameras, trivial rigs and frames) with pycolmap.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import struct
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, List, Optional, Sequence, Tuple

import numpy as np

from gsmsdr_ns.io.errors import InputError

MODEL_FILES = ("cameras", "images", "points3D", "rigs", "frames")
"""Files of a COLMAP model (``rigs`` / ``frames`` exist since COLMAP 3.12), each as ``.bin`` or ``.txt``."""

# COLMAP camera model -> (fx, fy, cx, cy, k1, k2, k3, k4, p1, p2) from its parameter vector. Other models are
# accepted only when their distortion parameters are all zero.
_PARAMS = {
    "SIMPLE_PINHOLE": lambda p: (p[0], p[0], p[1], p[2], 0, 0, 0, 0, 0, 0),
    "PINHOLE": lambda p: (p[0], p[1], p[2], p[3], 0, 0, 0, 0, 0, 0),
    "SIMPLE_RADIAL": lambda p: (p[0], p[0], p[1], p[2], p[3], 0, 0, 0, 0, 0),
    "RADIAL": lambda p: (p[0], p[0], p[1], p[2], p[3], p[4], 0, 0, 0, 0),
    "OPENCV": lambda p: (p[0], p[1], p[2], p[3], p[4], p[5], 0, 0, p[6], p[7]),
}
_REEXPORT = "Re-export the model from COLMAP (or re-run the tool that wrote it)."


@dataclass
class ColmapPoints:
    """Sparse points of a model (non-finite points dropped), optionally with their observations."""

    xyz: np.ndarray
    """[P, 3] float64 positions in the model's world frame."""
    rgb: np.ndarray
    """[P, 3] uint8 colours."""
    obs_point: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """[O] int64 point index of each observation (empty unless read with ``tracks=True``)."""
    obs_view: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """[O] int64 row (index into :attr:`ColmapModel.names`) of the image that observes it."""
    obs_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float64))
    """[O, 2] float64 pixel position of the observation."""


@dataclass
class ColmapModel:
    """A COLMAP model, one row per posed image, sorted by image name."""

    path: Path
    """The model folder (for messages)."""
    names: List[str]
    """Image names as COLMAP lists them (relative to the image folder)."""
    image_ids: List[int]
    """COLMAP image ids; the order of the rows is by name, never by id."""
    camera_models: List[str]
    """COLMAP camera model name of each image's camera (``PINHOLE``, ``OPENCV``, ...)."""
    w2c: np.ndarray
    """[N, 4, 4] float64 world-to-camera (COLMAP's cam_from_world)."""
    c2w: np.ndarray
    """[N, 4, 4] float64 camera-to-world (the inverse of ``w2c``)."""
    intrinsics: np.ndarray
    """[N, 4] float64 fx, fy, cx, cy in pixels of ``sizes``."""
    sizes: np.ndarray
    """[N, 2] int64 (width, height) of each image's camera."""
    distortion: np.ndarray
    """[N, 6] float64 k1, k2, k3, k4, p1, p2 (nerfstudio's order); zeros for pinhole cameras."""
    points: ColmapPoints
    """Sparse points (possibly none)."""
    unposed: List[str] = field(default_factory=list)
    """Images of the model without a pose (skipped when read with ``skip_unposed=True``)."""

    def __len__(self) -> int:
        return len(self.names)

    @property
    def Ks(self) -> np.ndarray:
        """[N, 3, 3] float64 pinhole calibration matrices."""
        fx, fy, cx, cy = self.intrinsics.T
        Ks = np.zeros((len(self.names), 3, 3))
        Ks[:, 0, 0], Ks[:, 1, 1], Ks[:, 0, 2], Ks[:, 1, 2], Ks[:, 2, 2] = fx, fy, cx, cy, 1.0
        return Ks


@contextlib.contextmanager
def quiet_pycolmap(verbose: bool = False) -> Iterator[None]:
    """pycolmap logs every step to stderr: inside this block only its warnings and errors (everything when
    ``verbose``); the previous level is restored after. Also usable as a function decorator."""
    import pycolmap

    previous = pycolmap.logging.minloglevel
    if not verbose:
        pycolmap.logging.minloglevel = 1
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous


def model_ext(model_dir: Path) -> Optional[str]:
    """``".bin"`` or ``".txt"`` for the format of the model in ``model_dir`` (cameras + images), None if none."""
    for ext in (".bin", ".txt"):
        if (Path(model_dir) / f"cameras{ext}").is_file() and (Path(model_dir) / f"images{ext}").is_file():
            return ext
    return None


def has_colmap_model(model_dir: Path) -> bool:
    """Whether ``model_dir`` holds a COLMAP model (cameras and images, binary or text)."""
    return model_ext(model_dir) is not None


def read_colmap(model_dir: Path, tracks: bool = False, skip_unposed: bool = False) -> ColmapModel:
    """Read and validate the COLMAP model in ``model_dir`` (see the module docstring).

    A missing ``points3D`` file counts as an empty point cloud. ``tracks`` also reads each point's observations
    (costly for big models). Images without a pose are an :class:`InputError` unless ``skip_unposed``. Errors
    name the file or image and say what to do: missing model, empty or truncated files, unsupported or invalid
    cameras, non-finite poses, duplicate names, no images.
    """
    model_dir = Path(model_dir)
    rec = _load_reconstruction(model_dir)
    rows, unposed = [], []
    for image_id in sorted(rec.images):
        image = rec.images[image_id]
        if not image.has_pose:
            if skip_unposed:
                unposed.append(image.name)
                continue
            raise InputError(
                f"gsmsdr: image '{image.name}' (COLMAP image id {image_id} in '{model_dir}') has no camera pose "
                "(not registered). Remove it from the model and the image folder, or re-run COLMAP's mapper."
            )
        rows.append((image.name, image_id, _w2c(image, image_id, model_dir), *_camera(rec, image, model_dir)))
    if not rows:
        raise InputError(
            f"gsmsdr: the COLMAP model in '{model_dir}' contains no posed images. Re-run COLMAP's mapper, or point "
            "to the right model folder."
        )
    names = [r[0] for r in rows]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise InputError(f"gsmsdr: the COLMAP model in '{model_dir}' lists image names twice: {dup[:5]}. {_REEXPORT}")
    rows.sort(key=lambda r: r[0])
    values = np.stack([r[4] for r in rows])
    w2c = np.stack([r[2] for r in rows])
    return ColmapModel(
        path=model_dir,
        names=[r[0] for r in rows],
        image_ids=[int(r[1]) for r in rows],
        camera_models=[r[3] for r in rows],
        w2c=w2c,
        c2w=np.stack([np.linalg.inv(m) for m in w2c]),
        intrinsics=values[:, :4].copy(),
        sizes=np.array([r[5] for r in rows], dtype=np.int64),
        distortion=values[:, 4:].copy(),
        points=_points(rec, {int(r[1]): v for v, r in enumerate(rows)}, tracks),
        unposed=unposed,
    )


def _w2c(image, image_id: int, model_dir: Path) -> np.ndarray:
    cfw = image.cam_from_world  # a method in pycolmap >= 3.12 (the pose lives in the frame), an attribute before
    pose = cfw() if callable(cfw) else cfw
    quat = np.asarray(pose.rotation.quat, dtype=np.float64)
    w2c = np.eye(4)
    w2c[:3, :4] = pose.matrix()
    if not np.all(np.isfinite(w2c)) or not np.all(np.isfinite(quat)) or np.linalg.norm(quat) < 1e-8:
        raise InputError(
            f"gsmsdr: image '{image.name}' (COLMAP image id {image_id} in '{model_dir}') has a non-finite or "
            f"degenerate camera pose (quaternion {quat.tolist()}, translation {w2c[:3, 3].tolist()}). Remove the "
            "image from the reconstruction or re-run COLMAP's mapper."
        )
    return w2c


def _camera(rec, image, model_dir: Path) -> Tuple[str, np.ndarray, Tuple[int, int]]:
    """(model name, [10] fx fy cx cy + distortion, (width, height)) of an image's camera, validated."""
    cam = rec.cameras[image.camera_id]
    model = cam.model.name
    params = np.asarray(cam.params, dtype=np.float64)
    if model in _PARAMS:
        values = np.asarray(_PARAMS[model](params), dtype=np.float64)
    else:
        extra = np.delete(params, list(cam.focal_length_idxs()) + list(cam.principal_point_idxs()))
        if np.any(extra != 0):
            raise InputError(
                f"gsmsdr: COLMAP camera {image.camera_id} in '{model_dir}' uses the {model} model with distortion "
                f"{extra.tolist()}; supported are {', '.join(_PARAMS)} (or any model with zero distortion). "
                "Undistort the images first (colmap image_undistorter)."
            )
        fx, fy = cam.focal_length_x, cam.focal_length_y
        values = np.array([fx, fy, cam.principal_point_x, cam.principal_point_y, 0, 0, 0, 0, 0, 0], np.float64)
    if not np.all(np.isfinite(values)) or values[0] <= 0 or values[1] <= 0 or cam.width <= 0 or cam.height <= 0:
        raise InputError(
            f"gsmsdr: COLMAP camera {image.camera_id} in '{model_dir}' has invalid intrinsics (model {model}, "
            f"{cam.width}x{cam.height}, params {params.tolist()}): the focal length must be finite and positive. "
            "Re-run COLMAP's mapper or fix cameras.txt."
        )
    return model, values, (int(cam.width), int(cam.height))


def _points(rec, view_of_id: dict, tracks: bool) -> ColmapPoints:
    ids = sorted(rec.points3D)
    if not ids:
        return ColmapPoints(np.zeros((0, 3), np.float64), np.zeros((0, 3), np.uint8))
    xyz = np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([rec.points3D[i].color for i in ids], dtype=np.uint8).reshape(-1, 3)
    finite = np.flatnonzero(np.all(np.isfinite(xyz), axis=1))
    points = ColmapPoints(xyz[finite], rgb[finite])
    if tracks:
        obs_point, obs_view, obs_uv = [], [], []
        for p, i in enumerate(finite):
            for element in rec.points3D[ids[i]].track.elements:
                if element.image_id in view_of_id:  # observations in skipped (unposed) images are dropped
                    obs_point.append(p)
                    obs_view.append(view_of_id[element.image_id])
                    obs_uv.append(rec.images[element.image_id].points2D[element.point2D_idx].xy)
        points.obs_point = np.asarray(obs_point, dtype=np.int64)
        points.obs_view = np.asarray(obs_view, dtype=np.int64)
        points.obs_uv = np.asarray(obs_uv, dtype=np.float64).reshape(-1, 2)
    return points


# --- validation and loading ----------------------------------------------------------------------------------


def _load_reconstruction(model_dir: Path):
    """pycolmap.Reconstruction of ``model_dir`` after the file checks; a missing points3D file reads as empty.

    pycolmap refuses a model without a points3D file, which some exporters omit; such a model is read through a
    temporary folder that links the other files and adds an empty points3D file.
    """
    import pycolmap

    ext = model_ext(model_dir)
    if ext is None:
        raise InputError(
            f"gsmsdr: no COLMAP model in '{model_dir}' (expected cameras.bin + images.bin or cameras.txt + "
            "images.txt). Run COLMAP on the images, or point to the folder that holds the model."
        )
    if ext == ".bin":
        check_binary_model(model_dir)
    try:
        if (model_dir / f"points3D{ext}").is_file():
            return pycolmap.Reconstruction(str(model_dir))
        with tempfile.TemporaryDirectory(prefix="gsmsdr-colmap-") as tmp:
            for name in MODEL_FILES[:2] + MODEL_FILES[3:]:
                src = model_dir / f"{name}{ext}"
                if src.is_file():
                    try:
                        os.symlink(src.resolve(), Path(tmp) / src.name)
                    except OSError:
                        shutil.copyfile(src, Path(tmp) / src.name)
            empty = Path(tmp) / f"points3D{ext}"
            empty.write_bytes(struct.pack("<Q", 0) if ext == ".bin" else b"")
            return pycolmap.Reconstruction(tmp)
    except Exception as err:  # pycolmap raises ValueError / RuntimeError / IndexError with its C++ message
        if ext == ".txt":
            _explain_text_model(model_dir)  # names the bad line when it can (C++ streams refuse 'nan')
        files = ", ".join(sorted(p.name for p in model_dir.iterdir() if p.suffix == ext))
        raise InputError(
            f"gsmsdr: cannot read the COLMAP model in '{model_dir}' ({files}): {str(err).strip()[:400]}. The model "
            f"files are malformed or do not belong together. {_REEXPORT}"
        ) from err


def _explain_text_model(model_dir: Path) -> None:
    """Raise an :class:`InputError` naming the camera or image line of a text model that has non-finite or
    unparsable numbers; return quietly if every line looks fine."""
    cameras = model_dir / "cameras.txt"
    for number, line in enumerate(cameras.read_text(encoding="utf8", errors="replace").splitlines(), 1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        try:
            values = [float(v) for v in fields[2:]]
        except ValueError:
            values = [float("nan")]
        if len(values) < 3 or not np.all(np.isfinite(values)) or values[2] <= 0:
            raise InputError(
                f"gsmsdr: COLMAP camera {fields[0]} in '{cameras}' (line {number}) has invalid intrinsics "
                f"({' '.join(fields[1:])}): size and parameters must be finite numbers, the focal length positive. "
                "Re-run COLMAP's mapper or fix cameras.txt."
            )
    images = model_dir / "images.txt"
    data_lines = [
        (number, line.split())
        for number, line in enumerate(images.read_text(encoding="utf8", errors="replace").splitlines(), 1)
        if not line.lstrip().startswith("#")
    ]
    for number, fields in data_lines[0::2]:  # image lines alternate with their 2D-point lines
        if len(fields) < 10:
            continue
        try:
            pose = np.array([float(v) for v in fields[1:8]])
        except ValueError:
            pose = np.full(7, np.nan)
        if not np.all(np.isfinite(pose)) or np.linalg.norm(pose[:4]) < 1e-8:
            raise InputError(
                f"gsmsdr: image '{' '.join(fields[9:])}' (COLMAP image id {fields[0]} in '{images}', line {number}) "
                f"has a non-finite or degenerate camera pose: qvec={fields[1:5]}, tvec={fields[5:8]}. Remove the "
                "image from the reconstruction or re-run COLMAP's mapper."
            )


class _Cursor:
    """Reads little-endian records from one binary model file; running past its end is an :class:`InputError`."""

    def __init__(self, path: Path):
        self.path, self.data, self.pos = path, path.read_bytes(), 0

    def take(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            raise InputError(
                f"gsmsdr: COLMAP file '{self.path}' is truncated: {what} ends past the end of the file "
                f"({len(self.data)} bytes). An interrupted copy or export? {_REEXPORT}"
            )
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return values

    def skip(self, size: int, what: str) -> None:
        self.take(f"{size}x", what)

    def name(self, what: str) -> None:
        end = self.data.find(b"\x00", self.pos)
        if end < 0:
            self.take(f"{len(self.data) - self.pos + 1}x", what)  # raises: the name never ends
        self.pos = end + 1


def check_binary_model(model_dir: Path) -> None:
    """Walk ``cameras.bin``, ``images.bin`` and ``points3D.bin`` record by record (without building anything).

    Raises :class:`InputError` naming the file when one is empty, shorter than its record count says, or names
    a camera model COLMAP does not know. ``rigs.bin`` / ``frames.bin`` are only checked for their header.
    """
    import pycolmap

    model_dir = Path(model_dir)
    for name in MODEL_FILES:
        path = model_dir / f"{name}.bin"
        if not path.is_file():
            continue
        if path.stat().st_size == 0:
            raise InputError(f"gsmsdr: COLMAP file '{path}' is empty (0 bytes). {_REEXPORT}")
        cursor = _Cursor(path)
        (count,) = cursor.take("Q", "the record count")
        if name == "cameras":
            for i in range(count):
                _, model_id, _, _ = cursor.take("iiQQ", f"camera {i + 1} of {count}")
                try:
                    num_params = len(
                        pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId(model_id), 1.0, 1, 1).params
                    )
                except Exception as err:
                    raise InputError(
                        f"gsmsdr: COLMAP file '{path}' names an unknown camera model id {model_id} (camera {i + 1} of "
                        f"{count}): the file is corrupt or from a newer COLMAP. {_REEXPORT}"
                    ) from err
                cursor.skip(8 * num_params, f"the parameters of camera {i + 1} of {count}")
        elif name == "images":
            for i in range(count):
                what = f"image {i + 1} of {count}"
                cursor.skip(4 + 7 * 8 + 4, what)
                cursor.name(what)
                (num_points2d,) = cursor.take("Q", what)
                cursor.skip(24 * num_points2d, what)
        elif name == "points3D":
            for i in range(count):
                what = f"point {i + 1} of {count}"
                cursor.skip(8 + 3 * 8 + 3 + 8, what)
                (track_length,) = cursor.take("Q", what)
                cursor.skip(8 * track_length, what)


# --- writing -------------------------------------------------------------------------------------------------


def build_reconstruction(
    names: Sequence[str],
    Ks: np.ndarray,
    sizes: Sequence[Tuple[int, int]],
    w2cs: np.ndarray,
    points: Optional[Any] = None,
    distortion: Optional[Sequence[Sequence[float]]] = None,
):
    """In-memory pycolmap.Reconstruction: image ids 1..V in the given order, identical intrinsics share a camera.

    Ks: [V, 3, 3] PINHOLE (no skew); sizes: V x (width, height); w2cs: [V, 4, 4] (or [V, 3, 4]) cam_from_world.
    ``points`` has ``xyz`` [P, 3], ``rgb`` [P, 3] uint8 and observations ``obs_point`` / ``obs_view`` [O] (view
    index) / ``obs_uv`` [O, 2] (``gsmsdr_ns.synth.points.SparsePoints`` or :class:`ColmapPoints`).
    ``distortion``: V x (k1, k2, k3, k4, p1, p2) (nerfstudio's transforms.json fields); an image with any non-zero
    term gets an OPENCV camera (FULL_OPENCV when k3 or k4 is set) instead of PINHOLE.
    """
    import pycolmap

    V = len(names)
    if not (len(Ks) == len(sizes) == len(w2cs) == V):
        raise ValueError("names, Ks, sizes and w2cs must have one entry per image")
    rec = pycolmap.Reconstruction()
    cam_ids: dict = {}
    view_cam = []
    for v, (K, (w, h)) in enumerate(zip(Ks, sizes)):
        if abs(K[0, 1]) > 1e-12:
            raise ValueError("PINHOLE cameras cannot have skew")
        model, params = "PINHOLE", [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]
        if distortion is not None and any(float(c) != 0.0 for c in distortion[v]):
            k1, k2, k3, k4, p1, p2 = (float(c) for c in distortion[v])
            if k3 == 0.0 and k4 == 0.0:
                model, params = "OPENCV", params + [k1, k2, p1, p2]
            else:
                model, params = "FULL_OPENCV", params + [k1, k2, p1, p2, k3, k4, 0.0, 0.0]
        key = (model, int(w), int(h), *params)
        if key not in cam_ids:
            cam_ids[key] = len(cam_ids) + 1
            cam = pycolmap.Camera(model=model, width=int(w), height=int(h), params=params, camera_id=cam_ids[key])
            rec.add_camera_with_trivial_rig(cam)
        view_cam.append(cam_ids[key])

    # Keypoints per image = the observations of sparse points in it; remember each one's index in its image.
    has_obs = points is not None and points.obs_view.size
    if has_obs:
        order = np.argsort(points.obs_view, kind="stable")
        counts = np.bincount(points.obs_view, minlength=V)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        point2d_idx = np.empty_like(points.obs_view)
        point2d_idx[order] = np.arange(order.size) - starts[points.obs_view[order]]
    for v in range(V):
        kps = points.obs_uv[order[starts[v] : starts[v] + counts[v]]] if has_obs else np.zeros((0, 2))
        image = pycolmap.Image(
            name=names[v], keypoints=np.asarray(kps, np.float64), camera_id=view_cam[v], image_id=v + 1
        )
        pose = pycolmap.Rigid3d(np.asarray(w2cs[v], np.float64)[:3, :4])
        rec.add_image_with_trivial_frame(image, pose)

    if points is not None and points.xyz.shape[0]:
        splits = np.cumsum(np.bincount(points.obs_point, minlength=points.xyz.shape[0]))[:-1]
        for p, (views, idxs) in enumerate(zip(np.split(points.obs_view, splits), np.split(point2d_idx, splits))):
            track = pycolmap.Track([pycolmap.TrackElement(int(v) + 1, int(j)) for v, j in zip(views, idxs)])
            rec.add_point3D(points.xyz[p], track, points.rgb[p])
        rec.update_point_3d_errors()  # exact projections: errors ~0, but nerfstudio reads the field
    return rec


def write_colmap_model(
    model_dir: Path,
    names: Sequence[str],
    Ks: np.ndarray,
    sizes: Sequence[Tuple[int, int]],
    w2cs: np.ndarray,
    points: Optional[Any] = None,
    distortion: Optional[Sequence[Sequence[float]]] = None,
):
    """Write cameras/images/points3D.bin (plus pycolmap 4's rigs/frames.bin) into ``model_dir``; see
    :func:`build_reconstruction` for the arguments. Returns the reconstruction."""
    rec = build_reconstruction(names, Ks, sizes, w2cs, points, distortion)
    model_dir = Path(model_dir)
    model_dir.mkdir(parents=True, exist_ok=True)
    rec.write(str(model_dir))
    return rec
