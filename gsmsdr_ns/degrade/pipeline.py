"""`degrade_scene`: a sharp scene in, a degraded scene in the Deblur-NeRF layout out, written atomically.

Output layout (contract: notes degrade_spec.md):
    <out>/images/<name>.png        sorted index % hold == 0: sharp test view; others: degraded training views
    <out>/images_test/<name>.png   sharp twin of every view
    <out>/sparse/0/                COLMAP model (PINHOLE), image ids 1..V in sorted-name order
    <out>/poses_bounds.npy         LLFF [V, 17]
    <out>/hold=<N>                 empty file
    <out>/degradation.json         effects and exact parameters per image (``border_crop_px``: see crop_border)
    <out>/depth/<stem>.npy         copied from the input when present (sharp z-depth)
    <out>/scene.json               copied from a generated input (generator config)
"""

from __future__ import annotations

import dataclasses
import json
import math
import multiprocessing
import os
import shutil
from collections.abc import Callable
from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from kornia.color import linear_rgb_to_rgb, rgb_to_linear_rgb

from .. import __version__
from ..data.cameras import llff_poses_bounds_rows
from ..data.effects import BLUR_EFFECTS
from ..data.mixres import mixres_factors
from ..io.atomic import atomic_dir, temp_sibling_dir
from ..io.colmap import write_colmap_model
from ..io.errors import require_free_space
from ..io.images import read_image, read_image_float, write_image
from ..synth.config import SynthSceneConfig
from ..synth.generate import check_target, to_uint8
from ..synth.points import SparsePoints
from .config import DegradeConfig
from .effects import (
    ViewContext,
    defocus_effect,
    mixres_effect,
    motion_effect,
    noise_effect,
    sample_assignment,
    view_rng,
)
from .source import SourceScene, load_depth, load_source
from .undistort import describe_distortion, undistort_scene

FORMAT_VERSION = 1
GENERATOR = f"gsmsdr-degrade {__version__}"


@dataclass
class ViewJob:
    """Everything one worker needs to write one view (picklable)."""

    index: int
    name: str
    src_path: Path
    out_root: Path
    K: np.ndarray
    size: tuple[int, int]
    c2w: np.ndarray
    depth_path: Path | None
    split: str  # "train" | "test"
    effects: tuple[str, ...]  # this view's effects, in application order
    mixres_factor: int | None
    synth_config: SynthSceneConfig | None
    config: DegradeConfig


def split_of(index: int, hold: int) -> str:
    """Deblur-NeRF split: sorted index % hold == 0 is a sharp held-out test view."""
    return "test" if index % hold == 0 else "train"


def plan_views(src: SourceScene, cfg: DegradeConfig, out_root: Path) -> list[ViewJob]:
    """Split views, assign effects (and mixres factors) to training views. Pure given (src, cfg)."""
    effects = cfg.resolved_effects()
    train = [i for i in range(len(src.names)) if split_of(i, cfg.hold) == "train"]
    per_view: dict[int, tuple[str, ...]] = {i: effects for i in train}
    blur = [e for e in effects if e in BLUR_EFFECTS]
    if cfg.assignment == "one_per_image" and len(blur) > 1:
        groups = sample_assignment(len(train), cfg.seed, len(blur))
        extra = tuple(e for e in effects if e not in BLUR_EFFECTS)
        per_view = {i: tuple(e for e in effects if e == blur[g] or e in extra) for i, g in zip(train, groups)}
    mix_views = [i for i in train if "mixres" in per_view[i]]
    factors = dict(zip(mix_views, mixres_factors(len(mix_views), cfg.seed, cfg.mixres.factors).tolist()))
    c2ws = np.linalg.inv(src.w2cs)
    return [
        ViewJob(
            index=i,
            name=name,
            src_path=src.image_paths[i],
            out_root=out_root,
            K=src.Ks[i],
            size=tuple(src.sizes[i]),
            c2w=c2ws[i],
            depth_path=src.depth_paths[i] if src.depth_paths else None,
            split=split_of(i, cfg.hold),
            effects=per_view.get(i, ()),
            mixres_factor=factors.get(i),
            synth_config=src.synth_config,
            config=cfg,
        )
        for i, name in enumerate(src.names)
    ]


