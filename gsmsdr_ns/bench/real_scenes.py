"""Benchmark scenes built from real photos: poses by structure-from-motion, degradation by ``gsmsdr-degrade``, poses
again from the degraded photos alone, and sharp held-out test views posed in that degraded run's frame.

For a :class:`RealSceneSpec` (a folder of sharp photos, e.g. ``llff-fern/images_16``, and a degradation preset)
:func:`ensure_real_scene` builds, once, under ``<bench>/scenes/``:

1. ``<photos>-sfm``: ``gsmsdr-process`` on all the sharp photos (undistorted pinhole scene);
2. ``<...>-degraded``: ``gsmsdr-degrade`` of that scene with the preset (Deblur-NeRF layout, true records);
3. ``<...>-degraded-sfm``: structure-from-motion on the degraded *training* photos alone (no poses given), then
   the held-out sharp photos registered into that model (its poses, intrinsics and points fixed), so the test
   views are posed in the degraded run's frame with the same camera, as a user's sharp reference photos would be;
   undistorted to pinhole (:func:`map_and_register`);
4. the scene the methods train on: step 3 with its images shrunk by ``train_downscale``, in the Deblur-NeRF
   layout (``hold=N``, the sharp test photos in ``images/`` at the held-out places) and without
   ``degradation.json``, so the dataparser estimates the records; ``records="true"`` also writes the true records
   of step 2. ``real_scene.json`` keeps what was built.

The sharp twin of a scene (the ``sharp`` upper bound) is the same spec with the ``sharp`` preset: the sharp
training photos processed the same way, so its poses and camera come from structure-from-motion on sharp photos.
``photos="sharp"`` builds the other bound: the sharp photos undistorted and posed by step 3's model of the
*degraded* photos (the same seeded, single-threaded mapping run again, writing the sharp photos), i.e. what a
perfect deblurring could reach with the poses and camera that blurred photos give.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Optional, Sequence

import numpy as np

from gsmsdr_ns.io.atomic import atomic_dir, exclusive_lock, temp_sibling_dir, write_json_atomic
from gsmsdr_ns.io.colmap import quiet_pycolmap
from gsmsdr_ns.io.errors import InputError
from gsmsdr_ns.io.photo_sets import DATA_DIR_ENV, photo_set_roots

REAL_SCENE_VERSION = 2
"""Bumped when built real scenes change for the same spec, so cached scenes of an older builder are not reused
(2: ``gsmsdr-degrade`` crops the border its blur filled from outside the photos)."""
COMPOSED_LAYOUT_VERSION = 3
"""Bumped when the layout of the scenes the methods train on changes (the structure-from-motion steps are reused)."""
REGISTRATION_FILE = "registration.json"
"""Written last into the registered scene of step 3 (its facts); its presence marks that scene complete."""
RECORDS = ("estimated", "true")
"""Which degradation records a built scene carries: none (the dataparser estimates them), or the true ones."""
PHOTOS = ("degraded", "sharp")
"""Which photos a built scene's training views show: the degraded ones, or their sharp originals posed by the
degraded photos' structure-from-motion (module docstring)."""


