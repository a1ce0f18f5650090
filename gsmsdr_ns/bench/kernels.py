"""`gsmsdr-bench kernels`: `apply_pixel_kernels` against the F.unfold version (BAGS) at 600x400 RGB.

Time: forward + backward (``out.backward(grad)`` into both ``image.grad`` and ``weights.grad``), median over
``repeats`` runs after one warm-up, the implementations interleaved run by run so that load from other processes
hits them alike.

Extra peak memory: every measurement runs in a fresh interpreter (``python -m gsmsdr_ns.bench.kernels --peak-memory
...``). The child warms the implementation up on a tiny input (extension loaded, thread pool started), allocates the
inputs with in-place fills (no temporaries), resets the kernel's high-water mark (``echo 5 > /proc/self/clear_refs``)
and reads it (VmHWM, now the resident set), runs one forward + backward and reads the high-water mark again.
Extra peak = VmHWM after - VmHWM before the run: every page the operation touched on top of the inputs, the gradients
included (``weights.grad`` alone is B*K*K*H*W floats, 277 MB at K=17, and is the same for every implementation).
Where clear_refs is not writable the child falls back to ``ru_maxrss`` (KiB on Linux) minus VmRSS at the reset,
which is only valid because nothing before the run allocated more than the inputs.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from typing import Callable, Dict, List, Sequence, Tuple

import torch

from gsmsdr_ns.bench.timing import PeakMemory

IMPLS = ("ours", "torch", "unfold")
"""ours: apply_pixel_kernels (backend auto: C++ on CPU); torch: its PyTorch twin; unfold: the BAGS version."""


def _impl(name: str) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    from gsmsdr_ns.ops.pixel_kernels import apply_pixel_kernels, apply_pixel_kernels_unfold

    if name == "ours":
        return apply_pixel_kernels
    if name == "torch":
        return lambda image, weights: apply_pixel_kernels(image, weights, backend="torch")
    if name == "unfold":
        return apply_pixel_kernels_unfold
    raise ValueError(f"impl: expected one of {IMPLS}, got {name!r}")


def make_inputs(
    K: int, height: int = 400, width: int = 600, channels: int = 3, batch: int = 1, seed: int = 0
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """image [B, C, H, W] in [0, 1), weights [B, K*K, H, W] (positive, summing to 1 per pixel), both leaves that
    require grad, and an upstream gradient; filled in place so no temporary larger than [B, 1, H, W] exists."""
    g = torch.Generator().manual_seed(seed)
    image = torch.empty(batch, channels, height, width).uniform_(generator=g)
    weights = torch.empty(batch, K * K, height, width).uniform_(0.05, 1.0, generator=g)
    weights.div_(weights.sum(1, keepdim=True))
    grad = torch.empty(batch, channels, height, width).normal_(generator=g)
    return image.requires_grad_(True), weights.requires_grad_(True), grad


def _forward_backward(fn, image, weights, grad) -> Tuple[float, float]:
    image.grad = weights.grad = None
    t0 = time.perf_counter()
    out = fn(image, weights)
    t1 = time.perf_counter()
    out.backward(grad)
    t2 = time.perf_counter()
    return t1 - t0, t2 - t1


def time_impls(
    impls: Sequence[str], K: int, height: int, width: int, channels: int, batch: int, repeats: int
) -> Dict[str, Tuple[float, float]]:
    """Median (forward s, backward s) per implementation; runs interleaved, one warm-up round first."""
    image, weights, grad = make_inputs(K, height, width, channels, batch)
    fns = {name: _impl(name) for name in impls}
    runs: Dict[str, List[Tuple[float, float]]] = {name: [] for name in impls}
    for r in range(repeats + 1):
        for name, fn in fns.items():
            f, b = _forward_backward(fn, image, weights, grad)
            if r > 0:
                runs[name].append((f, b))
    return {name: (statistics.median(f for f, _ in v), statistics.median(b for _, b in v)) for name, v in runs.items()}


def _peak_memory_child(impl: str, K: int, height: int, width: int, channels: int, batch: int) -> Dict:
    """Runs in the fresh child: extra peak resident memory (bytes) of one forward + backward."""
    fn = _impl(impl)
    tiny = make_inputs(K, 8, 8, channels, batch)
    _forward_backward(fn, *tiny)  # load the extension, start the thread pool, fault the code pages in
    del tiny
    image, weights, grad = make_inputs(K, height, width, channels, batch)
    peak = PeakMemory()
    peak.reset()  # VmHWM back to the current RSS where /proc allows it
    _forward_backward(fn, image, weights, grad)
    method = "VmHWM after clear_refs" if peak.span_reset else "ru_maxrss"
    return dict(impl=impl, K=K, extra_bytes=round(2**20 * peak.extra_rss_mb()), method=method)


def measure_peak_memory(
    impl: str, K: int, height: int = 400, width: int = 600, channels: int = 3, batch: int = 1
) -> Dict:
    """Extra peak resident memory of one forward + backward, measured in a fresh interpreter (see module doc)."""
    cmd = [
        sys.executable,
        "-m",
        "gsmsdr_ns.bench.kernels",
        "--peak-memory",
        impl,
        *map(str, (K, height, width, channels, batch)),
    ]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
    if proc.returncode != 0:
        raise RuntimeError(f"memory child for {impl} K={K} failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run_kernels_benchmark(
    kernel_sizes: Sequence[int] = (5, 9, 17),
    impls: Sequence[str] = ("ours", "unfold"),
    height: int = 400,
    width: int = 600,
    channels: int = 3,
    batch: int = 1,
    repeats: int = 5,
    memory_repeats: int = 1,
) -> List[Dict]:
    """One row per (K, impl): median forward / backward seconds and median extra peak bytes."""
    for name in impls:
        _impl(name)  # validate names before spending minutes
    rows = []
    for K in kernel_sizes:
        times = time_impls(impls, K, height, width, channels, batch, repeats)
        for name in impls:
            mems = [measure_peak_memory(name, K, height, width, channels, batch) for _ in range(memory_repeats)]
            rows.append(dict(
                K=K, impl=name, forward_s=times[name][0], backward_s=times[name][1],
                extra_bytes=statistics.median(m["extra_bytes"] for m in mems), method=mems[0]["method"],
            ))  # fmt: skip
    ref = {r["K"]: r for r in rows if r["impl"] == "unfold"}
    for r in rows:
        u = ref.get(r["K"])
        total = r["forward_s"] + r["backward_s"]
        r["time_ratio"] = total / (u["forward_s"] + u["backward_s"]) if u else None
        r["memory_ratio"] = r["extra_bytes"] / u["extra_bytes"] if u and u["extra_bytes"] > 0 else None
    return rows


def format_table(rows: List[Dict], height: int = 400, width: int = 600, channels: int = 3, batch: int = 1,
                 repeats: int = 5) -> str:  # fmt: skip
    def ratio(x):
        return "n/a" if x is None else f"{x:.2f}"

    methods = sorted({r["method"] for r in rows})
    lines = [
        f"apply_pixel_kernels vs F.unfold, [{batch}, {channels}, {height}, {width}] float32, forward+backward "
        f"(median of {repeats}), torch {torch.__version__}, {torch.get_num_threads()} threads; extra peak RSS "
        f"per fresh process ({', '.join(methods)})",
        "| K | impl | forward ms | backward ms | total ms | time / unfold | extra peak MB | memory / unfold |",
        "|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        total = r["forward_s"] + r["backward_s"]
        lines.append(
            f"| {r['K']} | {r['impl']} | {1000 * r['forward_s']:.1f} | {1000 * r['backward_s']:.1f} | "
            f"{1000 * total:.1f} | {ratio(r['time_ratio'])} | {r['extra_bytes'] / 2**20:.1f} | "
            f"{ratio(r['memory_ratio'])} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    if len(sys.argv) == 8 and sys.argv[1] == "--peak-memory":
        name, *nums = sys.argv[2:]
        print(json.dumps(_peak_memory_child(name, *map(int, nums))))
    else:
        sys.exit("usage: python -m gsmsdr_ns.bench.kernels --peak-memory IMPL K HEIGHT WIDTH CHANNELS BATCH")
