"""Where a training step's time goes: a recorder of the stages the model code marks (``gsmsdr_ns.timing_hooks``).

:class:`TimingRecorder` splits the wall time of training steps into

* ``rasterization``: the model's rasterizer call (parameter activation, projection, SH, tile sorting, pixel kernel),
  forward and backward;
* ``blur_field``: the blur field module (MAAN features, MCA, HPKO heads: kernel and mask prediction) and the thin
  lens's disk kernels, forward and backward;
* ``kernels``: kernel application (``BlurField.blur``: ``apply_pixel_kernels`` in linear light) and the
  resolution-loss model, forward and backward;
* ``densification``: the densification strategy's hooks (``strategy.step_pre_backward`` /
  ``step_post_backward``: gradient statistics, split / duplicate / prune, optimizer state surgery);
* ``data``: the datamanager's ``next_train`` (picking and copying the training image; ``GSMSDRDatamanager``);
* ``other``: everything else in the step: the camera pose, background and composite, the mask blend, the losses
  (L1 + D-SSIM, mask regulariser) and their backward, gradient bookkeeping between components, ``zero_grad``, the
  optimizer and scheduler steps and the training callbacks. It is the step's wall time minus the five categories above.

How it attaches: :meth:`TimingRecorder.attach` registers the recorder with ``gsmsdr_ns.timing_hooks``; the model
(``GSMSDRModel`` and its ``DegradationModel``) calls ``timed(category, ...)`` around its differentiable stages and
``stage(category)`` around densification, and ``GSMSDRDatamanager.next_train`` is the ``data`` stage that starts a
step. Nothing is replaced at run time; ``detach()`` unregisters the recorder.

Backward time: each timed call registers tensor hooks at the component's boundary. A hook on a component's
output fires when autograd starts that component's backward (the gradient with respect to the output is ready);
hooks on its inputs (including the leaf parameters of a module it ran) fire as its backward hands gradients on.
The time from the first to the last of these events is charged to the component, except while another component's
backward runs in between (PyTorch's CPU autograd engine runs ready nodes newest-first, so the blur field's backward
runs inside the kernel application's window; the recorder switches category at every event, so nested time goes to
the inner component). It is an attribution by event times, not a profiler: autograd glue that runs between two
events of one component (a ``permute``'s backward, gradient accumulation) is charged to that component. With CUDA
tensors, ``sync_cuda`` synchronises the device at every event so that wall time means execution time (this slows
CUDA training down; results are unchanged).

The recorder only observes: hooks return None, timed calls return what the call returned, and nothing touches
random state, so training is bit-identical with and without it (``tests/test_bench_suite.py`` checks the losses).
"""

from __future__ import annotations

import contextlib
import os
import resource
import time
from collections import defaultdict
from typing import Any, Callable, Dict, Iterator, List, Optional

import torch

from gsmsdr_ns import timing_hooks

CATEGORIES = ("rasterization", "blur_field", "kernels", "densification", "data", "other")
"""Time categories, in the order tables and plots show them."""
MEASURED = CATEGORIES[:-1]
"""Categories measured directly (``other`` is the remainder of the step time)."""


def _tensors(value: Any) -> Iterator[torch.Tensor]:
    """Tensors in ``value`` (a tensor, or dicts / lists / tuples of them, one level of nesting per call)."""
    if isinstance(value, torch.Tensor):
        yield value
    elif isinstance(value, dict):
        for item in value.values():
            yield from _tensors(item)
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from _tensors(item)


def _reachable_leaves(outputs: List[torch.Tensor], candidates: Dict[int, torch.Tensor], limit: int = 50000):
    """The tensors of ``candidates`` (id -> leaf) that the autograd graph of ``outputs`` reaches (so their gradient
    hooks will fire in backward: a module's parameters of unused branches are left out). Walks at most ``limit``
    graph nodes."""
    found: Dict[int, torch.Tensor] = {}
    stack = [t.grad_fn for t in outputs if t.grad_fn is not None]
    seen = set()
    while stack and len(seen) < limit and len(found) < len(candidates):
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        variable = getattr(node, "variable", None)  # AccumulateGrad: the leaf it accumulates into
        if variable is not None:
            if id(variable) in candidates:
                found[id(variable)] = variable
            continue
        stack.extend(next_node for next_node, _ in node.next_functions)
    return list(found.values())


