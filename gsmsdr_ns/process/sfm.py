"""Photos in, posed scene out: pycolmap SIFT, matching, incremental mapping and undistortion to pinhole.

The scene is written in the layout ``gsmsdr-data`` reads as a COLMAP scene (or, with a ``hold=N`` file, as a
Deblur-NeRF scene)::

    <out>/images/        undistorted photos (registered ones only), same names as the input
    <out>/sparse/0/      COLMAP binary model with PINHOLE cameras
    <out>/images_2/ ...  optional halved copies (``num_downscales``)
    <out>/hold=N         optional holdout rule

Everything is built in a hidden temp folder beside ``<out>`` and renamed into place at the end, so ``<out>`` is
either the complete new scene or untouched. An existing non-empty ``<out>`` is replaced only with
``overwrite=True``; the previous scene is removed only after the new one is in place.
"""

from __future__ import annotations

import os
import shutil
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
import pycolmap

from gsmsdr_ns.io.atomic import atomic_dir
from gsmsdr_ns.io.errors import InputError, InputWarning, require_free_space
from gsmsdr_ns.io.images import list_images, read_image_size
from gsmsdr_ns.process.config import ProcessConfig
from gsmsdr_ns.process.duplicates import find_duplicates
from gsmsdr_ns.process.sharpness import sharpness_scores

_CAMERA_MODES = {
    "single": pycolmap.CameraMode.SINGLE,
    "per-folder": pycolmap.CameraMode.PER_FOLDER,
    "per-image": pycolmap.CameraMode.PER_IMAGE,
}
_DEVICES = {"auto": pycolmap.Device.auto, "cpu": pycolmap.Device.cpu, "cuda": pycolmap.Device.cuda}


class RegistrationError(InputError):
    """Too few photos registered into one model."""


@dataclass
class ProcessResult:
    """What a ``gsmsdr-process`` run produced."""

    scene: Path
    """The written scene directory."""
    matching: str
    """The matching actually used ("exhaustive" or "sequential")."""
    registered: List[str]
    """Names of the photos in the written model, sorted."""
    unregistered: List[Tuple[str, float]]
    """Photos left out, with their sharpness (variance of the Laplacian), blurriest first."""
    num_points: int
    """Sparse points in the written model."""
    num_models: int
    """Models the mapper found (only the largest is written)."""
    seconds: Dict[str, float] = field(default_factory=dict)
    """Time spent per stage."""
    duplicates: Dict[str, str] = field(default_factory=dict)
    """Photos left out as copies of another one: ``{copy: the photo kept}`` (:func:`find_duplicates`)."""


def choose_matching(num_images: int, config: ProcessConfig) -> str:
    """ "exhaustive" or "sequential" for ``num_images`` photos under ``config.matching``."""
    if config.matching != "auto":
        return config.matching
    return "exhaustive" if num_images <= config.exhaustive_max_images else "sequential"


def check_config(config: ProcessConfig) -> None:
    """Reject option values that cannot work, naming the option."""
    if not 0.0 <= config.min_registered_fraction <= 1.0:
        raise InputError(
            f"gsmsdr-process: --min-registered-fraction {config.min_registered_fraction} is not in [0, 1]."
        )
    for name in ("max_image_size", "max_num_features", "sequential_overlap", "exhaustive_max_images"):
        if getattr(config, name) < 1:
            raise InputError(f"gsmsdr-process: --{name.replace('_', '-')} must be >= 1.")
    if config.hold is not None and config.hold < 1:
        raise InputError(f"gsmsdr-process: --hold {config.hold} must be >= 1 (or left unset).")
    if config.num_downscales < 0:
        raise InputError(f"gsmsdr-process: --num-downscales {config.num_downscales} must be >= 0.")
    if config.vocab_tree is not None and not Path(config.vocab_tree).is_file():
        raise InputError(f"gsmsdr-process: vocabulary tree '{config.vocab_tree}' does not exist.")


