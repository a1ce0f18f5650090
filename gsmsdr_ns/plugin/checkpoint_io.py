"""nerfstudio checkpoint files: loading under torch >= 2.6, finding, checking, reading and writing them atomically.

* :func:`find_checkpoint`, :func:`check_checkpoint_file`, :func:`load_checkpoint_file`: the file ``--load-dir`` /
  ``--load-checkpoint`` mean, with an :class:`InputError` naming the file and what to do when it is missing,
  empty, truncated or damaged, or when the folder is not a checkpoint folder.
* :func:`save_checkpoint_atomic`: temporary file, fsync, rename; a full disk raises :class:`DiskFullError`.

Whether a checkpoint's tensors fit the model is :mod:`gsmsdr_ns.plugin.checkpoint_compat`'s concern.

Loading under ``torch.load(..., weights_only=True)`` (torch's default since 2.6):

What a nerfstudio 1.1.5 checkpoint holds that the weights-only unpickler refuses (as
``torch.serialization.get_unsafe_globals_in_checkpoint`` lists them for a ``gsmsdr`` checkpoint): numpy float64 scalars.
nerfstudio's ``ExponentialDecayScheduler`` computes its learning-rate factor with ``np.exp`` / ``np.clip``, so
``LambdaLR`` writes ``numpy.float64`` values into every scheduled optimizer's ``param_groups[i]["lr"]`` and into
the scheduler's ``_last_lr``.  Pickle stores such a scalar as a call to numpy's scalar reconstructor
(``numpy.core.multiarray.scalar``, ``numpy._core.multiarray.scalar`` on numpy 2) with a ``numpy.dtype``
argument.  Everything else (tensors, dicts, lists, Python scalars) is allowed by default.

Both globals only rebuild plain numeric values: the reconstructor turns a dtype plus raw bytes into a scalar, and
``numpy.dtype`` builds a dtype descriptor.  Allowing exactly these (rather than ``weights_only=False``) keeps
``torch.load`` safe.  The registration runs when ``gsmsdr_ns.plugin`` is imported, which nerfstudio does while
discovering methods (``ns-train``, ``ns-eval``, ``ns-viewer``) and while reading a saved ``config.yml``.
"""

from __future__ import annotations

import os
import re
import secrets
import zipfile
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional

import numpy as np
import torch

from gsmsdr_ns.io.atomic import remove_stale_temporaries
from gsmsdr_ns.io.errors import (
    DiskFullError,
    InputError,
    disk_full_cause,
    disk_full_error,
    format_bytes,
    free_space_text,
)


def checkpoint_safe_globals() -> List[object]:
    """The numpy globals nerfstudio checkpoints need, resolved from the installed numpy.

    Taken from how numpy itself pickles a float64 scalar, so the names match whatever this numpy writes
    (``numpy.core`` on 1.x, ``numpy._core`` on 2.x).
    """
    scalar_reconstructor, (dtype, _raw) = np.float64(1.0).__reduce__()
    return [scalar_reconstructor, np.dtype, type(dtype)]


def register_checkpoint_safe_globals() -> None:
    """Allow-list the numpy scalar types for ``torch.load(weights_only=True)``. Idempotent; no-op on old torch."""
    add_safe_globals = getattr(torch.serialization, "add_safe_globals", None)
    if add_safe_globals is None:  # torch < 2.4 loads with weights_only=False by default anyway
        return
    already = set(map(id, torch.serialization.get_safe_globals()))
    missing = [g for g in checkpoint_safe_globals() if id(g) not in already]
    if missing:
        add_safe_globals(missing)


# -- finding, reading and writing checkpoint files ---------------------------------------------------------------

CHECKPOINT_NAME = re.compile(r"^step-(\d+)\.ckpt$")
"""nerfstudio's checkpoint file name: ``step-<step, 9 digits>.ckpt`` in ``<run>/nerfstudio_models``."""

_CUT_OFF = "it was cut off while being written (a full disk, or a run killed while saving)"


