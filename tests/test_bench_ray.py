"""`gsmsdr-bench suite --ray` (gsmsdr_ns.bench.ray_runner): a tiny generated suite on a local Ray instance with 2
worker CPUs gets the serial runner's records (CPU training on 1 thread is bit-reproducible for a seed, so PSNR, SSIM
and the Gaussian counts must be equal, not close), survives Ctrl-C and resumes, and finishes every run when a
worker process is killed mid-run (the run is retried once and gets the same numbers). Real Ray, real trainings."""

from __future__ import annotations

import io
import os
import re
import signal
import textwrap
from pathlib import Path
from typing import Dict

import pytest
import ray
from rich.console import Console

from gsmsdr_ns.bench.cli import entrypoint
from gsmsdr_ns.bench.ledger import plan_runs
from gsmsdr_ns.bench.ray_runner import (
    RaySetupError,
    build_units,
    connect,
    makespan,
    parse_address,
    run_order,
    run_suite_on_ray,
)
from gsmsdr_ns.bench.records import load_record
from gsmsdr_ns.bench.runner import run_suite
from gsmsdr_ns.bench.suite_config import find_suite_file, load_suite

SUITE = """\
name: tiny-ray
scene_defaults: {{width: 64, height: 48, num_views: 10, hold: 5, num_points: 400, seed: 0}}
scenes: [motion, defocus]
methods: [{methods}]
steps: [12]
eval_every: 6
schedule: {{num_downscales: 0}}
threads: 1
lpips: false
scene_root: {scenes}
"""
"""Two scenes x plain, full and the sharp bound: 6 runs, 5 trainings (the sharp bound of both scenes is one)."""

NUMBERS = ("psnr", "ssim", "num_gaussians", "num_test_views")


def write_suite(folder: Path, methods: str = "plain, full, sharp") -> Path:
    path = folder / f"tiny-ray-{methods.replace(', ', '-')}.yaml"
    path.write_text(textwrap.dedent(SUITE.format(methods=methods, scenes=folder / "scenes")), encoding="utf8")
    return path


def records(out: Path) -> Dict[str, dict]:
    found = {p.stem: load_record(p) for p in (out / "runs").glob("*.json")}
    assert all(r is not None for r in found.values()), found  # every record file is a whole record
    return found  # type: ignore[return-value]


def leftovers(out: Path) -> list:
    """Temporary files or folders of atomic writes still in runs/ (there must be none)."""
    return [p.name for p in (out / "runs").iterdir() if p.name.startswith(".")]


@pytest.fixture(scope="module")
def local_ray():
    assert connect("local:2")  # this process becomes the driver of a local instance with 2 CPUs
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def serial_and_ray(tmp_path_factory: pytest.TempPathFactory, local_ray):
    """The suite run serially, then on Ray interrupted (Ctrl-C, as SIGINT after its first finished run) and run
    again to the end."""
    work = tmp_path_factory.mktemp("ray")
    suite = load_suite(write_suite(work))
    serial = run_suite(suite, work / "serial", progress=False, plots=False)
    # SIGINT as a terminal's Ctrl-C meets it: a shell that starts jobs in the background makes them ignore it
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            run_suite_on_ray(suite, work / "ray", progress=False, plots=False, interrupt_after=1)
    finally:
        signal.signal(signal.SIGINT, previous)
    kept, left_after_interrupt = records(work / "ray"), leftovers(work / "ray")
    resumed = run_suite_on_ray(suite, work / "ray", progress=False, plots=False)
    return dict(work=work, suite=suite, serial=serial, kept=kept, left_after_interrupt=left_after_interrupt,
                resumed=resumed)  # fmt: skip


def test_ray_records_equal_the_serial_ones(serial_and_ray) -> None:
    s = serial_and_ray
    serial, on_ray = records(s["work"] / "serial"), records(s["work"] / "ray")
    assert sorted(serial) == sorted(on_ray) == sorted(key.id for key in s["suite"].runs())
    assert len(s["serial"].trained) == 5 and s["serial"].copied == ["defocus__sharp__12__s0"]
    for run_id, record in serial.items():
        twin = on_ray[run_id]
        assert twin["fingerprint"] == record["fingerprint"], run_id
        assert twin.get("same_training_as") == record.get("same_training_as"), run_id
        for name in NUMBERS:
            assert twin[name] == record[name], (run_id, name, twin[name], record[name])
        assert [p["psnr"] for p in twin["curve"]] == [p["psnr"] for p in record["curve"]], run_id
        assert "executor" not in record
        source = on_ray[twin.get("same_training_as", run_id)]
        assert source["executor"]["kind"] == "ray" and source["executor"]["attempt"] == 1
    table = (s["work"] / "ray" / "results.md").read_text(encoding="utf8")
    assert "| GS-MSDR (full) |" in table and "runs: 6 of 6 finished" in table