def _is_rgb8_png(path: Path) -> bool:
    """True for an 8-bit RGB PNG (its bytes can serve as the sharp output as they are); reads the IHDR only."""
    with open(path, "rb") as f:
        head = f.read(26)
    png = len(head) == 26 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR"
    return png and head[24:26] == b"\x08\x02"  # bit depth 8, colour type 2 (RGB)


def degrade_view(job: ViewJob) -> dict:
    """Read the sharp view, write images_test/<name> and images/<name>. -> its degradation.json entry."""
    cfg = job.config
    sharp_out = job.out_root / "images_test" / job.name
    if _is_rgb8_png(job.src_path):
        shutil.copyfile(job.src_path, sharp_out)  # same pixels as re-encoding, without the encoding cost
        sharp = None
    else:
        sharp = read_image_float(job.src_path, job.size)
        write_image(sharp_out, to_uint8(sharp))
    if job.split == "test" or not job.effects:
        shutil.copyfile(sharp_out, job.out_root / "images" / job.name)
        return {"split": job.split, "degraded": False, "effects": {}}
    if sharp is None:
        sharp = read_image_float(job.src_path, job.size)
    width, height = job.size
    scale = width / cfg.px_reference_width if cfg.px_reference_width > 0 else 1.0
    needs_depth = "defocus" in job.effects or ("motion" in job.effects and job.synth_config is not None)
    depth = load_depth(job.depth_path, job.size) if (needs_depth and job.depth_path is not None) else None
    ctx = ViewContext(job.K, width, height, job.c2w, depth, job.synth_config, scale, cfg.linear_light)
    x = torch.from_numpy(sharp).permute(2, 0, 1)[None].contiguous()  # [1, 3, H, W]
    records: dict[str, dict] = {}
    optical = [e for e in job.effects if e in ("motion", "defocus")]
    if optical:
        lin = rgb_to_linear_rgb(x) if cfg.linear_light else x
        if "motion" in optical:
            lin, records["motion"] = motion_effect(lin, ctx, cfg.motion, view_rng(cfg.seed, "motion", job.index))
        if "defocus" in optical:
            lin, records["defocus"] = defocus_effect(lin, ctx, cfg.defocus, view_rng(cfg.seed, "defocus", job.index))
        for name in optical:
            records[name]["linear_light"] = cfg.linear_light
        x = linear_rgb_to_rgb(lin.clamp_min(0.0)) if cfg.linear_light else lin
    if "mixres" in job.effects:
        x, records["mixres"] = mixres_effect(x, job.mixres_factor, cfg.mixres)
    if "noise" in job.effects:
        x, records["noise"] = noise_effect(x, cfg.noise, view_rng(cfg.seed, "noise", job.index))
    out = x[0].permute(1, 2, 0).clamp(0.0, 1.0).numpy()
    write_image(job.out_root / "images" / job.name, to_uint8(out))
    degraded = any(e != "mixres" or job.mixres_factor != 1 for e in records)
    return {"split": job.split, "degraded": degraded, "effects": records}


# ---------------------------------------------------------------------------------------------- LLFF bounds


