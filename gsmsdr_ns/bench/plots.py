"""PNG plots of a benchmark suite (matplotlib, Agg backend; files are written atomically).

* :func:`plot_psnr_vs_time`: one scene, test PSNR against cumulative training seconds, one line per method (and
  step budget) from the records' evaluation points (seed means), the final points' Pareto front marked (no other
  final point is both faster and better; the sharp upper bound is drawn as a dashed reference, not on the front);
* :func:`plot_time_breakdown`: stacked bars of the training time per category, one bar per scene and method.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

from gsmsdr_ns.bench.timing import CATEGORIES

COLOURS = {
    "rasterization": "#4C72B0",
    "blur_field": "#DD8452",
    "kernels": "#55A868",
    "densification": "#C44E52",
    "data": "#8172B3",
    "other": "#BBBBBB",
}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> Path:
    """Save ``fig`` as PNG through a temporary file renamed into place, then close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fig.savefig(tmp, format="png", dpi=120, bbox_inches="tight")
    _pyplot().close(fig)
    os.replace(tmp, path)
    return path


def pareto_front(points: Sequence[Tuple[float, float]]) -> List[int]:
    """Indices of the (seconds, psnr) points no other point dominates (faster or equal and better, or better or
    equal and faster), sorted by seconds."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], -math.inf
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


def _curve(records: Sequence[Mapping[str, Any]]) -> Tuple[List[float], List[float]]:
    """Seed-mean (seconds, psnr) per evaluation step of records of one method and budget."""
    by_step: Dict[int, List[Tuple[float, float]]] = {}
    for r in records:
        for p in r.get("curve", []):
            if p.get("psnr") is not None and math.isfinite(p["psnr"]):
                by_step.setdefault(int(p["step"]), []).append((float(p["seconds"]), float(p["psnr"])))
    steps = sorted(by_step)
    xs = [sum(s for s, _ in by_step[k]) / len(by_step[k]) for k in steps]
    ys = [sum(v for _, v in by_step[k]) / len(by_step[k]) for k in steps]
    return xs, ys


def plot_psnr_vs_time(
    records: Sequence[Mapping[str, Any]],
    path: Path,
    scene: str,
    labels: Optional[Mapping[str, str]] = None,
    references: Sequence[str] = (),
) -> Path:
    """Test PSNR against cumulative training seconds for the records of one scene; Pareto front of the end points.

    Methods in ``references`` (the sharp upper bound, which trains on images a real capture does not have) are drawn
    dashed and left out of the Pareto front.
    """
    plt = _pyplot()
    labels = labels or {}
    groups: Dict[Tuple[str, int], List[Mapping[str, Any]]] = {}
    for r in records:
        groups.setdefault((r["method"], int(r["steps"])), []).append(r)
    multi_budget = len({steps for _, steps in groups}) > 1
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    finals: List[Tuple[float, float]] = []
    cmap = plt.get_cmap("tab10")
    for i, ((method, steps), rs) in enumerate(groups.items()):
        xs, ys = _curve(rs)
        if not xs:
            continue
        name = labels.get(method, method) + (f" @{steps}" if multi_budget else "")
        colour = cmap(i % 10)
        reference = method in references
        ax.plot(xs, ys, marker="o", markersize=3, linewidth=1.5, color=colour, linestyle="--" if reference else "-",
                label=name)  # fmt: skip
        if not reference:
            finals.append((xs[-1], ys[-1]))
    if finals:
        front = pareto_front(finals)
        fx = [finals[i][0] for i in front]
        fy = [finals[i][1] for i in front]
        ax.step(fx, fy, where="post", linestyle="--", color="black", linewidth=1.0, alpha=0.7)
        ax.scatter(fx, fy, s=140, facecolors="none", edgecolors="black", linewidths=1.5, zorder=5,
                   label="Pareto front (final points)")  # fmt: skip
    ax.set_xlabel("cumulative training time (s, evaluation excluded)")
    ax.set_ylabel("test PSNR (dB, sharp test views)")
    ax.set_title(f"{scene}: test PSNR vs training time")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.01, 0.5))
    return _save(fig, path)


def plot_time_breakdown(
    records: Sequence[Mapping[str, Any]],
    path: Path,
    labels: Optional[Mapping[str, str]] = None,
) -> Path:
    """Stacked horizontal bars: training seconds per category (seed means), one bar per scene / method / budget."""
    plt = _pyplot()
    labels = labels or {}
    groups: Dict[Tuple[str, str, int], List[Mapping[str, Any]]] = {}
    for r in records:
        groups.setdefault((r["scene"], r["method"], int(r["steps"])), []).append(r)
    multi_budget = len({k[2] for k in groups}) > 1
    names, values = [], []
    for (scene, method, steps), rs in groups.items():
        names.append(f"{scene} / {labels.get(method, method)}" + (f" @{steps}" if multi_budget else ""))
        values.append([sum(r.get("breakdown", {}).get(c, 0.0) for r in rs) / len(rs) for c in CATEGORIES])
    fig, ax = plt.subplots(figsize=(8.5, 0.45 * max(len(names), 2) + 1.4))
    y = list(range(len(names)))
    left = [0.0] * len(names)
    for j, category in enumerate(CATEGORIES):
        widths = [v[j] for v in values]
        ax.barh(y, widths, left=left, color=COLOURS[category], label=category.replace("_", " "))
        left = [a + b for a, b in zip(left, widths)]
    ax.set_yticks(y)
    ax.set_yticklabels(names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("training time (s), forward + backward per category")
    ax.set_title("where the training time goes")
    ax.grid(True, axis="x", alpha=0.3)
    ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.01, 0.5))
    return _save(fig, path)


__all__ = ["pareto_front", "plot_psnr_vs_time", "plot_time_breakdown"]
