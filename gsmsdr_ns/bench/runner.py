"""Running a suite: every run trains in this process, one after the other
(:class:`gsmsdr_ns.bench.training.InProcessRun`), with the suite's :class:`gsmsdr_ns.plugin.schedule.TrainingSchedule`
for its step budget, is evaluated every ``eval_every`` steps (and at step 0 and the last step) by
:func:`gsmsdr_ns.bench.evaluation.evaluate_test_views`, and its training time is split into rasterization / blur
field / kernel application / densification / data / other
(:class:`gsmsdr_ns.bench.timing.TimingRecorder`). Evaluation time is not training time.

In the output folder:

* ``runs/<scene>__<method>__<steps>__s<seed>.json``: one record per finished run, written atomically when the run
  ends (with every step's training time and Gaussian count, ``step_trace``, and the schedule ``ns-train``'s time
  estimate would know, ``step_schedule``: ``gsmsdr-bench eta`` replays the estimate on them); ``runs/<same>.log``:
  what the run printed. A rerun of the suite skips every run whose record exists and
  matches the run's settings (:func:`fingerprint`), so an interrupted suite resumes where it stopped (the run that
  was interrupted starts over). A run on estimated records whose fingerprint changed only because the estimate did
  (its version, config or fitted ensembles) keeps its record when the records it trains on are the same as they
  were (:func:`gsmsdr_ns.bench.ledger.rekey_unchanged_estimates`);
* ``renders/<run id>/``: with the suite's ``final_renders``, each test view's final render and ground truth;
* ``results.csv``, ``results.md`` and the plots (:mod:`gsmsdr_ns.bench.report`), regenerated after every run;
* ``scenes/``: the generated scenes (made once, reused).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import signal
import sys
import time
import traceback
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional

from gsmsdr_ns.bench.evaluation import evaluate_test_views, make_lpips
from gsmsdr_ns.bench.fingerprint import RECORD_VERSION, fingerprint
from gsmsdr_ns.bench.ledger import SuiteLedger, SuiteOutcome, records_digest
from gsmsdr_ns.bench.machine import machine_info
from gsmsdr_ns.bench.methods import METHODS
from gsmsdr_ns.bench.suite_config import RunKey, Suite

ALIGNED_KEYS = ("psnr_aligned", "ssim_aligned", "lpips_aligned", "pose_correction_deg")
"""Record fields of a suite with ``align_poses`` (the final evaluation after test-pose alignment)."""


def train_and_record(
    suite: Suite,
    key: RunKey,
    scene_root: Path,
    work_dir: Path,
    lpips=None,
    on_step: Optional[Callable[[int], None]] = None,
    on_eval: Optional[Callable[[Dict[str, Any]], None]] = None,
    log: Optional[Callable[[str], None]] = None,
) -> Dict[str, Any]:
    """Train one run of ``suite`` and return its record (not written). ``on_step(n)`` after every n steps.
    ``work_dir`` is ``<out>/runs/nerfstudio`` (the suite's renders go to ``<out>/renders``)."""
    import torch

    from gsmsdr_ns.bench.evaluation import learnt_shake_paths, train_view_psnr
    from gsmsdr_ns.bench.timing import PeakMemory, TimingRecorder
    from gsmsdr_ns.bench.training import InProcessRun
    from gsmsdr_ns.plugin.pose_alignment import PoseAlignmentConfig

    method = METHODS[key.method]
    scene = suite.scene(key.scene)
    data = scene.data(method, scene_root, log)
    config = method.make_config(data, work_dir)
    scene.configure(config)
    config.experiment_name = key.id
    suite.schedule_for(key.steps).apply(config)
    estimated: Dict[str, str] = {}
    if scene.trains_on_estimated_records(method):  # what lets a later estimate that changes no label keep the record
        estimated = {"training_records": records_digest(config),
                     "fingerprint_without_estimate": fingerprint(suite, key, estimate=False)}  # fmt: skip

    memory = PeakMemory()
    memory.reset()
    started = time.perf_counter()
    run = InProcessRun(config, seed=key.seed)
    setup_seconds = time.perf_counter() - started
    device = str(run.trainer.device)
    recorder = TimingRecorder(sync_cuda=device.startswith("cuda")).attach(run.pipeline)
    curve: List[Dict[str, Any]] = []
    trace: Dict[str, List[Any]] = {"seconds": [], "gaussians": []}
    eval_seconds = 0.0
    shake_paths: Optional[Dict[str, Any]] = None
    try:
        eval_steps = suite.eval_steps(key.steps)
        alignment = PoseAlignmentConfig() if suite.align_poses else None
        for target in eval_steps:
            while run.step < target:
                before = recorder.wall
                with recorder.measure():
                    run.train(1)
                trace["seconds"].append(round(recorder.wall - before, 5))
                trace["gaussians"].append(int(run.model.num_points))
                if on_step is not None:
                    on_step(1)
            t0 = time.perf_counter()
            last = target == eval_steps[-1]
            renders = Path(work_dir).parent.parent / "renders" / key.id if last and suite.final_renders else None
            metrics = evaluate_test_views(run, lpips, align=alignment if last else None, renders_to=renders)
            if last and suite.train_fit:
                metrics["train_psnr"] = train_view_psnr(run)
                shake_paths = learnt_shake_paths(run)
            eval_seconds += time.perf_counter() - t0
            point = {"step": run.step, "seconds": recorder.wall, **metrics,
                     "num_gaussians": int(run.model.num_points), "breakdown": recorder.totals()}  # fmt: skip
            curve.append(point)
            if on_eval is not None:
                on_eval(point)
        final = curve[-1]
        record = {
            "version": RECORD_VERSION,
            "id": key.id,
            "suite": suite.name,
            "scene": key.scene,
            "method": key.method,
            "steps": key.steps,
            "seed": key.seed,
            "fingerprint": fingerprint(suite, key),
            **estimated,
            "data": str(data),
            "psnr": final["psnr"],
            "ssim": final["ssim"],
            "lpips": final["lpips"],
            "train_seconds": recorder.wall,
            "step_ms": 1000.0 * recorder.wall / max(key.steps, 1),
            "setup_seconds": setup_seconds,
            "eval_seconds": eval_seconds,
            "num_gaussians": final["num_gaussians"],
            "num_test_views": final["num_views"],
            **{k: final[k] for k in ALIGNED_KEYS if k in final},
            **{k: final[k] for k in ("psnr_views", "train_psnr") if k in final},
            "peak_rss_mb": memory.peak_rss_mb(),
            "peak_rss_span": memory.span_reset,
            "peak_cuda_mb": memory.peak_cuda_mb(),
            "breakdown": recorder.totals(),
            "breakdown_split": recorder.split(),
            "blur_field_modules": _active_modules(run.model),
            "curve": curve,
            **({"shake_paths": shake_paths} if shake_paths is not None else {}),
            "step_trace": trace,
            "step_schedule": dataclasses.asdict(_step_schedule(run, key.steps)),
            "machine": machine_info(),
            "finished": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        }
    finally:
        recorder.detach()
        run.close()
        if torch.cuda.is_available():
            torch.cuda.empty_cache()
    return record


def _step_schedule(run, steps: int):
    """The run's :class:`gsmsdr_ns.plugin.time_estimate.StepSchedule` (what ``ns-train``'s time estimate knows)."""
    from gsmsdr_ns.plugin.time_estimate import step_schedule_of

    cameras = run.pipeline.datamanager.train_dataparser_outputs.cameras
    sizes = list(zip(cameras.width.view(-1).tolist(), cameras.height.view(-1).tolist()))
    return step_schedule_of(run.model, sizes, steps)


def _active_modules(model) -> str:
    """What the model built (e.g. "blur field (full, RGB-D, kernels (5, 9, 17))"), from its own description."""
    describe = getattr(model, "_describe_modules", None)
    try:
        return str(describe()) if describe is not None else ""
    except Exception:  # noqa: BLE001 - informative only
        return ""


# -- the suite ----------------------------------------------------------------------------------------------------


def run_suite(
    suite: Suite,
    out: Path,
    command: str = "",
    progress: bool = True,
    plots: bool = True,
    console=None,
    interrupt_after: Optional[int] = None,
) -> SuiteOutcome:
    """Run every run of ``suite`` that has no matching record in ``out/runs``, one after another in this process;
    rewrite the outputs after each.

    ``interrupt_after``: after that many runs were trained (and their outputs written), send this process SIGINT,
    as Ctrl-C would: the interrupted suite then stops the same way (KeyboardInterrupt, finished records kept), at a
    point that does not depend on timing."""
    import torch
    from rich.console import Console
    from rich.progress import Progress

    if suite.threads > 0:
        torch.set_num_threads(suite.threads)
    console = console or Console(file=sys.stdout)
    ledger = SuiteLedger(suite, out, command, console, plots)
    todo = ledger.plan.todo
    lpips = None
    if suite.lpips and todo:
        lpips = make_lpips("cuda" if torch.cuda.is_available() else "cpu")
    if suite.lpips and lpips is None and todo:
        console.print(LPIPS_MISSING)
    ledger.start()

    current = ""
    try:
        with Progress(*progress_columns(), console=console, disable=not progress, redirect_stdout=False,
                      redirect_stderr=False) as bars:  # fmt: skip
            suite_task = bars.add_task(f"{suite.name}", total=ledger.plan.total,
                                       completed=ledger.plan.total - ledger.left, info="")  # fmt: skip
            for key in todo:
                current = key.id
                run_task = bars.add_task(f"  {key.scene} {key.method} s{key.seed}", total=key.steps, info="")

                def on_eval(point: Dict[str, Any], task=run_task) -> None:
                    bars.update(task, info=f"PSNR {point['psnr']:.2f} @ {point['step']}")

                log_path = ledger.log_path(key)
                started = time.perf_counter()
                try:
                    with open(log_path, "w", encoding="utf8") as log_file, contextlib.redirect_stdout(log_file), \
                            contextlib.redirect_stderr(log_file):  # fmt: skip
                        record = train_and_record(
                            suite, key, ledger.scene_root, ledger.work_dir, lpips,
                            on_step=lambda n, task=run_task: bars.advance(task, n), on_eval=on_eval,
                            log=lambda message: print(message, flush=True),
                        )  # fmt: skip
                    ledger.finished(key, record)
                except Exception as e:  # noqa: BLE001 - one failed run does not stop the suite
                    with open(log_path, "a", encoding="utf8") as log_file:
                        log_file.write(traceback.format_exc())
                    ledger.failed_run(key, f"{type(e).__name__}: {e}", time.perf_counter() - started)
                finally:
                    bars.remove_task(run_task)
                current = f"writing the outputs after {key.id}"
                bars.advance(suite_task, ledger.weight(key))
                ledger.refresh()
                if interrupt_after is not None and len(ledger.trained) + len(ledger.failed) >= interrupt_after:
                    signal.raise_signal(signal.SIGINT)
    except KeyboardInterrupt:
        ledger.interrupted(current)
        raise
    return ledger.outcome()


LPIPS_MISSING = ("[yellow]LPIPS: torchvision's AlexNet weights are not in the torch hub cache; LPIPS is left out "
                 "(nothing is downloaded)[/yellow]")  # fmt: skip


def progress_columns() -> tuple:
    """The progress bars' columns: description, bar, done / total, elapsed, time left, and a run's latest PSNR."""
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    return (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
            TextColumn("eta"), TimeRemainingColumn(), TextColumn("{task.fields[info]}"))  # fmt: skip


__all__ = [
    "LPIPS_MISSING",
    "SuiteOutcome",
    "progress_columns",
    "run_suite",
    "train_and_record",
]
