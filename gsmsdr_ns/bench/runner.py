"""Running a suite: every run trains in this process (:class:`gsmsdr_ns.bench.training.InProcessRun`) with the
suite's :class:`gsmsdr_ns.plugin.schedule.TrainingSchedule` for its step budget, is evaluated every ``eval_every``
steps (and at step 0 and the last step) by :func:`gsmsdr_ns.bench.evaluation.evaluate_test_views`, and its training
time is split into rasterization / blur field / kernel application / densification / data / other
(:class:`gsmsdr_ns.bench.timing.TimingRecorder`). Evaluation time is not training time.

In the output folder:

* ``runs/<scene>__<method>__<steps>__s<seed>.json``: one record per finished run, written atomically when the run
  ends; ``runs/<same>.log``: what the run printed. A rerun of the suite skips every run whose record exists and
  matches the run's settings (:func:`fingerprint`), so an interrupted suite resumes where it stopped (the run that
  was interrupted starts over). A run on estimated records whose fingerprint changed only because the estimate did
  (its version, config or fitted ensembles) keeps its record when the records it trains on are the same as they
  were (:func:`rekey_unchanged_estimates`);
* ``results.csv``, ``results.md`` and the plots (:mod:`gsmsdr_ns.bench.report`), regenerated after every run;
* ``scenes/``: the generated scenes (made once, reused).
"""

from __future__ import annotations

import contextlib
import copy
import datetime
import signal
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional

from gsmsdr_ns.bench.evaluation import evaluate_test_views, make_lpips
from gsmsdr_ns.bench.fingerprint import RECORD_VERSION, digest, fingerprint, training_identity
from gsmsdr_ns.bench.machine import machine_info
from gsmsdr_ns.bench.methods import METHODS
from gsmsdr_ns.bench.records import collect_records, finished_record, load_record, record_path, write_json_atomic
from gsmsdr_ns.bench.report import write_outputs
from gsmsdr_ns.bench.suite_config import RunKey, Suite

ALIGNED_KEYS = ("psnr_aligned", "ssim_aligned", "lpips_aligned", "pose_correction_deg")
"""Record fields of a suite with ``align_poses`` (the final evaluation after test-pose alignment)."""


def copied_record(suite: Suite, key: RunKey, source: Dict[str, Any]) -> Dict[str, Any]:
    """The record of run ``key`` made from the record ``source`` of a run with the same
    :func:`training_identity`: its numbers, under ``key``'s id, names and fingerprint, marked ``same_training_as``
    the source's id."""
    record = copy.deepcopy(source)
    record.update(
        id=key.id,
        suite=suite.name,
        scene=key.scene,
        method=key.method,
        steps=key.steps,
        seed=key.seed,
        fingerprint=fingerprint(suite, key),
        same_training_as=source.get("same_training_as", source["id"]),
    )
    if "fingerprint_without_estimate" in record:
        record["fingerprint_without_estimate"] = fingerprint(suite, key, estimate=False)
    return record


def records_digest(config) -> str:
    """Digest of the degradation records a configured TrainerConfig's model trains on, as its dataparser gives them
    for the train split (estimated records included: the estimate is cached beside the scene)."""
    parser = config.pipeline.datamanager.dataparser
    parser.data = config.pipeline.datamanager.data  # as the datamanager hands it over
    records = parser.setup().get_dataparser_outputs("train").metadata.get("degradations")
    return digest({"records": records})


def training_records_digest(suite: Suite, key: RunKey, scene_root: Path, work_dir: Path, log=None) -> str:
    """:func:`records_digest` of run ``key`` (its scene is built first if missing)."""
    method, scene = METHODS[key.method], suite.scene(key.scene)
    config = method.make_config(scene.data(method, scene_root, log), work_dir)
    scene.configure(config)
    return records_digest(config)


