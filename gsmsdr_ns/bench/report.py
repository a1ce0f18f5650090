"""A suite's results from its run records: ``results.csv`` (one row per run), ``results.md`` (tables shaped like the
paper's Tables 3-7 plus time and memory columns), the PNG plots (:mod:`gsmsdr_ns.bench.plots`), and publishing those
files into a results folder such as ``docs/results/<suite>/``."""

from __future__ import annotations

import collections
import csv
import datetime
import io
import math
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

from gsmsdr_ns.bench.machine import describe_machine, machine_info
from gsmsdr_ns.bench.methods import METHODS, TABLE6_METHODS, TABLE7_METHODS
from gsmsdr_ns.bench.records import collect_records, copy_file_atomic, write_text_atomic
from gsmsdr_ns.bench.suite_config import Suite, schedule_settings
from gsmsdr_ns.bench.timing import CATEGORIES
from gsmsdr_ns.resources import config_root

CSV_FIELDS = ("suite", "scene", "method", "steps", "seed", "psnr", "ssim", "lpips", "train_seconds", "step_ms",
              *(f"t_{c}" for c in CATEGORIES), "peak_rss_mb", "peak_cuda_mb", "num_gaussians", "eval_seconds",
              "setup_seconds", "device", "torch_threads", "psnr_aligned", "ssim_aligned",
              "lpips_aligned", "pose_correction_deg", "train_psnr")  # fmt: skip


def _num(value: Any, digits: int) -> str:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return ""
    return "" if not math.isfinite(v) else f"{v:.{digits}f}"


def write_csv(records: Sequence[Mapping[str, Any]], path: Path) -> None:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(CSV_FIELDS)
    for r in records:
        b = r.get("breakdown", {})
        m = r.get("machine", {})
        writer.writerow([r["suite"], r["scene"], r["method"], r["steps"], r["seed"], _num(r["psnr"], 4),
                         _num(r["ssim"], 5), _num(r["lpips"], 5), _num(r["train_seconds"], 2), _num(r["step_ms"], 2),
                         *(_num(b.get(c, float("nan")), 3) for c in CATEGORIES), _num(r["peak_rss_mb"], 1),
                         _num(r["peak_cuda_mb"], 1), r["num_gaussians"], _num(r["eval_seconds"], 2),
                         _num(r["setup_seconds"], 2), m.get("device", ""), m.get("torch_threads", ""),
                         _num(r.get("psnr_aligned"), 4), _num(r.get("ssim_aligned"), 5),
                         _num(r.get("lpips_aligned"), 5), _num(r.get("pose_correction_deg"), 3),
                         _num(r.get("train_psnr"), 4)])  # fmt: skip
    write_text_atomic(path, buffer.getvalue())


def _mean(values: Sequence[float]) -> float:
    finite = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return sum(finite) / len(finite) if finite else float("nan")


def aggregate(records: Sequence[Mapping[str, Any]]) -> Dict[Tuple[int, str, str], Dict[str, Any]]:
    """Seed means per (steps, scene, method): the metrics, times, memory, Gaussians and the breakdown; also the
    lowest and highest PSNR over the seeds (``psnr_min``, ``psnr_max``)."""
    groups: Dict[Tuple[int, str, str], List[Mapping[str, Any]]] = {}
    for r in records:
        groups.setdefault((r["steps"], r["scene"], r["method"]), []).append(r)
    out = {}
    for k, rs in groups.items():
        row: Dict[str, Any] = {"seeds": len(rs)}
        for name in ("psnr", "ssim", "lpips", "train_seconds", "step_ms", "peak_rss_mb", "peak_cuda_mb",
                     "num_gaussians", "eval_seconds", "psnr_aligned", "ssim_aligned", "lpips_aligned",
                     "pose_correction_deg", "train_psnr"):  # fmt: skip
            row[name] = _mean([r.get(name, float("nan")) for r in rs])
        psnrs = [float(r["psnr"]) for r in rs if math.isfinite(float(r["psnr"]))]
        row["psnr_min"], row["psnr_max"] = (min(psnrs), max(psnrs)) if psnrs else (float("nan"), float("nan"))
        row["breakdown"] = {c: _mean([r.get("breakdown", {}).get(c, float("nan")) for r in rs]) for c in CATEGORIES}
        split = [r.get("breakdown_split") for r in rs if r.get("breakdown_split")]
        row["backward"] = {c: _mean([s["backward"].get(c, float("nan")) for s in split]) for c in CATEGORIES[:-1]}
        out[k] = row
    return out


