"""Does the blur field pay off? A generated motion-blurred scene trained briefly with ``gsmsdr`` and with plain
Gaussians (the same preset with ``degradation sharp``: a splatfacto step on the blurry images), through nerfstudio's
trainer (``gsmsdr_ns.bench.accuracy``: same scene, cameras, seed, step budget and schedule for both).

Scene: the ``motion-strong`` variant (16-32 px of shake at 600 px width: 3.2-6.4 px at the 120 px used here, where
blur is large enough to matter), 24 views, every 6th a sharp held-out test view, 600 steps.

Measured on the 2-core CPU machine (2026-11-21, this configuration, seed 0, ``pytest tests/test_accuracy.py -s``):

============  ====================  ==================
method        blurry train-view fit  sharp test views
============  ====================  ==================
plain         28.78 dB               22.19 dB / 0.621
gsmsdr        29.13 dB               22.01 dB / 0.627
sharp bound   -                      22.81 dB / 0.698
============  ====================  ==================

What this test asserts, and the margins:

* the simulated degradation (render -> blur field) fits the blurry training views better than plain Gaussians do:
  by more than 0.1 dB (measured +0.35 dB; +0.31 dB in a second run: the blur field's multi-threaded
  reductions are not bit-reproducible);
* the sharp render is not damaged by the field: test PSNR at least plain's minus 0.75 dB (measured -0.18 dB and -0.23 dB). A
  field that explains the images without keeping the render honest (mask pinned near 1, no regulariser) measured
  -2.6 dB at 160x120 and fails this. At this budget the blur field does NOT yet render measurably sharper test views
  than plain Gaussians (the gap to the sharp bound is only 0.6 dB); the accuracy benchmark
  (``gsmsdr-bench suite --config accuracy``) reports the gains at larger budgets and the README says where the
  issue's targets are missed.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from gsmsdr_ns.bench.accuracy import RunResult, SceneSpec, Schedule, run_method

SPEC = SceneSpec("motion-strong", width=120, height=90, num_views=24, hold=6)
SCHEDULE = Schedule(600, num_downscales=1)
FIT_MARGIN_DB = 0.1
TEST_VIEW_TOLERANCE_DB = 0.75


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> dict:
    bench_dir: Path = tmp_path_factory.mktemp("accuracy")
    out: dict = {}
    for method in ("plain", "gsmsdr"):
        out[method] = run_method(method, SPEC, SCHEDULE, bench_dir, seed=0, train_fit=True, log=print)
    return out


def test_gsmsdr_fits_the_blurry_training_views_better_than_plain(results):
    plain: RunResult = results["plain"]
    gsmsdr: RunResult = results["gsmsdr"]
    assert gsmsdr.train_psnr > plain.train_psnr + FIT_MARGIN_DB, (
        f"blurry train-view fit: gsmsdr {gsmsdr.train_psnr:.2f} dB vs plain {plain.train_psnr:.2f} dB"
    )


def test_gsmsdr_keeps_the_sharp_render_honest(results):
    plain: RunResult = results["plain"]
    gsmsdr: RunResult = results["gsmsdr"]
    assert gsmsdr.psnr > plain.psnr - TEST_VIEW_TOLERANCE_DB, (
        f"sharp test views: gsmsdr {gsmsdr.psnr:.2f} dB vs plain {plain.psnr:.2f} dB"
    )
    assert gsmsdr.ssim > plain.ssim - 0.03, f"test SSIM: gsmsdr {gsmsdr.ssim:.4f} vs plain {plain.ssim:.4f}"
