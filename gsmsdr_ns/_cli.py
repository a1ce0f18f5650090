"""What the dataset-writing console scripts (`gsmsdr-synth`, `gsmsdr-degrade`) share: --preset lookup before tyro
parses, and the entry-point wrapper (SIGTERM handling, one-line errors)."""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from rich.console import Console


def preset_from_argv(argv: Sequence[str]) -> Path | None:
    """Find --preset before tyro parses, so the preset can become the defaults that flags override."""
    for i, arg in enumerate(argv):
        if arg == "--preset" and i + 1 < len(argv):
            return Path(argv[i + 1])
        if arg.startswith("--preset="):
            return Path(arg.split("=", 1)[1])
    return None


def _exit_on_sigterm(signum, _frame) -> None:
    # SystemExit unwinds through the writer's cleanup (generate_scene, degrade_scene), so a killed run leaves no
    # temp directory.
    raise SystemExit(128 + signum)


def run_entrypoint(parse: Callable[[], Any], console: Console) -> None:
    """Run `parse().main()` as a console script: SIGTERM exits through the cleanup code, and a FileExistsError,
    FileNotFoundError or ValueError is printed as one red "error:" line with exit status 1."""
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    try:
        parse().main()
    except (FileExistsError, FileNotFoundError, ValueError) as e:
        console.print(f"[bold red]error:[/bold red] {e}")
        sys.exit(1)
