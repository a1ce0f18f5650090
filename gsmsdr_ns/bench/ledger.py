"""The record keeping of a running suite, shared by the serial runner (:mod:`gsmsdr_ns.bench.runner`) and the Ray
runner (:mod:`gsmsdr_ns.bench.ray_runner`): which runs to train, reuse, copy or skip (:func:`plan_runs`), each
finished run's record written atomically and copied to the runs that share its training, failures, and the outputs
rewritten after every run (:class:`SuiteLedger`). Only the process that owns the output folder writes records."""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional

from gsmsdr_ns.bench.fingerprint import digest, fingerprint, training_identity
from gsmsdr_ns.bench.machine import machine_info
from gsmsdr_ns.bench.methods import METHODS
from gsmsdr_ns.bench.records import collect_records, finished_record, load_record, record_path, write_json_atomic
from gsmsdr_ns.bench.report import write_outputs
from gsmsdr_ns.bench.suite_config import RunKey, Suite


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


@dataclass
class RunPlan:
    """What a suite does with each of its runs, in the suite's run order."""

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


class SuiteLedger:
    """A suite being run into the output folder ``out``: its plan, and every finished or failed run recorded as it
    ends (whatever ran it). Creating it re-keys unchanged estimates and plans the runs; :meth:`start` announces the
    plan and copies the records of runs sharing a finished run's training."""

    def __init__(self, suite: Suite, out: Path, command: str, console, plots: bool = True) -> None:
        self.suite, self.out, self.command, self.console, self.plots = suite, Path(out), command, console, plots
        (self.out / "runs").mkdir(parents=True, exist_ok=True)
        self.scene_root = suite.scene_root if suite.scene_root is not None else self.out
        self.work_dir = self.out / "runs" / "nerfstudio"
        self.machine = machine_info()
        for run_id in rekey_unchanged_estimates(suite, self.out, self.scene_root, self.work_dir):
            console.print(f"{run_id}: the estimate changed but not the records this run trains on: its record is kept")
        self.plan = plan_runs(suite, self.out)
        self.followers: Dict[str, List[RunKey]] = {}  # a run in todo -> the runs that copy its record once trained
        self.trained: List[str] = []
        self.failed: Dict[str, str] = {}
        self.copied: List[str] = []
        self.outputs: List[Path] = []

    def log_path(self, key: RunKey) -> Path:
        """What run ``key`` printed while it trained."""
        return self.out / "runs" / f"{key.id}.log"

    @property
    def left(self) -> int:
        """Runs not finished yet: those to train and those waiting to copy their record."""
        return len(self.plan.todo) + sum(len(f) for f in self.followers.values())

    def weight(self, key: RunKey) -> int:
        """How many runs of the suite end when run ``key`` ends (itself and the runs that copy its record)."""
        return 1 + len(self.followers.get(key.id, []))

    def start(self) -> None:
        """Announce the plan; copy the records of runs sharing a finished run's training."""
        plan = self.plan
        self.console.print(f"suite [bold]{self.suite.name}[/bold]: {plan.total} runs ({len(plan.reused)} already "
                           f"finished, {len(plan.todo)} to train, {len(plan.same_as)} sharing another run's training, "
                           f"{len(plan.skipped)} skipped) -> {self.out}")  # fmt: skip
        for key, source in plan.same_as.items():
            if source.id in plan.reused:
                self._copy_record(key, source)
            else:
                self.followers.setdefault(source.id, []).append(key)

    def _copy_record(self, key: RunKey, source: RunKey) -> None:
        source_record = load_record(record_path(self.out, source))
        assert source_record is not None
        write_json_atomic(record_path(self.out, key), copied_record(self.suite, key, source_record))
        self.copied.append(key.id)
        self.console.print(f"{key.id}: same training as {source.id} (same images, model, settings and seed): its "
                           "record is copied")  # fmt: skip

    def finished(self, key: RunKey, record: Dict[str, Any], note: str = "") -> None:
        """Write the record of the trained run ``key`` (atomically) and copy it to the runs sharing its training."""
        write_json_atomic(record_path(self.out, key), record)
        self.trained.append(key.id)
        self.console.print(f"{key.id}: PSNR {record['psnr']:.2f}  SSIM {record['ssim']:.4f}  train "
                           f"{record['train_seconds']:.0f} s ({record['step_ms']:.0f} ms/step){note}")  # fmt: skip
        for follower in self.followers.get(key.id, []):
            self._copy_record(follower, key)

    def failed_run(self, key: RunKey, error: str, seconds: Optional[float] = None) -> None:
        """Record that run ``key`` failed with ``error`` (and the runs that would have copied its record)."""
        self.failed[key.id] = error
        for follower in self.followers.get(key.id, []):
            self.failed[follower.id] = f"same training as {key.id}, which failed"
        after = "" if seconds is None else f" after {seconds:.0f} s"
        self.console.print(f"[red]{key.id} failed{after}: {error} (log: {self.log_path(key)})[/red]")

    def refresh(self) -> None:
        """Rewrite results.csv, results.md and the plots from the records written so far."""
        self.outputs = write_outputs(self.suite, self.out, self.command, self.machine, self.plan.skipped, self.failed,
                                     plots=self.plots)  # fmt: skip

    def interrupted(self, where: str) -> None:
        """Say that the suite was interrupted while ``where`` and that its finished runs are kept."""
        kept = len(self.trained) + len(self.plan.reused) + len(self.copied)
        self.console.print(f"[red]interrupted ({where or 'before the first run'}); {kept} finished runs are kept in "
                           "runs/: run the same command again to resume[/red]")  # fmt: skip

    def outcome(self) -> SuiteOutcome:
        self.refresh()
        records = collect_records(self.suite, self.out)
        return SuiteOutcome(records, self.trained, self.plan.reused, self.failed, self.plan.skipped, self.outputs,
                            self.copied)  # fmt: skip


__all__ = [
    "RunPlan",
    "SuiteLedger",
    "SuiteOutcome",
    "copied_record",
    "plan_runs",
    "records_digest",
    "rekey_unchanged_estimates",
    "training_records_digest",
]