def llff_poses_bounds(
    w2cs: np.ndarray,  # [V, 4, 4]
    Ks: np.ndarray,  # [V, 3, 3]
    sizes: list[tuple[int, int]],
    points_xyz: np.ndarray | None = None,  # [P, 3]
    obs: tuple[np.ndarray, np.ndarray] | None = None,  # (obs_point [O], obs_view [O])
    depths: list[np.ndarray | None] | None = None,  # per view [H, W] or None
) -> np.ndarray:
    """LLFF poses_bounds [V, 17]: 3x5 [R | t | hwf] in LLFF's axis order (down, right, back), then near, far.

    The pose encoding is the data readers' own (`gsmsdr_ns.data.cameras.llff_poses_bounds_rows`: columns (x, y, z)
    of the OpenCV camera-to-world become (y, x, -z); hwf = (H, W, fx)); near/far are the 0.1 / 99.9 percentiles of
    the z-depths of the points each view observes, else of its depth map, else of all points in front of it, else a
    guess from the camera spread.
    """
    c2w = np.linalg.inv(w2cs)
    V = len(w2cs)
    bounds = np.zeros((V, 2))
    centres = c2w[:, :3, 3]
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).max()) or 1.0
    for v in range(V):
        has_points = points_xyz is not None and len(points_xyz) > 0
        cam = points_xyz @ w2cs[v, :3, :3].T + w2cs[v, :3, 3] if has_points else np.zeros((0, 3))
        zs = cam[obs[0][obs[1] == v], 2] if (has_points and obs is not None) else np.zeros(0)
        if zs.size == 0 and depths is not None and depths[v] is not None:
            zs = depths[v][np.isfinite(depths[v])]
        if zs.size == 0:
            zs = cam[cam[:, 2] > 1e-6, 2]
        if zs.size:
            bounds[v] = np.percentile(zs, 0.1), np.percentile(zs, 99.9)
        else:
            bounds[v] = 0.05 * spread, 20.0 * spread
    focal = np.array([K[0, 0] for K in Ks], dtype=np.float64)
    return llff_poses_bounds_rows(c2w, np.asarray(sizes).reshape(V, 2), focal, bounds)


# ------------------------------------------------------------------------------------------------ border crop


def border_crop_px(records: list[dict]) -> int:
    """Pixels to crop from each border of every image: the widest ``border_reach_px`` of any view's effects
    (how far a blur read from outside the photo), rounded up; 0 when no effect reached outside."""
    reach = [float(effect.get("border_reach_px", 0.0)) for r in records for effect in r["effects"].values()]
    return int(math.ceil(max(reach, default=0.0) - 1e-6))


def cropped_frame(src: SourceScene, margin: int) -> SourceScene:
    """The scene's cameras and sparse points after cropping ``margin`` pixels from every image border: principal
    points and point observations shift by -margin, observations that fall outside the crop are dropped."""
    Ks = src.Ks.copy()
    Ks[:, 0, 2] -= margin
    Ks[:, 1, 2] -= margin
    sizes = [(w - 2 * margin, h - 2 * margin) for w, h in src.sizes]
    points = src.points
    if points is not None:
        uv = points.obs_uv - margin
        limits = np.asarray(sizes, dtype=np.float64)[points.obs_view]
        keep = np.all((uv >= 0) & (uv <= limits), axis=1)
        points = SparsePoints(xyz=points.xyz, rgb=points.rgb, obs_point=points.obs_point[keep],
                              obs_view=points.obs_view[keep], obs_uv=uv[keep])  # fmt: skip
    return dataclasses.replace(src, Ks=Ks, sizes=sizes, points=points)


def _check_crop(src: SourceScene, margin: int) -> None:
    """Refuse a crop that would leave less than half of an image's width or height."""
    width, height = min(w for w, _ in src.sizes), min(h for _, h in src.sizes)
    if 4 * margin > min(width, height):
        raise ValueError(
            f"the simulated blur reaches {margin} px into the photos' borders; cropping it would leave less than "
            f"half of a {width}x{height} photo. Use a milder preset or larger photos, or --no-crop-border to keep "
            "the reflected borders"
        )


def _crop_images(root: Path, names: list[str], margin: int) -> None:
    """Crop ``margin`` pixels from every border of the written images (``images/`` and ``images_test/``)."""
    for folder in ("images", "images_test"):
        for name in names:
            path = root / folder / name
            write_image(path, read_image(path)[margin:-margin, margin:-margin])


