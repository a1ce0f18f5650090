"""`gsmsdr-bench sfm`: how well ``gsmsdr-process`` poses sharp and degraded real photos, against LLFF's poses.

For a photo set with LLFF ``poses_bounds.npy`` (the fern), each row runs ``gsmsdr-process`` on one version of the
photos and compares the registered camera centres and rotations with LLFF's after a similarity alignment:

* ``sharp``: the photos themselves;
* a ``gsmsdr-degrade`` preset (``motion-strong``, ``defocus-strong``, ...): the photos posed and undistorted once
  (``gsmsdr-process``, default options), degraded with the preset (the first photo stays sharp, as
  ``gsmsdr-degrade`` keeps a held-out view; the other photos are degraded), and the degraded photos ALONE processed
  again: the poses a user gets from a set of blurred photos.

Each version is processed with SIFT domain-size pooling on and off (``ProcessConfig.domain_size_pooling``).
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np


def llff_cameras_opencv(poses_bounds: Path) -> Tuple[np.ndarray, np.ndarray]:
    """Camera centres [N, 3] and camera-to-world rotations [N, 3, 3] (OpenCV axes) from LLFF poses_bounds.npy."""
    from gsmsdr_ns.data.cameras import llff_to_opencv

    c2w = llff_to_opencv(np.load(poses_bounds)[:, :15].reshape(-1, 3, 5))
    return c2w[:, :3, 3], c2w[:, :3, :3]


def similarity_fit(source: np.ndarray, target: np.ndarray) -> Tuple[float, np.ndarray, np.ndarray]:
    """Umeyama's similarity (scale, rotation [3, 3], translation [3]) minimising |scale R source + t - target|^2.

    source, target: [N, 3] corresponding points, N >= 3 not all on a line."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    xs, xt = source - mu_s, target - mu_t
    u, sigma, vt = np.linalg.svd(xt.T @ xs / len(source))
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ sign @ vt
    scale = float(np.trace(np.diag(sigma) @ sign) / xs.var(0).sum())
    return scale, rotation, mu_t - scale * rotation @ mu_s


