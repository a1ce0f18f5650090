"""The YAML configs shipped with the package (``configs/<kind>/<name>.yaml``), found the same way in a checkout and
in a wheel install.

The repository's top-level ``configs/`` folder is the one copy: ``gsmsdr_ns/configs`` is a symlink to it, and the
package data globs of pyproject.toml copy its files into the wheel, so ``importlib.resources`` finds them either way.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import List

CONFIG_KINDS = ("bench", "degrade", "synth")
"""Sub-folders of ``configs/``: benchmark suites, degradation presets, procedural scene presets."""


def config_root() -> Path:
    """The packaged ``configs`` folder."""
    # a regular install or checkout: a real folder (no zip import is supported for the package's data files)
    return Path(str(resources.files("gsmsdr_ns").joinpath("configs")))


def config_dir(kind: str) -> Path:
    """The packaged ``configs/<kind>`` folder."""
    if kind not in CONFIG_KINDS:
        raise ValueError(f"unknown config kind {kind!r}; valid: {', '.join(CONFIG_KINDS)}")
    return config_root() / kind


def config_names(kind: str) -> List[str]:
    """The names (file stems) of the packaged ``configs/<kind>/*.yaml`` files, sorted."""
    folder = config_dir(kind)
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


def config_file(kind: str, name: str) -> Path:
    """The packaged ``configs/<kind>/<name>.yaml``; FileNotFoundError naming the valid names when there is none."""
    path = config_dir(kind) / f"{name}.yaml"
    if not path.is_file():
        names = ", ".join(config_names(kind)) or "none (the package's configs/ folder is missing)"
        raise FileNotFoundError(f"no packaged config {path} ({kind} {name!r}); valid names: {names}")
    return path


__all__ = ["CONFIG_KINDS", "config_dir", "config_file", "config_names", "config_root"]
