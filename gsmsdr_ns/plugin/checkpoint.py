"""Make nerfstudio checkpoints load under torch >= 2.6 (``torch.load(..., weights_only=True)`` by default).

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

from typing import List

import numpy as np
import torch


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
