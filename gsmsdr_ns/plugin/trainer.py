"""nerfstudio's Trainer with atomic checkpoints and checked checkpoint loading (the gsmsdr presets use it).

* ``save_checkpoint`` writes the same file (``<run>/nerfstudio_models/step-<step:09d>.ckpt``, same contents) through
  a temporary file, fsync and rename (:func:`save_checkpoint_atomic`), so a full disk or a kill never leaves a
  truncated ``.ckpt``; a full disk raises :class:`DiskFullError` naming the file. ``save_only_latest_checkpoint``
  deletes the older checkpoints only after the new one is complete.
* ``_load_checkpoint`` (``ns-train --load-dir`` / ``--load-checkpoint``) finds and reads the file with
  :func:`find_checkpoint` / :func:`load_checkpoint_file`: a missing, empty, truncated or damaged checkpoint, a
  folder without checkpoints or a run folder given instead of its ``nerfstudio_models`` raise :class:`InputError`
  naming the file and what to do; a checkpoint of the other preset names both presets' widths.
* Ctrl-C (``setup`` / ``train``) prints one line and exits 130, naming the last complete checkpoint; closing the
  viewer after training exits normally. Step counts below 1 are an InputError before anything is read.
* :class:`GSMSDRTrainerConfig` checks ``load_dir`` when it is assigned after construction: nerfstudio's
  ``eval_setup`` (``ns-eval``, ``ns-viewer``, ``gsmsdr-eval``, ``gsmsdr-export``) does that right before its own
  loader, which names no file when it fails.
"""

from __future__ import annotations

import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional, Type

from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils import writer
from nerfstudio.utils.decorators import check_main_thread
from nerfstudio.utils.rich_utils import CONSOLE

from gsmsdr_ns._cli import INTERRUPT_EXIT_STATUS
from gsmsdr_ns.io.errors import InputError, exception_chain
from gsmsdr_ns.plugin.checkpoint_compat import CheckpointMismatchError
from gsmsdr_ns.plugin.checkpoint_io import (
    checkpoint_file,
    find_checkpoint,
    load_checkpoint_file,
    save_checkpoint_atomic,
)
from gsmsdr_ns.plugin.time_estimate import TimeEstimate, format_duration, step_schedule_of

STEP_OPTIONS = ("max_num_iterations", "steps_per_save", "steps_per_log")
"""Trainer step counts that must be >= 1 (0 ends nerfstudio's loop in a KeyError or divides by zero)."""


def check_step_options(config: TrainerConfig) -> None:
    """InputError naming the option and its allowed range when a step count of ``config`` is below 1."""
    values = {name: getattr(config, name, None) for name in STEP_OPTIONS}
    values["steps_per_log"] = config.logging.steps_per_log
    for name, value in values.items():
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
            flag = "--logging.steps-per-log" if name == "steps_per_log" else "--" + name.replace("_", "-")
            raise InputError(f"gsmsdr: {flag} must be an integer >= 1, got {value!r}")


def _exit_interrupted(message: str) -> None:
    """Print ``gsmsdr: <message>`` on stderr and exit with status 130 (128 + SIGINT), as shells report Ctrl-C.

    SystemExit, unlike KeyboardInterrupt, passes nerfstudio's launcher, which would print a traceback and return 0."""
    print(f"gsmsdr: {message}", file=sys.stderr, flush=True)
    raise SystemExit(INTERRUPT_EXIT_STATUS)


def trained_method(checkpoint: Path) -> Optional[str]:
    """The ``method_name`` in the ``config.yml`` of the run a checkpoint belongs to (``<run>/nerfstudio_models/``),
    or None when there is none. Read as text: loading the YAML would build the whole config."""
    config = Path(checkpoint).parent.parent / "config.yml"
    try:
        match = re.search(r"^method_name: *['\"]?([\w.-]+)", config.read_text(encoding="utf8"), re.MULTILINE)
    except (OSError, UnicodeDecodeError):
        return None
    return match.group(1) if match else None


PAUSE_CAP = 50
"""A loop iteration counts at most this many times its training step in the time estimate: longer is a pause in
the viewer (or a stall), not what the remaining steps will cost."""


def replace_eta(step: int, seconds: float) -> None:
    """Make ``seconds`` the ETA nerfstudio's writers show for ``step`` (the console table and the logged scalar)."""
    name = writer.EventName.ETA.value
    writer.GLOBAL_BUFFER.setdefault("events", {})[name] = format_duration(seconds)
    for event in reversed(writer.EVENT_STORAGE[-8:]):
        if event["name"] == name and event["step"] == step:
            event["event"] = seconds
            break


