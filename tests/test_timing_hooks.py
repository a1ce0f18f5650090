"""The model's named timing stages (``gsmsdr_ns.timing_hooks``): plain calls without a recorder, and every stage of a
blurred training step reported to an attached one, forward and (through the autograd boundary) backward."""

from __future__ import annotations

import contextlib
from typing import List, Tuple

import pytest
import torch
from test_plugin_blur import build, records
from test_plugin_model import look_from, make_camera

from gsmsdr_ns import timing_hooks
from gsmsdr_ns.bench.timing import _tensors
from gsmsdr_ns.blur import BlurFieldConfig, DegradationConfig


class ListRecorder:
    """Records (kind, category) events; calls through unchanged."""

    def __init__(self) -> None:
        self.events: List[Tuple[str, str]] = []

    def record(self, category, function, args, kwargs):
        self.events.append(("timed", category))
        out = function(*args, **kwargs)
        first = next((t for t in _tensors(out) if t.requires_grad), None)  # kernels may come as a GridKernels tuple
        if first is not None:
            first.register_hook(lambda _grad: self.events.append(("backward", category)))
        return out

    @contextlib.contextmanager
    def span(self, category, starts_step=False):
        self.events.append(("span", category))
        yield


def test_timed_and_stage_are_plain_calls_without_a_recorder():
    assert timing_hooks.attached_recorder() is None
    x = torch.ones(3, requires_grad=True)
    y = timing_hooks.timed("kernels", torch.mul, x, 2.0)
    assert torch.equal(y, torch.full((3,), 2.0)) and not y._backward_hooks and not x._backward_hooks
    with timing_hooks.stage("densification"):
        pass


def test_only_one_recorder_at_a_time():
    first, second = ListRecorder(), ListRecorder()
    timing_hooks.attach_recorder(first)
    try:
        with pytest.raises(RuntimeError, match="another timing recorder"):
            timing_hooks.attach_recorder(second)
        timing_hooks.detach_recorder(second)  # not attached: no-op
        assert timing_hooks.attached_recorder() is first
    finally:
        timing_hooks.detach_recorder(first)
    assert timing_hooks.attached_recorder() is None


def test_a_defocus_and_motion_step_reports_every_stage():
    both = {"split": "train", "degraded": True, "effects": {"motion": {}, "defocus": {}}}
    metadata = {"degradations": [both] + records("mixres", 2)[1:] + records("sharp", 1)}
    model = build(metadata, n=3, num_downscales=0, blur_field=BlurFieldConfig(mode="view"),
                  degradation_model=DegradationConfig(warmup=0, thin_lens_start="warmup"))  # fmt: skip
    model.train()
    model.optimizers = None
    recorder = ListRecorder()
    timing_hooks.attach_recorder(recorder)
    try:
        for view in (0, 1):
            camera = make_camera(look_from([2.0, 0.5, 1.0]), width=64, height=48)
            camera.metadata = {"cam_idx": view}
            model.get_outputs(camera)["rgb"].mean().backward()
    finally:
        timing_hooks.detach_recorder(recorder)
    timed = [c for kind, c in recorder.events if kind == "timed"]
    # view 0: rasterization, the thin lens (one fused op: kernels), the field, its kernels, their centres for the
    # kernel-centre regulariser (blur field); view 1: rasterization, resolution model
    assert timed == ["rasterization", "kernels", "blur_field", "kernels", "blur_field", "rasterization", "kernels"]
    assert [c for kind, c in recorder.events if kind == "span"] == ["densification", "densification"]
    assert {c for kind, c in recorder.events if kind == "backward"} == {"rasterization", "blur_field", "kernels"}