def _f(value: Any, digits: int = 2) -> str:
    s = _num(value, digits)
    return s if s else "-"


def format_markdown(
    suite: Suite,
    records: Sequence[Mapping[str, Any]],
    command: str = "",
    machine: Optional[Mapping[str, Any]] = None,
    skipped: Optional[Mapping[str, str]] = None,
    failed: Optional[Mapping[str, str]] = None,
) -> str:
    """results.md: header, then per step budget the per-scene tables (Tables 3-5), Table 7, Table 6, the time
    breakdown and the gaps; then failed and skipped runs."""
    machine = machine or machine_info()
    agg = aggregate(records)
    lines = _header_lines(suite, records, command, machine, skipped, failed)
    for steps in suite.steps:
        lines += _per_scene_tables(suite, agg, steps)
        lines += _paper_tables(suite, agg, steps)
        lines += _time_breakdown(suite, agg, steps)
        lines += _gap_table(suite, agg, records, steps)
        lines += _equal_time_table(suite, records, steps)
    if failed:
        lines += ["## Failed runs", ""] + [f"- `{k}`: {v} (log: `runs/{k}.log`)" for k, v in failed.items()] + [""]
    if skipped:
        lines += ["## Skipped runs", ""] + [f"- `{k}`: {v}" for k, v in skipped.items()] + [""]
    return "\n".join(lines).rstrip() + "\n"


def _header_lines(
    suite: Suite,
    records: Sequence[Mapping[str, Any]],
    command: str,
    machine: Mapping[str, Any],
    skipped: Optional[Mapping[str, str]],
    failed: Optional[Mapping[str, str]],
) -> List[str]:
    """Title and the bullet list saying when, where, how and what was measured."""
    expected = len(suite.runs()) - len(skipped or {})
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [f"# Benchmark suite `{suite.name}`", ""]
    lines.append(f"- date: {now}")
    lines.append(f"- machine: {describe_machine(machine)}; {machine.get('platform', '')}, Python "
                 f"{machine.get('python', '')}, git {machine.get('git') or '-'}")  # fmt: skip
    others = sorted({describe_machine(r["machine"]) for r in records if r.get("machine")} - {describe_machine(machine)})
    if others:
        lines.append(f"- some records were measured on: {'; '.join(others)}")
    trained = collections.Counter(r["machine"].get("git") or "-" for r in records if r.get("machine"))
    if trained and set(trained) != {machine.get("git") or "-"}:  # records kept from runs at other commits
        lines.append("- runs trained at git " + ", ".join(f"{g} ({n})" for g, n in sorted(trained.items())))
    if command:
        lines.append(f"- command: `{command}`")
    lines.append(f"- suite: `{_display_path(suite.source)}`" + (f": {suite.description}" if suite.description else ""))
    lines.append(f"- runs: {len(records)} of {expected} finished"
                 + (f", {len(failed)} failed" if failed else "")
                 + (f", {len(skipped)} skipped" if skipped else ""))  # fmt: skip
    shared = [r for r in records if r.get("same_training_as")]
    if shared:
        lines.append(
            f"- {len(shared)} of them trained the same images with the same model, settings and seed as "
            "another run, which trained once for both (each such record names it in `same_training_as`)"
        )
    for scene in suite.scenes:
        lines.append(f"- scene `{scene.name}`: {scene.describe()}")
    sched = ", ".join(f"{k} {v}" for k, v in schedule_settings(suite.schedule_for(1)).items() if k != "steps")
    lines.append(f"- budgets: {', '.join(map(str, suite.steps))} steps; seeds {', '.join(map(str, suite.seeds))}"
                 f" (tables show seed means); every method gets the same shortened schedule ({sched})")  # fmt: skip
    lines.append("- metrics on the held-out sharp test views (sharp renders vs sharp ground truth): PSNR; SSIM from "
                 "scikit-image (Gaussian window, sigma 1.5); LPIPS (AlexNet) only when its weights are cached, "
                 "else `-`")  # fmt: skip
    if suite.align_poses:
        lines.append("- aligned: the same metrics at the end of training after test-pose alignment (scene frozen, each "
                     "test camera's pose optimised on the photometric loss against its sharp photo, "
                     "`gsmsdr_ns/plugin/pose_alignment.py`; a pose is kept when alignment does not lower the loss); "
                     "pose corr.: mean rotation of the corrections in degrees")  # fmt: skip
    if suite.train_fit:
        lines.append("- train-view fit PSNR: at the end of training, each training view's render, degraded as the "
                     "model simulates it, against the degraded training photo (`train_view_psnr` in "
                     "`gsmsdr_ns/bench/evaluation.py`)")  # fmt: skip
    lines.append("- train s: training wall time without evaluation and set-up; ms/step = train s / steps; peak mem: "
                 "peak resident memory of the process during the run (includes the Python/torch baseline)"
                 + ("; peak CUDA: torch.cuda.max_memory_allocated" if machine.get("device") == "cuda" else "")
                 )  # fmt: skip
    lines.append("")
    return lines