def extract_and_match(database: Path, images_dir: Path, names: List[str], config: ProcessConfig) -> str:
    """SIFT features of ``names`` and their verified matches into ``database``; returns the matching used."""
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = config.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = config.max_image_size
    extraction.num_threads = config.num_threads
    extraction.sift.max_num_features = config.max_num_features
    extraction.sift.estimate_affine_shape = config.estimate_affine_shape
    extraction.sift.domain_size_pooling = config.domain_size_pooling
    device = _DEVICES[config.device]
    if config.camera_mode == "auto":  # one shared camera per image size: each call starts a new camera
        groups = [("single", group) for group in names_by_size(images_dir, names)]
    else:
        groups = [(config.camera_mode, names)]
    for mode, group in groups:
        pycolmap.extract_features(
            database, images_dir, image_names=group, camera_mode=_CAMERA_MODES[mode],
            reader_options=reader, extraction_options=extraction, device=device,
        )  # fmt: skip
    matching_options = pycolmap.FeatureMatchingOptions()
    matching_options.num_threads = config.num_threads
    matching = choose_matching(len(names), config)
    if matching == "exhaustive":
        pycolmap.match_exhaustive(database, matching_options=matching_options, device=device)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = config.sequential_overlap
        pairing.quadratic_overlap = config.quadratic_overlap
        if config.vocab_tree is not None:
            pairing.loop_detection = True
            pairing.vocab_tree_path = str(config.vocab_tree)
        pycolmap.match_sequential(database, matching_options=matching_options, pairing_options=pairing, device=device)
    return matching


def names_by_size(images_dir: Path, names: List[str]) -> List[List[str]]:
    """``names`` grouped by image size (width, height), groups in order of their first photo."""
    groups: Dict[Tuple[int, int], List[str]] = {}
    for name in names:
        groups.setdefault(read_image_size(Path(images_dir) / name), []).append(name)
    return list(groups.values())


def map_incrementally(
    database: Path, images_dir: Path, models_dir: Path, config: ProcessConfig, on_register: Callable[[], None]
) -> Dict[int, pycolmap.Reconstruction]:
    """Incremental mapping of the matched photos; every model found, keyed by index. ``on_register`` runs once per
    registered photo (for progress)."""
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = config.num_threads
    options.random_seed = config.seed
    options.mapper.random_seed = config.seed
    models_dir.mkdir(parents=True, exist_ok=True)

    def on_initial_pair() -> None:
        on_register()
        on_register()

    return pycolmap.incremental_mapping(
        database, images_dir, models_dir, options=options,
        initial_image_pair_callback=on_initial_pair, next_image_callback=on_register,
    )  # fmt: skip


def largest_model(models: Dict[int, pycolmap.Reconstruction]) -> Optional[pycolmap.Reconstruction]:
    """The model with the most registered photos (ties: the one with more points), None if there is none."""
    if not models:
        return None
    return max(models.values(), key=lambda rec: (rec.num_reg_images(), rec.num_points3D()))


def registered_names(model: Optional[pycolmap.Reconstruction]) -> List[str]:
    if model is None:
        return []
    return sorted(model.images[image_id].name for image_id in model.reg_image_ids())


def check_registration(names: List[str], registered: List[str], scores: Dict[str, float], config: ProcessConfig,
                       images_dir: Path) -> None:  # fmt: skip
    """Fail when fewer than ``min_registered`` photos (and never fewer than 2) or ``min_registered_fraction`` of
    them registered."""
    needed = max(2, config.min_registered, int(np.ceil(config.min_registered_fraction * len(names))))
    if len(registered) >= needed:
        return
    missing = describe_unregistered(names, registered, scores)
    advice = ["Photos must overlap and show the same static scene"]
    if len(names) < 4:  # mapping needs a first pair with enough parallax: two or three photos rarely have one
        advice.append(f"with {len(names)} photos, add a few more taken from nearby viewpoints")
    blurred = blurrier_than_the_rest(names, registered, scores)
    if blurred:
        advice.append(f"{', '.join(blurred)} look blurred next to the others: try a smaller --max-image-size")
    advice.append("for video frames try --matching sequential")
    raise RegistrationError(
        f"gsmsdr-process: only {len(registered)} of {len(names)} photos in '{images_dir}' registered into one model "
        f"(need {needed}: --min-registered {config.min_registered}, --min-registered-fraction "
        f"{config.min_registered_fraction}). Not registered (sharpness = variance of the Laplacian, lower is "
        f"blurrier): {missing}. " + "; ".join(advice) + "."
    )