class TimingRecorder:
    """Forward and backward seconds per category (:data:`CATEGORIES`) of the training steps run inside
    :meth:`measure` while attached to a pipeline.

    Usage::

        recorder = TimingRecorder().attach(pipeline)
        with recorder.measure():
            trainer.train_iteration(step)   # or any number of steps
        recorder.totals()                   # {"rasterization": s, ..., "other": s}
        recorder.detach()

    Calls outside :meth:`measure` (evaluation renders, for example) are not recorded.
    """

    def __init__(self, sync_cuda: bool = False) -> None:
        self.sync_cuda = sync_cuda
        self.forward: Dict[str, float] = defaultdict(float)
        self.backward: Dict[str, float] = defaultdict(float)
        self.wall = 0.0
        """Seconds spent inside :meth:`measure` (the steps' wall time)."""
        self.calls: Dict[str, int] = defaultdict(int)
        """Forward calls per category (to check that every component was seen)."""
        self._active = False
        self._restore: List[Callable[[], None]] = []
        self._leaf_handles: List[Any] = []
        self._bw_current: Optional[str] = None  # category whose backward is running, None before the first event
        self._bw_last = 0.0
        self._attached = False

    # -- clock ------------------------------------------------------------------------------------------------

    def _now(self) -> float:
        if self.sync_cuda and torch.cuda.is_available():
            torch.cuda.synchronize()
        return time.perf_counter()

    # -- attaching --------------------------------------------------------------------------------------------

    def attach(self, pipeline) -> "TimingRecorder":
        """Record the stages of ``pipeline`` (a nerfstudio pipeline whose model is a ``GSMSDRModel``). Returns self."""
        if self._attached:
            raise RuntimeError("TimingRecorder is already attached; detach() it first")
        timing_hooks.attach_recorder(self)
        self._attached = True
        self._restore.append(lambda: timing_hooks.detach_recorder(self))
        return self

    def detach(self) -> None:
        """Undo :meth:`attach` (safe to call twice)."""
        self._clear_leaf_handles()
        while self._restore:
            self._restore.pop()()
        self._attached = False

    def __enter__(self) -> "TimingRecorder":
        return self

    def __exit__(self, *exc) -> None:
        self.detach()

    # -- the timing_hooks.StageRecorder interface -----------------------------------------------------------------

    def record(self, category: str, function: Callable[..., Any], args: tuple, kwargs: dict) -> Any:
        """``function(*args, **kwargs)``, its forward time (and, through boundary hooks, its backward time) charged
        to ``category`` while :meth:`measure` is active."""
        if not self._active:
            return function(*args, **kwargs)
        started = self._now()
        out = function(*args, **kwargs)
        self._add_forward(category, self._now() - started)
        inputs: Any = (args, kwargs)
        if isinstance(function, torch.nn.Module) and torch.is_grad_enabled():
            params = {id(p): p for p in function.parameters() if p.requires_grad}
            used = _reachable_leaves([t for t in _tensors(out) if t.requires_grad], params)
            inputs = (args, kwargs, used)
        self._mark_backward(category, out, inputs)
        return out

    @contextlib.contextmanager
    def span(self, category: str, starts_step: bool = False) -> Iterator[None]:
        """The block's wall time goes to ``category`` (forward only) while :meth:`measure` is active."""
        if not self._active:
            yield
            return
        if starts_step:
            self._new_step()
        started = self._now()
        try:
            yield
        finally:
            self._add_forward(category, self._now() - started)

    # -- recording --------------------------------------------------------------------------------------------

    @contextlib.contextmanager
    def measure(self) -> Iterator[None]:
        """Record the training steps run inside; their wall time is added to :attr:`wall`."""
        self._new_step()
        self._active = True
        started = self._now()
        try:
            yield
        finally:
            self.wall += self._now() - started
            self._active = False
            self._new_step()

    def _new_step(self) -> None:
        """A new step starts: forget the previous backward's state and its hooks on leaf tensors."""
        self._clear_leaf_handles()
        self._bw_current = None

    def _clear_leaf_handles(self) -> None:
        for handle in self._leaf_handles:
            handle.remove()
        self._leaf_handles.clear()

    def _add_forward(self, category: str, seconds: float) -> None:
        self.forward[category] += seconds
        self.calls[category] += 1

    def _mark_backward(self, category: str, outputs: Any, inputs: Any) -> None:
        """Register the boundary hooks of one forward call of ``category`` (see the module docstring)."""
        if not torch.is_grad_enabled():
            return
        outs = [t for t in _tensors(outputs) if t.requires_grad]
        if not outs:
            return
        seen = {id(t) for t in outs}
        ins = []
        for t in _tensors(inputs):
            if t.requires_grad and id(t) not in seen:
                seen.add(id(t))
                ins.append(t)
        pending = [len(ins)]

        def on_output(_grad):
            self._bw_event(category, enter=True)

        def on_input(_grad):
            pending[0] -= 1
            self._bw_event(category, enter=False, done=pending[0] <= 0)

        for t in outs:
            t.register_hook(on_output)
        for t in ins:
            handle = t.register_hook(on_input)
            if t.is_leaf:  # non-leaf hooks die with the graph; leaf hooks are removed at the next step
                self._leaf_handles.append(handle)

    def _bw_event(self, category: str, enter: bool, done: bool = False) -> None:
        now = self._now()
        current = self._bw_current
        if enter:
            if current is not None and current != "other":
                self.backward[current] += now - self._bw_last
            self._bw_current, self._bw_last = category, now
        elif current == category:  # an input of the running component got its gradient
            self.backward[category] += now - self._bw_last
            self._bw_last = now
            if done:
                self._bw_current = "other"

    # -- results ----------------------------------------------------------------------------------------------

    def totals(self) -> Dict[str, float]:
        """Seconds per category (forward + backward), ``other`` = wall time minus the measured categories."""
        out = {c: self.forward.get(c, 0.0) + self.backward.get(c, 0.0) for c in MEASURED}
        out["other"] = max(self.wall - sum(out.values()), 0.0)
        return out

    def split(self) -> Dict[str, Dict[str, float]]:
        """``{"forward": {category: s}, "backward": {category: s}}`` for the measured categories."""
        return {
            "forward": {c: self.forward.get(c, 0.0) for c in MEASURED},
            "backward": {c: self.backward.get(c, 0.0) for c in MEASURED},
        }