def test_ctrl_c_keeps_finished_records_and_the_next_run_resumes(serial_and_ray) -> None:
    s = serial_and_ray
    assert 1 <= len(s["kept"]) < 6 and s["left_after_interrupt"] == []
    resumed = s["resumed"]
    assert set(resumed.reused) >= {run_id for run_id, r in s["kept"].items() if "same_training_as" not in r}
    assert len(resumed.trained) + len(resumed.reused) + len(resumed.copied) == 6 and not resumed.failed
    assert not set(resumed.trained) & set(s["kept"])  # nothing finished was trained again
    assert leftovers(s["work"] / "ray") == []


def test_a_killed_worker_is_retried_and_loses_nothing(serial_and_ray) -> None:
    s = serial_and_ray
    out = s["work"] / "fault"
    suite = load_suite(write_suite(s["work"], "full"))
    terminal = Console(file=io.StringIO(), force_terminal=True, width=200)  # the progress display, drawn
    outcome = run_suite_on_ray(suite, out, progress=True, plots=False, console=terminal,
                               kill_worker_at=("motion__full__12__s0", 5))  # fmt: skip
    assert not outcome.failed and len(outcome.trained) == 2
    shown = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", terminal.file.getvalue())  # the text, without colours
    assert "motion__full__12__s0: PSNR" in shown and "(attempt 2: its worker died before)" in shown, shown[-3000:]
    got, serial = records(out), records(s["work"] / "serial")
    assert sorted(got) == sorted(key.id for key in suite.runs())
    assert got["motion__full__12__s0"]["executor"]["attempt"] == 2  # killed once, retried once
    assert {r["executor"]["attempt"] for run_id, r in got.items() if run_id != "motion__full__12__s0"} == {1}
    for run_id, record in got.items():  # the retried run trained from the start: the same numbers
        assert [record[n] for n in NUMBERS] == [serial[run_id][n] for n in NUMBERS], run_id
    assert leftovers(out) == []


def test_scene_builds_are_grouped_by_what_they_share() -> None:
    real = load_suite(find_suite_file("real"))
    units = build_units(real, plan_runs(real, Path("/nonexistent")).todo)
    assert list(units) == ["real llff-fern-images_8 s0"]  # fern motion, defocus and sharp share one SfM of fern
    quick = load_suite(find_suite_file("quick"))
    units = build_units(quick, quick.runs())
    assert sorted(len(keys) for keys in units.values()) == [1, 1]  # the degraded scene and its sharp twin


def test_run_order_ends_the_runs_soonest() -> None:
    costs = [41.0, 87.0, 61.0, 66.0, 44.0]  # quick's plain, full, view, lite, sharp (s per run)
    longest_first = sorted(costs, reverse=True)
    assert makespan(longest_first, 2) == 66 + 61 + 41  # 87 | 66, 61 | 44 at 87 | 41 at 127
    order = run_order(costs, 2)
    assert sorted(order) == list(range(5))
    assert makespan([costs[i] for i in order], 2) == 151  # {87, 61} and {66, 44, 41}: the best split
    assert makespan(costs, 1) == sum(costs) and run_order([3.0], 4) == [0]


def test_a_local_instance_runs_its_tasks_at_the_drivers_priority(local_ray) -> None:
    """Ray starts workers at nice +15 unless told otherwise; a local instance's runs must not yield to every other
    busy process on the machine."""

    @ray.remote(num_cpus=1)
    def niceness() -> int:
        return os.nice(0)

    assert ray.get(niceness.remote(), timeout=600) == os.nice(0)


def test_ray_addresses() -> None:
    assert parse_address("local") == (None, None) and parse_address("local:2") == (None, 2)
    assert parse_address("auto") == ("auto", None) and parse_address("10.0.0.5:6379") == ("10.0.0.5:6379", None)
    for bad in ("local:0", "local:two", ""):
        with pytest.raises(RaySetupError, match="--ray"):
            parse_address(bad)


def test_without_ray_the_flag_says_how_to_install_it(tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.setitem(__import__("sys").modules, "ray", None)  # as if the extra were not installed
    with pytest.raises(SystemExit) as exit_info:
        entrypoint(["suite", "--config", str(write_suite(tmp_path)), "--out", str(tmp_path / "out"), "--ray", "local"])
    message = str(exit_info.value.code)
    assert message.count("\n") == 0 and "pip install 'gsmsdr-ns[ray]'" in message, message
    assert not (tmp_path / "out").exists()  # nothing started, nothing written
