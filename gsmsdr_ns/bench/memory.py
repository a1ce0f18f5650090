"""`gsmsdr-bench memory`: extra peak memory and time of the thin lens + blur field, forward and backward, on the CPU.

One row per (image size, lens implementation) for one blur-field configuration (``BlurFieldConfig`` with
``--set key=value`` overrides): the render goes through the thin lens (``fused``: ``ThinLensDefocus.blur``, the op
training uses; ``unfused``: its [B, K*K, H, W] kernels applied with ``apply_pixel_kernels``), then through the field
at the HPKO scale whose kernel is K (``BlurField.degrade``), and one backward runs from a random upstream gradient
into the render and every parameter. B = 1; the render and depth are random, the lens's aperture is wide enough that
its window is the full K x K.

Every measurement runs in a fresh interpreter (``python -m gsmsdr_ns.bench.memory --child <json>``) whose address
space is capped with ``RLIMIT_AS`` (``--limit-gb``): a configuration that needs more fails inside its own process
with an allocation error, reported as "> limit", instead of pushing a shared machine into swap. The child builds
the field, warms everything up on a small image (extension loaded, thread pool started), allocates the inputs,
resets the high-water mark (``echo 5 > /proc/self/clear_refs``) and reads it (VmHWM, now the resident set), runs
forward and backward and reads it again. Extra peak = VmHWM after - VmHWM before the run: every page the step
touched on top of the inputs and the parameters, gradients included, to within ``rss_resolution_mb`` (the kernel
counts pages per CPU; results.csv keeps the raw difference, which can be a fraction of a MiB below 0 for a step
that touches almost nothing, and the table shows that as 0). Where clear_refs is not writable the child
falls back to ``ru_maxrss`` minus VmRSS at the reset (an upper bound: the warm-up counts too). The limit counts
address space, not resident memory: the imports and the thread pools already reserve a few GB of it (the "set-up
address space" column), so the memory left for the step is the limit minus that.

Results: a table on stdout, and ``results.csv`` / ``results.md`` in ``--out``, merged with the rows already there
(same size, lens and field configuration: replaced), so "before" and "after" runs accumulate in one table.
"""

from __future__ import annotations

import ast
import csv
import dataclasses
import io
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

LENSES = ("fused", "unfused")
"""fused: ThinLensDefocus.blur (no K*K tensor); unfused: the lens's kernels, then apply_pixel_kernels."""

COLUMNS = ("size", "lens", "field", "status", "extra_peak_mb", "forward_s", "backward_s", "setup_rss_mb",
           "setup_vm_mb", "limit_gb", "method")  # fmt: skip

_OOM_MARKERS = ("can't allocate memory", "out of memory", "std::bad_alloc", "MemoryError", "Cannot allocate memory")


