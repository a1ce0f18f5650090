"""Training and evaluating one method on one generated scene, the same way for every method (used by the
``gsmsdr-bench suite`` runs and by tests/test_accuracy.py).

On a generated scene (``generate_variant``: motion, defocus, mixres, ...; Deblur-NeRF layout, sharp test views with
their ``images_test/`` twins) the same step budget trains:

* ``plain``: the ``gsmsdr`` preset with ``degradation sharp``, i.e. plain splatfacto Gaussians fitted straight to the
  degraded training images (no blur field, no resolution model; a plain splatfacto step);
* ``gsmsdr``: the ``gsmsdr`` preset, ``degradation auto`` (per image from the scene's ``degradation.json``);
* ``gsmsdr-lite``: the ``gsmsdr-lite`` preset, ``degradation auto``;
* ``sharp``: ``plain`` trained on the *sharp* variant of the same scene and seed (identical cameras and test
  views): the upper bound a perfect deblurring method could reach with this budget.

Every method gets the same shortened schedule (:func:`shorten_schedules`: resolution doubling, warm-ups,
densification window, learning-rate decay scaled to the step budget); nothing else of the presets changes.
Training runs in-process with nerfstudio's ``Trainer.train_iteration`` and training callbacks (no viewer, writers
or checkpoints); test metrics are ``pipeline.get_average_eval_image_metrics()``, which is what ``ns-eval``
(``ComputePSNR``) computes on the same split (the dataparser's ``val`` and ``test`` splits are the same held-out
views, ground truth from ``images_test/``). The train-view fit is the PSNR of the training-mode ``rgb`` (the
simulated degradation for gsmsdr, the render for plain) against the degraded training image.
"""

from __future__ import annotations

import dataclasses
import gc
import math
import os
import random
import shutil
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, Optional

import numpy as np
import torch

METHODS = ("plain", "gsmsdr", "gsmsdr-lite", "sharp")
"""plain (degradation sharp on the degraded images), gsmsdr, gsmsdr-lite, sharp (plain on the sharp variant)."""


SCENE_DATA_VERSION = 2
"""Bumped when generated scenes change for the same spec (2: motion sub-frames rendered with the scene's own
anti-aliasing), so cached scenes of an older generator are not reused."""


@dataclass(frozen=True)
class SceneSpec:
    """A generated scene: the procedural scene's size and seed, and the degradation variant."""

    variant: str
    width: int = 160
    height: int = 120
    num_views: int = 24
    seed: int = 0
    hold: int = 6
    num_points: int = 3000

    @property
    def name(self) -> str:
        return (
            f"{self.variant}-{self.width}x{self.height}-v{self.num_views}-h{self.hold}-s{self.seed}"
            f"-g{SCENE_DATA_VERSION}"
        )

    def with_variant(self, variant: str) -> "SceneSpec":
        return dataclasses.replace(self, variant=variant)


@dataclass(frozen=True)
class Schedule:
    """The step budget and the schedules derived from it, applied identically to every method."""

    steps: int
    num_downscales: int = 1
    """Resolution schedule: start at 1 / 2^num_downscales and double ``num_downscales`` times over the first
    ``resolution_fraction`` of the steps (the HPKO scale follows it)."""
    resolution_fraction: float = 0.5
    blur_warmup_fraction: float = 0.05
    """Blur field skipped for the first fraction of the steps (preset: 250 of 30000 steps, BAGS)."""
    densify_until_fraction: float = 0.5
    """Densification (split / duplicate) stops after this fraction of the steps (splatfacto: 15000 of 30000)."""
    refinements: int = 15
    """Refinement (densify / cull) rounds before ``stop_split_at``."""
    densify_grad_thresh: float = 0.002
    """Higher than splatfacto's 0.0008 to keep the Gaussian count CPU-sized (as ``make demo``), for all methods."""


@dataclass
class RunResult:
    scene: str
    method: str
    steps: int
    psnr: float
    ssim: float
    train_psnr: float
    train_seconds: float
    num_gaussians: int
    eval_seconds: float = 0.0

    @property
    def step_ms(self) -> float:
        return 1000.0 * self.train_seconds / max(self.steps, 1)


# -- scenes ------------------------------------------------------------------------------------------------------


