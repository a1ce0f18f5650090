"""``gsmsdr-bench step``: training-step time and peak memory per method through nerfstudio's trainer, on a tiny
generated motion scene on the CPU (the GPU check runs the same command on CUDA)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch

from gsmsdr_ns.bench.cli import entrypoint
from gsmsdr_ns.bench.step_cost import COLUMNS, StepCostSpec, measure_step_cost


@pytest.fixture(scope="module")
def motion_scene(tmp_path_factory) -> Path:
    from gsmsdr_ns.bench.scenes import SceneSpec, ensure_scene

    spec = SceneSpec("motion", 40, 30, num_views=6, hold=6, num_points=200)
    return ensure_scene(tmp_path_factory.mktemp("step"), spec)


def test_the_command_times_every_method_and_writes_its_table(motion_scene, tmp_path, capsys):
    out = tmp_path / "out"
    threads = torch.get_num_threads()
    entrypoint(["step", "--data", str(motion_scene), "--methods", "plain", "full", "--warmup", "1", "--steps", "2",
                "--breakdown-steps", "1", "--threads", "2", "1", "--out", str(out),
                "--work-dir", str(tmp_path / "work")])  # fmt: skip
    assert torch.get_num_threads() == threads  # the measurement's thread count does not outlive it
    printed = capsys.readouterr().out
    assert "Command: `gsmsdr-bench step --data" in printed and "device cpu" in printed
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [(r["method"], r["threads"]) for r in rows] == [("plain", "1"), ("full", "1"), ("plain", "2"), ("full", "2")]
    assert list(rows[0]) == list(COLUMNS)
    for one, two in zip(rows[:2], rows[2:]):  # each method against its own 1-thread step, ratios per thread count
        assert float(one["speedup_vs_1_thread"]) == 1.0
        assert float(two["speedup_vs_1_thread"]) == pytest.approx(float(one["median_ms"]) / float(two["median_ms"]))
        assert float(two["ratio_to_first"]) == pytest.approx(float(two["median_ms"]) / float(rows[2]["median_ms"]))
    plain, full = rows[:2]
    assert float(plain["ratio_to_first"]) == 1.0
    assert float(full["ratio_to_first"]) == pytest.approx(float(full["median_ms"]) / float(plain["median_ms"]))
    for r in rows:  # one round: the median of one round is the mean
        assert r["rounds"] == "1" and float(r["median_ms"]) == pytest.approx(float(r["step_ms"]))
    assert all(float(r["step_ms"]) > 0 for r in rows)
    # 5 training views, all motion-blurred: plain models none of them, full every one
    assert plain["blurred_views"] == "0/5" and full["blurred_views"] == "5/5"
    assert plain["size"] == "40x30" and plain["steps"] == "2" and plain["device"] == "cpu"
    assert "blur_field=0.00" in plain["breakdown_ms"] and "blur_field=0.00" not in full["breakdown_ms"]
    table = (out / "results.md").read_text()
    assert "| plain | " in table and "| full | " in table and "Time breakdown" in table


def test_rounds_split_the_timed_steps_and_the_methods_take_turns(motion_scene, tmp_path, monkeypatch):
    from gsmsdr_ns.bench import step_cost
    from gsmsdr_ns.bench.training import InProcessRun

    order = []
    train = InProcessRun.train

    def recording_train(self, num_steps):
        order.append((self.trainer.config.experiment_name, num_steps))
        return train(self, num_steps)

    monkeypatch.setattr(InProcessRun, "train", recording_train)
    specs = [StepCostSpec(m, motion_scene, warmup=1, steps=3, threads=1) for m in ("plain", "full")]
    rows = step_cost.run_step_cost(specs, tmp_path / "work", rounds=2)
    # warm-ups, then rounds of 2 and 1 timed steps in turn
    assert order == [("step-plain", 1), ("step-full", 1), ("step-plain", 2), ("step-full", 2), ("step-plain", 1),
                     ("step-full", 1)]  # fmt: skip
    for r in rows:
        assert r["rounds"] == 2 and r["steps"] == 3 and float(r["median_ms"]) > 0
    assert rows[1]["ratio_to_first"] == pytest.approx(rows[1]["median_ms"] / rows[0]["median_ms"])
    assert step_cost._round_sizes(10, 4) == [3, 3, 2, 2] and step_cost._round_sizes(2, 5) == [1, 1]
    with pytest.raises(ValueError, match="share a thread count"):
        step_cost.measure_step_costs([StepCostSpec("plain", motion_scene, threads=1),
                                      StepCostSpec("full", motion_scene, threads=2)], tmp_path)  # fmt: skip


def test_no_estimate_trains_images_without_records_with_the_blur_field(motion_scene, tmp_path):
    import shutil

    scene = tmp_path / "no-records"
    shutil.copytree(motion_scene, scene)
    (scene / "degradation.json").unlink()
    row = measure_step_cost(StepCostSpec("full", scene, warmup=1, steps=1, estimate=False), tmp_path / "work")
    assert row["blurred_views"] == "5/5" and row["records"].startswith("scene's, else none")


def test_bad_step_counts_are_refused(motion_scene, tmp_path):
    with pytest.raises(ValueError, match="warmup and steps must be >= 1"):
        measure_step_cost(StepCostSpec("plain", motion_scene, warmup=0, steps=1), tmp_path)


def test_field_ops_bench_times_each_op_and_its_twin(capsys):
    threads = torch.get_num_threads()
    entrypoint(["field-ops", "--width", "40", "--height", "30", "--kernel-size", "5", "--repeats", "2"])
    assert torch.get_num_threads() == threads  # its 1-thread default does not outlive it
    printed = capsys.readouterr().out
    assert "Command: `gsmsdr-bench field-ops --width 40" in printed and "C++ ops built for" in printed
    rows = [line for line in printed.splitlines() if line.startswith("| ") and "---" not in line][1:]
    cpp = [r for r in rows if "| cpp |" in r]
    torch_rows = [r for r in rows if "| torch |" in r]
    assert len(cpp) == 3 + 5 and len(torch_rows) == 1 + 5  # grid op: 3 parts / one twin; 5 depthwise layers each
    assert "[1, 16, 8, 10]" in printed  # the feature grid of a 40x30 render in cells of 4 px
    assert all(float(r.split("|")[4]) > 0 for r in rows)
