"""What one training step costs per method on one scene, on the device training runs on (``gsmsdr-bench step``).

Each method trains through nerfstudio's Trainer (:class:`gsmsdr_ns.bench.training.InProcessRun`) at full resolution
from the first step, with the blur field on from step 0, so every timed step is a full-size step of the method's
whole path. ``warmup`` steps run first (untimed: kernel builds, caches, the first views), then ``steps`` timed steps.
On CUDA the device is synchronised before and after the timed steps only, never inside them, so the time is what
training costs and not what a profiler would add. Densification and culling run as in the preset: before its first
refinement (splatfacto: step 500) every method trains the same Gaussians from the same points.

Peak memory: on CUDA, torch's peak allocation over the timed steps (``torch.cuda.max_memory_allocated``, reset after
the warm-up) and over the whole run; on the CPU, the peak resident set over the timed steps above the resident set
at their start (:class:`gsmsdr_ns.bench.timing.PeakMemory`).
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

import torch

from gsmsdr_ns.io.atomic import write_text_atomic

COLUMNS = ("method", "scene", "size", "records", "device", "threads", "warmup", "steps", "rounds", "step_ms",
           "median_ms", "ratio_to_first", "speedup_vs_1_thread", "peak_mb", "run_peak_mb", "num_gaussians",
           "blurred_views", "breakdown_steps", "breakdown_ms")  # fmt: skip
"""Columns of results.csv, in order (``step_ms``: mean over the timed steps; ``median_ms``: median over the rounds of
a round's time per step, the same with one round; ``ratio_to_first``: median step time over the first method's on
the same scene and thread count; ``speedup_vs_1_thread``: the same method's 1-thread median over this row's, when
both ran)."""


@dataclass(frozen=True)
class StepCostSpec:
    """One measurement: a bench method on a scene folder."""

    method: str
    """A bench method (``gsmsdr_ns.bench.methods.METHODS``): plain, full, view, lite, ..."""
    data: Path
    """Scene folder (any layout the gsmsdr dataparser reads)."""
    warmup: int = 10
    """Untimed steps before the timed ones."""
    steps: int = 50
    """Timed steps."""
    estimate: bool = True
    """Estimate a record for images without one (False: nothing known about them; every such image then trains with
    the blur field, the most expensive path)."""
    seed: int = 0
    """Training seed."""
    breakdown_steps: int = 0
    """Steps run after the timed ones with the bench's time breakdown (:class:`TimingRecorder`, which waits for the
    device at every stage boundary, so these steps are slower than the timed ones): ms per step per stage."""
    threads: int = 0
    """torch's (and our C++ kernels' OpenMP) intra-op threads for this measurement; 0: torch's default."""