def _crop_records(records: list[dict], jobs: list[ViewJob], margin: int) -> None:
    """Mixres records' low-resolution ``size`` for the cropped view (``mixres_effect``'s rule; the factor is
    unchanged)."""
    for record, job in zip(records, jobs):
        mixres = record["effects"].get("mixres")
        if mixres is not None:
            f = mixres["factor"]
            w, h = job.size[0] - 2 * margin, job.size[1] - 2 * margin
            mixres["size"] = [max(1, round(w / f)), max(1, round(h / f))]


# ------------------------------------------------------------------------------------------------ the driver


def _num_workers(cfg: DegradeConfig, jobs: list[ViewJob]) -> int:
    if cfg.workers:
        return cfg.workers
    # Only blur effects cost enough (0.3-2 s per 600x400 view) to repay the ~4 s of imports of each spawned worker.
    heavy_jobs = [j for j in jobs if j.split == "train" and {"motion", "defocus"} & set(j.effects)]
    heavy = len(heavy_jobs)
    pixels = sum(j.size[0] * j.size[1] for j in heavy_jobs)
    cpus = os.cpu_count() or 1
    return min(cpus, 8) if heavy >= 8 and pixels >= 8 * 200_000 else 1


def _init_worker(threads: int) -> None:
    torch.set_num_threads(threads)


def _run_jobs(jobs: list[ViewJob], workers: int, log: Callable[[str], None]) -> list[dict]:
    if workers <= 1:
        records = []
        for j in jobs:
            records.append(degrade_view(j))
            log(f"{j.name}: {j.split} {'+'.join(j.effects) or 'sharp'}")
        return records
    threads = max(1, (os.cpu_count() or 1) // workers)
    ctx = multiprocessing.get_context("spawn")  # fork after torch has started threads can deadlock
    with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker, initargs=(threads,)) as ex:
        futures = [ex.submit(degrade_view, j) for j in jobs]
        try:
            done, _ = wait(futures, return_when=FIRST_EXCEPTION)
            for f in done:
                if f.exception() is not None:
                    raise f.exception()
        except BaseException:
            for f in futures:
                f.cancel()
            raise
        records = [f.result() for f in futures]
    for j in jobs:
        log(f"{j.name}: {j.split} {'+'.join(j.effects) or 'sharp'}")
    return records


def _write_metadata(
    root: Path,
    src: SourceScene,
    jobs: list[ViewJob],
    records: list[dict],
    meta: dict,
    cfg: DegradeConfig,
    margin: int = 0,
) -> None:
    """Cameras, poses_bounds, hold file, depth maps and degradation.json; ``margin``: the border crop the images
    got (cameras, points and depth maps are cropped alike)."""
    crop = (slice(margin, -margin), slice(margin, -margin)) if margin else (slice(None), slice(None))
    depths = [np.load(p)[crop] if p is not None else None for p in src.depth_paths] if src.depth_paths else None
    if margin:
        src = cropped_frame(src, margin)
    points = src.points
    write_colmap_model(root / "sparse" / "0", src.names, src.Ks, src.sizes, src.w2cs, points)
    pb = llff_poses_bounds(
        src.w2cs,
        src.Ks,
        src.sizes,
        points.xyz if points is not None else None,
        (points.obs_point, points.obs_view) if points is not None else None,
        depths,
    )
    np.save(root / "poses_bounds.npy", pb)
    (root / f"hold={cfg.hold}").touch()
    if depths is not None and any(d is not None for d in depths):
        (root / "depth").mkdir()
        for name, path, depth in zip(src.names, src.depth_paths, depths):
            if depth is None:
                continue
            target = root / "depth" / (Path(name).stem + ".npy")
            if margin:
                np.save(target, depth)
            else:
                shutil.copyfile(path, target)
    if src.synth_config is not None and (src.root / "scene.json").is_file():
        shutil.copyfile(src.root / "scene.json", root / "scene.json")
    doc = {
        "version": FORMAT_VERSION,
        "generator": meta["generator"],
        "source": meta["source"],
        "seed": cfg.seed,
        "hold": cfg.hold,
        "effects": list(cfg.resolved_effects()),
        "preset": meta["preset"],
        "assignment": cfg.assignment,
        "config": dataclasses.asdict(cfg),
        "border_crop_px": margin,
        "images": {j.name: r for j, r in zip(jobs, records)},
    }
    with open(root / "degradation.json", "w", encoding="utf8") as f:
        json.dump(doc, f, indent=1)
        f.write("\n")


