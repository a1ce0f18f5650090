"""Whether the shaken photos' loss keeps the sharp bound's scene: a blur model trained on from the Gaussians of plain
Gaussians trained on the sharp twin (prints a table). Run from the repository root::

    python -m tools.shake.warm_start --suite <suite yaml> --out <folder>

``--suite`` names a generated scene, its schedule, thread count and scene root (a 6000-step suite of
``docs/results/real-size/shake-fit/``; its ``methods`` are not read). The tool

1. trains ``--bound-method`` (plain Gaussians on the sharp twin) for the suite's steps, or reads the Gaussians it
   kept in ``<out>/bound.pt`` from an earlier call (written to a temp path, then renamed);
2. builds ``--method`` (a blur model; ``cpu-shake-true-paths`` holds the recorded shake paths fixed) on the shaken
   scene, replaces its Gaussians by the bound's before any step, and moves it to step ``--start-step`` of the
   suite's schedule (resolution, SH degree, blur scale and every learning rate as training would have them there;
   past the end of densification, so the Gaussian count stays the bound's);
3. trains it on the shaken photos to the suite's last step, evaluating the sharp test views every ``--eval-every``
   steps, and its fit of the shaken training photos (:func:`gsmsdr_ns.bench.evaluation.train_view_psnr`) at the
   start and the end.

If the test PSNR stays at the bound's while the fit rises, the blurred loss has the sharp scene as a good optimum
and what keeps a run from scratch below the bound is the way there; if it falls while the fit rises, the shaken
photos' loss prefers a scene that is wrong for the test views. ``<out>/warm_start-<method>.json`` keeps the curve.
"""

from __future__ import annotations

import json
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List

import torch
import tyro

GAUSSIAN_PREFIX = "gauss_params."
"""State-dict keys of the Gaussian parameters (means, scales, quats, features, opacities)."""


def _write_atomic(path: Path, write) -> None:
    temp = path.with_name(path.name + ".tmp")
    write(temp)
    os.replace(temp, path)


def fast_forward_schedulers(optimizers, step: int) -> None:
    """Set every learning-rate scheduler of nerfstudio's ``optimizers`` to where ``step`` training steps leave it."""
    with warnings.catch_warnings():  # torch warns of a scheduler stepped before its optimizer: intended here
        warnings.simplefilter("ignore", UserWarning)
        for scheduler in optimizers.schedulers.values():
            scheduler.last_epoch = step - 1
            scheduler.step()


def with_gaussians(state: Dict[str, torch.Tensor], gaussians: Dict[str, torch.Tensor]) -> Dict[str, torch.Tensor]:
    """``state`` (a model's state dict) with its Gaussian parameters replaced by ``gaussians``'s."""
    missing = [k for k in state if k.startswith(GAUSSIAN_PREFIX) and k not in gaussians]
    if missing:
        raise ValueError(f"the bound's Gaussians lack {missing}")
    return {**state, **{k: v for k, v in gaussians.items() if k.startswith(GAUSSIAN_PREFIX)}}


