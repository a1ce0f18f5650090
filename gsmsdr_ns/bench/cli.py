"""`gsmsdr-bench`: benchmarks that print tables (they are not tests)."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, List, Optional, Sequence, Tuple

import tyro


@dataclass
class RasterBench:
    """CPU rasterizer forward+backward time per path (C++, PyTorch tiles, dense all-pairs) at 240x135."""

    sizes: Tuple[int, ...] = (5000, 20000, 80000)
    """Gaussian counts to measure."""
    paths: Tuple[str, ...] = ("cpp", "torch", "dense")
    """Paths to time: cpp (compiled kernel), torch (PyTorch tiles), dense (every Gaussian x every pixel)."""
    repeats: int = 3
    """Timed repetitions per tiled path after one warm-up (the dense path is timed once)."""
    dense_max: int = 20000
    """Skip the dense baseline (every Gaussian at every pixel, minutes per pass) above this many Gaussians."""

    def main(self) -> None:
        from gsmsdr_ns.bench.raster import format_table, run_raster_benchmark

        rows = run_raster_benchmark(self.sizes, self.paths, self.repeats, self.dense_max)
        print(format_table(rows))


@dataclass
class DegradeBench:
    """gsmsdr-degrade wall time per effect on a 50-view 600x400 procedural scene (generated once, cached)."""

    rows: Tuple[str, ...] = ("motion", "defocus", "mixres", "all")
    """Rows to time: motion (mild), motion-strong, defocus, mixres, all (motion+defocus+mixres+noise), mixed."""
    num_views: int = 50
    """Views of the benchmark scene."""
    width: int = 600
    """Image width of the benchmark scene."""
    height: int = 400
    """Image height of the benchmark scene."""
    workers: int = 0
    """Worker processes for gsmsdr-degrade (0: its automatic choice)."""
    cache_dir: Path = Path(tempfile.gettempdir()) / "gsmsdr-bench"
    """Where the sharp benchmark scene is cached between runs."""

    def main(self) -> None:
        from gsmsdr_ns.bench.degrade import format_table, run_degrade_benchmark
        from gsmsdr_ns.synth.config import SynthSceneConfig

        scene = SynthSceneConfig(num_views=self.num_views, width=self.width, height=self.height)
        rows = run_degrade_benchmark(self.rows, scene, self.cache_dir, self.workers)
        print(format_table(rows, scene, self.workers))


@dataclass
class KernelsBench:
    """apply_pixel_kernels vs the F.unfold version (BAGS) at 600x400 RGB: forward+backward time, extra peak memory."""

    kernel_sizes: Tuple[int, ...] = (5, 9, 17)
    """Kernel sizes K (odd) to measure."""
    impls: Tuple[str, ...] = ("ours", "unfold")
    """Implementations: ours (apply_pixel_kernels, C++ on CPU), torch (its PyTorch twin), unfold (BAGS)."""
    width: int = 600
    """Image width."""
    height: int = 400
    """Image height."""
    channels: int = 3
    """Image channels."""
    batch: int = 1
    """Batch size."""
    repeats: int = 5
    """Timed forward+backward runs per implementation after one warm-up (medians are reported)."""
    memory_repeats: int = 1
    """Fresh processes per peak-memory measurement (the median is reported)."""

    def main(self) -> None:
        from gsmsdr_ns.bench.kernels import format_table, run_kernels_benchmark

        rows = run_kernels_benchmark(self.kernel_sizes, self.impls, self.height, self.width, self.channels,
                                     self.batch, self.repeats, self.memory_repeats)  # fmt: skip
        print(format_table(rows, self.height, self.width, self.channels, self.batch, self.repeats))


@dataclass
class FieldOpsBench:
    """The blur field's compiled CPU ops against their PyTorch twins at a render size (float32): the grid-kernel op's
    forward and gradients, the feature network's depthwise convolutions on the feature grid; min and median of
    --repeats calls. See gsmsdr_ns/bench/field_ops.py."""

    width: int = 458
    """Render width (458x333: the real-size fern after its border crop)."""
    height: int = 333
    """Render height."""
    kernel_size: int = 17
    """Kernel size K of the grid-kernel op (the full-resolution scale's)."""
    factor: int = 4
    """Feature-grid cell size in pixels (the field's feature_downsample)."""
    repeats: int = 15
    """Timed calls per op after one untimed call."""
    threads: int = 1
    """torch's and the C++ kernels' intra-op threads (0: torch's default)."""
    impls: Tuple[str, ...] = ("cpp", "torch")
    """Implementations: cpp (the compiled ops) and/or torch (their PyTorch twins)."""

    def main(self) -> None:
        import shlex

        import torch

        from gsmsdr_ns._cpp_ext import cpu_isa
        from gsmsdr_ns.bench.field_ops import format_table, run_field_ops_benchmark
        from gsmsdr_ns.bench.machine import describe_machine, machine_info

        threads_before = torch.get_num_threads()
        if self.threads > 0:
            torch.set_num_threads(self.threads)
        try:
            rows = run_field_ops_benchmark(
                self.width, self.height, self.kernel_size, self.factor, self.repeats, self.impls
            )
            threads = torch.get_num_threads()
        finally:
            torch.set_num_threads(threads_before)
        command = "gsmsdr-bench " + " ".join(shlex.quote(a) for a in _invocation_args())
        header = (f"# Blur-field ops\n\nCommand: `{command}`\n\nMachine: {describe_machine(machine_info())}; C++ "
                  f"ops built for {cpu_isa()}; {threads} thread(s); min and median of "
                  f"{self.repeats} calls after one untimed call.")  # fmt: skip
        print(format_table(rows, header))


@dataclass
class MemoryBench:
    """Extra peak memory and time of the thin lens + blur field forward and backward at K = 17 on the CPU, each size
    and lens in a fresh process under an address-space limit; writes results.md / results.csv into --out (merged
    with earlier rows). See gsmsdr_ns/bench/memory.py."""

    sizes: Tuple[str, ...] = ("600x400", "1297x840")
    """Image sizes, WIDTHxHEIGHT."""
    lens: Tuple[str, ...] = ("fused", "unfused")
    """Thin lens implementations: fused (ThinLensDefocus.blur, what training runs) and/or unfused (its kernels)."""
    set: Annotated[Tuple[str, ...], tyro.conf.UseAppendAction] = ()
    """BlurFieldConfig override key=value, repeatable (--set size=lite --set mode=view); default: today's field."""
    field: bool = True
    """Run the blur field after the lens (--no-field: the lens alone)."""
    kernel_size: int = 17
    """Lens window and field kernel size K (one of the field's kernel sizes)."""
    limit_gb: float = 10.0
    """Address-space limit of each measuring process (GB, 2^30 bytes); a run that needs more is reported "> limit"."""
    threads: int = 0
    """torch intra-op threads in the measuring processes (0: torch's default)."""
    out: Path = Path("bench-results") / "memory"
    """Folder of results.md and results.csv."""

    def main(self) -> None:
        import shlex

        from gsmsdr_ns.bench.memory import format_table, run_memory_benchmark, table_header, write_results

        try:
            rows = run_memory_benchmark(self.sizes, self.lens, self.set, self.kernel_size, self.limit_gb, self.field,
                                        self.threads)  # fmt: skip
        except ValueError as e:
            raise SystemExit(f"gsmsdr-bench memory: {e}") from None
        command = "gsmsdr-bench " + " ".join(shlex.quote(a) for a in _invocation_args())
        header = table_header(self.kernel_size, self.limit_gb, self.threads, command)
        print(format_table(rows, header))
        print("wrote " + ", ".join(str(p) for p in write_results(self.out, rows, header)))


@dataclass
class StepBench:
    """Training-step time and peak memory per method on scene folders, on the device training runs on (CUDA when
    available): full resolution and the blur field from the first step, warm-up untimed, the device synchronised only
    around the timed steps. Writes results.md / results.csv into --out. See gsmsdr_ns/bench/step_cost.py."""

    data: Tuple[Path, ...]
    """Scene folders (any layout the gsmsdr dataparser reads)."""
    methods: Tuple[str, ...] = ("plain", "full")
    """Bench methods (as in suite files); step-time ratios are to the first."""
    warmup: int = 10
    """Untimed steps before the timed ones."""
    steps: int = 50
    """Timed steps per method."""
    estimate: bool = True
    """Estimate a record for images without one (--no-estimate: nothing known about them, so every such image trains
    with the blur field, the most expensive path)."""
    breakdown_steps: int = 0
    """Steps after the timed ones with the time breakdown per stage (they wait for the device at every stage)."""
    threads: Tuple[int, ...] = (0,)
    """Intra-op thread counts to measure each method at (torch's and our C++ kernels'); 0: torch's default. With 1
    among them, the table gives each method's speed-up over its 1-thread step."""
    rounds: int = 1
    """Rounds the timed steps are split into: the methods of a scene and thread count take turns each round, and the
    table adds the median over the rounds of a round's time per step (on a shared or unsteady machine, 8 rounds)."""
    out: Path = Path("bench-results") / "step"
    """Folder of results.md and results.csv."""
    work_dir: Path = Path(tempfile.gettempdir()) / "gsmsdr-bench-step"
    """Trainer output folder (nothing is saved there but nerfstudio's config)."""

    def main(self) -> None:
        import shlex

        from gsmsdr_ns.bench.machine import describe_machine, machine_info
        from gsmsdr_ns.bench.step_cost import StepCostSpec, format_table, run_step_cost, write_results

        if any(n < 0 for n in self.threads):
            raise SystemExit(f"gsmsdr-bench step: --threads must be >= 0 (0: torch's default), got {self.threads}")
        if self.rounds < 1:
            raise SystemExit(f"gsmsdr-bench step: --rounds must be >= 1, got {self.rounds}")
        specs = [StepCostSpec(m, d, self.warmup, self.steps, self.estimate, breakdown_steps=self.breakdown_steps,
                              threads=n)
                 for d in self.data for n in sorted(self.threads) for m in self.methods]  # fmt: skip
        rows = run_step_cost(specs, self.work_dir, log=print, rounds=self.rounds)
        command = "gsmsdr-bench " + " ".join(shlex.quote(a) for a in _invocation_args())
        header = (
            f"# Training-step cost per method\n\nCommand: `{command}`\n\nMachine: {describe_machine(machine_info())}"
            f"\n\n{self.warmup} untimed warm-up steps, then {self.steps} timed steps per method at full "
            "resolution with the blur field on from step 0; the device synchronised only around the timed steps"
            + (
                f", split into {self.rounds} rounds in which the methods of a scene and thread count take turns."
                if self.rounds > 1
                else "."
            )
        )
        print(format_table(rows, header))
        print("wrote " + ", ".join(str(p) for p in write_results(self.out, rows, header)))


@dataclass
class SuiteBench:
    """Run a benchmark suite (configs/bench/*.yaml: scenes x methods x step budgets x seeds) through nerfstudio's
    trainer; writes results.csv, results.md and PNG plots into --out. Finished runs are kept in <out>/runs/ and
    skipped when the suite runs again (an interrupted suite resumes). `gsmsdr-bench --quick` = `suite --config
    quick`. `--publish docs/results/<suite>` also copies results.md, results.csv and the plots into the
    repository's results folder. See gsmsdr_ns/bench/suite.py."""

    config: str = "quick"
    """Suite YAML file, or the name of a packaged one in configs/bench/ (quick, full, ablations, ...)."""
    out: Optional[Path] = None
    """Output folder: runs/, scenes/ and the results (default: bench-results/<suite name>)."""
    publish: Optional[Path] = None
    """Also copy results.md, results.csv and the plots into this folder (e.g. docs/results/quick) at the end."""
    threads: Optional[int] = None
    """torch intra-op threads, overriding the suite's `threads` (0: torch's default)."""
    plots: bool = True
    """Write the PNG plots."""
    progress: bool = True
    """Show progress bars."""
    interrupt_after: Optional[int] = None
    """Stop as Ctrl-C would (SIGINT to this process) after this many trained runs; the suite resumes on a rerun."""
    ray: Optional[str] = None
    """Run every run as a task on Ray (the `ray` extra): local (a local instance on all cores), local:N (on N
    cores), auto (the cluster `ray start --head` started on this machine) or a cluster address HOST:PORT. Default:
    one run after another in this process."""
    kill_worker_at: Optional[str] = None
    """Fault drill under --ray, RUN_ID:STEP: that run's worker process kills itself at that step of its first
    attempt; Ray starts the run again."""

    def main(self) -> None:
        import shlex
        import sys
        import time
        import warnings

        # nerfstudio's camera utilities use torch.jit.script, which torch >= 2.10 reports as deprecated on import
        warnings.filterwarnings("ignore", message=".*torch.jit.script.*", category=FutureWarning)
        from gsmsdr_ns.bench.report import main_tables, publish_outputs
        from gsmsdr_ns.bench.runner import run_suite
        from gsmsdr_ns.bench.suite_config import SuiteConfigError, find_suite_file, load_suite

        try:
            suite = load_suite(find_suite_file(self.config))
        except SuiteConfigError as e:
            print(f"gsmsdr-bench suite: {e}", file=sys.stderr)
            raise SystemExit(2) from None
        if self.threads is not None:
            suite.threads = self.threads
        out = self.out if self.out is not None else Path("bench-results") / suite.name
        command = "gsmsdr-bench " + " ".join(shlex.quote(a) for a in _invocation_args())
        started = time.perf_counter()
        try:
            if self.ray is None:
                if self.kill_worker_at is not None:
                    raise SystemExit("gsmsdr-bench suite: --kill-worker-at is a fault drill for --ray runs")
                outcome = run_suite(suite, out, command=command, progress=self.progress, plots=self.plots,
                                    interrupt_after=self.interrupt_after)  # fmt: skip
            else:
                outcome = self._run_on_ray(suite, out, command)
        except KeyboardInterrupt:
            raise SystemExit(130) from None
        print(main_tables((out / "results.md").read_text(encoding="utf8")))
        copied = f", {len(outcome.copied)} copied from a run with the same training" if outcome.copied else ""
        print(
            f"suite {suite.name}: {len(outcome.trained)} runs trained, {len(outcome.reused)} reused, "
            f"{len(outcome.failed)} failed, {len(outcome.skipped)} skipped{copied} in "
            f"{time.perf_counter() - started:.0f} s"
        )
        print("wrote " + ", ".join(str(p) for p in outcome.outputs))
        if self.publish is not None:
            print("published " + ", ".join(str(p) for p in publish_outputs(out, self.publish, outcome.outputs)))
        if outcome.failed:
            raise SystemExit(1)

    def _run_on_ray(self, suite, out: Path, command: str):
        from gsmsdr_ns.bench.ray_runner import RaySetupError, run_suite_on_ray

        drill = None
        if self.kill_worker_at is not None:
            run_id, _, step = self.kill_worker_at.rpartition(":")
            if not run_id or not step.isdigit() or int(step) < 1:
                raise SystemExit(f"gsmsdr-bench suite: --kill-worker-at {self.kill_worker_at}: expected RUN_ID:STEP "
                                 "with STEP >= 1, e.g. motion__full__1000__s0:300")  # fmt: skip
            drill = (run_id, int(step))
        try:
            return run_suite_on_ray(suite, out, self.ray, command=command, progress=self.progress, plots=self.plots,
                                    interrupt_after=self.interrupt_after, kill_worker_at=drill)  # fmt: skip
        except RaySetupError as e:
            raise SystemExit(f"gsmsdr-bench suite: {e}") from None


@dataclass
class SfmBench:
    """gsmsdr-process on the LLFF fern photos, sharp and degraded by gsmsdr-degrade presets, with SIFT domain-size
    pooling on and off: photos registered, time, and camera errors against LLFF's poses. See
    gsmsdr_ns/bench/sfm.py."""

    dataset: str = "llff-fern"
    """Photo set folder with poses_bounds.npy (under $GSMSDR_DATA_DIR or shared/data), or an absolute path."""
    images: str = "images_8"
    """Folder of the photos inside the set."""
    versions: Tuple[str, ...] = ("sharp", "motion-mild", "motion-strong", "defocus", "defocus-strong")
    """Rows: "sharp" (the photos) and gsmsdr-degrade presets (the degraded photos alone)."""
    pooling: Tuple[bool, ...] = (False, True)
    """Domain-size pooling settings to run each version with."""
    threads: int = -1
    """pycolmap threads (-1: all cores)."""
    seed: int = 0
    """Degradation and SfM seed."""
    work: Path = Path(tempfile.gettempdir()) / "gsmsdr-bench" / "sfm"
    """Scratch folder for the processed scenes."""
    out: Path = Path("bench-results") / "sfm"
    """Folder of results.md."""

    def main(self) -> None:
        import shlex

        from gsmsdr_ns.bench.real_scenes import RealSceneSpec, resolve_photos
        from gsmsdr_ns.bench.sfm import format_table, run_sfm_benchmark, write_results
        from gsmsdr_ns.io.errors import InputError

        try:
            photos = resolve_photos(RealSceneSpec(dataset=self.dataset, images=self.images))
            poses = photos.parent / "poses_bounds.npy"
            if not poses.is_file():
                raise InputError(f"gsmsdr-bench sfm: {poses} is missing; the benchmark compares with LLFF poses")
            rows = run_sfm_benchmark(photos, poses, self.versions, self.pooling, self.work, self.threads, self.seed)
        except InputError as e:
            raise SystemExit(str(e)) from None
        command = "gsmsdr-bench " + " ".join(shlex.quote(a) for a in _invocation_args())
        print(format_table(rows))
        print(f"wrote {write_results(self.out, rows, f'{Path(self.dataset).name}/{self.images}', command)}")


@dataclass
class EtaBench:
    """How right ns-train's time estimate is: replayed on the step times a suite's runs recorded, at 10 / 25 / 50 /
    75 % of each run, beside nerfstudio's own estimate."""

    runs: Path
    """A suite's output folder (or its runs/ folder); records without a step trace are skipped."""

    def main(self) -> None:
        from gsmsdr_ns.bench.eta import format_table, load_traced_records, replay

        try:
            records = load_traced_records(self.runs)
        except FileNotFoundError as e:
            raise SystemExit(f"gsmsdr-bench eta: {e}") from None
        if not records:
            raise SystemExit(f"gsmsdr-bench eta: no run record with a step trace under {self.runs}")
        print(format_table([replay(record) for record in records]))


SUBCOMMANDS = {
    "raster": RasterBench,
    "degrade": DegradeBench,
    "kernels": KernelsBench,
    "field-ops": FieldOpsBench,
    "memory": MemoryBench,
    "suite": SuiteBench,
    "sfm": SfmBench,
    "step": StepBench,
    "eta": EtaBench,
}

_ARGS: List[str] = []


def _invocation_args() -> List[str]:
    return list(_ARGS)


def map_quick(argv: Sequence[str]) -> List[str]:
    """``--quick`` (anywhere) means ``suite --config quick``: tyro's subcommands have no bare top-level flag."""
    args = list(argv)
    if "--quick" not in args:
        return args
    args = [a for a in args if a != "--quick"]
    if args and args[0] == "suite":
        args = args[1:]
    elif args and not args[0].startswith("-"):
        raise SystemExit(f"gsmsdr-bench: --quick runs the quick suite; it does not combine with {args[0]!r}")
    if any(a == "--config" or a.startswith("--config=") for a in args):
        raise SystemExit("gsmsdr-bench: --quick already selects the quick suite; drop --config")
    return ["suite", "--config", "quick", *args]


def entrypoint(argv: Optional[Sequence[str]] = None) -> None:
    import os
    import sys

    # Idle OpenMP threads spin briefly, then sleep (see the Makefile); must be set before torch loads OpenMP.
    os.environ.setdefault("GOMP_SPINCOUNT", "1000")
    raw = list(sys.argv[1:] if argv is None else argv)
    _ARGS[:] = raw
    description = "gsmsdr benchmarks. `gsmsdr-bench --quick` runs the quick suite (= `suite --config quick`)."
    from rich.console import Console

    from gsmsdr_ns._cli import run_entrypoint

    # The suite prints what it kept itself and exits 130; this line covers the other benchmarks and the start-up.
    interrupted = "interrupted; tables were not printed, a suite's finished runs are kept in its runs/ folder"

    def parse():
        return tyro.extras.subcommand_cli_from_dict(SUBCOMMANDS, args=map_quick(raw), description=description)

    run_entrypoint(parse, Console(stderr=True), interrupted=interrupted)


if __name__ == "__main__":
    entrypoint()