def _config(spec: StepCostSpec, work_dir: Path):
    from gsmsdr_ns.bench.methods import method_spec

    config = method_spec(spec.method).make_config(spec.data, work_dir)
    config.experiment_name = f"step-{spec.method}"
    config.max_num_iterations = spec.warmup + spec.steps
    config.steps_per_save = 10**9
    config.logging.steps_per_log = 10**9
    config.logging.local_writer.enable = False
    config.pipeline.datamanager.dataparser.estimate_degradations = spec.estimate
    model = config.pipeline.model
    model.num_downscales = 0  # full resolution (and the HPKO's full-size kernels) from the first step
    model.degradation_model = dataclasses.replace(model.degradation_model, warmup=0)
    return config


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class _Measurement:
    """One spec's run, trained in timed chunks (one per round) between which other methods may train."""

    def __init__(self, spec: StepCostSpec, work_dir: Path) -> None:
        from gsmsdr_ns.bench.timing import PeakMemory
        from gsmsdr_ns.bench.training import InProcessRun

        if spec.warmup < 1 or spec.steps < 1:
            raise ValueError(f"warmup and steps must be >= 1, got {spec.warmup} and {spec.steps}")
        self.spec = spec
        self.memory = PeakMemory()
        self.memory.reset()
        self.run = InProcessRun(_config(spec, work_dir), seed=spec.seed)
        self.device = torch.device(self.run.trainer.device)
        self.chunks: List[tuple] = []  # (steps, seconds) per timed chunk
        self.peak = 0.0
        self.run.train(spec.warmup)
        _synchronize(self.device)
        self.run_peak = self.memory.peak_cuda_mb()

    def timed(self, steps: int) -> None:
        """Train ``steps`` more timed steps (the device synchronised before and after only)."""
        self.memory.reset()
        _synchronize(self.device)
        started = time.perf_counter()
        self.run.train(steps)
        _synchronize(self.device)
        self.chunks.append((steps, time.perf_counter() - started))
        self.run_peak = max(self.run_peak, self.memory.peak_cuda_mb())
        peak = self.memory.peak_cuda_mb() if self.device.type == "cuda" else self.memory.extra_rss_mb()
        self.peak = max(self.peak, peak)

    def row(self) -> Dict[str, object]:
        """The breakdown steps, then the row of :data:`COLUMNS` (ratio and speed-up not yet set)."""
        from gsmsdr_ns.bench.timing import TimingRecorder

        spec, run = self.spec, self.run
        breakdown = {}
        if spec.breakdown_steps > 0:
            recorder = TimingRecorder(sync_cuda=self.device.type == "cuda").attach(run.pipeline)
            try:
                with recorder.measure():
                    run.train(spec.breakdown_steps)
            finally:
                recorder.detach()
            breakdown = {k: 1000.0 * v / spec.breakdown_steps for k, v in recorder.totals().items()}
        model = run.model
        cameras = run.pipeline.datamanager.train_dataparser_outputs.cameras
        blurred = sum(1 for profile in model.degradation.profiles if profile.needs_blur_field)
        gpu = torch.cuda.get_device_name(self.device) if self.device.type == "cuda" else ""
        steps = sum(n for n, _ in self.chunks)
        return {
            "method": spec.method,
            "scene": Path(spec.data).name,
            "size": f"{int(cameras.width[0])}x{int(cameras.height[0])}",
            "records": "scene's, else estimated" if spec.estimate else "scene's, else none (blur path)",
            "device": f"cuda ({gpu})" if gpu else self.device.type,
            "threads": torch.get_num_threads(),
            "warmup": spec.warmup,
            "steps": steps,
            "rounds": len(self.chunks),
            "step_ms": 1000.0 * sum(t for _, t in self.chunks) / steps,
            "median_ms": 1000.0 * statistics.median(t / n for n, t in self.chunks),
            "ratio_to_first": float("nan"),
            "speedup_vs_1_thread": float("nan"),
            "peak_mb": self.peak,
            "run_peak_mb": self.run_peak if self.device.type == "cuda" else float("nan"),
            "num_gaussians": int(model.num_points),
            "blurred_views": f"{blurred}/{len(model.degradation.profiles)}",
            "breakdown_steps": spec.breakdown_steps,
            "breakdown_ms": " ".join(f"{k}={v:.2f}" for k, v in breakdown.items()),
        }

    def close(self) -> None:
        self.run.close()
        if torch.cuda.is_available():
            torch.cuda.empty_cache()