def parse_size(text: str) -> Tuple[int, int]:
    """ "WIDTHxHEIGHT" -> (width, height)."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"size: expected WIDTHxHEIGHT such as 600x400, got {text!r}") from None
    if width < 1 or height < 1:
        raise ValueError(f"size: expected positive WIDTHxHEIGHT, got {text!r}")
    return width, height


def _literal(text: str) -> Any:
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    if text.lower() == "none":
        return None
    try:
        value = ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text  # a bare word: a string field such as mode=view
    return tuple(value) if isinstance(value, list) else value


def parse_overrides(items: Sequence[str]) -> Dict[str, Any]:
    """``["key=value", ...]`` -> ``{key: value}`` for ``BlurFieldConfig`` or ``DegradationConfig`` (values as Python
    literals; bare words are strings, true / false / none as booleans and None, lists become tuples).

    Raises:
        ValueError: an item without "=", or a key that is a field of neither config (the message lists them).
    """
    from gsmsdr_ns.blur.degradation_config import DegradationConfig
    from gsmsdr_ns.blur.field import BlurFieldConfig

    names = [f.name for config in (BlurFieldConfig, DegradationConfig) for f in dataclasses.fields(config)]
    out: Dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"--set: expected key=value, got {item!r}")
        if key not in names:
            raise ValueError(
                f"--set {item!r}: no blur-field or degradation option {key!r}; options: {', '.join(names)}"
            )
        out[key] = _literal(value.strip())
    return out


def describe_field(overrides: Mapping[str, Any], field: bool = True) -> str:
    """The field column: "none" (lens only), "default" or the overrides as ``key=value`` words."""
    if not field:
        return "none"
    return " ".join(f"{k}={v}" for k, v in overrides.items()) or "default"


# -- the child process --------------------------------------------------------------------------------------------


def _build(spec: Mapping[str, Any]):
    """(field or None, lens, scale, linear_light) for the child's spec; the lens's window is the full K at any image
    size."""
    import math

    import torch

    from gsmsdr_ns.bench.method_base import apply_overrides
    from gsmsdr_ns.blur.defocus import ThinLensDefocus
    from gsmsdr_ns.blur.degradation_config import DegradationConfig
    from gsmsdr_ns.blur.field import BlurFieldConfig

    config, degradation = apply_overrides(BlurFieldConfig(), DegradationConfig(), dict(spec["overrides"]))
    K = int(spec["kernel_size"])
    field = config.setup(num_train_views=1, use_depth=True)
    sizes = {field.kernel_size(s): s for s in field.scales}
    if K not in sizes:
        raise ValueError(f"kernel_size {K} is none of the field's scales' kernel sizes {sorted(sizes)}")
    lens = ThinLensDefocus(1, degradation.thin_lens_initial_aperture, occlusion=degradation.thin_lens_occlusion)
    with torch.no_grad():
        lens.log_aperture.fill_(math.log(4.0 * K))  # radii up to ~K: the full window everywhere
        lens.inverse_focus.fill_(0.5)
        lens.focus_initialised.fill_(True)
    return (field if spec.get("field", True) else None), lens, sizes[K], degradation.linear_light


def _inputs(width: int, height: int, seed: int):
    """render [1, 3, H, W] (requires grad), depth [1, 1, H, W] in [1, 6), upstream gradient; filled in place."""
    import torch

    g = torch.Generator().manual_seed(seed)
    render = torch.empty(1, 3, height, width).uniform_(generator=g).requires_grad_(True)
    depth = torch.empty(1, 1, height, width).uniform_(1.0, 6.0, generator=g)
    grad = torch.empty(1, 3, height, width).normal_(generator=g)
    return render, depth, grad


def _step(
    field, lens, scale: int, linear_light: bool, lens_impl: str, K: int, render, depth, grad
) -> Tuple[float, float]:
    """Forward (lens, then field) and backward; (forward s, backward s)."""
    import torch

    from gsmsdr_ns.blur.field import BlurField

    ids = torch.tensor([0])
    t0 = time.perf_counter()
    if lens_impl == "fused":
        image = lens.blur(render, depth, ids, K, 1.0, linear_light)
    else:
        image = BlurField.blur(render, lens(depth, ids, K, 1.0), linear_light)
    if field is not None:
        kernels, mask = field(image, depth, ids, scale, dense=False)  # as training: kernels kept on the field's grid
        image = BlurField.degrade(image, kernels, mask, linear_light)
    t1 = time.perf_counter()
    image.backward(grad)
    t2 = time.perf_counter()
    return t1 - t0, t2 - t1


def run_child(spec: Mapping[str, Any]) -> Dict[str, Any]:
    """One measurement in this (fresh) process, under the spec's address-space limit; see the module docstring."""
    limit = int(spec["limit_bytes"])
    if limit > 0:
        _, hard = resource.getrlimit(resource.RLIMIT_AS)
        resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    import torch  # after the limit: importing torch counts towards it

    from gsmsdr_ns.bench.timing import PeakMemory, proc_status_kib

    if spec.get("threads"):
        torch.set_num_threads(int(spec["threads"]))
    torch.manual_seed(int(spec.get("seed", 0)))
    result: Dict[str, Any] = {"status": "ok"}
    try:
        field, lens, scale, linear_light = _build(spec)
        K = int(spec["kernel_size"])
        _step(field, lens, scale, linear_light, spec["lens"], K, *_inputs(48, 32, 1))  # warm-up
        field_params = [] if field is None else list(field.parameters())
        for p in field_params + list(lens.parameters()):
            p.grad = None
        render, depth, grad = _inputs(int(spec["width"]), int(spec["height"]), int(spec.get("seed", 0)))
        peak = PeakMemory()
        peak.reset()  # VmHWM back to the current RSS where /proc allows it
        vm_before = proc_status_kib("VmSize")  # VmSize counts to the limit
        forward_s, backward_s = _step(field, lens, scale, linear_light, spec["lens"], K, render, depth, grad)
        method = "VmHWM after clear_refs" if peak.span_reset else "ru_maxrss"
        result.update(extra_peak_mb=peak.extra_rss_mb(), forward_s=forward_s, backward_s=backward_s,
                      setup_rss_mb=peak.baseline_mb, setup_vm_mb=vm_before / 1024.0, method=method)  # fmt: skip
    except (RuntimeError, MemoryError) as exc:
        if not any(marker in f"{type(exc).__name__}: {exc}" for marker in _OOM_MARKERS):
            raise
        result.update(status="> limit", error=f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}")
    return result