_Aggregate = Mapping[Tuple[int, str, str], Mapping[str, Any]]


def _per_scene_tables(suite: Suite, agg: _Aggregate, steps: int) -> List[str]:
    """One table per scene at ``steps``: metrics (aligned ones when measured), time, memory, Gaussians, seeds."""
    show_cuda = any(math.isfinite(row["peak_cuda_mb"]) for row in agg.values())
    multi_seed = len(suite.seeds) > 1
    lines = [f"## Per scene, {steps} steps (the paper's Tables 3-5)", ""]
    for scene in suite.scenes:
        rows = [(m, agg.get((steps, scene.name, m))) for m in suite.methods]
        rows = [(m, r) for m, r in rows if r is not None]
        if not rows:
            continue
        lines.append(f"### {scene.name}")
        lines.append("")
        show_aligned = any(math.isfinite(r["psnr_aligned"]) for _, r in rows)
        head = ["method", "PSNR", "SSIM", "LPIPS"]
        head += ["PSNR aligned", "SSIM aligned", "pose corr. °"] if show_aligned else []
        show_fit = any(math.isfinite(r["train_psnr"]) for _, r in rows)
        head += ["train-view fit PSNR"] if show_fit else []
        head += ["train s", "ms/step", "peak mem MB"]
        head += ["peak CUDA MB"] if show_cuda else []
        head += ["Gaussians"] + (["seeds", "PSNR lowest - highest seed"] if multi_seed else [])
        lines.append("| " + " | ".join(head) + " |")
        lines.append("| --- | " + " | ".join("---:" for _ in head[1:]) + " |")
        for m, r in rows:
            cells = [METHODS[m].label, _f(r["psnr"]), _f(r["ssim"], 4), _f(r["lpips"], 4)]
            if show_aligned:
                cells += [_f(r["psnr_aligned"]), _f(r["ssim_aligned"], 4), _f(r["pose_correction_deg"], 2)]
            cells += [_f(r["train_psnr"])] if show_fit else []
            cells += [_f(r["train_seconds"], 0), _f(r["step_ms"], 0), _f(r["peak_rss_mb"], 0)]
            cells += [_f(r["peak_cuda_mb"], 0)] if show_cuda else []
            cells += [_f(r["num_gaussians"], 0)]
            cells += [str(r["seeds"]), f"{_f(r['psnr_min'])} - {_f(r['psnr_max'])}"] if multi_seed else []
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    return lines


def _paper_tables(suite: Suite, agg: _Aggregate, steps: int) -> List[str]:
    """The paper's Table 7 (deblurring vs resolution enhancement) and Table 6 (module ablation) at ``steps``, each
    when the suite trains enough of its rows; PSNR and SSIM per scene."""
    scene_names = [s.name for s in suite.scenes]

    def scene_cells(method: str) -> List[str]:
        cells = []
        for name in scene_names:
            r = agg.get((steps, name, method))
            cells += [_f(r["psnr"]) if r else "-", _f(r["ssim"], 4) if r else "-"]
        return cells

    header_pairs = " | ".join(f"{n} PSNR | {n} SSIM" for n in scene_names)
    align = " | ".join("---: | ---:" for _ in scene_names)
    lines: List[str] = []
    t7 = [(m, label) for m, label in TABLE7_METHODS if m in suite.methods]
    if sum(m != "plain" for m, _ in t7) >= 2:
        lines += [f"## Table 7, {steps} steps: multi-scale deblurring vs resolution enhancement", ""]
        lines.append(f"| configuration | {header_pairs} |")
        lines.append(f"| --- | {align} |")
        for m, label in t7:
            lines.append(f"| {label} | " + " | ".join(scene_cells(m)) + " |")
        lines.append("")
    t6 = [m for m in TABLE6_METHODS if m in suite.methods]
    if sum(m not in ("plain", "full", "msd-only") for m in t6) >= 1:
        lines += [f"## Table 6, {steps} steps: module ablation (✓ present, ✗ removed; RE-only = -HPKO)", ""]
        lines.append(f"| GAKA | SAFM | MCA | RGBD | HPKO | method | {header_pairs} |")
        lines.append(f"| :-: | :-: | :-: | :-: | :-: | --- | {align} |")
        for m in t6:
            mods = METHODS[m].modules() or {}
            marks = " | ".join("✓" if mods.get(k) else "✗" for k in ("GAKA", "SAFM", "MCA", "RGBD", "HPKO"))
            lines.append(f"| {marks} | {METHODS[m].label} | " + " | ".join(scene_cells(m)) + " |")
        lines.append("")
    return lines


