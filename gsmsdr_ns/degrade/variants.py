"""Built-in degradation presets and `generate_variant`: a procedural scene written straight as a degraded scene.

configs/degrade/<name>.yaml mirror BUILTIN_PRESETS (a test keeps them equal); the installed package does not
need the repository's configs/ folder.
"""

from __future__ import annotations

import dataclasses
import os
import secrets
import shutil
from collections.abc import Callable
from pathlib import Path

from .. import __version__
from ..synth.config import SynthSceneConfig
from ..synth.generate import check_target, generate_scene
from .config import DefocusConfig, DegradeConfig, MotionConfig
from .pipeline import degrade_scene

BUILTIN_PRESETS: dict[str, DegradeConfig] = {
    "sharp": DegradeConfig(effects=()),
    "motion-mild": DegradeConfig(effects=("motion",), motion=MotionConfig(min_blur_px=6.0, max_blur_px=12.0)),
    "motion-strong": DegradeConfig(effects=("motion",), motion=MotionConfig(min_blur_px=16.0, max_blur_px=32.0)),
    "defocus": DegradeConfig(effects=("defocus",), defocus=DefocusConfig(min_coc_px=8.0, max_coc_px=14.0)),
    "defocus-strong": DegradeConfig(effects=("defocus",), defocus=DefocusConfig(min_coc_px=16.0, max_coc_px=32.0)),
    "defocus-disk": DegradeConfig(
        effects=("defocus",), defocus=DefocusConfig(model="disk", min_coc_px=13.0, max_coc_px=28.0)
    ),
    "mixres": DegradeConfig(effects=("mixres",)),
    "mixed": DegradeConfig(effects=("motion", "defocus", "mixres"), assignment="one_per_image"),
}
"""Named degradation configs; pixel values are for 600 px wide images (scaled with the width)."""

VARIANTS: dict[str, str] = {
    "sharp": "sharp",
    "motion": "motion-mild",
    "motion-strong": "motion-strong",
    "defocus": "defocus",
    "defocus-strong": "defocus-strong",
    "defocus-disk": "defocus-disk",
    "mixres": "mixres",
    "mixed": "mixed",
}
"""`gsmsdr-synth --variant` names -> BUILTIN_PRESETS keys."""


def generate_variant(
    out_dir: str | Path,
    scene_config: SynthSceneConfig | None = None,
    variant: str = "motion",
    degrade_config: DegradeConfig | None = None,
    hold: int | None = None,
    overwrite: bool = False,
    log: Callable[[str], None] | None = None,
    preset_name: str | None = None,
) -> Path:
    """Render the procedural scene (sharp, into a hidden temp dir) and degrade it into out_dir.

    degrade_config (named preset_name in degradation.json) replaces the variant's built-in preset; its seed is
    replaced by the scene seed so one --seed controls both; hold, if given, overrides the preset's.
    out_dir is written atomically (as degrade_scene); the sharp temp scene is always removed.
    """
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; valid variants: {sorted(VARIANTS)}")
    scene_config = scene_config if scene_config is not None else SynthSceneConfig()
    cfg = degrade_config if degrade_config is not None else BUILTIN_PRESETS[VARIANTS[variant]]
    cfg = dataclasses.replace(cfg, seed=scene_config.seed, hold=cfg.hold if hold is None else hold)
    if degrade_config is None:
        preset_name = VARIANTS[variant]
    out = Path(out_dir).absolute()
    check_target(out, overwrite)  # fail before rendering anything
    sharp = out.parent / f".{out.name}.sharp-{os.getpid()}-{secrets.token_hex(4)}"
    try:
        generate_scene(sharp, scene_config, log=log)
        return degrade_scene(
            sharp,
            out,
            cfg,
            overwrite=overwrite,
            preset=preset_name,
            generator=f"gsmsdr-synth {__version__} (variant {variant})",
            source_label="procedural",
            log=log,
        )
    finally:
        shutil.rmtree(sharp, ignore_errors=True)
