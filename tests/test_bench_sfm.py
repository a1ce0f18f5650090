"""``gsmsdr-bench sfm``: the pose comparison against reference cameras, and the benchmark on the real fern photos
(degraded by ``gsmsdr-degrade``, then posed from the degraded photos alone)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import shared_fern
from scipy.spatial.transform import Rotation

from gsmsdr_ns.bench.sfm import format_table, llff_cameras_opencv, pose_errors, run_sfm_benchmark, write_results

FERN = shared_fern()


def _c2w(centres: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    c2w = np.tile(np.eye(4), (len(centres), 1, 1))
    c2w[:, :3, :3], c2w[:, :3, 3] = rotations, centres
    return c2w


def test_pose_errors_ignore_a_similarity_and_measure_what_is_left() -> None:
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(40, 3))
    rotations = Rotation.random(40, random_state=1).as_matrix()
    # the same cameras in another frame: scale 3, a rotation, a shift
    scale, frame, shift = 3.0, Rotation.from_euler("xyz", [20, -40, 70], degrees=True).as_matrix(), np.array([1, 2, 3])
    moved = _c2w(scale * centres @ frame.T + shift, frame @ rotations)
    exact = pose_errors(moved, centres, rotations)
    assert exact.max_centre < 1e-9 and exact.max_rotation_deg < 1e-5

    turned = moved.copy()
    turned[7, :3, :3] = turned[7, :3, :3] @ Rotation.from_euler("z", 2.0, degrees=True).as_matrix()
    errors = pose_errors(turned, centres, rotations)
    assert errors.max_centre < 1e-9 and errors.max_rotation_deg == pytest.approx(2.0, abs=1e-6)

    diameter = np.max(np.linalg.norm(centres[:, None] - centres[None], axis=-1))
    shifted = moved.copy()
    shifted[4, :3, 3] += scale * frame @ np.array([0.05 * diameter, 0.0, 0.0])  # one centre 5 % of the diameter off
    errors = pose_errors(shifted, centres, rotations)
    # the alignment absorbs a share of one camera's error (about 1/40 of it, plus a little scale and rotation)
    assert 0.04 < errors.max_centre <= 0.05 and errors.max_rotation_deg < 0.5


@pytest.mark.slow  # structure-from-motion of the shaken fern photos; the pose maths and the refusals stay in make test
def test_benchmark_rows_for_the_strongly_shaken_small_fern(tmp_path: Path) -> None:
    """The small fern photos (252x189) shaken by ``motion-strong``, posed from the shaken photos alone: every one
    registers; at this size even the sharp photos' cameras are 2-4 % / 3-4 degrees off LLFF's (docs/results/sfm),
    so only a loose bound is checked here. The rotation error is mostly the tilt of the similarity fitted to the
    nearly planar trajectory's centres (the same 8-10 degrees on every photo of cropped shaken photos; about 1
    degree when the rotations are aligned instead)."""
    photos = FERN / "images_16"
    lines = []
    rows = run_sfm_benchmark(photos, FERN / "poses_bounds.npy", ["motion-strong"], [False], tmp_path / "work",
                             threads=1, log=lines.append)  # fmt: skip
    (row,) = rows
    assert row.photos == "motion-strong" and not row.pooling
    assert row.total == 19  # the first photo stays sharp (gsmsdr-degrade's held-out view) and is left out
    assert row.registered == 19
    assert 16 * 252 / 600 < row.largest_blur_px <= 32 * 252 / 600 * 1.01  # the preset: 16-32 px at 600 px
    assert row.errors is not None and row.errors.max_centre < 0.08 and row.errors.max_rotation_deg < 14.0
    assert 150 < row.focal < 260  # the sharp photos' run: about 190 px
    assert lines == [format_table(rows).splitlines()[-1]]
    written = write_results(tmp_path / "out", rows, "llff-fern/images_16", "gsmsdr-bench sfm")
    assert written.read_text(encoding="utf8").count(f"| motion-strong | {row.largest_blur_px:.1f} | off | 19/19 |") == 1
    assert len(llff_cameras_opencv(FERN / "poses_bounds.npy")[0]) == 20


def test_a_bad_preset_is_reported_before_any_row_runs(tmp_path: Path) -> None:
    """A misspelt preset among the versions stops the benchmark before it poses a photo (the work folder stays
    empty), naming the preset and the valid ones."""
    from gsmsdr_ns.io.errors import InputError

    with pytest.raises(InputError, match="'motion-strnog'.*motion-strong"):
        run_sfm_benchmark(FERN / "images_16", FERN / "poses_bounds.npy", ["sharp", "motion-strnog"], [False],
                          tmp_path / "work", threads=1)  # fmt: skip
    assert not (tmp_path / "work").exists()