BLURRED_SHARPNESS_RATIO = 0.5
"""A photo is called blurred next to the others when its sharpness is below this fraction of the median sharpness of
the registered photos (of all photos when none registered)."""


def blurrier_than_the_rest(names: List[str], registered: List[str], scores: Dict[str, float]) -> List[str]:
    """The unregistered photos much blurrier than the reference (:data:`BLURRED_SHARPNESS_RATIO`), so blur is a
    likely reason they did not register; sharp photos that failed are not blamed on blur."""
    reference = float(np.median([scores[n] for n in (registered or names)]))
    kept = set(registered)
    return [n for n in names if n not in kept and scores[n] < BLURRED_SHARPNESS_RATIO * reference]


def unregistered_with_scores(names: List[str], registered: List[str], scores: Dict[str, float]):
    """(name, sharpness) of the photos not in ``registered``, blurriest first."""
    kept = set(registered)
    return sorted(((n, scores[n]) for n in names if n not in kept), key=lambda item: item[1])


def describe_unregistered(names: List[str], registered: List[str], scores: Dict[str, float], limit: int = 20) -> str:
    rows = unregistered_with_scores(names, registered, scores)
    text = ", ".join(f"{name} ({score:.2e})" for name, score in rows[:limit])
    return text + (f", ... ({len(rows)} in all)" if len(rows) > limit else "") if rows else "none"


def write_undistorted(model: pycolmap.Reconstruction, images_dir: Path, scene: Path, work: Path) -> None:
    """``scene/images`` (registered photos undistorted to pinhole) and ``scene/sparse/0`` (their binary model)."""
    distorted = work / "distorted"
    distorted.mkdir(parents=True)
    model.write(distorted)
    undistorted = work / "undistorted"
    pycolmap.undistort_images(undistorted, distorted, images_dir, output_type="COLMAP")
    (scene / "sparse").mkdir(parents=True)
    os.rename(undistorted / "images", scene / "images")
    os.rename(undistorted / "sparse", scene / "sparse" / "0")