def rekey_unchanged_estimates(
    suite: Suite, out: Path, scene_root: Path, work_dir: Path, log: Optional[Callable[[str], None]] = None
) -> List[str]:
    """Give the current fingerprint to the records of runs on estimated records whose fingerprint differs only by
    the estimate's (``fingerprint_without_estimate`` unchanged) while the records they trained on are the same as
    the current estimate gives (``training_records``): the same training, so no rerun. -> the ids re-keyed."""
    rekeyed = []
    for key in suite.runs():
        scene, method = suite.scene(key.scene), METHODS[key.method]
        if not (scene.supports(method) and scene.trains_on_estimated_records(method)):
            continue
        record = load_record(record_path(out, key))
        current = fingerprint(suite, key)
        if record is None or record.get("fingerprint") == current or "training_records" not in record:
            continue
        if record.get("fingerprint_without_estimate") != fingerprint(suite, key, estimate=False):
            continue
        if training_records_digest(suite, key, scene_root, work_dir, log) != record["training_records"]:
            continue
        record["rekeyed_from"] = record.get("rekeyed_from", []) + [record["fingerprint"]]
        record["fingerprint"] = current
        write_json_atomic(record_path(out, key), record)
        rekeyed.append(key.id)
    return rekeyed


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
    """Train one run of ``suite`` and return its record (not written). ``on_step(n)`` after every n steps."""
    import torch

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
    eval_seconds = 0.0
    try:
        eval_steps = suite.eval_steps(key.steps)
        alignment = PoseAlignmentConfig() if suite.align_poses else None
        for target in eval_steps:
            while run.step < target:
                with recorder.measure():
                    run.train(1)
                if on_step is not None:
                    on_step(1)
            t0 = time.perf_counter()
            metrics = evaluate_test_views(run, lpips, align=alignment if target == eval_steps[-1] else None)
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
            "peak_rss_mb": memory.peak_rss_mb(),
            "peak_rss_span": memory.span_reset,
            "peak_cuda_mb": memory.peak_cuda_mb(),
            "breakdown": recorder.totals(),
            "breakdown_split": recorder.split(),
            "blur_field_modules": _active_modules(run.model),
            "curve": curve,
            "machine": machine_info(),
            "finished": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        }
    finally:
        recorder.detach()
        run.close()
        if torch.cuda.is_available():
            torch.cuda.empty_cache()
    return record


def _active_modules(model) -> str:
    """What the model built (e.g. "blur field (full, RGB-D, kernels (5, 9, 17))"), from its own description."""
    describe = getattr(model, "_describe_modules", None)
    try:
        return str(describe()) if describe is not None else ""
    except Exception:  # noqa: BLE001 - informative only
        return ""


# -- the suite ---------------------------------------------------------------------------------------------------


@dataclass
class SuiteOutcome:
    records: List[Dict[str, Any]]
    trained: List[str]
    reused: List[str]
    failed: Dict[str, str]
    skipped: Dict[str, str]
    outputs: List[Path]
    copied: List[str] = field(default_factory=list)
    """Ids of runs whose record was copied from a run with the same training (:func:`training_identity`)."""


@dataclass
class RunPlan:
    """What :func:`run_suite` does with each run of a suite, in the suite's run order."""

    todo: List[RunKey]
    """Runs to train."""
    reused: List[str]
    """Ids of runs with a finished record in ``out/runs``."""
    skipped: Dict[str, str]
    """{id: why} of runs no scene supports."""
    same_as: Dict[RunKey, RunKey] = field(default_factory=dict)
    """{run: source} of runs that are not trained because ``source`` (finished, or trained earlier in ``todo``) has
    the same :func:`training_identity`: they get a copy of its record."""

    @property
    def total(self) -> int:
        return len(self.todo) + len(self.reused) + len(self.skipped) + len(self.same_as)


def plan_runs(suite: Suite, out: Path) -> RunPlan:
    """Sort every run of ``suite`` into :class:`RunPlan`'s lists."""
    plan = RunPlan([], [], {})
    finished: Dict[str, RunKey] = {}  # training identity -> a run with a finished record
    trained: Dict[str, RunKey] = {}  # training identity -> the run in todo that trains it
    pending: List[RunKey] = []
    for key in suite.runs():
        scene, method = suite.scene(key.scene), METHODS[key.method]
        if not scene.supports(method):
            plan.skipped[key.id] = f"scene {scene.name} has no sharp_path for the sharp upper bound"
        elif finished_record(suite, out, key) is not None:
            plan.reused.append(key.id)
            finished.setdefault(training_identity(suite, key), key)
        else:
            pending.append(key)
    for key in pending:
        identity = training_identity(suite, key)
        source = finished.get(identity) or trained.get(identity)
        if source is not None:
            plan.same_as[key] = source
        else:
            trained[identity] = key
            plan.todo.append(key)
    return plan


