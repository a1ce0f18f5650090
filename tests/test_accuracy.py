"""Does the blur field pay off? A generated motion-blurred scene trained briefly with ``gsmsdr-lite`` (gsmsdr's CPU
preset) and with plain Gaussians (the same preset with ``degradation sharp``: a splatfacto step on the blurry images),
through nerfstudio's trainer (``gsmsdr_ns.bench.training``: same scene, cameras, seed, step budget and schedule for
both).

The comparison is ``slow`` (``make test-slow``): two trainings of 1000 steps. Scene: the ``motion-strong`` variant
(16-32 px of shake at 600 px width: 4.3-8.5 px at the 160 px used here), 24 views, every 6th a sharp held-out test
view (4 test views, 20 blurry training views), 1000 steps (50 draws of each training view: the per-view kernels
learn from those draws; with fewer draws per view the field does not beat plain on the test views).

What the comparison asserts:

* the simulated degradation (render -> blur field) fits the blurry training views better than plain Gaussians do,
  by more than ``FIT_MARGIN_DB``;
* the sharp test views are rendered sharper: PSNR above plain's by more than ``TEST_PSNR_MARGIN_DB`` and SSIM by
  more than ``TEST_SSIM_MARGIN``. The margins sit well below the measured gains and well above the run-to-run
  differences of one configuration (the blur field's multi-threaded reductions are not bit-reproducible).

The default suite runs the same code path (``run_method`` with the train-view fit, both methods on one generated
scene) on a tiny scene for a few steps, where only its outputs, not the gain, are checked.

The full ``gsmsdr`` preset is measured at larger budgets by ``gsmsdr-bench suite --config accuracy`` (README).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from gsmsdr_ns.bench.scenes import SceneSpec
from gsmsdr_ns.bench.training import RunResult, run_method
from gsmsdr_ns.plugin.schedule import TrainingSchedule

SPEC = SceneSpec("motion-strong", width=160, height=120, num_views=24, hold=6)
SCHEDULE = TrainingSchedule.bench(1000, num_downscales=1)
METHOD = "gsmsdr-lite"
FIT_MARGIN_DB = 0.2
TEST_PSNR_MARGIN_DB = 0.2
TEST_SSIM_MARGIN = 0.02

TINY_SPEC = SceneSpec("motion-strong", width=64, height=48, num_views=8, hold=4, num_points=400)
TINY_SCHEDULE = TrainingSchedule.bench(20, num_downscales=1, refinements=4)


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> dict:
    bench_dir: Path = tmp_path_factory.mktemp("accuracy")
    out: dict = {}
    for method in ("plain", METHOD):
        out[method] = run_method(method, SPEC, SCHEDULE, bench_dir, seed=0, train_fit=True, log=print)
    return out


def test_run_method_trains_and_evaluates_both_methods_on_one_scene(tmp_path):
    """The comparison's path on a tiny scene: one generated scene shared by both methods, each trained for the
    schedule's steps in-process and evaluated on the sharp test views and on the blurry training views."""
    results = {method: run_method(method, TINY_SPEC, TINY_SCHEDULE, tmp_path, seed=0, train_fit=True)
               for method in ("plain", METHOD)}  # fmt: skip
    assert [p.name for p in (tmp_path / "scenes").iterdir() if not p.name.startswith(".")] == [TINY_SPEC.name]
    for method, result in results.items():
        assert (result.method, result.scene, result.steps) == (method, "motion-strong", TINY_SCHEDULE.steps)
        assert 5.0 < result.psnr < 60.0 and 0.0 < result.ssim <= 1.0, result
        assert math.isfinite(result.train_psnr) and 5.0 < result.train_psnr < 60.0, result
        assert result.num_gaussians > 0 and result.train_seconds > 0.0, result
    assert results["plain"].psnr != results[METHOD].psnr, "the blur field changed nothing"


@pytest.mark.slow
def test_gsmsdr_fits_the_blurry_training_views_better_than_plain(results):
    plain: RunResult = results["plain"]
    gsmsdr: RunResult = results[METHOD]
    assert gsmsdr.train_psnr > plain.train_psnr + FIT_MARGIN_DB, (
        f"blurry train-view fit: {METHOD} {gsmsdr.train_psnr:.2f} dB vs plain {plain.train_psnr:.2f} dB"
    )


@pytest.mark.slow
def test_gsmsdr_renders_sharper_test_views_than_plain(results):
    plain: RunResult = results["plain"]
    gsmsdr: RunResult = results[METHOD]
    assert gsmsdr.psnr > plain.psnr + TEST_PSNR_MARGIN_DB, (
        f"sharp test views: {METHOD} {gsmsdr.psnr:.2f} dB vs plain {plain.psnr:.2f} dB"
    )
    assert gsmsdr.ssim > plain.ssim + TEST_SSIM_MARGIN, (
        f"test SSIM: {METHOD} {gsmsdr.ssim:.4f} vs plain {plain.ssim:.4f}"
    )
