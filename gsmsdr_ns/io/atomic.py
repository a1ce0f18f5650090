"""Atomic writes: a file (bytes / text / JSON) or a whole folder appears complete or not at all.

Files are written to a hidden temporary sibling, flushed to disk and renamed over the target (``os.replace`` is
atomic within one file system). Folders are built in a hidden temporary sibling folder and swapped into place;
an existing target is first renamed aside and deleted only after the swap succeeded, so an error never leaves
the caller without either the old or the new folder.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator, Optional


def _temp_name(target: Path, tag: str) -> Path:
    return target.parent / f".{target.name}.{tag}-{os.getpid()}-{secrets.token_hex(4)}"


def write_bytes_atomic(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary sibling file (fsynced, then renamed into place)."""
    return write_file_atomic(path, lambda tmp: Path(tmp).write_bytes(data))


def write_text_atomic(path: Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`write_bytes_atomic`)."""
    return write_bytes_atomic(path, text.encode("utf8"))


def write_json_atomic(
    path: Path, payload: Any, indent: Optional[int] = 1, default: Optional[Callable[[Any], Any]] = None,
    allow_nan: bool = True,
) -> Path:
    """Write ``payload`` as JSON to ``path`` atomically; ``default`` / ``allow_nan`` as in :func:`json.dumps`."""
    return write_text_atomic(path, json.dumps(payload, indent=indent, default=default, allow_nan=allow_nan))


def write_file_atomic(path: Path, write: Callable[[Path], Any]) -> Path:
    """Let ``write(tmp_path)`` produce the file (an image encoder, ``np.save``, ``fig.savefig``), then rename it.

    The temporary name keeps the target's extension, for writers that choose the format from it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_name(path, "tmp").with_suffix(path.suffix)
    try:
        write(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def temp_sibling_dir(target: Path, tag: str = "partial") -> Path:
    """Create and return an empty hidden folder next to ``target`` (``.<name>.<tag>-<pid>-<random>``).

    Made with ``mkdir`` rather than ``mkdtemp``: mkdtemp's 0700 mode would end up on the final folder, mkdir
    honours the umask.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_name(target, tag)
    tmp.mkdir()
    return tmp


def replace_dir(tmp: Path, target: Path) -> None:
    """Rename the finished folder ``tmp`` to ``target``; an existing target is removed only after the swap.

    If the final rename fails, the old target is put back (unless something else took its place meanwhile) and
    the error propagates; ``tmp`` is left for the caller to clean up.
    """
    tmp, target = Path(tmp), Path(target)
    old = None
    if target.exists():
        old = _temp_name(target, "old")
        os.rename(target, old)
    try:
        os.rename(tmp, target)
    except BaseException:
        if old is not None and not target.exists():
            os.rename(old, target)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextmanager
def atomic_dir(target: Path) -> Iterator[Path]:
    """Build a folder in a temporary sibling (the yielded path) and swap it into ``target`` when the block ends.

    Any exception in the block (or in the swap) removes the temporary folder and leaves ``target`` untouched.
    Checks that must happen right before the swap (has something appeared at ``target``?) go at the end of the
    block.
    """
    tmp = temp_sibling_dir(target)
    try:
        yield tmp
        replace_dir(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