# -- peak memory -------------------------------------------------------------------------------------------------


def proc_status_kib(field: str) -> int:
    """A memory field of ``/proc/self/status`` in KiB (``VmRSS``, ``VmHWM``, ``VmSize``, ...); OSError without
    /proc, RuntimeError when the field is missing."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"{field} not found in /proc/self/status")


def rss_resolution_mb() -> float:
    """How far apart two reads of this process' resident set (VmRSS, VmHWM) can be without a page touched (MiB).

    Linux (6.2 on) keeps the file, anon and shmem page counts as per-CPU counters and /proc reads their shared
    part only: each can be off by up to one batch (``max(32, 2 * CPUs)`` pages) per CPU. A difference of two reads
    is off by at most twice the sum over the three counters: 1.5 MiB on 2 CPUs with 4 KiB pages.
    """
    cpus = os.cpu_count() or 1
    page = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096
    return 2 * 3 * max(32, 2 * cpus) * cpus * page / 2**20


class PeakMemory:
    """Peak resident memory of this process over a span (and peak CUDA memory allocated by torch).

    On Linux the RSS high-water mark is reset at :meth:`reset` (writing ``5`` to ``/proc/self/clear_refs``) and read
    from ``VmHWM`` in ``/proc/self/status``, so the peak is that of the span, including the process' baseline
    (Python, torch, nerfstudio: a few hundred MB). Where the reset is not possible, the peak is the process-wide
    ``getrusage`` maximum since start (``span_reset`` is False then and tables say so).
    """

    def __init__(self) -> None:
        self.span_reset = False
        self.baseline_mb = float("nan")  # resident set at reset, from the counter peak_rss_mb reads

    def reset(self) -> None:
        baseline = None
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")
            # Read after the reset: an RSS read before it can sit pages above the new high-water mark.
            baseline = self._vmhwm_mb()
        except OSError:
            pass
        self.span_reset = baseline is not None
        if baseline is None:
            try:
                baseline = proc_status_kib("VmRSS") / 1024.0
            except (OSError, RuntimeError):
                baseline = float("nan")
        self.baseline_mb = float(baseline)
        if torch.cuda.is_available():
            torch.cuda.reset_peak_memory_stats()

    @staticmethod
    def _vmhwm_mb() -> Optional[float]:
        try:
            return proc_status_kib("VmHWM") / 1024.0
        except (OSError, RuntimeError):
            return None

    def peak_rss_mb(self) -> float:
        value = self._vmhwm_mb() if self.span_reset else None
        if value is None:
            value = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux
        return float(value)

    def extra_rss_mb(self) -> float:
        """Peak resident memory since :meth:`reset` above the resident set at the reset (MiB); exact to within
        :func:`rss_resolution_mb` either way, so a span that touches almost nothing can read slightly below 0."""
        return self.peak_rss_mb() - self.baseline_mb

    @staticmethod
    def peak_cuda_mb() -> float:
        """Peak CUDA memory allocated by torch since :meth:`reset` (NaN without CUDA)."""
        if not torch.cuda.is_available():
            return float("nan")
        return torch.cuda.max_memory_allocated() / 2**20


__all__ = ["CATEGORIES", "MEASURED", "PeakMemory", "TimingRecorder", "proc_status_kib", "rss_resolution_mb"]
