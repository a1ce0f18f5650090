"""`gsmsdr-degrade`: turn a sharp scene into a degraded one (Deblur-NeRF layout).

    gsmsdr-degrade --input data/demo --out data/demo-motion --effect motion
    gsmsdr-degrade --input data/demo --out data/demo-md --effect motion,defocus --noise-sigma 0.01 --seed 3
    gsmsdr-degrade --input data/demo --out data/demo-mixed --preset configs/degrade/mixed.yaml --overwrite

Precedence: built-in defaults < --preset YAML < explicit flags (--effect replaces the preset's effect list).
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import tyro
from rich.console import Console
from typing_extensions import Annotated

from .._cli import preset_from_argv, run_entrypoint
from .config import DegradeConfig, load_preset
from .pipeline import degrade_scene

CONSOLE = Console()


@dataclass
class DegradeCLI:
    """Degrade a sharp scene (COLMAP images/ + sparse/0, or nerfstudio transforms.json) into a Deblur-NeRF layout:
    degraded training views, sharp test views every --hold-th view, images_test/, degradation.json."""

    input: Annotated[Path, tyro.conf.arg(aliases=("--data",))]
    """Sharp input scene directory."""
    out: Path
    """Output directory for the degraded scene."""
    preset: Path | None = None
    """YAML preset with DegradeConfig fields (e.g. configs/degrade/motion-mild.yaml); explicit flags override it."""
    overwrite: bool = False
    """Replace an existing non-empty output directory."""
    verbose: bool = False
    """Log every written view."""
    config: Annotated[DegradeConfig, tyro.conf.arg(name="")] = field(default_factory=DegradeConfig)
    """Degradation parameters (--effect, --seed, --hold, --noise-sigma, --motion.*, --defocus.*, ...)."""

    def main(self) -> Path:
        t0 = time.perf_counter()
        log = (lambda msg: CONSOLE.log(msg)) if self.verbose else None
        preset_name = self.preset.stem if self.preset is not None else None

        def notice(message: str) -> None:  # shown without --verbose (the undistortion of a distorted input)
            CONSOLE.print(message, soft_wrap=True, markup=False, highlight=False)

        out = degrade_scene(self.input, self.out, self.config, self.overwrite, preset=preset_name, log=log,
                            notice=notice)  # fmt: skip
        effects = "+".join(self.config.resolved_effects()) or "sharp"
        CONSOLE.print(f"[bold green]wrote {effects} scene (hold={self.config.hold}) to {out} "
                      f"in {time.perf_counter() - t0:.1f}s")  # fmt: skip
        return out


def parse(argv: Sequence[str] | None = None) -> DegradeCLI:
    """Parse CLI args (sys.argv[1:] by default) into a DegradeCLI."""
    argv = list(sys.argv[1:] if argv is None else argv)
    preset = preset_from_argv(argv)
    base = load_preset(preset) if preset is not None else DegradeConfig()
    # --effect appends to its default: start from an empty list and fall back to the preset's afterwards.
    default = DegradeCLI(
        input=tyro.MISSING, out=tyro.MISSING, preset=preset, config=dataclasses.replace(base, effects=())
    )
    cli = tyro.cli(DegradeCLI, args=argv, default=default)
    if not cli.config.effects:
        cli.config = dataclasses.replace(cli.config, effects=base.effects)
    return cli


def entrypoint() -> None:
    """Console-script entry point."""
    run_entrypoint(parse, CONSOLE)


if __name__ == "__main__":
    entrypoint()