class GSMSDRTrainer(Trainer):
    """nerfstudio's Trainer; checkpoints are written atomically and loaded with errors that name the file, and
    Ctrl-C ends ``ns-train`` with one line and exit status 130 (nerfstudio's launcher prints a traceback and exits 0,
    so a script would count an interrupted run as a success)."""

    config: "GSMSDRTrainerConfig"

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        check_step_options(self.config)
        try:
            super().setup(test_mode)
        except BaseException as e:
            # Ctrl-C itself, or an error a library made of it (pycolmap's import: "Cannot import the C++ backend")
            if any(isinstance(cause, KeyboardInterrupt) for cause in exception_chain(e)):
                _exit_interrupted("interrupted while setting up; nothing was trained")
            raise

    def train(self) -> None:
        self._training_finished = False
        self._time_estimate = self._new_time_estimate()
        self._step_clock = time.perf_counter()
        try:
            super().train()
        except KeyboardInterrupt:
            if self._training_finished:  # Ctrl-C is how a finished run's viewer is closed: not an interruption
                CONSOLE.print("gsmsdr: viewer closed; training had finished")
                return
            kept = sorted(self.checkpoint_dir.glob("step-*.ckpt")) if self.checkpoint_dir.is_dir() else []
            what = f"the last complete checkpoint is {kept[-1]}" if kept else "no checkpoint had been written yet"
            _exit_interrupted(f"interrupted at step {self.step}; {what}")

    def _train_complete_viewer(self) -> None:
        self._training_finished = True
        super()._train_complete_viewer()

    def _new_time_estimate(self) -> Optional[TimeEstimate]:
        cameras = getattr(self.pipeline.datamanager, "train_dataparser_outputs", None)
        if cameras is None:
            return None
        cameras = cameras.cameras
        sizes = list(zip(cameras.width.view(-1).tolist(), cameras.height.view(-1).tolist()))
        last = self._start_step + self.config.max_num_iterations
        return TimeEstimate(step_schedule_of(self.pipeline.model, sizes, last))

    def _update_viewer_state(self, step: int) -> None:
        """The viewer's update (nerfstudio's), then the ETA: nerfstudio's (the remaining steps times the mean of the
        last 20 step times) is replaced by :class:`TimeEstimate`'s, which follows the resolution schedule and the
        Gaussians' growth and counts what a loop iteration costs besides the step (viewer, evaluations, checkpoints),
        up to :data:`PAUSE_CAP` times the step itself."""
        super()._update_viewer_state(step)
        now = time.perf_counter()
        seconds, self._step_clock = now - self._step_clock, now
        if self._time_estimate is None:
            return
        iteration = writer.GLOBAL_BUFFER.get("events", {}).get(writer.EventName.ITER_TRAIN_TIME.value)
        if iteration and iteration.get("buffer"):  # a pause in the viewer is not training time
            seconds = min(seconds, PAUSE_CAP * iteration["buffer"][-1])
        self._time_estimate.add(step, seconds, int(getattr(self.pipeline.model, "num_points", 0)))
        remaining = self._time_estimate.remaining()
        if remaining is not None:
            replace_eta(step, remaining)

    @check_main_thread
    def save_checkpoint(self, step: int) -> None:
        """Save the pipeline, optimizers, schedulers and grad scaler as nerfstudio does, atomically (after the model's
        non-finite check, which raises instead of saving a NaN)."""
        pipeline = self.pipeline.module if hasattr(self.pipeline, "module") else self.pipeline
        # a NaN the model's deferred check has not read yet stops training here instead of reaching the checkpoint
        check_finite = getattr(pipeline.model, "raise_if_nonfinite", None)
        if check_finite is not None:
            check_finite()
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        path = checkpoint_file(self.checkpoint_dir, step)
        payload = {
            "step": step,
            "pipeline": pipeline.state_dict(),  # type: ignore[union-attr]
            "optimizers": {k: v.state_dict() for (k, v) in self.optimizers.optimizers.items()},
            "schedulers": {k: v.state_dict() for (k, v) in self.optimizers.schedulers.items()},
            "scalers": self.grad_scaler.state_dict(),
        }
        save_checkpoint_atomic(payload, path)
        if self.config.save_only_latest_checkpoint:
            for old in self.checkpoint_dir.glob("*.ckpt"):
                if old != path:
                    old.unlink()

    def _load_checkpoint(self) -> None:
        """Load the pipeline, optimizers, schedulers and grad scaler from ``--load-dir`` / ``--load-checkpoint``."""
        if self.config.load_dir is not None:
            if self.config.load_step is None:
                CONSOLE.print("Loading latest Nerfstudio checkpoint from load_dir...")
            path = find_checkpoint(self.config.load_dir, self.config.load_step)
        elif self.config.load_checkpoint is not None:
            path = Path(self.config.load_checkpoint)
        else:
            CONSOLE.print("No Nerfstudio checkpoint to load, so training from scratch.")
            return
        loaded_state = load_checkpoint_file(path)
        self._start_step = loaded_state["step"] + 1
        try:
            self.pipeline.load_pipeline(loaded_state["pipeline"], loaded_state["step"])
        except CheckpointMismatchError as e:
            raise e.for_file(path, trained_method(path)) from None
        self.optimizers.load_optimizers(loaded_state["optimizers"])
        if "schedulers" in loaded_state and self.config.load_scheduler:
            self.optimizers.load_schedulers(loaded_state["schedulers"])
        self.grad_scaler.load_state_dict(loaded_state["scalers"])
        CONSOLE.print(f"Done loading Nerfstudio checkpoint from {path}")


@dataclass
class GSMSDRTrainerConfig(TrainerConfig):
    """nerfstudio's TrainerConfig building a :class:`GSMSDRTrainer`; assigning ``load_dir`` checks the folder."""

    _target: Type = field(default_factory=lambda: GSMSDRTrainer)

    def __setattr__(self, name: str, value) -> None:
        # eval_setup assigns the run's checkpoint folder here right before nerfstudio's loader reads the latest file
        # (which fails without naming it). Not while __init__ runs (load_step is set after load_dir): the trainer
        # checks --load-dir itself, after the config is printed.
        if name == "load_dir" and value is not None and "load_step" in self.__dict__:
            find_checkpoint(Path(value), self.load_step, nerfstudio_names=True)
        super().__setattr__(name, value)