_BREAKDOWN_NAMES = {"rasterization": "raster", "blur_field": "blur field", "kernels": "kernels",
                    "densification": "densify", "data": "data", "other": "other"}  # fmt: skip
_BREAKDOWN_LEGEND = (
    "raster: `_rasterize` (activation, projection, SH, tiles, pixel kernel); blur field: kernel and mask prediction "
    "(MAAN, MCA, HPKO heads); kernels: kernel application (`BlurField.blur`), the thin lens (one fused op) and the "
    "resolution-loss model; densify: the strategy's pre/post-backward hooks; data: `next_train`; other: the rest of "
    "the step (mask blend, losses and their backward, composite, optimizer and scheduler steps, callbacks). Backward "
    "time is attributed by gradient-hook event times at component boundaries (see `gsmsdr_ns/bench/timing.py`)."
)


def _time_breakdown(suite: Suite, agg: _Aggregate, steps: int) -> List[str]:
    """Seconds of training per component (forward + backward) and the backward share, per scene and method."""
    lines = [f"## Time breakdown, {steps} steps (seconds of training, forward + backward)", ""]
    lines.append("| scene | method | " + " | ".join(_BREAKDOWN_NAMES[c] for c in CATEGORIES)
                 + " | total | of which backward (raster / blur field / kernels) |")  # fmt: skip
    lines.append("| --- | --- | " + " | ".join("---:" for _ in CATEGORIES) + " | ---: | ---: |")
    for scene in suite.scenes:
        for m in suite.methods:
            r = agg.get((steps, scene.name, m))
            if r is None:
                continue
            b, bw = r["breakdown"], r["backward"]
            back = " / ".join(_f(bw.get(c), 1) for c in ("rasterization", "blur_field", "kernels"))
            lines.append(f"| {scene.name} | {METHODS[m].label} | "
                         + " | ".join(_f(b[c], 1) for c in CATEGORIES)
                         + f" | {_f(r['train_seconds'], 1)} | {back} |")  # fmt: skip
    return lines + ["", _BREAKDOWN_LEGEND, ""]