def run_suite(
    suite: Suite,
    out: Path,
    command: str = "",
    progress: bool = True,
    plots: bool = True,
    console=None,
    interrupt_after: Optional[int] = None,
) -> SuiteOutcome:
    """Run every run of ``suite`` that has no matching record in ``out/runs``; rewrite the outputs after each.

    ``interrupt_after``: after that many runs were trained (and their outputs written), send this process SIGINT,
    as Ctrl-C would: the interrupted suite then stops the same way (KeyboardInterrupt, finished records kept), at a
    point that does not depend on timing."""
    import torch
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    out = Path(out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    scene_root = suite.scene_root if suite.scene_root is not None else out
    if suite.threads > 0:
        torch.set_num_threads(suite.threads)
    console = console or Console(file=sys.stdout)
    machine = machine_info()

    for run_id in rekey_unchanged_estimates(suite, out, scene_root, out / "runs" / "nerfstudio"):
        console.print(f"{run_id}: the estimate changed but not the records this run trains on: its record is kept")
    plan = plan_runs(suite, out)
    todo, reused, skipped = plan.todo, plan.reused, plan.skipped
    followers: Dict[str, List[RunKey]] = {}  # a run in todo -> the runs that copy its record once it is trained
    copied: List[str] = []

    def copy_record(key: RunKey, source: RunKey) -> None:
        source_record = load_record(record_path(out, source))
        assert source_record is not None
        write_json_atomic(record_path(out, key), copied_record(suite, key, source_record))
        copied.append(key.id)
        console.print(f"{key.id}: same training as {source.id} (same images, model, settings and seed): its record "
                      "is copied")  # fmt: skip

    lpips = None
    if suite.lpips and todo:
        lpips = make_lpips("cuda" if torch.cuda.is_available() else "cpu")
    if suite.lpips and lpips is None and todo:
        console.print("[yellow]LPIPS: torchvision's AlexNet weights are not in the torch hub cache; LPIPS is left out "
                      "(nothing is downloaded)[/yellow]")  # fmt: skip

    console.print(f"suite [bold]{suite.name}[/bold]: {plan.total} runs ({len(reused)} already finished, "
                  f"{len(todo)} to train, {len(plan.same_as)} sharing another run's training, {len(skipped)} "
                  f"skipped) -> {out}")  # fmt: skip
    for key, source in plan.same_as.items():
        if source.id in reused:
            copy_record(key, source)
        else:
            followers.setdefault(source.id, []).append(key)
    trained: List[str] = []
    failed: Dict[str, str] = {}
    outputs: List[Path] = []

    def refresh() -> None:
        nonlocal outputs
        outputs = write_outputs(suite, out, command, machine, skipped, failed, plots=plots)

    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TextColumn("eta"), TimeRemainingColumn(), TextColumn("{task.fields[info]}"))  # fmt: skip
    current = ""
    try:
        with Progress(*columns, console=console, disable=not progress, redirect_stdout=False,
                      redirect_stderr=False) as bars:  # fmt: skip
            left = len(todo) + sum(len(f) for f in followers.values())
            suite_task = bars.add_task(f"{suite.name}", total=plan.total, completed=plan.total - left, info="")
            for key in todo:
                current = key.id
                run_task = bars.add_task(f"  {key.scene} {key.method} s{key.seed}", total=key.steps, info="")

                def on_eval(point: Dict[str, Any], task=run_task) -> None:
                    bars.update(task, info=f"PSNR {point['psnr']:.2f} @ {point['step']}")

                log_path = out / "runs" / f"{key.id}.log"
                started = time.perf_counter()
                try:
                    with open(log_path, "w", encoding="utf8") as log_file, contextlib.redirect_stdout(log_file), \
                            contextlib.redirect_stderr(log_file):  # fmt: skip
                        record = train_and_record(
                            suite, key, scene_root, out / "runs" / "nerfstudio", lpips,
                            on_step=lambda n, task=run_task: bars.advance(task, n), on_eval=on_eval,
                            log=lambda message: print(message, flush=True),
                        )  # fmt: skip
                    write_json_atomic(record_path(out, key), record)
                    trained.append(key.id)
                    console.print(f"{key.id}: PSNR {record['psnr']:.2f}  SSIM {record['ssim']:.4f}  train "
                                  f"{record['train_seconds']:.0f} s ({record['step_ms']:.0f} ms/step)")  # fmt: skip
                    for follower in followers.get(key.id, []):
                        copy_record(follower, key)
                except Exception as e:  # noqa: BLE001 - one failed run does not stop the suite
                    with open(log_path, "a", encoding="utf8") as log_file:
                        log_file.write(traceback.format_exc())
                    failed[key.id] = f"{type(e).__name__}: {e}"
                    for follower in followers.get(key.id, []):
                        failed[follower.id] = f"same training as {key.id}, which failed"
                    console.print(f"[red]{key.id} failed after {time.perf_counter() - started:.0f} s: "
                                  f"{type(e).__name__}: {e} (log: {log_path})[/red]")  # fmt: skip
                finally:
                    bars.remove_task(run_task)
                current = f"writing the outputs after {key.id}"
                bars.advance(suite_task, 1 + len(followers.get(key.id, [])))
                refresh()
                if interrupt_after is not None and len(trained) + len(failed) >= interrupt_after:
                    signal.raise_signal(signal.SIGINT)
    except KeyboardInterrupt:
        console.print(f"[red]interrupted ({current or 'before the first run'}); "
                      f"{len(trained) + len(reused) + len(copied)} "
                      "finished runs are kept in runs/: run the same command again to resume[/red]")  # fmt: skip
        raise
    refresh()
    records = collect_records(suite, out)
    return SuiteOutcome(records, trained, reused, failed, skipped, outputs, copied)


__all__ = [
    "SuiteOutcome",
    "plan_runs",
    "RunPlan",
    "copied_record",
    "run_suite",
    "train_and_record",
]
