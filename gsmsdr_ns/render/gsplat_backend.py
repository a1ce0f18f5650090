"""Whether gsplat's CUDA backend can be loaded, checked once with an error that says what is missing.

gsplat 1.4.0 compiles its CUDA kernels with nvcc on first import of ``gsplat.cuda._backend``; when nvcc is missing it
only prints a warning and leaves the backend as None, so the first render fails far from the cause
(``'NoneType' object has no attribute ...``). :func:`require_gsplat_cuda` turns that into one clear error at set-up.
"""

from __future__ import annotations

import functools
import importlib
import shutil
from typing import Optional

import torch


class GsplatUnavailableError(RuntimeError):
    """gsplat's CUDA backend cannot be built or loaded on this machine."""


def _fixes() -> str:
    cuda = torch.version.cuda or "none (this torch build has no CUDA)"
    return (
        f"To use the GPU, install the CUDA toolkit matching torch's CUDA version ({cuda}) so that `nvcc` is on PATH "
        "(or CUDA_HOME points at it) and a C++ compiler is installed, then run again (gsplat compiles its kernels "
        "on first use, which takes a few minutes). Or train on the CPU: --machine.device-type cpu."
    )


@functools.lru_cache(maxsize=1)
def gsplat_cuda_problem() -> Optional[str]:
    """None when gsplat's CUDA backend loads, else a sentence saying why it does not (the check runs once)."""
    try:
        backend = importlib.import_module("gsplat.cuda._backend")
    except Exception as exc:  # a failed JIT build raises from the import (compiler errors, missing headers)
        return f"building or loading gsplat's CUDA kernels failed: {type(exc).__name__}: {exc}"
    if getattr(backend, "_C", None) is not None:
        return None
    if shutil.which("nvcc") is None:
        return "gsplat's CUDA kernels are not built and the CUDA compiler `nvcc` was not found on PATH"
    return "gsplat's CUDA backend is not available (its JIT build produced no module)"


def require_gsplat_cuda() -> None:
    """Raise :class:`GsplatUnavailableError` (what is missing, how to install it) unless gsplat's CUDA backend loads."""
    problem = gsplat_cuda_problem()
    if problem is not None:
        raise GsplatUnavailableError(f"gsmsdr: CUDA rendering needs gsplat's CUDA backend: {problem}. {_fixes()}")