def degrade_scene(
    input_dir: str | Path,
    out_dir: str | Path,
    config: DegradeConfig | None = None,
    overwrite: bool = False,
    preset: str | None = None,
    generator: str = GENERATOR,
    source_label: str | None = None,
    log: Callable[[str], None] | None = None,
    notice: Callable[[str], None] | None = None,
) -> Path:
    """Degrade the sharp scene at input_dir into out_dir (Deblur-NeRF layout) and return out_dir.

    An input with lens distortion is first undistorted to pinhole (``gsmsdr_ns.degrade.undistort``, pycolmap's
    undistorter, as ``gsmsdr-process``), in a hidden folder beside out_dir that is removed afterwards; the degraded
    scene is the undistorted one, and ``notice`` (default: ``log``) gets one line saying so.

    The input is validated first (cameras, every image decodable and of the camera's size). Everything is
    written into a hidden temp directory beside out_dir and renamed into place at the end; any error (or
    interrupt) removes the temp directory, so out_dir is either complete or untouched. An existing non-empty
    out_dir is refused (FileExistsError) unless overwrite=True.
    """
    cfg = config if config is not None else DegradeConfig()
    cfg.resolved_effects()  # fail on a bad effect list before reading anything
    log = log or (lambda _msg: None)
    inp = Path(input_dir).absolute()
    out = Path(out_dir).absolute()
    if inp.resolve() == out.resolve() or out.resolve() in inp.resolve().parents:
        raise ValueError(f"the output {out} must not be (or contain) the input scene {inp}")
    check_target(out, overwrite)
    if (inp / "degradation.json").exists():
        load_source(inp)  # refuses an already degraded scene, before undistorting anything
    distortion = describe_distortion(inp)
    work = temp_sibling_dir(out, "undistort") if distortion is not None else None
    try:
        if work is not None:
            (notice or log)(f"{inp} has lens distortion ({distortion}); undistorting it to pinhole images first "
                            "(the degraded scene is the undistorted one)")  # fmt: skip
            src = load_source(undistort_scene(inp, work))
            src.depth_paths = []  # depth maps of the distorted images do not fit the undistorted ones
        else:
            src = load_source(inp)
        # the output holds every view twice (degraded in images/, sharp in images_test/); a full disk midway would
        # leave the work undone anyway: say so before starting
        needed = 2 * sum(path.stat().st_size for path in src.image_paths) + 8 * 2**20
        require_free_space(
            out.parent, needed, "gsmsdr-degrade", "Free some space, or choose --out on a disk with room."
        )
        with atomic_dir(out) as tmp:
            (tmp / "images").mkdir()
            (tmp / "images_test").mkdir()
            jobs = plan_views(src, cfg, tmp)
            records = _run_jobs(jobs, _num_workers(cfg, jobs), log)
            margin = border_crop_px(records) if cfg.crop_border and src.synth_config is None else 0
            if margin:
                _check_crop(src, margin)
                _crop_images(tmp, src.names, margin)
                _crop_records(records, jobs, margin)
                log(f"cropped {margin} px from every border of every image: the simulated blur read that far "
                    "outside the photos")  # fmt: skip
            meta = {"generator": generator, "source": source_label or str(inp), "preset": preset}
            _write_metadata(tmp, src, jobs, records, meta, cfg, margin)
            check_target(out, overwrite)  # re-check: something may have appeared meanwhile
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
    return out


__all__ = [
    "degrade_scene",
    "degrade_view",
    "plan_views",
    "llff_poses_bounds",
    "border_crop_px",
    "cropped_frame",
    "split_of",
    "ViewJob",
    "GENERATOR",
]
