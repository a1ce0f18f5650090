"""`gsmsdr-estimate`: estimate which photos of a scene are sharp, motion-blurred, defocused or low-resolution, and
write the estimate into the scene's degradation.json as editable, marked records.

    gsmsdr-estimate --scene data/my-capture                 # writes data/my-capture/degradation.json
    gsmsdr-estimate --images data/my-capture/images         # prints the estimate only
    gsmsdr-estimate --scene data/x --replace-records        # also replaces true (non-estimated) records
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Optional

import tyro
from rich.console import Console
from rich.table import Column, Table

from .._cli import run_entrypoint
from .config import EstimateConfig
from .records import DEGRADATION_FILE, estimate_entries, is_estimated, write_scene_estimate

CONSOLE = Console()


@dataclass
class EstimateCLI:
    """Estimate per-image degradations (sharp / motion / defocus / mixres / unknown) of a set of photos."""

    scene: Optional[Path] = None
    """Scene directory: its images/ folder is estimated and the result merged into its degradation.json."""
    images: Optional[Path] = None
    """Image folder to estimate instead of a scene (printed; written only with --out)."""
    images_dir: str = "images"
    """Image folder inside --scene."""
    out: Optional[Path] = None
    """degradation.json to write (default: the scene's; with --images nothing is written unless given)."""
    replace_records: bool = False
    """Replace true (non-estimated) records too; by default they are kept and only missing or earlier
    estimated entries are written."""
    dry_run: bool = False
    """Print the estimate, write nothing."""
    config: EstimateConfig = field(default_factory=EstimateConfig)
    """Estimate settings (thresholds relative to the set)."""

    def main(self) -> Dict[str, Any]:
        if (self.scene is None) == (self.images is None):
            raise ValueError("give exactly one of --scene SCENE or --images DIR")
        if self.scene is not None and not self.scene.is_dir():
            raise FileNotFoundError(f"scene directory {self.scene} does not exist")
        folder = self.images if self.images is not None else self.scene / self.images_dir
        write = not self.dry_run and (self.scene is not None or self.out is not None)
        if write:
            if self.scene is not None:
                root, images_dir = self.scene, self.images_dir
            else:
                root, images_dir = folder.parent, folder.name
            out = self.out if self.out is not None else root / DEGRADATION_FILE
            path, doc, kept = write_scene_estimate(root, self.config, images_dir, out, self.replace_records)
            entries = {n: e for n, e in doc["images"].items() if is_estimated(e)}
        else:
            entries, kept, path = estimate_entries(folder, self.config), [], None
        self._print(entries)
        if kept:
            CONSOLE.print(f"kept {len(kept)} true record(s) (e.g. {kept[:3]}); --replace-records replaces them")
        if path is not None:
            CONSOLE.print(f"[bold green]wrote {len(entries)} estimated record(s) to {path}")
        return entries

    @staticmethod
    def _print(entries: Dict[str, Dict[str, Any]]) -> None:
        width = max((len(n) for n in entries), default=5)
        numbers = [Column(head, min_width=4) for head in ("conf", "shp", "p(d)", "p(m)", "iso", "dir", "foc", "sprd",
                                                           "rise", "f")]  # fmt: skip
        table = Table(Column("image", no_wrap=True, min_width=width), Column("label", no_wrap=True, min_width=7),
                      *numbers, padding=(0, 1), collapse_padding=True, pad_edge=False, show_edge=False)  # fmt: skip

        def number(value: Any) -> str:
            return "-" if value is None else f"{value:.2f}"

        for name, entry in entries.items():
            ev = entry["estimate"]
            factor = ev["mixres_factor"]
            table.add_row(name, ev["label"], f"{ev['confidence']:.2f}", f"{ev['sharpness']:.2f}",
                          *(number(ev.get(key)) for key in ("degraded_probability", "motion_probability", "isotropy",
                                                            "directional_loss", "sharpest_region", "detail_spread",
                                                            "edge_rise")),
                          "?" if factor is None else str(factor))  # fmt: skip
        CONSOLE.print(table)
        CONSOLE.print("conf: confidence; shp: sharpness relative to the set; p(d): the fitted ensemble's "
                      "probability that an image sharp by its sharpness is degraded; kind of blur: p(m) (the fitted "
                      "ensemble's probability of motion, which names it) and its evidence iso (detail isotropy), "
                      "dir (directional loss), foc (sharpest region's edge width), sprd (detail spread over tiles), "
                      "rise (edge rise ratio); f: mixres factor")  # fmt: skip


def parse(argv: Sequence[str] | None = None) -> EstimateCLI:
    """Parse CLI args (sys.argv[1:] by default) into an EstimateCLI."""
    return tyro.cli(EstimateCLI, args=list(sys.argv[1:] if argv is None else argv))


def entrypoint() -> None:
    """Console-script entry point."""
    run_entrypoint(parse, CONSOLE)


if __name__ == "__main__":
    entrypoint()