def checkpoint_file(checkpoint_dir: Path, step: int) -> Path:
    """``<checkpoint_dir>/step-<step:09d>.ckpt``, the name nerfstudio writes and reads."""
    return Path(checkpoint_dir) / f"step-{step:09d}.ckpt"


def checkpoint_steps(checkpoint_dir: Path) -> Dict[int, Path]:
    """The checkpoints in ``checkpoint_dir`` by step (files named like nerfstudio's; anything else is ignored)."""
    found = {}
    for path in Path(checkpoint_dir).iterdir():
        match = CHECKPOINT_NAME.match(path.name)
        if match and path.is_file():
            found[int(match.group(1))] = path
    return found


def _names_nerfstudio_cannot_parse(checkpoint_dir: Path) -> List[str]:
    # nerfstudio's loaders take the latest step as int(name[name.find("-") + 1 : name.find(".")]) of *every* entry
    bad = []
    for name in sorted(os.listdir(checkpoint_dir)):
        try:
            int(name[name.find("-") + 1 : name.find(".")])
        except ValueError:
            bad.append(name)
    return bad


def _fallback_advice(path: Path) -> str:
    older = sorted(step for step in checkpoint_steps(path.parent) if checkpoint_file(path.parent, step) != path)
    if older:
        previous = checkpoint_file(path.parent, older[-1])
        return (f"Delete it to use the previous checkpoint '{previous.name}' (ns-eval and --load-dir then take "
                f"the latest one left; ns-train also takes --load-step {older[-1]}).")  # fmt: skip
    return "Delete it and train again (or resume from another run's checkpoint with --load-checkpoint)."


