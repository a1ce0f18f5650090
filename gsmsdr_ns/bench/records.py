"""The bench's record store: run records as standard JSON in ``<out>/runs/<run id>.json``, written and copied with
``gsmsdr_ns.io.atomic``, loaded, and collected for a suite (only records matching the runs' current settings)."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any, Dict, List, Optional

from gsmsdr_ns.bench.fingerprint import fingerprint
from gsmsdr_ns.bench.suite_config import RunKey, Suite
from gsmsdr_ns.io import atomic
from gsmsdr_ns.io.atomic import write_text_atomic


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


def write_json_atomic(path: Path, payload: Any) -> Path:
    """A run record or other payload as standard JSON (NaN and infinity become null), written atomically."""
    return atomic.write_json_atomic(path, _finite_or_none(payload), default=_json_default, allow_nan=False)


def copy_file_atomic(source: Path, path: Path) -> Path:
    """Copy ``source`` to ``path`` atomically (a temporary sibling, then a rename)."""
    return atomic.write_file_atomic(path, lambda tmp: shutil.copyfile(source, tmp), size=Path(source).stat().st_size)


def load_record(path: Path) -> Optional[Dict[str, Any]]:
    """A run record, or None when the file is missing, unreadable or not a record."""
    try:
        with open(path, encoding="utf8") as f:
            record = json.load(f)
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and "id" in record else None


def record_path(out: Path, key: RunKey) -> Path:
    """Where run ``key``'s record is kept in the suite's output folder ``out``."""
    return Path(out) / "runs" / f"{key.id}.json"


def finished_record(suite: Suite, out: Path, key: RunKey) -> Optional[Dict[str, Any]]:
    """The run's record if it exists and matches the run's current settings."""
    record = load_record(record_path(out, key))
    if record is None or record.get("fingerprint") != fingerprint(suite, key):
        return None
    return record


def collect_records(suite: Suite, out: Path) -> List[Dict[str, Any]]:
    """The suite's finished records in ``out/runs`` (current settings only), in the suite's run order."""
    records = []
    for key in suite.runs():
        record = finished_record(suite, out, key)
        if record is not None:
            records.append(record)
    return records


__all__ = [
    "collect_records",
    "copy_file_atomic",
    "finished_record",
    "load_record",
    "record_path",
    "write_json_atomic",
    "write_text_atomic",
]
