"""Generate, on this machine, the scenes the GPU check (scripts/gpu_check.sh) trains on, into <out>/scenes.

The lent GPU machine has no network and 15 minutes; rendering these scenes there would cost minutes of it, so they
are generated here (CPU) and carried. Depth maps (not read by training) are dropped to keep the carry small.

    .venv/bin/python scripts/gpu_scenes.py .gpu
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from gsmsdr_ns.bench.scenes import SceneSpec, ensure_scene

SCENES = {
    # step time and peak memory at a Deblur-NeRF-like size, blur records known (motion)
    "motion-strong-600x400": SceneSpec("motion-strong", 600, 400, num_views=8, hold=6),
    # step time and peak memory at 1297x840 (Mip-NeRF 360 at 1/4) with no degradation records: its degradation.json
    # is dropped, and gpu_check.sh trains it with the estimate off, so every view takes the blur path
    "sharp-1297x840": SceneSpec("sharp", 1297, 840, num_views=4, hold=100),
    # ns-train gsmsdr-lite to the end of its schedule, against plain Gaussians
    "motion-strong-160x120": SceneSpec("motion-strong", 160, 120, num_views=24, hold=6),
}

WITHOUT_RECORDS = ("sharp-1297x840",)
"""Scenes carried without their degradation.json."""


def main(out: Path) -> None:
    cache = out / "scene-cache"
    for name, spec in SCENES.items():
        target = out / "scenes" / name
        if target.is_dir():
            print(f"{target}: exists")
            continue
        source = ensure_scene(cache, spec, log=print)
        partial = target.with_name(target.name + ".partial")
        shutil.rmtree(partial, ignore_errors=True)
        dropped = ["depth"] + (["degradation.json"] if name in WITHOUT_RECORDS else [])
        shutil.copytree(source, partial, ignore=shutil.ignore_patterns(*dropped))
        partial.rename(target)
        print(f"{target}: written")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else ".gpu"))