def ensure_scene(bench_dir: Path, spec: SceneSpec, log: Optional[Callable[[str], None]] = None) -> Path:
    """The generated scene of ``spec`` under ``bench_dir/scenes/<name>``, generated once and reused."""
    from gsmsdr_ns.degrade.variants import generate_variant
    from gsmsdr_ns.synth.config import SynthSceneConfig

    out = Path(bench_dir) / "scenes" / spec.name

    def complete(folder: Path) -> bool:
        return (folder / "degradation.json").is_file() and (folder / "images_test").is_dir()

    if complete(out):
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    scene = SynthSceneConfig(
        seed=spec.seed, num_views=spec.num_views, width=spec.width, height=spec.height, num_points=spec.num_points
    )
    if log is not None:
        log(f"accuracy: generating {out}")
    # generated beside its final place, then renamed: a suite running in parallel never sees half a scene, and two
    # processes generating the same scene both end up with one complete copy
    partial = Path(tempfile.mkdtemp(prefix=f".{spec.name}.", dir=out.parent))
    try:
        generate_variant(partial, scene, spec.variant, hold=spec.hold, overwrite=True)
        if out.exists() and not complete(out):
            shutil.rmtree(out)  # left by an interrupted run of an older version
        try:
            os.rename(partial, out)
        except OSError:
            if not complete(out):
                raise
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return out


# -- configs -----------------------------------------------------------------------------------------------------


def method_config(method: str, data: Path, output_dir: Path):
    """The TrainerConfig of ``method`` (see the module docstring) on ``data``, CPU unless CUDA is there."""
    from gsmsdr_ns.plugin.method_config import gsmsdr_lite_trainer_config, gsmsdr_trainer_config

    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; valid: {', '.join(METHODS)}")
    config = gsmsdr_lite_trainer_config() if method == "gsmsdr-lite" else gsmsdr_trainer_config()
    if method in ("plain", "sharp"):
        config.pipeline.model.degradation = "sharp"
    config.data = Path(data)
    config.pipeline.datamanager.data = Path(data)
    config.output_dir = Path(output_dir)
    config.vis = "tensorboard"
    config.steps_per_eval_image = 0
    config.steps_per_eval_all_images = 0
    config.pipeline.model.viewer_blur_outputs = False  # evaluation renders rgb only (the metrics use rgb alone)
    return config


