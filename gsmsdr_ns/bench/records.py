"""The bench's file I/O in one place: atomic JSON / text / file writes (temporary file in the same folder, then
rename), run records, and reading YAML mappings."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path
from typing import Any, Callable, Dict, Optional


def _finite_or_none(value: Any) -> Any:
    """NaN / infinity -> None (null): records are standard JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_none(v) for v in value]
    return value


def _json_default(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "item"):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _temporary(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def write_json_atomic(path: Path, payload: Any) -> None:
    """Write ``payload`` as JSON to a temporary file in the same folder, then rename it into place."""
    path = Path(path)
    tmp = _temporary(path)
    with open(tmp, "w", encoding="utf8") as f:
        json.dump(_finite_or_none(payload), f, indent=1, default=_json_default, allow_nan=False)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` (UTF-8) to a temporary file in the same folder, then rename it into place."""
    path = Path(path)
    tmp = _temporary(path)
    tmp.write_text(text, encoding="utf8")
    os.replace(tmp, path)


def copy_file_atomic(source: Path, path: Path) -> Path:
    """Copy ``source`` to a temporary file beside ``path``, then rename it into place."""
    path = Path(path)
    tmp = _temporary(path)
    shutil.copyfile(source, tmp)
    os.replace(tmp, path)
    return path


def load_yaml_mapping(source: Path, error: Callable[[str], Exception], what: str = "file") -> Dict[str, Any]:
    """The YAML mapping in ``source``; raises ``error(message)`` (the message starts with the path) when the ``what``
    is missing, not YAML or not a mapping."""
    import yaml

    source = Path(source)
    if not source.is_file():
        raise error(f"{source}: {what} not found")
    try:
        values = yaml.safe_load(source.read_text(encoding="utf8"))
    except yaml.YAMLError as e:
        raise error(f"{source}: not valid YAML: {e}") from e
    if not isinstance(values, dict):
        raise error(f"{source}: must be a YAML mapping, got {type(values).__name__}")
    return values


def load_record(path: Path) -> Optional[Dict[str, Any]]:
    """A run record, or None when the file is missing, unreadable or not a record."""
    try:
        with open(path, encoding="utf8") as f:
            record = json.load(f)
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and "id" in record else None


__all__ = ["copy_file_atomic", "load_record", "load_yaml_mapping", "write_json_atomic", "write_text_atomic"]
