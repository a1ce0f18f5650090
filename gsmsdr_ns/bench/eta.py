"""How right ``ns-train``'s time estimate is (``gsmsdr-bench eta``): the estimate replayed on the step times a suite
recorded.

A suite's run records keep every training step's time and Gaussian count (``step_trace``) and the schedule the
estimate knows (``step_schedule``). :func:`replay` feeds :class:`gsmsdr_ns.plugin.time_estimate.TimeEstimate` the
steps up to a fraction of the run, exactly as the trainer does, and compares what it answers with the time the
remaining steps took; nerfstudio's own estimate (the remaining steps times the mean of the last 20 step times) is
replayed beside it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List, Sequence

from gsmsdr_ns.plugin.time_estimate import StepSchedule, TimeEstimate

FRACTIONS = (0.1, 0.25, 0.5, 0.75)
"""Points of a run (fraction of its steps done) where the estimate is compared with the truth."""

NERFSTUDIO_WINDOW = 20
"""nerfstudio's ETA averages the last 20 step times (its GLOBAL_BUFFER max_buffer_size)."""


def load_traced_records(folder: Path) -> List[Dict]:
    """Run records under ``folder`` (a suite's output or its runs/ folder) that carry a step trace, sorted by id."""
    folder = Path(folder)
    runs = folder / "runs" if (folder / "runs").is_dir() else folder
    if not runs.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder (give a suite's output folder or its runs/ folder)")
    records = []
    for path in sorted(runs.glob("*.json")):
        record = json.loads(path.read_text())
        if isinstance(record, dict) and record.get("step_trace") and record.get("step_schedule"):
            records.append(record)
    return records


def replay(record: Dict, fractions: Sequence[float] = FRACTIONS) -> Dict:
    """One row: the run's id and, per fraction f, the relative error (estimate / truth - 1) of our estimate and of
    nerfstudio's after ``round(f * steps)`` steps."""
    seconds = [float(s) for s in record["step_trace"]["seconds"]]
    gaussians = [int(n) for n in record["step_trace"]["gaussians"]]
    raw = dict(record["step_schedule"])
    schedule = StepSchedule(**{k: tuple(v) if isinstance(v, list) else v for k, v in raw.items()})
    estimate = TimeEstimate(schedule)
    row: Dict = {"run": record["id"], "steps": len(seconds), "train_s": sum(seconds), "ours": {}, "nerfstudio": {}}
    done = 0
    for fraction in sorted(fractions):
        stop = max(1, min(len(seconds) - 1, round(fraction * len(seconds))))
        for step in range(done, stop):
            estimate.add(step, seconds[step], gaussians[step])
        done = stop
        truth = sum(seconds[stop:])
        recent = seconds[max(0, stop - NERFSTUDIO_WINDOW) : stop]
        naive = (schedule.max_steps - stop) * sum(recent) / len(recent)
        ours = estimate.remaining()
        row["ours"][fraction] = (ours / truth - 1.0) if ours is not None and truth > 0 else float("nan")
        row["nerfstudio"][fraction] = naive / truth - 1.0 if truth > 0 else float("nan")
    return row


def format_table(rows: Sequence[Dict], fractions: Sequence[float] = FRACTIONS) -> str:
    """Markdown table: per run, the estimate's error (ours / nerfstudio's) at each point of the run."""
    head = " | ".join(f"at {int(round(100 * f))} %: ours / nerfstudio" for f in fractions)
    rule = " | ".join("---:" for _ in fractions)
    lines = [f"| run | steps | train s | {head} |", f"| --- | ---: | ---: | {rule} |"]
    for row in rows:
        cells = " | ".join(f"{100 * row['ours'][f]:+.0f} % / {100 * row['nerfstudio'][f]:+.0f} %" for f in fractions)
        lines.append(f"| {row['run']} | {row['steps']} | {row['train_s']:.0f} | {cells} |")
    worst = max((abs(row["ours"][f]) for row in rows for f in fractions), default=float("nan"))
    lines.append("")
    lines.append(f"Largest error of ours: {100 * worst:.0f} % (estimate / time the remaining steps took - 1).")
    return "\n".join(lines)


__all__ = ["FRACTIONS", "format_table", "load_traced_records", "replay"]
