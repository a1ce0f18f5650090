"""The remaining-time estimate ns-train prints (gsmsdr_ns.plugin.time_estimate) and its replay (gsmsdr-bench eta)."""

from __future__ import annotations

import dataclasses
import json

import pytest

from gsmsdr_ns.bench.eta import format_table, load_traced_records, replay
from gsmsdr_ns.plugin.time_estimate import StepSchedule, TimeEstimate, format_duration


def feed(estimate: TimeEstimate, times, gaussians=None, upto=None):
    for step, seconds in enumerate(times[:upto]):
        estimate.add(step, seconds, gaussians[step] if gaussians is not None else 0)


def test_constant_cost_is_the_remaining_steps_times_the_step_time():
    estimate = TimeEstimate(StepSchedule(100, (0,), (1000.0,)))
    assert estimate.remaining() is None
    feed(estimate, [0.5] * 40)
    assert estimate.remaining() == pytest.approx(60 * 0.5)


def test_later_resolution_stages_cost_their_pixel_ratio_to_the_exponent():
    # three stages at 1/16, 1/4 and all of the pixels; a step costs pixels ** the estimate's exponent
    schedule = StepSchedule(300, (0, 100, 200), (100.0, 400.0, 1600.0))
    exponent = TimeEstimate(schedule).pixel_exponent
    cost = [0.01 * (schedule.stage_pixels[schedule.stage(s)] / 100.0) ** exponent for s in range(300)]
    for done in (50, 150, 250):
        estimate = TimeEstimate(schedule)
        feed(estimate, cost, upto=done)
        assert estimate.remaining() == pytest.approx(sum(cost[done:]), rel=1e-6)
    # nerfstudio's estimate at step 50 (20-step mean times the steps left) would be far below the truth
    assert 250 * 0.01 < 0.4 * sum(cost[50:])


def test_growing_gaussians_raise_the_cost_ahead_until_densification_stops():
    schedule = StepSchedule(400, (0,), (1000.0,), densify_until=200)
    gaussians = [1000 + 20 * min(s, 200) for s in range(400)]
    estimate = TimeEstimate(schedule)
    cost = [0.001 * n**estimate.gaussian_exponent for n in gaussians]
    feed(estimate, cost, gaussians, upto=100)
    truth = sum(cost[100:])
    assert estimate.remaining() == pytest.approx(truth, rel=0.03)
    flat = TimeEstimate(schedule, gaussian_exponent=0.0)
    feed(flat, cost, gaussians, upto=100)
    assert flat.remaining() < 0.9 * truth  # without the growth term the estimate is short


def test_the_steps_after_a_cost_change_settle_before_they_count():
    schedule = StepSchedule(100, (0,), (1000.0,), phase_starts=(50,))
    times = [0.1] * 50 + [5.0, 5.0, 5.0] + [0.2] * 10  # the first steps of a phase are slow (caches, new kernels)
    estimate = TimeEstimate(schedule)
    feed(estimate, times)
    assert estimate.remaining() == pytest.approx((100 - len(times)) * 0.2)
    estimate = TimeEstimate(schedule)
    feed(estimate, times, upto=51)  # nothing settled yet: the settling step is all there is
    assert estimate.remaining() == pytest.approx(49 * 5.0)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(max_steps=0, stage_starts=(0,), stage_pixels=(1.0,)), "max_steps"),
        (dict(max_steps=10, stage_starts=(1,), stage_pixels=(1.0,)), "stage_starts"),
        (dict(max_steps=10, stage_starts=(0, 5), stage_pixels=(1.0,)), "stage_pixels"),
    ],
)
def test_bad_schedules_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        StepSchedule(**kwargs)


def test_format_duration():
    assert [format_duration(s) for s in (4.4, 75, 3725)] == ["4 s", "1 m 15 s", "1 h 02 m"]


def test_replay_of_recorded_traces(tmp_path):
    schedule = StepSchedule(200, (0, 100), (100.0, 400.0))
    times = [0.01] * 100 + [0.01 * 4 ** TimeEstimate(schedule).pixel_exponent] * 100
    record = {"id": "scene__full__200__s0", "step_trace": {"seconds": times, "gaussians": [500] * 200},
              "step_schedule": dataclasses.asdict(schedule)}  # fmt: skip
    (tmp_path / "runs").mkdir()
    (tmp_path / "runs" / "a.json").write_text(json.dumps(record))
    (tmp_path / "runs" / "old.json").write_text(json.dumps({"id": "old", "curve": []}))  # no trace: skipped
    records = load_traced_records(tmp_path)
    assert [r["id"] for r in records] == ["scene__full__200__s0"]
    row = replay(records[0])
    assert row["ours"][0.25] == pytest.approx(0.0, abs=1e-6)  # the model is exact here
    assert row["nerfstudio"][0.25] < -0.2  # nerfstudio's misses the full-resolution stage
    table = format_table([row])
    assert "scene__full__200__s0" in table and "Largest error of ours: 0 %" in table
    with pytest.raises(FileNotFoundError, match="no such folder"):
        load_traced_records(tmp_path / "missing")