def write_downscaled(scene: Path, num_downscales: int, names: List[str]) -> None:
    """``images_2/``, ``images_4/``, ...: each photo halved ``k`` times (sizes floor(w / 2^k), as nerfstudio's
    camera rescaling computes them)."""
    from PIL import Image

    for k in range(1, num_downscales + 1):
        factor = 2**k
        folder = scene / f"images_{factor}"
        folder.mkdir()
        for name in names:
            with Image.open(scene / "images" / name) as image:
                size = (image.width // factor, image.height // factor)
                if min(size) < 1:
                    raise InputError(
                        f"gsmsdr-process: '{name}' ({image.width}x{image.height}) is too small for "
                        f"--num-downscales {num_downscales}; lower it."
                    )
                image.resize(size, Image.Resampling.LANCZOS).save(folder / name)


def _check_target(out: Path, overwrite: bool) -> None:
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise FileExistsError(f"gsmsdr-process: output '{out}' exists and is not a directory.")
        if any(out.iterdir()) and not overwrite:
            raise FileExistsError(f"gsmsdr-process: output '{out}' exists and is not empty; pass --overwrite.")


def process_photos(
    images_dir: Path, out: Path, config: ProcessConfig, overwrite: bool = False, progress=None
) -> ProcessResult:
    """Run SfM on the photos directly inside ``images_dir`` and write the scene to ``out`` (module docstring).

    ``progress`` is an optional ``rich.progress.Progress`` to report stages on. Raises :class:`RegistrationError`
    (nothing written) when too few photos register, InputError for unusable input, FileExistsError for an
    existing output without ``overwrite``.
    """
    images_dir, out = Path(images_dir), Path(out)
    check_config(config)
    names = list_images(images_dir)
    if len(names) < 2:
        raise InputError(
            f"gsmsdr-process: '{images_dir}' has {len(names)} photo(s); structure-from-motion needs at least 2 "
            "overlapping photos (png, jpg, ...) directly inside the folder."
        )
    duplicates = find_duplicates(images_dir, names)
    if duplicates:  # a copy could end up a test view of its own original: scores would measure memory
        names = [name for name in names if name not in duplicates]
        warnings.warn(InputWarning(
            f"gsmsdr-process: left out {len(duplicates)} photo(s) that copy another one in '{images_dir}': "
            + ", ".join(f"{copy} (= {kept})" for copy, kept in sorted(duplicates.items()))
        ), stacklevel=2)  # fmt: skip
        if len(names) < 2:
            raise InputError(f"gsmsdr-process: '{images_dir}' holds copies of {len(names)} photo(s) only; "
                             "structure-from-motion needs at least 2 different overlapping photos.")  # fmt: skip
    _check_target(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    # pycolmap aborts the whole process (no Python error) when its database finds the disk full: check first. The
    # database holds about a megabyte of features per photo, the scene a copy of every photo (and smaller ones).
    needed = sum((images_dir / name).stat().st_size for name in names) * (2 if config.num_downscales else 1)
    require_free_space(out.parent, needed + len(names) * 2**20 + 8 * 2**20, "gsmsdr-process",
                       "Free some space, or choose --out on a disk with room.")  # fmt: skip
    pycolmap.set_random_seed(config.seed)
    seconds: Dict[str, float] = {}
    stage = _Stages(progress, seconds)
    with atomic_dir(out) as tmp:
        work = tmp / ".sfm"
        work.mkdir()
        with stage("sharpness", len(names)) as advance:
            scores = sharpness_scores(images_dir, names, on_image=advance)
        with stage("features + matching", None):
            matching = extract_and_match(work / "database.db", images_dir, names, config)
        with stage("mapping (registered photos)", len(names)) as advance:
            models = map_incrementally(work / "database.db", images_dir, work / "models", config, advance)
        model = largest_model(models)
        registered = registered_names(model)
        check_registration(names, registered, scores, config, images_dir)
        with stage("undistortion", None):
            write_undistorted(model, images_dir, tmp, work)
        shutil.rmtree(work)
        if config.num_downscales:
            with stage("downscaled copies", None):
                write_downscaled(tmp, config.num_downscales, registered)
        if config.hold is not None:
            (tmp / f"hold={config.hold}").touch()
        _check_target(out, overwrite)  # something may have appeared meanwhile
    return ProcessResult(
        scene=out, matching=matching, registered=registered,
        unregistered=unregistered_with_scores(names, registered, scores),
        num_points=model.num_points3D(), num_models=len(models), seconds=seconds, duplicates=duplicates,
    )  # fmt: skip


class _Stages:
    """One progress task per stage (a bar when the amount of work is known) and the seconds each stage took."""

    def __init__(self, progress, seconds: Dict[str, float]):
        self.progress, self.seconds = progress, seconds

    def __call__(self, name: str, total: Optional[int]):
        return _Stage(self, name, total)


class _Stage:
    def __init__(self, stages: _Stages, name: str, total: Optional[int]):
        self.stages, self.name, self.total = stages, name, total

    def __enter__(self) -> Callable[[], None]:
        self.start = time.perf_counter()
        progress = self.stages.progress
        if progress is None:
            return lambda: None
        self.task = progress.add_task(self.name, total=self.total)
        return lambda: progress.advance(self.task)

    def __exit__(self, exc_type, exc, tb) -> None:
        self.stages.seconds[self.name] = time.perf_counter() - self.start
        progress = self.stages.progress
        if progress is not None and exc_type is None and self.total is None:
            progress.update(self.task, total=1, completed=1)  # a stage without a count shows as done
