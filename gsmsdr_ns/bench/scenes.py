"""Generated benchmark scenes: a procedural scene and a degradation variant, generated once and reused."""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

from gsmsdr_ns.io.atomic import exclusive_lock, replace_dir, temp_sibling_dir

SCENE_DATA_VERSION = 2
"""Bumped when generated scenes change for the same spec (2: motion sub-frames rendered with the scene's own
anti-aliasing), so cached scenes of an older generator are not reused."""


@dataclass(frozen=True)
class SceneSpec:
    """A generated scene: the procedural scene's size and seed, and the degradation variant."""

    variant: str
    """Degradation variant (``gsmsdr_ns.degrade.variants.VARIANTS``)."""
    width: int = 160
    """Image width in pixels."""
    height: int = 120
    """Image height in pixels."""
    num_views: int = 24
    """Views of the procedural scene (training + test)."""
    seed: int = 0
    """Procedural scene and degradation seed."""
    hold: int = 6
    """Every ``hold``-th view (from the first) is a held-out sharp test view."""
    num_points: int = 3000
    """Sparse points of the generated COLMAP model (the Gaussians' initialisation)."""

    @property
    def name(self) -> str:
        return (
            f"{self.variant}-{self.width}x{self.height}-v{self.num_views}-h{self.hold}-s{self.seed}"
            f"-g{SCENE_DATA_VERSION}"
        )

    def with_variant(self, variant: str) -> "SceneSpec":
        return dataclasses.replace(self, variant=variant)


def ensure_scene(bench_dir: Path, spec: SceneSpec, log: Optional[Callable[[str], None]] = None) -> Path:
    """The generated scene of ``spec`` under ``bench_dir/scenes/<name>``, generated once and reused."""
    from gsmsdr_ns.degrade.variants import generate_variant
    from gsmsdr_ns.synth.config import SynthSceneConfig

    out = Path(bench_dir) / "scenes" / spec.name

    def complete(folder: Path) -> bool:
        return (folder / "degradation.json").is_file() and (folder / "images_test").is_dir()

    if complete(out):
        return out
    scene = SynthSceneConfig(
        seed=spec.seed, num_views=spec.num_views, width=spec.width, height=spec.height, num_points=spec.num_points
    )
    # suites running in parallel may need the same scene at once: one generates it, the others wait and reuse it
    with exclusive_lock(out):
        if complete(out):
            return out
        if log is not None:
            log(f"accuracy: generating {out}")
        # generated beside its final place, then renamed: a reader that takes no lock never sees half a scene
        partial = temp_sibling_dir(out)
        try:
            generate_variant(partial, scene, spec.variant, hold=spec.hold, overwrite=True)
            replace_dir(partial, out)  # also replaces a folder left by an interrupted run of an older version
        finally:
            shutil.rmtree(partial, ignore_errors=True)
    return out


__all__ = ["SCENE_DATA_VERSION", "SceneSpec", "ensure_scene"]
