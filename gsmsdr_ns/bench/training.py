"""Training one bench run in this process, the same way for every method: nerfstudio's ``Trainer`` (pipeline,
optimizers, ``train_iteration`` and the training callbacks) without viewer, event writers or checkpoints, with one
:class:`gsmsdr_ns.plugin.schedule.TrainingSchedule` applied to every method; evaluated by
:mod:`gsmsdr_ns.bench.evaluation`."""

from __future__ import annotations

import gc
import math
import random
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from gsmsdr_ns.bench.scenes import SceneSpec
from gsmsdr_ns.plugin.schedule import TrainingSchedule


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
        # reading the loss waits for the device: on a GPU it is read once per call (the model's own finite check
        # catches a non-finite step in between), on the CPU after every step, where it costs nothing
        check_every_step = torch.device(trainer.device).type == "cpu"
        started = time.perf_counter()
        for index in range(num_steps):
            step = self.step
            for callback in trainer.callbacks:
                callback.run_callback_at_location(step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
            loss, loss_dict, _ = trainer.train_iteration(step)
            for callback in trainer.callbacks:
                callback.run_callback_at_location(step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
            if (check_every_step or index == num_steps - 1) and not math.isfinite(float(loss.detach())):
                raise FloatingPointError(f"non-finite loss at step {step}: {loss_dict}")
            self.step += 1
        self.train_seconds += time.perf_counter() - started

    def close(self) -> None:
        self.trainer = None  # type: ignore[assignment]
        gc.collect()


def method_run_config(method: str, data: Path, output_dir: Path, schedule: TrainingSchedule):
    """The TrainerConfig of the registered ``method`` on ``data`` with ``schedule`` applied."""
    from gsmsdr_ns.bench.methods import method_spec

    config = method_spec(method).make_config(data, output_dir)
    schedule.apply(config)
    return config


@dataclass
class RunResult:
    """One method trained and evaluated on one generated scene (:func:`run_method`)."""

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


def run_method(
    method: str,
    spec: SceneSpec,
    schedule: TrainingSchedule,
    bench_dir: Path,
    seed: int = 0,
    train_fit: bool = False,
    log: Optional[Callable[[str], None]] = None,
) -> RunResult:
    """Train the registered ``method`` on the scene of ``spec`` (its sharp twin for the upper bound) for
    ``schedule.steps`` steps and evaluate it; ``train_fit`` adds the training-view fit (:func:`train_view_psnr`)."""
    from gsmsdr_ns.bench.evaluation import evaluate_test_views, train_view_psnr
    from gsmsdr_ns.bench.methods import method_spec
    from gsmsdr_ns.bench.scenes import ensure_scene

    scene_spec = spec.with_variant("sharp") if method_spec(method).sharp_data else spec
    data = ensure_scene(bench_dir, scene_spec, log)
    config = method_run_config(method, data, Path(bench_dir) / "runs", schedule)
    config.experiment_name = f"{spec.name}-{method}"
    run = InProcessRun(config, seed=seed)
    try:
        run.train(schedule.steps)
        started = time.perf_counter()
        metrics = evaluate_test_views(run)
        eval_seconds = time.perf_counter() - started
        result = RunResult(
            scene=spec.variant,
            method=method,
            steps=schedule.steps,
            psnr=metrics["psnr"],
            ssim=metrics["ssim"],
            train_psnr=train_view_psnr(run) if train_fit else float("nan"),
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


__all__ = ["InProcessRun", "RunResult", "method_run_config", "run_method", "seed_everything"]
