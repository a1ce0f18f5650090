"""`gsmsdr-process`: a folder of photos (no poses) -> a scene ``ns-train gsmsdr --data`` reads.

    gsmsdr-process --images photos/ --out data/my-scene
    gsmsdr-process --images frames/ --out data/walk --matching sequential --hold 8 --overwrite

SIFT features (pycolmap, CPU or GPU), exhaustive or sequential matching, incremental mapping, the largest model
kept and undistorted to pinhole, written as ``images/`` + ``sparse/0``. Photos that do not register are listed with
their sharpness. The output is built beside ``--out`` and renamed into place; an existing output is replaced only
with ``--overwrite``.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import tyro
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from typing_extensions import Annotated

from .._cli import run_entrypoint
from ..io.colmap import quiet_pycolmap
from .config import ProcessConfig
from .sfm import ProcessResult, process_photos

CONSOLE = Console()


@dataclass
class ProcessCLI:
    """Pose a folder of photos with structure-from-motion and write an undistorted COLMAP scene (images/, sparse/0)."""

    images: Path
    """Folder of photos (png, jpg, ...; read directly inside it, sorted by file name)."""
    out: Path
    """Output scene directory."""
    overwrite: bool = False
    """Replace an existing non-empty output directory (the old one is deleted only once the new one is complete)."""
    config: Annotated[ProcessConfig, tyro.conf.arg(name="")] = field(default_factory=ProcessConfig)
    """Structure-from-motion options (--matching, --max-image-size, --hold, ...)."""

    def main(self) -> ProcessResult:
        columns = (SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                   TimeElapsedColumn())  # fmt: skip
        with quiet_pycolmap(self.config.verbose), Progress(*columns, console=CONSOLE) as progress:
            result = process_photos(self.images, self.out, self.config, self.overwrite, progress=progress)
        total = len(result.registered) + len(result.unregistered)
        CONSOLE.print(
            f"[bold green]registered {len(result.registered)}/{total} photos[/bold green] ({result.matching} "
            f"matching, {result.num_points} points, {result.num_models} model(s) found, largest kept) in "
            f"{sum(result.seconds.values()):.1f}s; wrote {result.scene}"
        )
        if result.duplicates:
            CONSOLE.print(
                "[yellow]left out as copies of another photo (a copy could become a test view of its original):"
                "[/yellow] " + ", ".join(f"{copy} (= {kept})" for copy, kept in sorted(result.duplicates.items())),
                soft_wrap=True,
            )
        if result.unregistered:
            CONSOLE.print(
                "[yellow]not registered (sharpness = variance of the Laplacian, lower is blurrier):[/yellow] "
                + ", ".join(f"{name} ({score:.2e})" for name, score in result.unregistered),
                soft_wrap=True,
            )
        return result


def parse(argv: Sequence[str] | None = None) -> ProcessCLI:
    """Parse CLI args (sys.argv[1:] by default) into a ProcessCLI."""
    return tyro.cli(ProcessCLI, args=list(sys.argv[1:] if argv is None else argv))


def entrypoint() -> None:
    """Console-script entry point."""
    run_entrypoint(parse, CONSOLE)


if __name__ == "__main__":
    entrypoint()