@dataclass
class WarmStart:
    suite: Path
    """A suite file with one generated scene (its scene, schedule, steps, threads and scene root are used)."""
    out: Path
    """Output folder: bound.pt (the bound's Gaussians, reused), warm_start-<method>.json, nerfstudio work files."""
    method: str = "cpu-shake-true-paths"
    """The blur model trained on from the bound's Gaussians."""
    bound_method: str = "sharp"
    """The bound whose Gaussians start it."""
    start_step: int = 4500
    """The step of the suite's schedule the warm start begins at (after the end of densification)."""
    eval_every: int = 250
    """Test views evaluated every this many steps."""
    seed: int = 0
    """Training seed of both runs."""

    def main(self) -> None:
        from gsmsdr_ns.bench.evaluation import evaluate_test_views, train_view_psnr
        from gsmsdr_ns.bench.methods import METHODS
        from gsmsdr_ns.bench.suite_config import load_suite
        from gsmsdr_ns.bench.training import InProcessRun

        suite = load_suite(self.suite)
        if len(suite.scenes) != 1 or len(suite.steps) != 1:
            raise SystemExit(f"{self.suite}: name one scene and one step budget (has {len(suite.scenes)} / "
                             f"{len(suite.steps)})")  # fmt: skip
        steps = suite.steps[0]
        if not 0 < self.start_step < steps:
            raise SystemExit(f"--start-step {self.start_step} must lie inside the suite's {steps} steps")
        scene = suite.scene(suite.scenes[0].name)
        scene_root = Path(suite.scene_root or self.out)
        self.out.mkdir(parents=True, exist_ok=True)
        work = self.out / "nerfstudio"
        if suite.threads > 0:
            torch.set_num_threads(suite.threads)
        schedule = suite.schedule_for(steps)

        def make_run(method_name: str) -> InProcessRun:
            method = METHODS[method_name]
            config = method.make_config(scene.data(method, scene_root, print), work)
            scene.configure(config)
            config.experiment_name = f"warm-start-{method_name}"
            schedule.apply(config)
            return InProcessRun(config, seed=self.seed)

        bound_file = self.out / "bound.pt"
        if bound_file.is_file():
            saved = torch.load(bound_file, map_location="cpu")
        else:
            run = make_run(self.bound_method)
            run.train(steps)
            metrics = evaluate_test_views(run)
            gaussians = {k: v.detach().cpu().clone() for k, v in run.model.state_dict().items()
                         if k.startswith(GAUSSIAN_PREFIX)}  # fmt: skip
            saved = {"gaussians": gaussians, "psnr": metrics["psnr"], "psnr_views": metrics["psnr_views"],
                     "train_seconds": run.train_seconds, "method": self.bound_method, "steps": steps}  # fmt: skip
            run.close()
            _write_atomic(bound_file, lambda p: torch.save(saved, p))
        print(f"bound {saved['method']}: {saved['psnr']:.2f} dB after {saved['steps']} steps")

        run = make_run(self.method)
        model = run.model
        gaussians = {k: v.to(model.device) for k, v in saved["gaussians"].items()}
        model.load_state_dict(with_gaussians(model.state_dict(), gaussians))
        run.step = self.start_step
        model.step_cb(run.trainer.optimizers, self.start_step)  # what the first step's callback would set
        fast_forward_schedulers(run.trainer.optimizers, self.start_step)

        curve: List[Dict[str, Any]] = []

        def evaluate(with_fit: bool) -> None:
            started = time.perf_counter()
            metrics = evaluate_test_views(run)
            point = {"step": run.step, "train_seconds": run.train_seconds, "psnr": metrics["psnr"],
                     "psnr_views": metrics["psnr_views"], "num_gaussians": int(model.num_points)}  # fmt: skip
            if with_fit:
                point["train_psnr"] = train_view_psnr(run)
            curve.append(point)
            fit = f", training fit {point['train_psnr']:.2f}" if with_fit else ""
            print(f"step {run.step}: test {point['psnr']:.2f} dB {point['psnr_views']}{fit} "
                  f"({time.perf_counter() - started:.0f} s to evaluate)", flush=True)  # fmt: skip

        evaluate(with_fit=True)
        while run.step < steps:
            run.train(min(self.eval_every, steps - run.step))
            evaluate(with_fit=run.step == steps)
        run.close()
        bound = {k: v for k, v in saved.items() if k != "gaussians"}
        result = {"suite": str(self.suite), "method": self.method, "bound": bound, "start_step": self.start_step,
                  "threads": suite.threads, "curve": curve}  # fmt: skip
        _write_atomic(self.out / f"warm_start-{self.method}.json", lambda p: p.write_text(json.dumps(result, indent=1)))
        print("| step | test PSNR | per test view | training fit |\n| ---: | ---: | --- | ---: |")
        for point in curve:
            fit = f"{point['train_psnr']:.2f}" if "train_psnr" in point else ""
            views = " / ".join(f"{v:.2f}" for v in point["psnr_views"])
            print(f"| {point['step']} | {point['psnr']:.2f} | {views} | {fit} |")


if __name__ == "__main__":
    tyro.cli(WarmStart).main()