def _round_sizes(steps: int, rounds: int) -> List[int]:
    """``steps`` split into ``rounds`` chunks as even as possible (none empty)."""
    rounds = max(1, min(rounds, steps))
    return [steps // rounds + (1 if i < steps % rounds else 0) for i in range(rounds)]


def measure_step_costs(specs: Sequence[StepCostSpec], work_dir: Path, rounds: int = 1) -> List[Dict[str, object]]:
    """Rows of :data:`COLUMNS` (ratio and speed-up not yet set) for specs that share a thread count, in order.

    The specs' runs are open together: after each one's warm-up, they take turns for ``rounds`` rounds, each training
    its next chunk of timed steps, so a machine that slows down for a while slows every method alike. ``median_ms``
    is the median over the rounds of a chunk's time per step (``step_ms``: the mean over all timed steps).
    """
    if not specs:
        return []
    threads = {spec.threads for spec in specs}
    if len(threads) != 1:
        raise ValueError(f"specs measured together must share a thread count, got {sorted(threads)}")
    threads_before = torch.get_num_threads()
    if specs[0].threads > 0:
        torch.set_num_threads(specs[0].threads)  # also OpenMP's, which our C++ kernels use
    measurements: List[_Measurement] = []
    try:
        for spec in specs:
            measurements.append(_Measurement(spec, work_dir))
        chunks = {id(m): _round_sizes(m.spec.steps, rounds) for m in measurements}
        for r in range(max(len(c) for c in chunks.values())):
            for m in measurements:
                if r < len(chunks[id(m)]):
                    m.timed(chunks[id(m)][r])
        return [m.row() for m in measurements]
    finally:
        for m in measurements:
            m.close()
        torch.set_num_threads(threads_before)


def measure_step_cost(spec: StepCostSpec, work_dir: Path) -> Dict[str, object]:
    """Train ``spec`` for its warm-up and timed steps and return one row of :data:`COLUMNS` (ratio not yet set)."""
    return measure_step_costs([spec], work_dir)[0]


def run_step_cost(
    specs: Sequence[StepCostSpec],
    work_dir: Path,
    log: Optional[Callable[[str], None]] = None,
    rounds: int = 1,
) -> List[Dict[str, object]]:
    """Measure every spec, those of one scene and thread count together (:func:`measure_step_costs`, ``rounds``
    rounds); ``ratio_to_first`` is each row's median step time over the first row's of its scene (and thread count),
    ``speedup_vs_1_thread`` the same method's 1-thread median over its own (1-thread rows first)."""
    rows: List[Dict[str, object]] = []
    first_ms: Dict[str, float] = {}
    one_thread_ms: Dict[str, float] = {}
    groups: Dict[tuple, List[StepCostSpec]] = {}
    for spec in specs:
        groups.setdefault((str(spec.data), spec.threads), []).append(spec)
    for group in groups.values():
        for row in measure_step_costs(group, work_dir, rounds):
            key = f"{row['scene']}|{row['records']}|{row['threads']}"
            first_ms.setdefault(key, float(row["median_ms"]))
            row["ratio_to_first"] = float(row["median_ms"]) / first_ms[key]
            method_key = f"{row['scene']}|{row['records']}|{row['method']}"
            if row["threads"] == 1:
                one_thread_ms[method_key] = float(row["median_ms"])
            if method_key in one_thread_ms:
                row["speedup_vs_1_thread"] = one_thread_ms[method_key] / float(row["median_ms"])
            rows.append(row)
            if log is not None:
                log(f"step: {row['scene']} {row['method']} ({row['threads']} thread(s)): {row['median_ms']:.1f} "
                    f"ms/step (median of {row['rounds']} round(s)), peak {row['peak_mb']:.0f} MiB")  # fmt: skip
    return rows


def format_table(rows: Sequence[Dict[str, object]], header: str = "") -> str:
    """A markdown table of :func:`run_step_cost` rows, under ``header``."""
    lines = [header, ""] if header else []
    lines += [
        "| scene | size | records | method | threads | ms/step (mean) | ms/step (median of rounds) | x first "
        "| speed-up vs 1 thread | peak MiB (timed) | peak MiB (run) | Gaussians | views with a blur model |",
        "| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        speedup = float(r["speedup_vs_1_thread"])
        lines.append(
            f"| {r['scene']} | {r['size']} | {r['records']} | {r['method']} | {r['threads']} "
            f"| {float(r['step_ms']):.1f} | {float(r['median_ms']):.1f} ({r['rounds']}) "
            f"| {float(r['ratio_to_first']):.2f} | "
            f"{'-' if speedup != speedup else f'{speedup:.2f}'} | {max(float(r['peak_mb']), 0.0):.0f} "
            f"| {float(r['run_peak_mb']):.0f} | {r['num_gaussians']} | {r['blurred_views']} |"
        )
    broken_down = [r for r in rows if r.get("breakdown_ms")]
    if broken_down:
        lines += [
            "",
            f"Time breakdown (ms per step over {broken_down[0]['breakdown_steps']} more steps, the device "
            "synchronised at every stage boundary):",
            "",
        ]
        lines += [f"- {r['scene']} {r['method']} ({r['threads']} thread(s)): {r['breakdown_ms']}" for r in broken_down]
    return "\n".join(lines) + "\n"


def write_results(out: Path, rows: Sequence[Dict[str, object]], header: str) -> List[Path]:
    """results.md and results.csv into ``out`` (each written atomically)."""
    import csv
    import io

    out = Path(out)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(COLUMNS), lineterminator="\n")
    writer.writeheader()
    writer.writerows([{k: r[k] for k in COLUMNS} for r in rows])
    paths = [out / "results.md", out / "results.csv"]
    write_text_atomic(paths[0], format_table(rows, header))
    write_text_atomic(paths[1], buffer.getvalue())
    return paths


__all__ = [
    "COLUMNS",
    "StepCostSpec",
    "format_table",
    "measure_step_cost",
    "measure_step_costs",
    "run_step_cost",
    "write_results",
]
