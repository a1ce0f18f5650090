"""Reading a sharp input scene: COLMAP (images/ + sparse/0) or nerfstudio transforms.json, with clear errors.

Every image is listed in capture order = sorted output name (<stem>.png). Poses are COLMAP cam_from_world
(x right, y down, z forward); transforms.json's OpenGL camera-to-world poses (x right, y up, z back) are converted.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io.colmap import ColmapModel, read_colmap
from ..io.errors import InputError
from ..io.images import read_image_float
from ..synth.cameras import world_to_camera
from ..synth.config import SynthSceneConfig, config_from_dict
from ..synth.points import SparsePoints

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiplying a camera-to-world pose flips its camera y and z axes (OpenGL <-> OpenCV)."""


@dataclass
class SourceScene:
    """A sharp scene, views sorted by output name (= capture order)."""

    root: Path
    kind: str  # "colmap" | "transforms"
    names: list[str]  # output names <stem>.png, sorted
    image_paths: list[Path]  # input files, aligned with names
    Ks: np.ndarray  # [V, 3, 3] pinhole intrinsics (COLMAP pixel convention)
    sizes: list[tuple[int, int]]  # V x (width, height)
    w2cs: np.ndarray  # [V, 4, 4] cam_from_world
    points: SparsePoints | None = None  # sparse points with observations (view indices into `names`)
    depth_paths: list[Path | None] = field(default_factory=list)  # depth/<stem>.npy z-depth maps where present
    synth_config: SynthSceneConfig | None = None  # set when scene.json says the scene is procedural


def _out_name(name: str) -> str:
    """Output file name for an input image name: sub-folders flattened with '__', extension .png."""
    p = Path(name)
    return "__".join([*p.parent.parts, p.stem]) + ".png" if p.parent.parts else p.stem + ".png"


def _synth_config(root: Path) -> SynthSceneConfig | None:
    meta_path = root / "scene.json"
    if not meta_path.is_file():
        return None
    try:
        meta = json.loads(meta_path.read_text(encoding="utf8"))
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read {meta_path}: {e}") from e
    if meta.get("generator") != "gsmsdr_ns.synth" or "config" not in meta:
        return None
    try:
        return config_from_dict(meta["config"], source=meta_path)
    except InputError as e:
        raise InputError(f"invalid generator config: {e}") from e


def _load_colmap(root: Path, model_dir: Path) -> SourceScene:
    model = read_colmap(model_dir, tracks=True, skip_unposed=True)
    for v, name in enumerate(model.names):
        if np.any(model.distortion[v] != 0):
            raise InputError(
                f"{model_dir}: image '{name}' has a {model.camera_models[v]} camera with distortion "
                f"{model.distortion[v].tolist()}; degrading needs undistorted pinhole images (`degrade_scene` and "
                "gsmsdr-degrade undistort such a scene first)"
            )
    order = sorted(range(len(model.names)), key=lambda v: _out_name(model.names[v]))
    names = [_out_name(model.names[v]) for v in order]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise InputError(f"{model_dir}: several images map to the same output name(s) {dup}")
    return SourceScene(
        root=root,
        kind="colmap",
        names=names,
        image_paths=[root / "images" / model.names[v] for v in order],
        Ks=model.Ks[order],
        sizes=[tuple(int(x) for x in model.sizes[v]) for v in order],
        w2cs=model.w2c[order],
        points=_sparse_points(model, order),
    )


def _sparse_points(model: ColmapModel, order: list[int]) -> SparsePoints | None:
    """The model's points seen by at least 2 of its posed views, with view indices in output-name ``order``."""
    pts = model.points
    view_of_row = np.empty(len(order), dtype=np.int64)
    view_of_row[np.asarray(order, dtype=np.int64)] = np.arange(len(order))
    seen = np.bincount(pts.obs_point, minlength=len(pts.xyz))
    keep = seen >= 2
    if not keep.any():
        return None
    new_index = np.cumsum(keep) - 1
    obs = keep[pts.obs_point]
    return SparsePoints(
        xyz=pts.xyz[keep],
        rgb=pts.rgb[keep],
        obs_point=new_index[pts.obs_point[obs]],
        obs_view=view_of_row[pts.obs_view[obs]],
        obs_uv=pts.obs_uv[obs],
    )


@dataclass
class TransformsFrame:
    """One frame of a transforms.json capture, as read (distortion not applied)."""

    name: str  # output name <stem>.png
    path: Path  # the image file
    K: np.ndarray  # [3, 3] pinhole intrinsics
    size: tuple[int, int]  # (width, height)
    w2c: np.ndarray  # [4, 4] cam_from_world
    distortion: list[float]  # k1, k2, k3, k4, p1, p2