# -- the parent ---------------------------------------------------------------------------------------------------


def measure(spec: Mapping[str, Any], timeout_s: float = 7200.0) -> Dict[str, Any]:
    """Run one measurement in a fresh interpreter; its result dict (status "ok", "> limit" or "failed: ...")."""
    cmd = [sys.executable, "-m", "gsmsdr_ns.bench.memory", "--child", json.dumps(dict(spec))]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"status": f"failed: no result within {timeout_s:.0f} s"}
    lines = proc.stdout.strip().splitlines()
    if proc.returncode == 0 and lines:
        return json.loads(lines[-1])
    tail = proc.stderr.strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
    if "failed to map segment" in proc.stderr:  # the address space of the imports alone exceeds the limit
        return {"status": f"failed: --limit-gb too low to import torch and the field (raise it): {tail[0][:120]}"}
    if any(marker in proc.stderr for marker in _OOM_MARKERS):  # an allocation failed outside the guarded step
        return {"status": "> limit", "error": tail[0][:200]}
    return {"status": f"failed: {tail[0][:200]}"}


def run_memory_benchmark(
    sizes: Sequence[str] = ("600x400", "1297x840"),
    lenses: Sequence[str] = LENSES,
    overrides: Sequence[str] = (),
    kernel_size: int = 17,
    limit_gb: float = 10.0,
    field: bool = True,
    threads: int = 0,
    progress: bool = True,
) -> List[Dict[str, Any]]:
    """One row per (size, lens): the columns of :data:`COLUMNS` (memory in MiB, times in s; empty when the run did
    not finish)."""
    parsed = parse_overrides(overrides)
    dims = [parse_size(s) for s in sizes]
    for lens in lenses:
        if lens not in LENSES:
            raise ValueError(f"lens: expected one of {LENSES}, got {lens!r}")
    rows = []
    for (width, height), size in zip(dims, sizes):
        for lens in lenses:
            spec = dict(width=width, height=height, kernel_size=kernel_size, lens=lens, overrides=parsed,
                        field=field, limit_bytes=int(limit_gb * 2**30), threads=threads)  # fmt: skip
            started = time.perf_counter()
            result = measure(spec)
            row = {c: "" for c in COLUMNS}
            row.update(size=f"{width}x{height}", lens=lens, field=describe_field(parsed, field),
                       limit_gb=f"{limit_gb:g}")  # fmt: skip
            row.update({k: v for k, v in result.items() if k in COLUMNS})
            rows.append(row)
            if progress:
                print(f"{row['size']} lens {lens}, field {row['field']}: {format_cell(row)} "
                      f"({time.perf_counter() - started:.0f} s)", file=sys.stderr, flush=True)  # fmt: skip
    return rows


