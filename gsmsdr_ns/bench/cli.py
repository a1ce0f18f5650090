"""`gsmsdr-bench`: benchmarks that print tables (they are not tests)."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Tuple

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
    """Skip the dense baseline above this many Gaussians (measured: 154 s forward+backward at 20k on 2 cores)."""

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


def entrypoint() -> None:
    tyro.extras.subcommand_cli_from_dict(
        {"raster": RasterBench, "degrade": DegradeBench, "kernels": KernelsBench}
    ).main()


if __name__ == "__main__":
    entrypoint()