@dataclass(frozen=True)
class RealSceneSpec:
    """A scene built from a folder of real sharp photos and a ``gsmsdr-degrade`` preset (module docstring)."""

    dataset: str = "llff-fern"
    """Photo set: a folder name looked up under $GSMSDR_DATA_DIR and ``shared/data/`` beside the repository, or a
    path."""
    images: str = "images_16"
    """Sub-folder of the photo set with the photos (e.g. ``images_16``: fern at 252x189)."""
    preset: str = "motion-strong"
    """Degradation preset: a ``gsmsdr-degrade`` built-in name (``sharp``, ``motion-strong``, ...) or a YAML file."""
    hold: int = 8
    """Every ``hold``-th photo (sorted by name, from the first) is a held-out sharp test view."""
    seed: int = 0
    """Degradation and structure-from-motion seed."""
    train_downscale: int = 1
    """Training and test read copies of the built scene's images shrunk by this factor (``images_<N>/``, the
    dataparser's ``downscale_factor``); the full-size images stay in ``images/``."""
    max_image_size: int = 1000
    """Longest side SIFT sees (``gsmsdr-process --max-image-size``)."""

    @property
    def photos_name(self) -> str:
        return f"{Path(self.dataset).name}-{self.images}"

    @property
    def degraded_name(self) -> str:
        return f"{self.photos_name}-{Path(self.preset).stem}-h{self.hold}-s{self.seed}-r{REAL_SCENE_VERSION}"

    def name(self, records: str = "estimated", photos: str = "degraded") -> str:
        kind = records if photos == "degraded" else f"{photos}-photos"
        return f"{self.degraded_name}-x{self.train_downscale}-{kind}-l{COMPOSED_LAYOUT_VERSION}"

    def configure(self, config) -> None:
        """Point a method's TrainerConfig at the shrunk copies (the Deblur-NeRF reader's ``downscale_factor``)."""
        config.pipeline.datamanager.dataparser.deblur.downscale_factor = self.train_downscale

    def sharp_twin(self) -> "RealSceneSpec":
        return dataclasses.replace(self, preset="sharp")

    def describe(self) -> str:
        size = ("trained at full size" if self.train_downscale == 1 else
                f"trained on copies shrunk {self.train_downscale}x (images_{self.train_downscale}/; the degradation "
                "estimate judges the full-size images)")  # fmt: skip
        return (f"real photos `{self.dataset}/{self.images}` degraded with `{self.preset}` (every {self.hold}th photo "
                "a sharp test view), SfM on the degraded training photos alone with the sharp test photos registered "
                f"into that model, {size}")  # fmt: skip


def parse_real_spec(values: Any, fail: Callable[[str, str], Exception]) -> RealSceneSpec:
    """A suite file's ``real:`` mapping -> :class:`RealSceneSpec`; ``fail(key_suffix, message)`` makes the error
    (naming the file and the key) that is raised."""
    if not isinstance(values, dict):
        raise fail("", f"must be a mapping of {', '.join(f.name for f in dataclasses.fields(RealSceneSpec))}")
    fields = {f.name: f for f in dataclasses.fields(RealSceneSpec)}
    out: Dict[str, Any] = {}
    for k, v in values.items():
        if k not in fields:
            raise fail(f".{k}", f"unknown key; valid: {', '.join(fields)}")
        default = fields[k].default
        if isinstance(default, str):
            if not isinstance(v, str) or not v:
                raise fail(f".{k}", f"must be a non-empty string, got {v!r}")
        else:
            minimum = 0 if k == "seed" else (2 if k == "hold" else 1)
            if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
                raise fail(f".{k}", f"must be an integer >= {minimum}, got {v!r}")
        out[k] = v
    spec = RealSceneSpec(**out)
    try:
        degrade_config(spec)
    except (InputError, FileNotFoundError, ValueError) as e:
        raise fail(".preset", str(e)) from e
    return spec


def resolve_photos(spec: RealSceneSpec, anchors: Sequence[Path] = ()) -> Path:
    """The folder of ``spec``'s photos: ``dataset`` as a path, else under $GSMSDR_DATA_DIR, else ``shared/data/``
    in a parent of the ``anchors`` (the suite file, the working directory); InputError naming the places looked."""
    direct = Path(spec.dataset).expanduser()
    roots = photo_set_roots([*anchors, Path.cwd()])
    candidates = [direct] if direct.is_absolute() else [root / spec.dataset for root in roots]
    for folder in candidates:
        if (folder / spec.images).is_dir():
            return folder / spec.images
    shown = ", ".join(str(c / spec.images) for c in candidates[:6])
    raise InputError(
        f"gsmsdr-bench: photo set '{spec.dataset}' (folder '{spec.images}') not found; looked in {shown}. Put the "
        f"photos there, set {DATA_DIR_ENV} to the folder holding '{spec.dataset}', or give the scene's 'dataset' "
        "as an absolute path."
    )