def _gap_table(suite: Suite, agg: _Aggregate, records: Sequence[Mapping[str, Any]], steps: int) -> List[str]:
    """Each method's PSNR / SSIM gain over plain and distance to the sharp bound at ``steps`` (aligned, and the
    lowest and highest per-seed gain, when measured); nothing when a scene has neither plain nor sharp."""
    multi_seed = len(suite.seeds) > 1
    by_seed = {(r["scene"], r["method"], r["seed"]): float(r["psnr"]) for r in records if r["steps"] == steps}

    def seed_gaps(scene: str, method: str) -> str:
        """Lowest and highest PSNR gap to plain over the seeds both were trained with (same seed = same data
        order and initialisation)."""
        gaps = [v - by_seed[(scene, "plain", sd)] for (sc, m, sd), v in by_seed.items()
                if sc == scene and m == method and (scene, "plain", sd) in by_seed]  # fmt: skip
        return f"{_sign(min(gaps))} .. {_sign(max(gaps))}" if gaps else "-"

    rows = []
    aligned = any(math.isfinite(r["psnr_aligned"]) for (st, _, _), r in agg.items() if st == steps)
    nan = float("nan")
    for scene in suite.scenes:
        plain, sharp = agg.get((steps, scene.name, "plain")), agg.get((steps, scene.name, "sharp"))
        if plain and sharp:
            cells = ["0.00", "0.0000", _sign(sharp["psnr"] - plain["psnr"])]
            cells += ["0.00"] if aligned else []
            cells += ["-"] if multi_seed else []
            rows.append(f"| {scene.name} | {METHODS['plain'].label} | " + " | ".join(cells) + " |")
        for m in suite.methods:
            if m in ("plain", "sharp"):
                continue
            r = agg.get((steps, scene.name, m))
            if r is None or (plain is None and sharp is None):
                continue
            cells = [_sign(r["psnr"] - plain["psnr"] if plain else nan),
                     _sign(r["ssim"] - plain["ssim"] if plain else nan, 4),
                     _sign(sharp["psnr"] - r["psnr"] if sharp else nan)]  # fmt: skip
            if aligned:
                cells.append(_sign(r["psnr_aligned"] - plain["psnr_aligned"] if plain else nan))
            if multi_seed:
                cells.append(seed_gaps(scene.name, m))
            rows.append(f"| {scene.name} | {METHODS[m].label} | " + " | ".join(cells) + " |")
    if not rows:
        return []
    extra = " PSNR aligned: method - plain |" if aligned else ""
    extra += " PSNR: method - plain, per seed (lowest .. highest) |" if multi_seed else ""
    return [f"## Gaps, {steps} steps (test PSNR in dB, SSIM)", "",
            "| scene | method | PSNR: method - plain | SSIM: method - plain | PSNR: sharp - method |" + extra,
            "| --- | --- | ---: | ---: | ---: |" + " ---: |" * (aligned + multi_seed), *rows, ""]  # fmt: skip


def _interpolate(points: Sequence[Tuple[float, float]], x: float) -> float:
    """Piecewise-linear value at ``x`` of ``points`` (x, y) sorted by x; the last y beyond the last x."""
    if not points:
        return float("nan")
    for (x0, y0), (x1, y1) in zip(points, points[1:]):
        if x <= x1:
            return y0 + (y1 - y0) * (x - x0) / (x1 - x0) if x1 > x0 else y1
    return points[-1][1]


def _equal_time_table(suite: Suite, records: Sequence[Mapping[str, Any]], steps: int) -> List[str]:
    """Per scene and method (seed means): training and whole-run minutes, test PSNR, plain Gaussians' PSNR after the
    same training time (along plain's evaluation curve of the same seed; plain's last value when the method trained
    longer than plain did) and the PSNR gained over the last quarter of the steps and of the training time. Only for
    suites that evaluate along the run (at least 3 points per curve)."""
    runs = {(r["scene"], r["method"], r["seed"]): r for r in records if r["steps"] == steps}
    if not any(len(r.get("curve") or []) >= 3 for r in runs.values()):
        return []
    rows = []
    for scene in suite.scenes:
        for m in suite.methods:
            mine = [r for (sc, me, _), r in runs.items() if sc == scene.name and me == m and len(r["curve"]) >= 3]
            if not mine:
                continue
            equal, beyond = [], False
            for r in mine:
                plain = runs.get((scene.name, "plain", r["seed"]))
                if plain is not None and len(plain["curve"]) >= 3:
                    curve = [(c["seconds"], c["psnr"]) for c in plain["curve"]]
                    equal.append(_interpolate(curve, r["train_seconds"]))
                    beyond = beyond or r["train_seconds"] > curve[-1][0]
            last_quarter = [r["psnr"] - _interpolate([(c["step"], c["psnr"]) for c in r["curve"]], 0.75 * steps)
                            for r in mine]  # fmt: skip
            # low-resolution steps are cheap, so the last quarter of the time is fewer steps than that of the steps
            last_quarter_time = [r["psnr"] - _interpolate([(c["seconds"], c["psnr"]) for c in r["curve"]],
                                                          0.75 * r["train_seconds"]) for r in mine]  # fmt: skip
            whole = _mean([r["train_seconds"] + r.get("eval_seconds", 0.0) + r.get("setup_seconds", 0.0) for r in mine])
            psnr, plain_then = _mean([r["psnr"] for r in mine]), _mean(equal)
            mark = " *" if beyond else ""
            rows.append(f"| {scene.name} | {METHODS[m].label} | {_f(_mean([r['train_seconds'] for r in mine]) / 60, 1)}"
                        f" | {_f(whole / 60, 1)} | {_f(psnr)} | {_f(plain_then)}{mark} | {_sign(psnr - plain_then)}"
                        f" | {_sign(_mean(last_quarter))} | {_sign(_mean(last_quarter_time))} |")  # fmt: skip
    return [f"## Against wall time, {steps} steps (test PSNR in dB)", "",
            "| scene | method | train min | whole run min | PSNR | plain after the same training time | gain at equal "
            "time | PSNR gained over the last quarter of the steps | of the training time |",
            "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |", *rows, "",
            "whole run: set-up, training and every evaluation along the run. plain after the same training time: plain "
            "Gaussians' test PSNR interpolated along their evaluation curve at this row's training time (*: longer "
            "than plain trained; its last value). Last quarter: final PSNR minus the PSNR interpolated at 3/4 of the "
            "steps, or at 3/4 of the training time along the PSNR-vs-time curve.", ""]  # fmt: skip