def read_transforms_frames(root: Path, path: Path) -> list[TransformsFrame]:
    """The frames of a transforms.json capture sorted by output name, with their distortion; InputError naming the
    frame for bad entries."""
    try:
        meta = json.loads(path.read_text(encoding="utf8"))
    except (OSError, ValueError) as e:
        raise InputError(f"cannot parse {path}: {e}") from e
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not frames:
        raise InputError(f"{path} has no 'frames'")
    model = str(meta.get("camera_model", "OPENCV")).upper()
    if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise InputError(f"{path}: camera_model {model} is not supported (need a pinhole camera)")
    entries = []
    for i, fr in enumerate(frames):
        where = f"{path} frames[{i}]"
        get = lambda k: fr.get(k, meta.get(k))  # noqa: E731  (per-frame values override the shared ones)
        if "file_path" not in fr or "transform_matrix" not in fr:
            raise InputError(f"{where}: needs 'file_path' and 'transform_matrix'")
        img_path = root / fr["file_path"]
        if not img_path.suffix and not img_path.exists() and img_path.with_suffix(".png").exists():
            img_path = img_path.with_suffix(".png")  # Blender-style paths without extension
        dist = [float(get(k) or 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2")]
        w, h = get("w"), get("h")
        if w is None or h is None:
            w, h = read_image_float(img_path).shape[1::-1]
        w, h = int(w), int(h)
        fx, fy = get("fl_x"), get("fl_y")
        if fx is None and get("camera_angle_x") is not None:
            fx = 0.5 * w / math.tan(0.5 * float(get("camera_angle_x")))
        if fx is None:
            raise InputError(f"{where}: no focal length (fl_x or camera_angle_x)")
        fy = fx if fy is None else fy
        cx = get("cx") if get("cx") is not None else 0.5 * w
        cy = get("cy") if get("cy") is not None else 0.5 * h
        K = np.array([[float(fx), 0.0, float(cx)], [0.0, float(fy), float(cy)], [0.0, 0.0, 1.0]])
        c2w_gl = np.asarray(fr["transform_matrix"], dtype=np.float64)
        if c2w_gl.shape == (3, 4):
            c2w_gl = np.vstack([c2w_gl, [0.0, 0.0, 0.0, 1.0]])
        if c2w_gl.shape != (4, 4) or not np.isfinite(c2w_gl).all():
            raise InputError(f"{where}: transform_matrix must be a finite 4x4 matrix")
        w2c = world_to_camera(c2w_gl @ OPENGL_TO_OPENCV)
        entries.append(TransformsFrame(_out_name(img_path.name), img_path, K, (w, h), w2c, dist))
    entries.sort(key=lambda e: e.name)
    names = [e.name for e in entries]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise InputError(f"{path}: several frames map to the same output name(s) {dup}")
    return entries


def _load_transforms(root: Path, path: Path) -> SourceScene:
    entries = read_transforms_frames(root, path)
    for e in entries:
        if any(abs(d) > 0 for d in e.distortion):
            raise InputError(
                f"{path}: frame {e.path.name} has non-zero distortion {e.distortion}; degrading needs undistorted "
                "images (`degrade_scene` and gsmsdr-degrade undistort such a capture first)"
            )
    return SourceScene(
        root=root,
        kind="transforms",
        names=[e.name for e in entries],
        image_paths=[e.path for e in entries],
        Ks=np.stack([e.K for e in entries]),
        sizes=[e.size for e in entries],
        w2cs=np.stack([e.w2c for e in entries]),
    )


def load_source(root: str | Path, check_images: bool = True) -> SourceScene:
    """Read a sharp scene directory. COLMAP (sparse/0) wins over transforms.json when both exist.

    check_images=True decodes every image once so that a missing, empty, corrupted or wrongly sized file fails
    here, before any output is written.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"input scene {root} does not exist or is not a directory")
    if (root / "degradation.json").exists():
        raise InputError(
            f"{root} is already a degraded scene (it has degradation.json); degrade its sharp source instead"
        )
    model_dir = root / "sparse" / "0"
    if model_dir.is_dir():
        src = _load_colmap(root, model_dir)
    elif (root / "transforms.json").is_file():
        src = _load_transforms(root, root / "transforms.json")
    else:
        raise InputError(f"{root} has no COLMAP model (sparse/0/) and no transforms.json: nothing to read cameras from")
    if len(src.names) < 2:
        raise InputError(f"{root}: need at least 2 views, found {len(src.names)}")
    for name, path in zip(src.names, src.image_paths):
        if not path.is_file():
            listed = "sparse/0" if src.kind == "colmap" else "transforms.json"
            raise InputError(f"image {path.name} is listed in {listed} but missing: {path}")
    if check_images:
        for path, size in zip(src.image_paths, src.sizes):
            read_image_float(path, size)
    depth_dir = root / "depth"
    src.depth_paths = [
        (depth_dir / (Path(n).stem + ".npy")) if (depth_dir / (Path(n).stem + ".npy")).is_file() else None
        for n in src.names
    ]
    src.synth_config = _synth_config(root)
    if src.synth_config is not None:
        cfg = src.synth_config
        if any(tuple(s) != (cfg.width, cfg.height) for s in src.sizes):
            src.synth_config = None  # images were resized since generation: treat them as photos
    return src


def load_depth(path: Path, size: tuple[int, int]) -> np.ndarray:
    """A depth/<stem>.npy z-depth map -> float64 [H, W]; checks shape and positivity (inf allowed)."""
    try:
        d = np.load(path)
    except Exception as e:
        raise InputError(f"cannot read depth map {path}: {e}") from e
    if d.shape != (size[1], size[0]):
        raise InputError(f"depth map {path} is {d.shape} but the image is {size[1]}x{size[0]} (H x W)")
    d = d.astype(np.float64)
    if np.any(~(d > 0)):
        raise InputError(f"depth map {path} has zero, negative or NaN depths")
    return d
