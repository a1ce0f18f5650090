"""`gsmsdr-bench degrade`: how long gsmsdr-degrade takes per effect on a 50-view 600x400 procedural scene.

The sharp scene is generated once (about a minute on 2 cores) and cached; each row degrades it into a temporary
directory that is deleted afterwards. Wall time is what a user waits; CPU time (this process plus its worker
processes) shows how much the machine's other load inflated it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Sequence

from gsmsdr_ns.degrade.config import DegradeConfig, NoiseConfig
from gsmsdr_ns.degrade.pipeline import degrade_scene
from gsmsdr_ns.degrade.variants import BUILTIN_PRESETS
from gsmsdr_ns.synth.config import SynthSceneConfig
from gsmsdr_ns.synth.generate import generate_scene

ROWS: Dict[str, DegradeConfig] = {
    "motion": BUILTIN_PRESETS["motion-mild"],
    "motion-strong": BUILTIN_PRESETS["motion-strong"],
    "defocus": BUILTIN_PRESETS["defocus"],
    "mixres": BUILTIN_PRESETS["mixres"],
    "all": DegradeConfig(effects=("motion", "defocus", "mixres"), noise=NoiseConfig(sigma=0.01)),
    "mixed": BUILTIN_PRESETS["mixed"],
}
"""Benchmark rows: 'all' applies motion, defocus, mixres and noise to every training view."""


def cached_scene(cache_dir: Path, cfg: SynthSceneConfig) -> Path:
    """The sharp scene for cfg under cache_dir (generated on first use, reused while scene.json matches)."""
    path = cache_dir / f"scene-{cfg.num_views}v-{cfg.width}x{cfg.height}-seed{cfg.seed}"
    meta = path / "scene.json"
    if meta.is_file() and json.loads(meta.read_text())["config"] == dataclasses.asdict(cfg):
        return path
    t0 = time.perf_counter()
    generate_scene(path, cfg, overwrite=True)
    print(f"generated the sharp scene {path} in {time.perf_counter() - t0:.1f} s (cached for later runs)")
    return path


def _cpu_seconds() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def run_degrade_benchmark(
    rows: Sequence[str], scene_cfg: SynthSceneConfig, cache_dir: Path, workers: int = 0
) -> List[Dict]:
    """Degrade the cached scene once per row. -> [{row, effects, train_views, views, wall_s, cpu_s, workers}]."""
    unknown = sorted(set(rows) - set(ROWS))
    if unknown:
        raise ValueError(f"unknown rows {unknown}; valid: {sorted(ROWS)}")
    scene = cached_scene(cache_dir, scene_cfg)
    results = []
    for row in rows:
        cfg = dataclasses.replace(ROWS[row], workers=workers)
        with tempfile.TemporaryDirectory(prefix="gsmsdr-bench-degrade-") as tmp:
            c0, t0 = _cpu_seconds(), time.perf_counter()
            out = degrade_scene(scene, Path(tmp) / row, cfg)
            wall, cpu = time.perf_counter() - t0, _cpu_seconds() - c0
            doc = json.loads((out / "degradation.json").read_text())
            shutil.rmtree(out)
        n_train = sum(1 for r in doc["images"].values() if r["split"] == "train")
        results.append({"row": row, "effects": "+".join(doc["effects"]), "train_views": n_train,
                        "views": len(doc["images"]), "wall_s": wall, "cpu_s": cpu})  # fmt: skip
        print(f"{row}: {wall:.1f} s", flush=True)
    return results


def format_table(results: List[Dict], scene_cfg: SynthSceneConfig, workers: int, target_s: float = 60.0) -> str:
    load = os.getloadavg()[0]
    lines = [
        f"gsmsdr-degrade on a {scene_cfg.num_views}-view {scene_cfg.width}x{scene_cfg.height} procedural scene, "
        f"{os.cpu_count()} CPU cores, workers={workers or 'auto'}, 1-min load average at the end {load:.1f}",
        f"| row | effects | train views | wall s | s / train view | CPU s (all processes) | < {target_s:.0f} s |",
        "|---|---|---:|---:|---:|---:|---|",
    ]
    for r in results:
        ok = "yes" if r["wall_s"] < target_s else "NO"
        lines.append(
            f"| {r['row']} | {r['effects']} | {r['train_views']}/{r['views']} | {r['wall_s']:.1f} | "
            f"{r['wall_s'] / max(r['train_views'], 1):.2f} | {r['cpu_s']:.1f} | {ok} |"
        )
    return "\n".join(lines)
