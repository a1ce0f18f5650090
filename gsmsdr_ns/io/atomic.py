"""Atomic writes: a file (bytes / text / JSON) or a whole folder appears complete or not at all.

Files are written to a hidden temporary sibling, flushed to disk and renamed over the target (``os.replace`` is
atomic within one file system). Folders are built in a hidden temporary sibling folder and swapped into place;
an existing target is first renamed aside and deleted only after the swap succeeded, so an error never leaves
the caller without either the old or the new folder.

Temporary names end in ``-<pid>-<8 hex digits>``: what a killed process (SIGKILL, a power cut) left behind is
removed by the next writer of the same target (:func:`remove_stale_temporaries`), not by the process that died.
A file that finds the disk full raises :class:`~gsmsdr_ns.io.errors.DiskFullError` naming the file, the room it
needs and the room there is.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import secrets
import shutil
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator, List, Optional

from gsmsdr_ns.io.errors import DiskFullError, disk_full_cause, disk_full_error, format_bytes, free_space_text

STALE_AFTER_S = 60.0
"""A temporary of a process that no longer runs is removed only once untouched this long (a process of another
machine writing to the same shared folder keeps touching its own)."""

_TEMP_SUFFIX = re.compile(r"-(\d+)-[0-9a-f]{8}(\.[^/]*)?$")


def _temp_name(target: Path, tag: str) -> Path:
    return target.parent / f".{target.name}.{tag}-{os.getpid()}-{secrets.token_hex(4)}"


def _process_exists(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale_temporaries(folder: Path, prefix: str) -> List[Path]:
    """Remove what writers that died left in ``folder``: entries named ``<prefix>...-<pid>-<8 hex>[.ext]`` whose
    process no longer runs and that nobody touched for :data:`STALE_AFTER_S`. Returns the removed paths.

    ``prefix``: the start of the temporary names of one target (``.scene.`` for the folder ``scene``), so a writer
    cleans up after earlier writers of the same target only.
    """
    removed = []
    try:
        entries = [e for e in Path(folder).iterdir() if e.name.startswith(prefix)]
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        match = _TEMP_SUFFIX.search(entry.name)
        if match is None or _process_exists(int(match.group(1))):
            continue
        try:
            if now - entry.lstat().st_mtime < STALE_AFTER_S:
                continue
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()
        except OSError:
            continue  # gone meanwhile, or not ours to remove
        removed.append(entry)
    return removed


def write_bytes_atomic(path: Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary sibling file (fsynced, then renamed into place)."""
    return write_file_atomic(path, lambda tmp: Path(tmp).write_bytes(data), size=len(data))


def write_text_atomic(path: Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`write_bytes_atomic`)."""
    return write_bytes_atomic(path, text.encode("utf8"))


def write_json_atomic(
    path: Path,
    payload: Any,
    indent: Optional[int] = 1,
    default: Optional[Callable[[Any], Any]] = None,
    allow_nan: bool = True,
) -> Path:
    """Write ``payload`` as JSON to ``path`` atomically; ``default`` / ``allow_nan`` as in :func:`json.dumps`."""
    return write_text_atomic(path, json.dumps(payload, indent=indent, default=default, allow_nan=allow_nan))


def write_file_atomic(path: Path, write: Callable[[Path], Any], size: Optional[int] = None) -> Path:
    """Let ``write(tmp_path)`` produce the file (an image encoder, ``np.save``, ``fig.savefig``), then rename it.

    The temporary name keeps the target's extension, for writers that choose the format from it. ``size``: the
    file's size in bytes when known, named by the DiskFullError a full disk raises (else the bytes written before
    the disk filled, as a lower bound).
    """
    path = Path(path)
    created = _make_parents(path.parent)
    remove_stale_temporaries(path.parent, f".{path.name}.")
    tmp = _temp_name(path, "tmp")
    tmp = tmp.with_name(tmp.name + path.suffix)
    try:
        write(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        full = disk_full_cause(exc) if isinstance(exc, Exception) else None
        written = tmp.stat().st_size if full is not None and tmp.exists() else 0
        tmp.unlink(missing_ok=True)
        for folder in reversed(created):  # the folders made for this file, if nothing else went into them
            try:
                folder.rmdir()
            except OSError:
                break
        if full is not None and not isinstance(exc, DiskFullError):
            raise _file_disk_full(path, full, size, written) from exc
        raise
    return path


def _file_disk_full(path: Path, error: OSError, size: Optional[int], written: int) -> DiskFullError:
    """The one-line error of a file that did not fit: its name, the room it needs, the room there is."""
    needs = f"it needs {format_bytes(size)}" if size is not None else f"it needs more than {format_bytes(written)}"
    return disk_full_error(
        f"gsmsdr: no space left on the disk writing '{path}' ({needs}, {free_space_text(path.parent)}); it was not "
        "written. Free some space, or write to a disk with room.",
        error.errno,
    )


def _make_parents(folder: Path) -> List[Path]:
    """``mkdir -p folder``; returns the folders it created, outermost first."""
    missing = []
    while not folder.exists() and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    missing.reverse()
    for created in missing:
        created.mkdir(exist_ok=True)
    return missing


def temp_sibling_dir(target: Path, tag: str = "partial") -> Path:
    """Create and return an empty hidden folder next to ``target`` (``.<name>.<tag>-<pid>-<random>``).

    Made with ``mkdir`` rather than ``mkdtemp``: mkdtemp's 0700 mode would end up on the final folder, mkdir
    honours the umask.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(target.parent, f".{target.name}.")
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


@contextmanager
def exclusive_lock(target: Path) -> Iterator[Path]:
    """Hold an exclusive lock on ``target`` (through the hidden file ``.<name>.lock`` beside it) for the block.

    Processes that build the same ``target`` take turns: the second one enters the block after the first left it
    and can find the finished target. The lock is released when the process dies; the lock file stays (empty).
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    lock = target.parent / f".{target.name}.lock"
    with open(lock, "a") as handle:
        fcntl.flock(handle.fileno(), fcntl.LOCK_EX)
        try:
            yield lock
        finally:
            fcntl.flock(handle.fileno(), fcntl.LOCK_UN)