def rotation_angle_deg(rotations: np.ndarray) -> np.ndarray:
    """Angles [N] of rotation matrices [N, 3, 3] in degrees."""
    cos = (np.trace(rotations, axis1=1, axis2=2) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


@dataclass
class PoseErrors:
    """Registered cameras against reference ones after the best similarity alignment."""

    max_centre: float
    """Largest camera-centre error, as a fraction of the reference trajectory's diameter."""
    max_rotation_deg: float
    """Largest rotation error in degrees."""


def pose_errors(c2w: np.ndarray, ref_centres: np.ndarray, ref_rotations: np.ndarray) -> PoseErrors:
    """c2w: [N, 3 or 4, 4] registered camera-to-world (OpenCV axes); ref_centres [N, 3], ref_rotations [N, 3, 3]:
    the same cameras' reference poses, in the same order."""
    centres, rotations = c2w[:, :3, 3], c2w[:, :3, :3]
    scale, rotation, translation = similarity_fit(centres, ref_centres)
    aligned = scale * centres @ rotation.T + translation
    diameter = float(np.max(np.linalg.norm(ref_centres[:, None] - ref_centres[None], axis=-1)))
    centre = np.linalg.norm(aligned - ref_centres, axis=1) / diameter
    angle = rotation_angle_deg(np.swapaxes(ref_rotations, 1, 2) @ rotation @ rotations)
    return PoseErrors(float(centre.max()), float(angle.max()))


@dataclass
class SfmRow:
    """One ``gsmsdr-process`` run of the benchmark."""

    photos: str
    """"sharp" or the gsmsdr-degrade preset."""
    pooling: bool
    registered: int
    total: int
    seconds: float
    """Wall time of ``process_photos`` (SfM, undistortion and writing)."""
    focal: float
    """Focal length (px) of the undistorted pinhole camera."""
    errors: Optional[PoseErrors]
    """None when fewer than 3 photos registered."""
    largest_blur_px: float = 0.0
    """Longest shake path or widest circle of confusion (px) among the photos (gsmsdr-degrade's records)."""


def _process(images: Path, out: Path, pooling: bool, threads: int, seed: int):
    """``gsmsdr-process`` of ``images`` into ``out`` -> (its ProcessResult, wall seconds)."""
    from gsmsdr_ns.io.colmap import quiet_pycolmap
    from gsmsdr_ns.process import ProcessConfig, process_photos

    config = ProcessConfig(domain_size_pooling=pooling, num_threads=threads, seed=seed)
    with quiet_pycolmap():
        start = time.perf_counter()
        result = process_photos(images, out, config, overwrite=True)
        return result, time.perf_counter() - start


def largest_blur_px(records: dict) -> float:
    """Longest shake path or widest circle of confusion (px) over a gsmsdr-degrade ``degradation.json``."""
    sizes = [0.0]
    for image in records["images"].values():
        effects = image.get("effects", {})
        sizes.append(float(effects.get("motion", {}).get("blur_px", 0.0)))
        sizes.append(float(effects.get("defocus", {}).get("max_coc_px", 0.0)))
    return max(sizes)


def _degraded_photos(photos: Path, preset: str, work: Path, seed: int) -> Tuple[Path, float]:
    """A folder with ``photos`` posed once, degraded by ``preset``, the held-out sharp photo left out; and the
    largest blur (px) among them."""
    from gsmsdr_ns.bench.real_scenes import RealSceneSpec, degrade_config
    from gsmsdr_ns.degrade import degrade_scene
    from gsmsdr_ns.degrade.pipeline import split_of
    from gsmsdr_ns.io.images import list_images

    hold = max(2, len(list_images(photos)))  # only the first photo stays sharp
    config = degrade_config(RealSceneSpec(preset=preset, seed=seed, hold=hold))
    posed = work / f"posed-{photos.parent.name}-{photos.name}"  # reused by the other presets of the same photos
    if not (posed / "sparse" / "0").is_dir():
        _process(photos, posed, pooling=False, threads=-1, seed=seed)
    degraded = work / f"degraded-{Path(preset).stem}"
    degrade_scene(posed, degraded, config, overwrite=True, preset=Path(preset).stem)
    only = work / f"photos-{Path(preset).stem}"
    shutil.rmtree(only, ignore_errors=True)
    only.mkdir(parents=True)
    for index, name in enumerate(sorted(p.name for p in (degraded / "images").iterdir())):
        if split_of(index, config.hold) == "train":
            shutil.copy2(degraded / "images" / name, only / name)
    records = json.loads((degraded / "degradation.json").read_text(encoding="utf8"))
    return only, largest_blur_px(records)


def run_sfm_benchmark(photos: Path, poses_bounds: Path, versions: Sequence[str], pooling: Sequence[bool],
                      work: Path, threads: int = -1, seed: int = 0, log=print) -> List[SfmRow]:  # fmt: skip
    """One :class:`SfmRow` per (version, pooling). photos: the folder of photos whose sorted order is
    ``poses_bounds.npy``'s; versions: "sharp" and/or gsmsdr-degrade presets; work: scratch folder (the photos'
    first posing is kept there and reused by later runs on the same photos)."""
    from gsmsdr_ns.bench.real_scenes import RealSceneSpec, degrade_config
    from gsmsdr_ns.io.colmap import read_colmap
    from gsmsdr_ns.io.images import list_images

    for version in versions:  # a bad preset is reported before any row runs
        if version != "sharp":
            degrade_config(RealSceneSpec(preset=version))
    photos, work = Path(photos), Path(work)
    names = list_images(photos)
    ref_centres, ref_rotations = llff_cameras_opencv(poses_bounds)
    if len(ref_centres) != len(names):
        raise ValueError(f"{poses_bounds} has {len(ref_centres)} poses for {len(names)} photos in {photos}")
    row_of: Dict[str, int] = {n: i for i, n in enumerate(names)}
    rows = []
    for version in versions:
        images, blur = (photos, 0.0) if version == "sharp" else _degraded_photos(photos, version, work, seed)
        total = len(list_images(images))
        for pool in pooling:
            out = work / f"scene-{Path(version).stem}-pooling-{'on' if pool else 'off'}"
            result, seconds = _process(images, out, pool, threads, seed)
            model = read_colmap(out / "sparse" / "0")
            index = [row_of[n] for n in model.names]
            errors = (pose_errors(model.c2w, ref_centres[index], ref_rotations[index])
                      if len(index) >= 3 else None)  # fmt: skip
            row = SfmRow(version, pool, len(result.registered), total, seconds, float(model.intrinsics[0, 0]),
                         errors, blur)  # fmt: skip
            log(format_row(row))
            rows.append(row)
    return rows


HEADER = ("| photos | largest blur px | domain-size pooling | registered | SfM s | f px (undistorted) | max centre "
          "error, % of the trajectory diameter | max rotation error ° |\n"
          "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: |")  # fmt: skip


def format_row(row: SfmRow) -> str:
    errors = ("- | -" if row.errors is None else
              f"{100 * row.errors.max_centre:.2f} | {row.errors.max_rotation_deg:.2f}")  # fmt: skip
    return (f"| {row.photos} | {row.largest_blur_px:.1f} | {'on' if row.pooling else 'off'} | "
            f"{row.registered}/{row.total} | {row.seconds:.1f} | {row.focal:.1f} | {errors} |")  # fmt: skip


def format_table(rows: Sequence[SfmRow]) -> str:
    return "\n".join([HEADER, *(format_row(r) for r in rows)])


def write_results(out: Path, rows: Sequence[SfmRow], photos: str, command: str) -> Path:
    """``out/results.md``: the command, the machine, the photo set's name ``photos`` and the table (written
    atomically)."""
    from gsmsdr_ns.bench.machine import describe_machine, machine_info
    from gsmsdr_ns.io.atomic import write_text_atomic

    info = machine_info()
    text = (
        "# Structure-from-motion on sharp and degraded real photos (`gsmsdr-process`)\n\n"
        f"- command: `{command}`\n"
        f"- machine: {describe_machine(info)}, git {info.get('git')}\n"
        f"- photos: `{photos}`; degraded rows: the photos posed once, degraded by the preset (the first photo stays "
        "sharp and is left out), the degraded photos alone processed again\n"
        "- errors: registered cameras against LLFF's `poses_bounds.npy` after a similarity alignment (largest over "
        "the photos); SfM s: wall time of `process_photos`\n\n" + format_table(rows) + "\n"
    )
    Path(out).mkdir(parents=True, exist_ok=True)
    return write_text_atomic(Path(out) / "results.md", text)


__all__ = [
    "PoseErrors",
    "SfmRow",
    "format_table",
    "largest_blur_px",
    "llff_cameras_opencv",
    "pose_errors",
    "rotation_angle_deg",
    "run_sfm_benchmark",
    "similarity_fit",
    "write_results",
]