def _display_path(path: Optional[Path]) -> str:
    """``path`` relative to the working directory when it is inside it, else ``configs/...`` for a packaged config
    (wherever the package is installed), else as given."""
    if path is None:
        return "-"
    resolved = Path(path).resolve()
    for base, prefix in ((Path.cwd(), ""), (config_root(), "configs/")):
        try:
            return prefix + resolved.relative_to(base.resolve()).as_posix()
        except ValueError:
            continue
    return str(path)


def _sign(value: float, digits: int = 2) -> str:
    return "-" if not math.isfinite(value) else f"{value:+.{digits}f}"


def write_outputs(
    suite: Suite,
    out: Path,
    command: str = "",
    machine: Optional[Mapping[str, Any]] = None,
    skipped: Optional[Mapping[str, str]] = None,
    failed: Optional[Mapping[str, str]] = None,
    plots: bool = True,
    records: Optional[Sequence[Mapping[str, Any]]] = None,
) -> List[Path]:
    """Regenerate results.csv, results.md and the PNG plots from ``records`` (default: the suite's finished records
    in ``out/runs``)."""
    out = Path(out)
    if records is None:
        records = collect_records(suite, out)
    write_csv(records, out / "results.csv")
    write_text_atomic(out / "results.md", format_markdown(suite, records, command, machine, skipped, failed))
    written = [out / "results.csv", out / "results.md"]
    if plots and records:
        from gsmsdr_ns.bench.plots import plot_psnr_vs_time, plot_time_breakdown

        labels = {name: spec.label for name, spec in METHODS.items()}
        for scene in suite.scenes:
            scene_records = [r for r in records if r["scene"] == scene.name]
            if scene_records:
                references = [name for name, spec in METHODS.items() if spec.sharp_data]
                written.append(plot_psnr_vs_time(scene_records, out / f"psnr_vs_time_{scene.name}.png", scene.name,
                                                 labels, references))  # fmt: skip
        written.append(plot_time_breakdown(records, out / "time_breakdown.png", labels))
    return written


def main_tables(markdown: str) -> str:
    """The part of results.md to print at the end: from the first table section to the time breakdown."""
    start = markdown.find("## ")
    return markdown[start:] if start >= 0 else markdown


PUBLISHED = ("results.md", "results.csv", "*.png")
"""The outputs a results folder gets (not ``runs/`` or ``scenes/``)."""


def publish_outputs(out: Path, folder: Path, files: Optional[Sequence[Path]] = None) -> List[Path]:
    """Copy results.md, results.csv and the PNG plots of the output folder ``out`` into ``folder`` (e.g.
    ``docs/results/quick``), each written atomically; returns the copies. ``files``: only these outputs (what
    the suite just wrote: another suite sharing ``out`` leaves plots of its own scenes there)."""
    out, folder = Path(out), Path(folder)
    if folder.resolve() == out.resolve():
        return []
    sources = [p for pattern in PUBLISHED for p in sorted(out.glob(pattern)) if p.is_file()]
    if files is not None:
        wanted = {Path(f).resolve() for f in files}
        sources = [p for p in sources if p.resolve() in wanted]
    if not sources:
        raise FileNotFoundError(f"{out} has no results.md, results.csv or plots to publish")
    return [copy_file_atomic(p, folder / p.name) for p in sources]


__all__ = [
    "CSV_FIELDS",
    "aggregate",
    "format_markdown",
    "main_tables",
    "publish_outputs",
    "write_csv",
    "write_outputs",
]