def shorten_schedules(config, schedule: Schedule) -> None:
    """Scale the step-dependent schedules of ``config`` to ``schedule.steps`` (the same for every method)."""
    steps = schedule.steps
    config.max_num_iterations = steps
    config.steps_per_save = steps
    model = config.pipeline.model
    model.num_downscales = schedule.num_downscales
    doublings = max(schedule.num_downscales, 1)
    model.resolution_schedule = max(int(steps * schedule.resolution_fraction) // doublings, 1)
    model.blur_field = dataclasses.replace(model.blur_field, warmup=max(int(steps * schedule.blur_warmup_fraction), 1))
    model.stop_split_at = max(int(steps * schedule.densify_until_fraction), 1)
    model.refine_every = max(model.stop_split_at // schedule.refinements, 1)
    model.warmup_length = model.refine_every
    model.stop_screen_size_at = max(steps * 4000 // 30000, 1)  # splatfacto: 4000 of 30000 steps
    model.reset_alpha_every = 10**6  # no opacity reset in a run this short (splatfacto: every 3000 steps)
    model.densify_grad_thresh = schedule.densify_grad_thresh
    model.sh_degree_interval = max(steps // 4, 1)
    for name in ("means", "camera_opt", "bilateral_grid"):
        scheduler = config.optimizers.get(name, {}).get("scheduler")
        if scheduler is not None:
            scheduler.max_steps = steps
            scheduler.warmup_steps = min(scheduler.warmup_steps, steps // 10)


# -- training and evaluation -------------------------------------------------------------------------------------


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


class InProcessRun:
    """One training run in this process: nerfstudio's Trainer (pipeline, optimizers, callbacks) without viewer,
    event writers or checkpoints. ``train(n)`` runs n more steps; ``close()`` drops everything it holds."""

    def __init__(self, config, seed: int = 0):
        from nerfstudio.engine.callbacks import TrainingCallbackAttributes
        from nerfstudio.engine.trainer import Trainer

        from gsmsdr_ns.plugin.model import GSMSDRWarning

        config.machine.seed = seed
        config.pipeline.datamanager.train_cameras_sampling_seed = seed
        seed_everything(seed)
        trainer = Trainer(config)
        device = trainer.device
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", GSMSDRWarning)
            trainer.pipeline = config.pipeline.setup(
                device=device, test_mode="val", world_size=1, local_rank=0, grad_scaler=trainer.grad_scaler
            )
        trainer.optimizers = trainer.setup_optimizers()
        attributes = TrainingCallbackAttributes(trainer.optimizers, trainer.grad_scaler, trainer.pipeline, trainer)
        trainer.callbacks = trainer.pipeline.get_training_callbacks(attributes)
        self.trainer = trainer
        self.step = 0
        self.train_seconds = 0.0

    @property
    def pipeline(self):
        return self.trainer.pipeline

    @property
    def model(self):
        return self.trainer.pipeline.model

    def train(self, num_steps: int) -> None:
        from nerfstudio.engine.callbacks import TrainingCallbackLocation

        trainer = self.trainer
        trainer.pipeline.train()
        started = time.perf_counter()
        for _ in range(num_steps):
            step = self.step
            for callback in trainer.callbacks:
                callback.run_callback_at_location(step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
            loss, loss_dict, _ = trainer.train_iteration(step)
            for callback in trainer.callbacks:
                callback.run_callback_at_location(step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
            if not math.isfinite(float(loss)):
                raise FloatingPointError(f"non-finite loss at step {step}: {loss_dict}")
            self.step += 1
        self.train_seconds += time.perf_counter() - started

    def test_metrics(self) -> Dict[str, float]:
        """ns-eval's metrics (``get_average_eval_image_metrics``) on the held-out sharp test views."""
        with torch.random.fork_rng(devices=[]):
            return self.pipeline.get_average_eval_image_metrics()

    def train_view_psnr(self) -> float:
        """Mean PSNR over the training views of the training-mode ``rgb`` (the simulated degradation when the view
        has a degradation model, else the render) against the degraded training image. Rendered with gradients
        enabled (splatfacto's training forward retains the 2D means' gradients) and the random state restored, so
        training could continue unchanged."""
        model = self.model
        datamanager = self.pipeline.datamanager
        cameras = datamanager.train_dataset.cameras
        values = []
        model.train()
        with torch.random.fork_rng(devices=[]):
            for index, data in enumerate(datamanager.cached_train):
                camera = cameras[index : index + 1].to(model.device)
                camera.metadata = {**(camera.metadata or {}), "cam_idx": index}
                outputs = model(camera)
                rgb = outputs["rgb"].detach()
                gt = model.composite_with_background(model.get_gt_img(data["image"]), outputs["background"])
                mse = torch.mean((rgb - gt[..., :3]) ** 2).clamp_min(1e-10)
                values.append(float(-10.0 * torch.log10(mse)))
                del outputs
        model.info = {}  # drop the graph of the last render
        return float(np.mean(values))

    def close(self) -> None:
        self.trainer = None  # type: ignore[assignment]
        gc.collect()


def run_method(
    method: str,
    spec: SceneSpec,
    schedule: Schedule,
    bench_dir: Path,
    seed: int = 0,
    train_fit: bool = False,
    log: Optional[Callable[[str], None]] = None,
) -> RunResult:
    """Train ``method`` on the scene of ``spec`` (its sharp twin for ``sharp``) and evaluate it."""
    scene_spec = spec.with_variant("sharp") if method == "sharp" else spec
    data = ensure_scene(bench_dir, scene_spec, log)
    config = method_config(method, data, Path(bench_dir) / "runs")
    config.experiment_name = f"{spec.name}-{method}"
    shorten_schedules(config, schedule)
    run = InProcessRun(config, seed=seed)
    try:
        run.train(schedule.steps)
        started = time.perf_counter()
        metrics = run.test_metrics()
        eval_seconds = time.perf_counter() - started
        train_psnr = run.train_view_psnr() if train_fit else float("nan")
        result = RunResult(
            scene=spec.variant,
            method=method,
            steps=schedule.steps,
            psnr=float(metrics["psnr"]),
            ssim=float(metrics["ssim"]),
            train_psnr=train_psnr,
            train_seconds=run.train_seconds,
            num_gaussians=int(run.model.num_points),
            eval_seconds=eval_seconds,
        )
    finally:
        run.close()
    if log is not None:
        log(
            f"accuracy: {spec.variant:8s} {method:12s} psnr {result.psnr:6.2f} ssim {result.ssim:.4f} "
            f"train-view psnr {result.train_psnr:6.2f} train {result.train_seconds:7.1f} s "
            f"({result.step_ms:.0f} ms/step, {result.num_gaussians} Gaussians)"
        )
    return result
