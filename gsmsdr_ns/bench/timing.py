"""Where a training step's time goes: a recorder attached to a nerfstudio pipeline from the outside.

:class:`TimingRecorder` splits the wall time of training steps into

* ``rasterization``: ``model._rasterize`` (parameter activation, projection, SH, tile sorting, pixel kernel), forward
  and backward;
* ``blur_field``: the blur field module (MAAN features, MCA, HPKO heads: kernel and mask prediction; the thin
  lens's disk kernels), forward and backward;
* ``kernels``: kernel application (``BlurField.blur``: ``apply_pixel_kernels`` in linear light) and the
  resolution-loss model, forward and backward;
* ``densification``: the densification strategy's hooks (``strategy.step_pre_backward`` /
  ``step_post_backward``: gradient statistics, split / duplicate / prune, optimizer state surgery);
* ``data``: ``datamanager.next_train`` (picking and copying the training image);
* ``other``: everything else in the step: the camera pose, background and composite, the mask blend, the losses
  (L1 + D-SSIM, mask regulariser) and their backward, gradient bookkeeping between components, ``zero_grad``, the
  optimizer and scheduler steps and the training callbacks. It is the step's wall time minus the five categories above.

How it attaches (nothing in the model is edited): instance attributes shadow ``model._rasterize``,
``datamanager.next_train`` and the strategy's two hooks; forward pre/post hooks time the ``blur_field`` (and its
``thin_lens``) and ``resolution_model`` modules; ``BlurField.blur`` (a staticmethod) is wrapped on the class while
the recorder is attached. ``detach()`` restores all of it.

Backward time: the forward wrappers register tensor hooks at each component's boundary. A hook on a component's
output fires when autograd starts that component's backward (the gradient with respect to the output is ready);
hooks on its inputs (including leaf parameters) fire as its backward hands gradients on. The time from the first to
the last of these events is charged to the component, except while another component's backward runs in between
(PyTorch's CPU autograd engine runs ready nodes newest-first, so the blur field's backward runs inside the kernel
application's window; the recorder switches category at every event, so nested time goes to the inner component).
It is an attribution by event times, not a profiler: autograd glue that runs between two events of one component
(a ``permute``'s backward, gradient accumulation) is charged to that component. With CUDA tensors, ``sync_cuda``
synchronises the device at every event so that wall time means execution time (this slows CUDA training down;
results are unchanged).

The recorder only observes: hooks return None, wrappers return what the wrapped call returned, and nothing touches
random state, so training is bit-identical with and without it (``tests/test_bench_suite.py`` checks the losses).
"""

from __future__ import annotations

import contextlib
import resource
import time
from collections import defaultdict
from typing import Any, Callable, Dict, Iterator, List, Optional

