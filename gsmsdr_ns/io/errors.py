"""The error and warning types shared by every reader and writer (core tools and nerfstudio glue), and what a failed
write says: a full disk or a refused write found behind any exception (:func:`storage_error_line`), and a check for
room before a writer that a full disk would stop uncleanly (:func:`require_free_space`)."""

from __future__ import annotations

import errno
import shutil
from pathlib import Path
from typing import Iterator, Optional

DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
"""errno values of a write that found no room (the disk, or the user's quota)."""


class InputError(ValueError):
    """Input that gsmsdr cannot use; the message names the file or value and says how to fix it."""


class SceneFolderMissingError(InputError):
    """The scene folder a command was given, or a run's config.yml names, is not there."""

    LOADED_RUN_COMMANDS = ("ns-eval", "ns-viewer", "ns-render", "gsmsdr-eval", "gsmsdr-export")
    """Commands that read the scene folder from a run's config.yml instead of a --data option."""

    def __init__(self, folder) -> None:
        self.folder = Path(folder)
        super().__init__(
            f"gsmsdr: data directory '{folder}' does not exist or is not a directory. Pass the scene directory with "
            "--data <dir> (make a test scene with `gsmsdr-synth`)."
        )

    def for_command(self, command: str) -> str:
        """The message with the fix that exists for ``command`` (those loading a run take no --data)."""
        if command not in self.LOADED_RUN_COMMANDS:
            return str(self)
        return (
            f"gsmsdr: the scene folder '{self.folder}' that the run's config.yml names does not exist (moved or "
            f"deleted?). {command} reads it from config.yml: put the scene back there, or change every `data:` "
            "entry in config.yml to the folder's new place."
        )


class InputWarning(UserWarning):
    """Input that is usable, but only after a guess (a default hold, unknown degradations, ...)."""


class DiskFullError(OSError):
    """No space left for an output; the message names the file and says how to free space or write elsewhere."""


def disk_full_error(message: str, error_number: int = errno.ENOSPC) -> DiskFullError:
    """A :class:`DiskFullError` that prints as ``message`` alone: its errno is set afterwards, without strerror or
    filename, which would turn str() into the ``[Errno 28] ...`` form."""
    error = DiskFullError(message)
    error.errno = error_number
    return error


def disk_full_cause(exc: BaseException) -> Optional[OSError]:
    """The OSError of a full disk behind ``exc`` (itself, or in its ``__cause__`` / ``__context__`` chain), else None.

    Writers in C++ can turn the ENOSPC of a Python file object into an error of their own: torch's checkpoint writer
    raises ``RuntimeError("[enforce fail at inline_container.cc:...] unexpected pos ...")`` with the OSError as its
    context.
    """
    return _oserror_in_chain(exc, DISK_FULL_ERRNOS)


WRITE_REFUSED_ERRNOS = (errno.EROFS, errno.EACCES, errno.EPERM)
"""errno values of a write the file system refused (read-only, no permission)."""


def exception_chain(exc: Optional[BaseException]) -> Iterator[BaseException]:
    """``exc`` and the exceptions behind it (its ``__cause__``, else its ``__context__``, and so on), each once."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


def _oserror_in_chain(exc: Optional[BaseException], errnos) -> Optional[OSError]:
    for error in exception_chain(exc):
        if isinstance(error, OSError) and error.errno in errnos:
            return error
    return None


def format_bytes(size: float) -> str:
    """``1.5 MiB``-style size (bytes below 1 KiB)."""
    for unit in ("bytes", "KiB", "MiB", "GiB"):
        if size < 1024 or unit == "GiB":
            return f"{int(size)} {unit}" if unit == "bytes" else f"{size:.1f} {unit}"
        size /= 1024
    return ""  # unreachable


def _existing(folder: Path) -> Path:
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    return folder


def free_space_text(folder: Path) -> str:
    """``"1.2 GiB free in '<folder>'"`` for ``folder`` (or its nearest existing parent)."""
    folder = _existing(folder)
    try:
        return f"{format_bytes(shutil.disk_usage(folder).free)} free in '{folder}'"
    except OSError:
        return f"free space in '{folder}' unknown"


def require_free_space(folder: Path, needed: int, what: str, fix: str) -> None:
    """Raise :class:`DiskFullError` (``what`` needs about ``needed`` bytes in ``folder``, how much is free, ``fix``)
    when the disk of ``folder`` has less room; for writers that a full disk would stop uncleanly (pycolmap's
    database aborts the process)."""
    folder = _existing(Path(folder))
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return
    if free < needed:
        raise disk_full_error(
            f"gsmsdr: no space left on the disk for {what}: it needs about {format_bytes(needed)} in '{folder}', "
            f"{format_bytes(free)} are free; nothing was written. {fix}"
        )


def storage_error_line(exc: BaseException) -> Optional[str]:
    """One line for a write that failed for lack of room or of permission (``exc`` or its cause), else None.

    A full disk names the file and the free space left; a read-only file system or a refused permission names the
    file and asks for another folder. Used by every console script and, through the exception hook, by ns-train.
    """
    if isinstance(exc, DiskFullError):
        return None  # already says what to do, in its own words
    full = _oserror_in_chain(exc, DISK_FULL_ERRNOS)
    if full is not None:
        target = Path(full.filename) if full.filename else None
        where = f"writing '{target}'" if target else "writing its output"
        free = free_space_text(target.parent if target else Path.cwd())
        return f"gsmsdr: no space left on the disk {where} ({free}). Free some space, or write to a disk with room."
    refused = _oserror_in_chain(exc, WRITE_REFUSED_ERRNOS)
    if refused is not None and refused.filename:
        if refused.errno == errno.EROFS:
            return f"gsmsdr: cannot write '{refused.filename}': the file system is read-only. Write to another folder."
        return (
            f"gsmsdr: permission denied for '{refused.filename}'. Check its permissions; for an output, use a "
            "folder you may write to."
        )
    return None
