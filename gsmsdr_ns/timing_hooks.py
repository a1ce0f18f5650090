"""Named timing points in the training step, for a profiler attached from the outside (``gsmsdr_ns.bench.timing``).

The model code marks its stages explicitly: :func:`timed` calls a differentiable piece of work (rasterization,
the blur field, a kernel application) and charges its forward and backward time to a category; :func:`stage` is a
span without autograd (densification, data loading). Both are plain calls when no recorder is attached: one
``None`` check, no hooks, no clock reads and no host-device synchronisation.

A recorder is any object with the :class:`StageRecorder` methods; at most one is attached at a time.
"""

from __future__ import annotations

import contextlib
from typing import Any, Callable, ContextManager, Iterator, Optional, Protocol, TypeVar

__all__ = ["StageRecorder", "attach_recorder", "detach_recorder", "attached_recorder", "timed", "stage"]

T = TypeVar("T")


class StageRecorder(Protocol):
    """What the model calls on an attached recorder."""

    def record(self, category: str, function: Callable[..., Any], args: tuple, kwargs: dict) -> Any:
        """Call ``function(*args, **kwargs)``, charging its forward (and later its backward) time to ``category``."""

    def span(self, category: str, starts_step: bool = False) -> ContextManager[None]:
        """Charge the wall time of the block to ``category``; ``starts_step``: the block begins a training step."""


_recorder: Optional[StageRecorder] = None


def attach_recorder(recorder: StageRecorder) -> None:
    """Route every :func:`timed` / :func:`stage` call to ``recorder`` until :func:`detach_recorder`."""
    global _recorder
    if _recorder is not None and _recorder is not recorder:
        raise RuntimeError("another timing recorder is attached; detach it first")
    _recorder = recorder


def detach_recorder(recorder: StageRecorder) -> None:
    """Stop routing to ``recorder`` (no-op if it is not the attached one)."""
    global _recorder
    if _recorder is recorder:
        _recorder = None


def attached_recorder() -> Optional[StageRecorder]:
    """The attached recorder, or None."""
    return _recorder


def timed(category: str, function: Callable[..., T], *args: Any, **kwargs: Any) -> T:
    """``function(*args, **kwargs)``; with a recorder attached, its time (forward and backward) goes to ``category``.

    A module passed as ``function`` has its parameters counted as inputs, so its backward ends when they got their
    gradients.
    """
    recorder = _recorder
    if recorder is None:
        return function(*args, **kwargs)
    return recorder.record(category, function, args, kwargs)


@contextlib.contextmanager
def stage(category: str, starts_step: bool = False) -> Iterator[None]:
    """With a recorder attached, the block's wall time goes to ``category`` (no backward part)."""
    recorder = _recorder
    if recorder is None:
        yield
        return
    with recorder.span(category, starts_step):
        yield