import torch

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
        """Instrument ``pipeline`` (a nerfstudio pipeline whose model is a ``GSMSDRModel``). Returns self."""
        if self._attached:
            raise RuntimeError("TimingRecorder is already attached; detach() it first")
        self._attached = True
        model = pipeline.model
        self._wrap_method(pipeline.datamanager, "next_train", "data", backward=False, starts_step=True)
        self._wrap_method(model, "_rasterize", "rasterization")
        strategy = getattr(model, "strategy", None)
        if strategy is not None:
            self._wrap_method(strategy, "step_pre_backward", "densification", backward=False)
            self._wrap_method(strategy, "step_post_backward", "densification", backward=False)
        blur_field = getattr(model, "blur_field", None)
        modules = (
            (blur_field, "blur_field"),
            (getattr(blur_field, "thin_lens", None), "blur_field"),  # called by the model, not inside the field
            (getattr(model, "resolution_model", None), "kernels"),
        )
        for module, category in modules:
            if isinstance(module, torch.nn.Module):
                self._hook_module(module, category)
        self._wrap_blur()
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

    def _wrap_method(self, obj: Any, name: str, category: str, backward: bool = True, starts_step: bool = False):
        original = getattr(obj, name)
        had_instance_attr = name in vars(obj)
        recorder = self

        def wrapper(*args, **kwargs):
            if not recorder._active:
                return original(*args, **kwargs)
            if starts_step:
                recorder._new_step()
            started = recorder._now()
            out = original(*args, **kwargs)
            recorder._add_forward(category, recorder._now() - started)
            if backward:
                recorder._mark_backward(category, out, (args, kwargs))
            return out

        setattr(obj, name, wrapper)

        def restore() -> None:
            if had_instance_attr:
                setattr(obj, name, original)
            else:
                delattr(obj, name)

        self._restore.append(restore)

    def _hook_module(self, module: torch.nn.Module, category: str) -> None:
        starts: List[float] = []

        def pre_hook(_module, _args):
            if self._active:
                starts.append(self._now())

        def post_hook(_module, args, output):
            if self._active and starts:
                self._add_forward(category, self._now() - starts.pop())
                params = {id(p): p for p in _module.parameters() if p.requires_grad}
                used = _reachable_leaves([t for t in _tensors(output) if t.requires_grad], params)
                self._mark_backward(category, output, (args, used))

        handles = [module.register_forward_pre_hook(pre_hook), module.register_forward_hook(post_hook)]
        self._restore.append(lambda: [h.remove() for h in handles])

    def _wrap_blur(self) -> None:
        """``BlurField.blur`` (the kernel application, called by ``degrade`` and for the thin lens) is a staticmethod
        the model calls through the class: wrap it there."""
        from gsmsdr_ns.blur.field import BlurField

        original = BlurField.__dict__["blur"]  # the staticmethod object
        function = original.__func__
        recorder = self

        def blur(*args, **kwargs):
            if not recorder._active:
                return function(*args, **kwargs)
            started = recorder._now()
            out = function(*args, **kwargs)
            recorder._add_forward("kernels", recorder._now() - started)
            recorder._mark_backward("kernels", out, (args, kwargs))
            return out

        blur.__doc__ = function.__doc__
        BlurField.blur = staticmethod(blur)  # type: ignore[method-assign]

        def restore() -> None:
            BlurField.blur = original  # type: ignore[method-assign]

        self._restore.append(restore)

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

    @contextlib.contextmanager
    def paused(self) -> Iterator[None]:
        """Inside :meth:`measure`: do not record (and do not count the wall time of) what runs inside."""
        was_active = self._active
        self._active = False
        started = self._now()
        try:
            yield
        finally:
            self.wall -= (self._now() - started) if was_active else 0.0
            self._active = was_active

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


class PeakMemory:
    """Peak resident memory of this process over a span (and peak CUDA memory allocated by torch).

    On Linux the RSS high-water mark is reset at :meth:`reset` (writing ``5`` to ``/proc/self/clear_refs``) and read
    from ``VmHWM`` in ``/proc/self/status``, so the peak is that of the span, including the process' baseline
    (Python, torch, nerfstudio: a few hundred MB). Where the reset is not possible, the peak is the process-wide
    ``getrusage`` maximum since start (``span_reset`` is False then and tables say so).
    """

    def __init__(self) -> None:
        self.span_reset = False

    def reset(self) -> None:
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")
            self.span_reset = self._vmhwm_mb() is not None
        except OSError:
            self.span_reset = False
        if torch.cuda.is_available():
            torch.cuda.reset_peak_memory_stats()

    @staticmethod
    def _vmhwm_mb() -> Optional[float]:
        try:
            with open("/proc/self/status") as f:
                for line in f:
                    if line.startswith("VmHWM:"):
                        return int(line.split()[1]) / 1024.0
        except OSError:
            return None
        return None

    def peak_rss_mb(self) -> float:
        value = self._vmhwm_mb() if self.span_reset else None
        if value is None:
            value = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux
        return float(value)

    @staticmethod
    def peak_cuda_mb() -> float:
        """Peak CUDA memory allocated by torch since :meth:`reset` (NaN without CUDA)."""
        if not torch.cuda.is_available():
            return float("nan")
        return torch.cuda.max_memory_allocated() / 2**20


__all__ = ["CATEGORIES", "MEASURED", "PeakMemory", "TimingRecorder"]