def degrade_config(spec: RealSceneSpec):
    """The ``gsmsdr-degrade`` config of ``spec``'s preset (built-in name or .yaml file) with its seed and hold, one
    worker; InputError naming the valid presets otherwise."""
    from gsmsdr_ns.degrade.config import load_preset
    from gsmsdr_ns.degrade.variants import BUILTIN_PRESETS

    if spec.preset in BUILTIN_PRESETS:
        base = BUILTIN_PRESETS[spec.preset]
    elif Path(spec.preset).suffix in (".yaml", ".yml"):
        base = load_preset(spec.preset)
    else:
        raise InputError(f"gsmsdr-bench: unknown degradation preset {spec.preset!r}; valid: "
                         f"{', '.join(BUILTIN_PRESETS)} or a .yaml preset file")  # fmt: skip
    return dataclasses.replace(base, seed=spec.seed, hold=spec.hold, workers=1)


def _process(photos: Path, out: Path, spec: RealSceneSpec, log: Callable[[str], None]):
    """``gsmsdr-process`` of ``photos`` into ``out`` (one thread: the bench shares the CPU)."""
    from gsmsdr_ns.process import ProcessConfig, process_photos

    config = ProcessConfig(max_image_size=spec.max_image_size, num_threads=1, seed=spec.seed)
    with quiet_pycolmap():
        result = process_photos(photos, out, config, overwrite=True)
    total = len(result.registered) + len(result.unregistered)
    log(f"real scene: structure-from-motion registered {len(result.registered)}/{total} photos of {photos} -> {out}")
    return result


def _mapping_options(spec: RealSceneSpec, names: Sequence[str]):
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = 1
    options.random_seed = spec.seed
    options.mapper.random_seed = spec.seed
    options.image_names = list(names)
    return options


@quiet_pycolmap()
def map_and_register(photos: Path, train: Sequence[str], test: Sequence[str], out: Path, spec: RealSceneSpec,
                     log: Callable[[str], None], written_photos: Optional[Path] = None) -> Dict[str, Any]:  # fmt: skip
    """SfM on the ``train`` photos alone, then the ``test`` photos registered into that model, written to ``out``
    (``images/`` undistorted to pinhole, ``sparse/0``); returns the registration facts. ``written_photos``: a
    folder of other photos with the same names and sizes (the sharp originals of degraded ones) that are
    undistorted and written instead of ``photos``; the model is still made from ``photos``.

    ``gsmsdr-process``'s SIFT and matching over all photos (one shared camera, as for one capture), incremental
    mapping restricted to the training photos, then a second mapping pass from that model with its frames and
    the camera's intrinsics fixed, which adds the test photos. The written model is the first pass's (training
    poses, intrinsics and points untouched by the test photos) plus the test photos' registered poses."""
    import pycolmap

    from gsmsdr_ns.process import ProcessConfig
    from gsmsdr_ns.process.sfm import extract_and_match, largest_model, write_undistorted

    config = ProcessConfig(max_image_size=spec.max_image_size, num_threads=1, seed=spec.seed, camera_mode="single")
    pycolmap.set_random_seed(spec.seed)
    work = temp_sibling_dir(out, "sfm")
    try:
        database = work / "database.db"
        extract_and_match(database, photos, [*train, *test], config)
        model = largest_model(pycolmap.incremental_mapping(database, photos, work / "train",
                                                           _mapping_options(spec, train)))  # fmt: skip
        registered = set() if model is None else {model.images[i].name for i in model.reg_image_ids()}
        missing = [n for n in train if n not in registered]
        if missing:
            raise InputError(
                f"gsmsdr-bench: structure-from-motion on the degraded training photos in {photos} did not register "
                f"{', '.join(missing)}; the held-out split needs every training photo. Use larger photos (images_N "
                "with a smaller N) or a milder preset."
            )
        (work / "train-model").mkdir()
        model.write(work / "train-model")
        options = _mapping_options(spec, [*train, *test])
        options.fix_existing_frames = True
        options.ba_refine_focal_length = options.ba_refine_principal_point = options.ba_refine_extra_params = False
        extended = largest_model(pycolmap.incremental_mapping(database, photos, work / "test", options,
                                                              input_path=work / "train-model"))  # fmt: skip
        poses = {extended.images[i].name: extended.images[i].cam_from_world() for i in extended.reg_image_ids()}
        missing = [n for n in test if n not in poses]
        if missing:
            raise InputError(f"gsmsdr-bench: the held-out photos {', '.join(missing)} did not register into the "
                             f"model of the degraded training photos in {photos}")  # fmt: skip
        # the training poses must come out of the second pass as they went in (fixed frames)
        train_moved = max(float(np.abs(poses[image.name].matrix() - image.cam_from_world().matrix()).max())
                          for image in (model.images[i] for i in model.reg_image_ids()))  # fmt: skip
        camera_id = next(iter(model.cameras))
        next_id = max(model.images) + 1
        for offset, name in enumerate(test):
            image = pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=camera_id,
                                   image_id=next_id + offset)  # fmt: skip
            model.add_image_with_trivial_frame(image, poses[name])
        facts = {"training_poses_moved_by_registration": train_moved,
                 "focal_px": float(model.cameras[camera_id].focal_length_x)}  # fmt: skip
        scene = work / "scene"
        scene.mkdir()
        write_undistorted(model, written_photos or photos, scene, work)
        write_json_atomic(scene / REGISTRATION_FILE, facts)  # last: marks the folder complete
        if out.exists():
            shutil.rmtree(out)
        os.rename(scene, out)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    log(f"real scene: {len(train)} degraded training photos mapped, {len(test)} sharp test photos registered -> {out}")
    return facts


