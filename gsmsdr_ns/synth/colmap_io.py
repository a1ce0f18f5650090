"""COLMAP model I/O through pycolmap (4.x API: cameras get a trivial rig, images a trivial frame).

Conventions: w2c is COLMAP's cam_from_world (x right, y down, z forward); pixel centres at +0.5;
image ids are 1..V in capture order; identical intrinsics share one camera.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pycolmap

from .points import SparsePoints


def _cam_from_world(image: pycolmap.Image) -> pycolmap.Rigid3d:
    # pycolmap >= 3.12 made this a method (pose lives in the frame); older versions exposed an attribute.
    cfw = image.cam_from_world
    return cfw() if callable(cfw) else cfw


def build_reconstruction(
    names: Sequence[str],
    Ks: np.ndarray,
    sizes: Sequence[tuple[int, int]],
    w2cs: np.ndarray,
    points: SparsePoints | None = None,
) -> pycolmap.Reconstruction:
    """In-memory reconstruction. Ks: [V, 3, 3]; sizes: V x (width, height); w2cs: [V, 4, 4] (or [V, 3, 4])."""
    V = len(names)
    if not (len(Ks) == len(sizes) == len(w2cs) == V):
        raise ValueError("names, Ks, sizes and w2cs must have one entry per image")
    rec = pycolmap.Reconstruction()
    cam_ids: dict[tuple, int] = {}
    view_cam = []
    for K, (w, h) in zip(Ks, sizes, strict=False):
        if abs(K[0, 1]) > 1e-12:
            raise ValueError("PINHOLE cameras cannot have skew")
        key = (int(w), int(h), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        if key not in cam_ids:
            cam_ids[key] = len(cam_ids) + 1
            cam = pycolmap.Camera(
                model="PINHOLE", width=key[0], height=key[1], params=list(key[2:]), camera_id=cam_ids[key]
            )
            rec.add_camera_with_trivial_rig(cam)
        view_cam.append(cam_ids[key])

    # Keypoints per image = the observations of sparse points in it; remember each one's index in its image.
    if points is not None and points.obs_view.size:
        order = np.argsort(points.obs_view, kind="stable")
        counts = np.bincount(points.obs_view, minlength=V)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        point2d_idx = np.empty_like(points.obs_view)
        point2d_idx[order] = np.arange(order.size) - starts[points.obs_view[order]]
    for v in range(V):
        if points is not None and points.obs_view.size:
            kps = points.obs_uv[order[starts[v] : starts[v] + counts[v]]]
        else:
            kps = np.zeros((0, 2))
        image = pycolmap.Image(
            name=names[v], keypoints=np.asarray(kps, np.float64), camera_id=view_cam[v], image_id=v + 1
        )
        pose = pycolmap.Rigid3d(np.asarray(w2cs[v], np.float64)[:3, :4])
        rec.add_image_with_trivial_frame(image, pose)

    if points is not None and points.xyz.shape[0]:
        splits = np.cumsum(np.bincount(points.obs_point, minlength=points.xyz.shape[0]))[:-1]
        for p, (views, idxs) in enumerate(
            zip(np.split(points.obs_view, splits), np.split(point2d_idx, splits), strict=False)
        ):
            track = pycolmap.Track(
                [pycolmap.TrackElement(int(v) + 1, int(j)) for v, j in zip(views, idxs, strict=False)]
            )
            rec.add_point3D(points.xyz[p], track, points.rgb[p])
        rec.update_point_3d_errors()  # exact projections: errors ~0, but nerfstudio reads the field
    return rec


def write_colmap_model(
    model_dir: str | Path,
    names: Sequence[str],
    Ks: np.ndarray,
    sizes: Sequence[tuple[int, int]],
    w2cs: np.ndarray,
    points: SparsePoints | None = None,
) -> pycolmap.Reconstruction:
    """Write cameras/images/points3D(.bin, plus pycolmap 4's rigs/frames.bin) into model_dir."""
    rec = build_reconstruction(names, Ks, sizes, w2cs, points)
    model_dir = Path(model_dir)
    model_dir.mkdir(parents=True, exist_ok=True)
    rec.write(str(model_dir))
    return rec


def read_colmap_cameras(model_dir: str | Path) -> dict[str, np.ndarray | list]:
    """Cameras of a model in image-id order: names [V], Ks [V, 3, 3], sizes V x (w, h), w2cs [V, 4, 4]."""
    rec = pycolmap.Reconstruction(str(model_dir))
    names, Ks, sizes, w2cs = [], [], [], []
    for image_id in sorted(rec.images.keys()):
        image = rec.images[image_id]
        cam = rec.cameras[image.camera_id]
        w2c = np.eye(4)
        w2c[:3, :4] = _cam_from_world(image).matrix()
        names.append(image.name)
        Ks.append(cam.calibration_matrix())
        sizes.append((cam.width, cam.height))
        w2cs.append(w2c)
    return {"names": names, "Ks": np.stack(Ks), "sizes": sizes, "w2cs": np.stack(w2cs)}
