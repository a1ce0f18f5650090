"""Time of the blur field's compiled CPU ops at a render size, each implementation against its PyTorch twin
(``gsmsdr-bench field-ops``): the grid-kernel op (forward, image gradient, kernel-grid gradient) and the feature
network's depthwise convolutions on the feature grid.

Every timing is the minimum and the median of ``repeats`` calls after one untimed call: on a shared or unsteady
machine the minimum is the one least disturbed.
"""

from __future__ import annotations

import statistics
import time
from typing import Callable, Dict, List, Sequence

import torch

from gsmsdr_ns.ops.depthwise_conv import depthwise_conv2d
from gsmsdr_ns.ops.grid_kernels import EXTENSION as GRID_EXTENSION
from gsmsdr_ns.ops.grid_kernels import apply_grid_kernels, grid_size

# The feature network's depthwise layers: (channels, kernel, dilation) and how many of each a field step runs (two
# FANs: LKA3 = 3x3 then 5x5 dilated 2, LKA5 = 5x5 then 7x7 dilated 3, the 3x3 / 5x5 transforms, SAFM's 7x7)
DEPTHWISE_LAYERS = ((16, 3, 1, 4), (16, 5, 2, 2), (16, 5, 1, 4), (16, 7, 3, 2), (32, 7, 1, 2))


def _time(fn: Callable[[], object], repeats: int) -> Dict[str, float]:
    fn()
    seconds: List[float] = []
    for _ in range(repeats):
        started = time.perf_counter()
        fn()
        seconds.append(time.perf_counter() - started)
    return {"min_ms": 1e3 * min(seconds), "median_ms": 1e3 * statistics.median(seconds)}


def run_field_ops_benchmark(
    width: int, height: int, kernel_size: int, factor: int, repeats: int, impls: Sequence[str] = ("cpp", "torch")
) -> List[Dict[str, object]]:
    """Rows (op, implementation, shape, min_ms, median_ms) on a [1, 3, height, width] render (float32, CPU)."""
    gen = torch.Generator().manual_seed(0)
    rows: List[Dict[str, object]] = []
    image = torch.rand(1, 3, height, width, generator=gen)
    grid = torch.softmax(torch.randn(1, kernel_size**2, *grid_size((height, width), factor), generator=gen), dim=1)
    grad = torch.randn(1, 3, height, width, generator=gen)
    shape = f"[1, 3, {height}, {width}], K = {kernel_size}, cells of {factor} px"
    for impl in impls:
        if impl == "cpp":
            ops = GRID_EXTENSION.load()
            parts = {
                "grid kernels: forward": lambda: ops.grid_kernels_fwd(image, grid, kernel_size, factor),
                "grid kernels: image gradient": lambda: ops.grid_kernels_bwd(
                    grad, image, grid, kernel_size, factor, True, False
                ),
                "grid kernels: kernel-grid gradient": lambda: ops.grid_kernels_bwd(
                    grad, image, grid, kernel_size, factor, False, True
                ),
            }
        else:
            leaf_image, leaf_grid = image.clone().requires_grad_(), grid.clone().requires_grad_()

            def forward_backward() -> None:
                out = apply_grid_kernels(leaf_image, leaf_grid, factor, backend="torch")
                torch.autograd.grad(out, (leaf_image, leaf_grid), grad)

            parts = {"grid kernels: forward + both gradients": forward_backward}
        for op, fn in parts.items():
            rows.append({"op": op, "impl": impl, "shape": shape, **_time(fn, repeats)})
    h, w = grid_size((height, width), factor)
    for channels, k, dilation, per_step in DEPTHWISE_LAYERS:
        x = torch.randn(1, channels, h, w, generator=gen, requires_grad=True)
        weight = torch.randn(channels, 1, k, k, generator=gen, requires_grad=True)
        bias = torch.randn(channels, generator=gen, requires_grad=True)
        g = torch.randn(1, channels, h, w, generator=gen)
        for impl in impls:

            def depthwise(impl: str = impl) -> None:
                out = depthwise_conv2d(x, weight, bias, dilation, backend=impl)
                torch.autograd.grad(out, (x, weight, bias), g)

            op = f"depthwise {k}x{k} dilation {dilation}, forward + gradients (x{per_step} per field step)"
            rows.append({"op": op, "impl": impl, "shape": f"[1, {channels}, {h}, {w}]", **_time(depthwise, repeats)})
    return rows


def format_table(rows: Sequence[Dict[str, object]], header: str) -> str:
    """A markdown table of :func:`run_field_ops_benchmark` rows under ``header``."""
    lines = [header, "", "| op | implementation | shape | min ms | median ms |", "| --- | --- | --- | ---: | ---: |"]
    for r in rows:
        lines.append(f"| {r['op']} | {r['impl']} | {r['shape']} | {r['min_ms']:.2f} | {r['median_ms']:.2f} |")
    return "\n".join(lines) + "\n"


__all__ = ["DEPTHWISE_LAYERS", "format_table", "run_field_ops_benchmark"]