def check_checkpoint_file(path: Path) -> Path:
    """Raise :class:`InputError` naming ``path`` (and what to do) when it is missing, empty or truncated.

    A torch checkpoint is a zip archive whose index sits at its end, so a file cut off while being written lacks it:
    that is checked here without reading the tensors.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"gsmsdr: checkpoint '{path}' does not exist.")
    size = path.stat().st_size
    if size == 0:
        raise InputError(f"gsmsdr: checkpoint '{path}' is empty (0 bytes): {_CUT_OFF}. {_fallback_advice(path)}")
    if not zipfile.is_zipfile(path):
        raise InputError(f"gsmsdr: checkpoint '{path}' is truncated or not a torch checkpoint ({size} bytes, no zip "
                         f"index at its end): {_CUT_OFF}. {_fallback_advice(path)}")  # fmt: skip
    return path


def find_checkpoint(load_dir: Path, load_step: Optional[int] = None, nerfstudio_names: bool = False) -> Path:
    """The checkpoint ``--load-dir load_dir`` (``--load-step load_step``, default: the latest) means, checked.

    Raises :class:`InputError` saying where checkpoints are expected when ``load_dir`` does not exist, is a run folder
    (``<run>`` instead of ``<run>/nerfstudio_models``) or holds no ``step-*.ckpt``; and, for the file chosen, what
    :func:`check_checkpoint_file` checks. ``nerfstudio_names``: also reject entries that nerfstudio's own loader
    (which parses a step number out of every name in the folder) would fail on.
    """
    load_dir = Path(load_dir)
    where = (
        "checkpoints are written to <run>/nerfstudio_models (outputs/<scene>/<method>/<timestamp>/nerfstudio_models)"
    )
    if load_dir.is_file():
        raise InputError(
            f"gsmsdr: '{load_dir}' is a file; --load-dir takes a folder of checkpoints "
            "(<run>/nerfstudio_models). To load one file, pass it with --load-checkpoint instead."
        )
    if not load_dir.is_dir():
        raise InputError(f"gsmsdr: checkpoint folder '{load_dir}' does not exist; {where}.")
    steps = checkpoint_steps(load_dir)
    if not steps:
        models = load_dir / "nerfstudio_models"
        if models.is_dir():
            raise InputError(f"gsmsdr: '{load_dir}' is a run folder; its checkpoints are expected in '{models}'. "
                             f"Pass --load-dir {models}.")  # fmt: skip
        raise InputError(f"gsmsdr: no checkpoint (step-*.ckpt) in '{load_dir}'; {where} every --steps-per-save "
                         "steps and when training ends. Point --load-dir at such a folder.")  # fmt: skip
    if nerfstudio_names:
        bad = _names_nerfstudio_cannot_parse(load_dir)
        if bad:
            raise InputError(f"gsmsdr: '{load_dir / bad[0]}' is not a checkpoint (step-<step>.ckpt); nerfstudio "
                             "reads a step number from every name in the checkpoint folder. Move it out of "
                             f"'{load_dir}'.")  # fmt: skip
    if load_step is None:
        load_step = max(steps)
    if load_step not in steps:
        raise InputError(f"gsmsdr: no checkpoint of step {load_step} in '{load_dir}' (it has steps "
                         f"{sorted(steps)}); pass one of them with --load-step.")  # fmt: skip
    return check_checkpoint_file(steps[load_step])


def load_checkpoint_file(path: Path) -> Dict[str, Any]:
    """``torch.load(path, map_location="cpu")`` after :func:`check_checkpoint_file`; a file torch cannot read
    (corrupt inside) raises :class:`InputError` naming it."""
    path = check_checkpoint_file(path)
    try:
        return torch.load(path, map_location="cpu")
    except (RuntimeError, EOFError, zipfile.BadZipFile) as e:
        # torch's first sentence says what is missing; the rest is generic advice
        reason = str(e).strip().split(". ")[0].splitlines()[0] if str(e).strip() else type(e).__name__
        raise InputError(f"gsmsdr: cannot read checkpoint '{path}' ({reason}): the file is damaged. "
                         f"{_fallback_advice(path)}") from e  # fmt: skip


def tensor_bytes(payload: Any) -> int:
    """Bytes of the tensor storages in a nested dict / list / tuple (each storage counted once): about the size of a
    checkpoint of ``payload``."""
    seen, total, todo = set(), 0, [payload]
    while todo:
        item = todo.pop()
        if isinstance(item, torch.Tensor):
            storage = item.untyped_storage()
            if storage.data_ptr() not in seen:
                seen.add(storage.data_ptr())
                total += storage.nbytes()
        elif isinstance(item, Mapping):
            todo.extend(item.values())
        elif isinstance(item, (list, tuple)):
            todo.extend(item)
    return total


def _disk_full_error(path: Path, error: OSError, needed: int) -> DiskFullError:
    return disk_full_error(
        f"gsmsdr: no space left on the disk to save checkpoint '{path}' (it needs about {format_bytes(needed)}, "
        f"{free_space_text(path.parent)}); nothing was written, the "
        f"checkpoints already in '{path.parent}' are kept. Free some space, or train with --output-dir on a disk "
        f"with room (resume with --load-dir {path.parent}).",
        error.errno,
    )


def save_checkpoint_atomic(payload: Mapping[str, Any], path: Path) -> Path:
    """``torch.save(payload, path)`` that never leaves a partial ``path``: written to a hidden temporary file,
    fsynced, then renamed over ``path``.

    The temporary file sits in the folder above ``path`` (same file system, so the rename is atomic) rather than
    next to it: nerfstudio's loaders parse a step number out of every name in the checkpoint folder, so a temporary
    file left by a killed run must not be there. A full disk (ENOSPC / EDQUOT) raises :class:`DiskFullError` naming
    ``path``; any error removes the temporary file.
    """
    path = Path(path)
    remove_stale_temporaries(path.parent.parent, f".{path.parent.name}.")  # of earlier runs that were killed
    tmp = path.parent.parent / f".{path.parent.name}.{path.name}.partial-{os.getpid()}-{secrets.token_hex(4)}"
    try:
        # A Python file object (not a path) makes torch report a failed write as the OSError it is.
        with open(tmp, "wb") as f:
            torch.save(dict(payload), f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        tmp.unlink(missing_ok=True)
        full = disk_full_cause(e)
        if full is not None:
            raise _disk_full_error(path, full, tensor_bytes(payload)) from full
        raise
    _fsync_dir(path.parent)
    return path


def _fsync_dir(folder: Path) -> None:
    # Makes the rename itself durable; not every file system can open a folder for that (best effort).
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