def _copy_image(src: Path, dst: Path, factor: int) -> None:
    if factor == 1:
        shutil.copyfile(src, dst)
        return
    from PIL import Image

    with Image.open(src) as image:
        image.convert("RGB").resize((image.width // factor, image.height // factor),
                                    Image.Resampling.LANCZOS).save(dst)  # fmt: skip


def compose_scene(out: Path, registered: Path, hold: int, factor: int) -> Dict[str, Any]:
    """Write the scene the methods train on into ``out``: the ``registered`` scene (every photo posed in the
    degraded run's frame) with its full-size images in ``images/``, copies shrunk by ``factor`` in
    ``images_<factor>/`` (what training reads, as nerfstudio's downscaled folders; the degradation estimate judges
    the full-size copies) and a ``hold=N`` file; returns its build facts."""
    from gsmsdr_ns.data.layout import holdout_split
    from gsmsdr_ns.io.colmap import read_colmap, write_colmap_model
    from gsmsdr_ns.synth.points import SparsePoints

    model = read_colmap(registered / "sparse" / "0", tracks=True, skip_unposed=True)
    pts = model.points
    points = SparsePoints(xyz=pts.xyz, rgb=pts.rgb, obs_point=pts.obs_point, obs_view=pts.obs_view,
                          obs_uv=pts.obs_uv)  # fmt: skip
    folders = {1: out / "images"} | ({factor: out / f"images_{factor}"} if factor > 1 else {})
    for f, folder in folders.items():
        folder.mkdir()
        for name in model.names:
            _copy_image(registered / "images" / name, folder / name, f)
    sizes = [(int(w), int(h)) for w, h in model.sizes]
    write_colmap_model(out / "sparse" / "0", model.names, model.Ks, sizes, model.w2c, points)
    (out / f"hold={hold}").touch()
    _, test = holdout_split(len(model.names), hold)
    return {"views": len(model.names), "names": model.names, "test_views": [model.names[i] for i in test],
            "size": [sizes[0][0] // factor, sizes[0][1] // factor],
            "full_size": list(sizes[0]), "points": int(len(pts.xyz))}  # fmt: skip


def true_records(degradation_json: Path, names: Sequence[str]) -> Dict[str, Any]:
    """``gsmsdr-degrade``'s ``degradation.json`` restricted to ``names`` (the built scene's images), for poses that
    structure-from-motion estimated from the degraded photos.

    The motion records lose their ``"reference": "mid_exposure"``: it says the scene's pose of a shaken photo is the
    mid-exposure pose of its shake, which holds in ``gsmsdr-degrade``'s output but not here, where every pose comes
    from the degraded photos themselves (near the centre of each blur). The model then keeps those photos' kernels
    centred, as for any estimated pose; the kinds and sizes of the blurs stay true.
    """
    doc = json.loads(Path(degradation_json).read_text(encoding="utf8"))
    doc["images"] = {n: doc["images"][n] for n in names}
    for entry in doc["images"].values():
        motion = entry.get("effects", {}).get("motion")
        if isinstance(motion, dict):
            motion.pop("reference", None)
    return doc


def _ensure_degraded(root: Path, spec: RealSceneSpec, sharp_scene: Path, log: Callable[[str], None]) -> Path:
    """Step 2 of ``spec`` (its ``gsmsdr-degrade`` output), built once."""
    from gsmsdr_ns.degrade import degrade_scene

    degraded = root / f"{spec.degraded_name}-degraded"
    if not (degraded / "degradation.json").is_file():
        log(f"real scene: degrading {sharp_scene} with {spec.preset} -> {degraded}")
        degrade_scene(sharp_scene, degraded, degrade_config(spec), overwrite=True, preset=Path(spec.preset).stem)
    return degraded


def ensure_real_scene(bench_dir: Path, spec: RealSceneSpec, records: str = "estimated",
                      anchors: Sequence[Path] = (), log: Optional[Callable[[str], None]] = None,
                      photos: str = "degraded") -> Path:  # fmt: skip
    """The built scene of ``spec`` under ``bench_dir/scenes`` (module docstring), built once and reused;
    ``records``: "estimated" (no degradation.json) or "true"; ``photos``: "degraded", or "sharp" (the sharp
    originals posed by the degraded photos' structure-from-motion; no records: every photo is sharp)."""
    from gsmsdr_ns.degrade.pipeline import split_of

    if records not in RECORDS:
        raise ValueError(f"records must be one of {RECORDS}, got {records!r}")
    if photos not in PHOTOS:
        raise ValueError(f"photos must be one of {PHOTOS}, got {photos!r}")
    log = log or (lambda _message: None)
    root = Path(bench_dir) / "scenes"
    out = root / spec.name(records, photos)
    if (out / "real_scene.json").is_file():
        return out
    # suites running in parallel may need the same scene (or its shared structure-from-motion) at once: builds
    # take turns, and a later one reuses what an earlier one built
    with exclusive_lock(root):
        if (out / "real_scene.json").is_file():
            return out
        root.mkdir(parents=True, exist_ok=True)
        source = resolve_photos(spec, anchors)
        sharp_scene = root / f"{spec.photos_name}-sfm-s{spec.seed}-r{REAL_SCENE_VERSION}"
        if not (sharp_scene / "sparse" / "0").is_dir():
            _process(source, sharp_scene, spec, log)
        degraded = _ensure_degraded(root, spec, sharp_scene, log)
        suffix = "" if photos == "degraded" else f"-{photos}-photos"
        registered = root / f"{spec.degraded_name}-degraded-sfm{suffix}"
        if not (registered / REGISTRATION_FILE).is_file():
            names = sorted(p.name for p in (degraded / "images").iterdir())
            split = [(name, split_of(index, spec.hold)) for index, name in enumerate(names)]
            train, test = [n for n, s in split if s == "train"], [n for n, s in split if s == "test"]
            # the degraded scene's sharp twins: the originals cropped as the degraded photos were
            sharp = None if photos == "degraded" else degraded / "images_test"
            map_and_register(degraded / "images", train, test, registered, spec, log, written_photos=sharp)
        with atomic_dir(out) as tmp:
            facts = compose_scene(tmp, registered, spec.hold, spec.train_downscale)
            facts.update(json.loads((registered / REGISTRATION_FILE).read_text(encoding="utf8")))
            if records == "true" and photos == "degraded":
                records_doc = true_records(degraded / "degradation.json", facts["names"])
                write_json_atomic(tmp / "degradation.json", records_doc)
            write_json_atomic(tmp / "real_scene.json", {"version": REAL_SCENE_VERSION, "photos": str(source),
                                                        "spec": dataclasses.asdict(spec), "records": records,
                                                        "training_photos": photos, **facts})  # fmt: skip
    shown = "degraded photos" if photos == "degraded" else "sharp photos, posed by the degraded photos' model"
    log(
        f"real scene: wrote {out} ({facts['views']} views: {shown}; {len(facts['test_views'])} sharp test views "
        "registered into the degraded photos' model)"
    )
    return out


__all__ = [
    "DATA_DIR_ENV",
    "REAL_SCENE_VERSION",
    "PHOTOS",
    "RECORDS",
    "RealSceneSpec",
    "degrade_config",
    "compose_scene",
    "ensure_real_scene",
    "map_and_register",
    "parse_real_spec",
    "resolve_photos",
    "true_records",
]