def _extra_peak(row: Mapping[str, Any]) -> str:
    """The extra peak in whole MiB; a read below 0 (within the counters' resolution) shows as 0."""
    return f"{max(float(row['extra_peak_mb']), 0.0):.0f}"


def format_cell(row: Mapping[str, Any]) -> str:
    if row["status"] != "ok":
        return f"> {row['limit_gb']} GB" if row["status"] == "> limit" else str(row["status"])
    return f"{_extra_peak(row)} MiB"


def merge_rows(old: Sequence[Mapping[str, Any]], new: Sequence[Mapping[str, Any]]) -> List[Dict[str, Any]]:
    """``old`` with the rows of ``new`` replacing those of the same (size, lens, field), the rest appended."""
    key = lambda r: (r["size"], r["lens"], r["field"])  # noqa: E731
    fresh = {key(r): dict(r) for r in new}
    merged = [fresh.pop(key(r), dict(r)) for r in old]
    return merged + [r for r in (dict(r) for r in new) if key(r) in fresh]


def format_table(rows: Sequence[Mapping[str, Any]], header: str = "") -> str:
    def number(value: Any, fmt: str) -> str:
        return "" if value in ("", None) else format(float(value), fmt)

    lines = [header] if header else []
    lines += [
        "| size | lens | field | extra peak MiB | forward s | backward s | set-up RSS MiB | set-up address space MiB |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        peak = _extra_peak(r) if r["status"] == "ok" else format_cell(r)
        lines.append(f"| {r['size']} | {r['lens']} | {r['field']} | {peak} | {number(r['forward_s'], '.2f')} | "
                     f"{number(r['backward_s'], '.2f')} | {number(r['setup_rss_mb'], '.0f')} | "
                     f"{number(r['setup_vm_mb'], '.0f')} |")  # fmt: skip
    return "\n".join(lines)


def read_rows(path: Path) -> List[Dict[str, Any]]:
    """The rows of an earlier results.csv ([] when there is none)."""
    if not path.is_file():
        return []
    with open(path, newline="", encoding="utf8") as fh:
        return [{c: r.get(c, "") for c in COLUMNS} for r in csv.DictReader(fh)]


def write_results(out: Path, rows: Sequence[Mapping[str, Any]], header: str) -> List[Path]:
    """Merge ``rows`` into ``out``/results.csv and rewrite ``out``/results.md (both written atomically)."""
    from gsmsdr_ns.bench.records import write_text_atomic

    out.mkdir(parents=True, exist_ok=True)
    merged = merge_rows(read_rows(out / "results.csv"), rows)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(COLUMNS), lineterminator="\n")
    writer.writeheader()
    writer.writerows(merged)
    csv_path = write_text_atomic(out / "results.csv", buffer.getvalue())
    md_path = write_text_atomic(out / "results.md", "# gsmsdr-bench memory\n\n" + format_table(merged, header) + "\n")
    return [md_path, csv_path]


def table_header(kernel_size: int, limit_gb: float, threads: int = 0, command: Optional[str] = None) -> str:
    """What the latest run measured, on what (the merged table may hold rows of earlier runs)."""
    from gsmsdr_ns.bench.machine import describe_machine, machine_info
    from gsmsdr_ns.bench.timing import rss_resolution_mb

    info = machine_info()
    if threads:
        info["torch_threads"] = threads  # the measuring processes' setting
    text = (f"Thin lens + blur field, forward and backward, B = 1, K = {kernel_size}, float32; extra peak RSS per "
            f"fresh process under a {limit_gb:g} GB address-space limit, to within {rss_resolution_mb():.1f} MiB "
            f"(the kernel's per-CPU page counters). Latest run: {describe_machine(info)}, git "
            f"{info.get('git')}.")  # fmt: skip
    return text + (f"\n\n`{command}`\n" if command else "")


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        print(json.dumps(run_child(json.loads(sys.argv[2]))))
    else:
        sys.exit("usage: python -m gsmsdr_ns.bench.memory --child SPEC_JSON (gsmsdr-bench memory runs it)")
