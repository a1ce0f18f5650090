"""`gsmsdr-synth`: generate the procedural default scene, sharp or degraded.

The command lives here, above both packages it drives: ``gsmsdr_ns.synth`` renders the sharp scene and
``gsmsdr_ns.degrade`` degrades it into a variant (``--variant``).

    gsmsdr-synth --out data/demo --seed 0 --num-views 32
    gsmsdr-synth --out data/demo --preset configs/synth/default.yaml --overwrite
    gsmsdr-synth --out data/demo-motion --variant motion       # degraded Deblur-NeRF layout (gsmsdr_ns.degrade)

Precedence: built-in defaults < --preset YAML < explicit flags.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import tyro
from rich.console import Console

from .._cli import preset_from_argv, run_entrypoint
from ..synth.config import SynthSceneConfig, load_preset
from ..synth.generate import generate_scene
from .config import load_preset as load_degrade_preset
from .variants import generate_variant

CONSOLE = Console()


@dataclass
class SynthCLI:
    """Render a small procedural textured scene with known cameras into a COLMAP-style dataset."""

    out: Path = Path("data/demo")
    """Output directory (images/, depth/, sparse/0/, scene.json)."""
    preset: Path | None = None
    """YAML preset with SynthSceneConfig fields; explicit flags override it."""
    overwrite: bool = False
    """Replace an existing non-empty output directory."""
    verbose: bool = False
    """Log every rendered view."""
    variant: Literal[
        "none", "sharp", "motion", "motion-strong", "defocus", "defocus-strong", "defocus-disk", "mixres", "mixed"
    ] = "none"
    """none: the plain sharp COLMAP scene. Otherwise a Deblur-NeRF layout (images/ with sharp test views every
    --hold-th view, images_test/, degradation.json) degraded with the built-in preset of that name (sharp: no
    degradation; mixed: one of motion/defocus/mixres per training view); the degradation seed is --seed."""
    degrade_preset: Path | None = None
    """YAML degradation preset (configs/degrade/*.yaml) replacing the variant's built-in one."""
    hold: int | None = None
    """Test-view spacing of a variant (default: the preset's, 8)."""
    scene: tyro.conf.OmitArgPrefixes[SynthSceneConfig] = field(default_factory=SynthSceneConfig)
    """Scene parameters (flags without prefix, e.g. --seed, --num-views)."""

    def main(self) -> Path:
        t0 = time.perf_counter()
        log = (lambda msg: CONSOLE.log(msg)) if self.verbose else None
        if self.variant == "none":
            out = generate_scene(self.out, self.scene, overwrite=self.overwrite, log=log)
        else:
            preset = self.degrade_preset
            degrade = load_degrade_preset(preset) if preset is not None else None
            out = generate_variant(
                self.out, self.scene, self.variant, degrade, hold=self.hold, overwrite=self.overwrite, log=log,
                preset_name=preset.stem if preset is not None else None,
            )  # fmt: skip
        CONSOLE.print(
            f"[bold green]wrote {self.scene.num_views} views{'' if self.variant == 'none' else f' ({self.variant})'} "
            f"({self.scene.width}x{self.scene.height}, seed {self.scene.seed}) to {out} "
            f"in {time.perf_counter() - t0:.1f}s"
        )
        return out


def parse(argv: Sequence[str] | None = None) -> SynthCLI:
    """Parse CLI args (sys.argv[1:] by default) into a SynthCLI."""
    argv = list(sys.argv[1:] if argv is None else argv)
    preset = preset_from_argv(argv)
    scene = load_preset(preset) if preset is not None and preset.is_file() else SynthSceneConfig()
    if preset is not None and not preset.is_file():
        raise FileNotFoundError(f"preset {preset} not found")
    return tyro.cli(SynthCLI, args=argv, default=SynthCLI(preset=preset, scene=scene))


def entrypoint() -> None:
    """Console-script entry point."""
    run_entrypoint(parse, CONSOLE)


if __name__ == "__main__":
    entrypoint()
