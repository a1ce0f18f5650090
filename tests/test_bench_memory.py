"""`gsmsdr-bench memory` (gsmsdr_ns.bench.memory): argument parsing, the measuring child processes (a real one, and
one over its address-space limit) and the merged results files."""

from __future__ import annotations

import csv

import pytest

from gsmsdr_ns.bench.cli import entrypoint
from gsmsdr_ns.bench.memory import format_table, measure, merge_rows, parse_overrides, parse_size
from gsmsdr_ns.bench.timing import rss_resolution_mb


def test_sizes_and_overrides_parse_and_bad_ones_name_the_fix():
    assert parse_size("1297x840") == (1297, 840)
    with pytest.raises(ValueError, match="WIDTHxHEIGHT"):
        parse_size("600 by 400")
    assert parse_overrides(["mode=view", "size=lite", "kernel_sizes=[5, 9]", "gaka=false", "switch_steps=None"]) == {
        "mode": "view", "size": "lite", "kernel_sizes": (5, 9), "gaka": False, "switch_steps": None,
    }  # fmt: skip
    with pytest.raises(ValueError, match="no blur-field or degradation option 'feature_dim_typo'; options: mode, size"):
        parse_overrides(["feature_dim_typo=2"])
    with pytest.raises(ValueError, match="expected key=value"):
        parse_overrides(["mode"])


def test_merged_rows_replace_the_same_configuration_and_keep_the_others():
    old = [dict(size="600x400", lens="fused", field="default", v=1), dict(size="600x400", lens="unfused",
                                                                           field="default", v=2)]  # fmt: skip
    new = [dict(size="600x400", lens="fused", field="default", v=3), dict(size="600x400", lens="fused",
                                                                         field="size=lite", v=4)]  # fmt: skip
    assert [r["v"] for r in merge_rows(old, new)] == [3, 2, 4]


def test_a_run_over_the_limit_is_reported_not_fatal():
    spec = dict(width=30000, height=30000, kernel_size=9, lens="fused", overrides={"mode": "view",
                "kernel_sizes": (5, 9)}, field=True, limit_bytes=5 * 2**30, threads=1)  # fmt: skip
    result = measure(spec, timeout_s=600)
    assert result["status"] == "> limit", result
    assert "can't allocate memory" in result["error"]


def test_the_command_measures_in_fresh_processes_and_merges_its_results(tmp_path, capsys):
    out = tmp_path / "memory"
    common = ["--sizes", "40x24", "--kernel-size", "9", "--set", "mode=view", "--set", "kernel_sizes=(5,9)",
              "--threads", "1", "--out", str(out)]  # fmt: skip
    entrypoint(["memory", "--lens", "fused", "unfused", "--no-field", *common])
    printed = capsys.readouterr().out
    assert "| 40x24 | fused | none |" in printed and "| 40x24 | unfused | none |" in printed
    entrypoint(["memory", "--lens", "fused", *common])  # the field after the lens: a third row
    with open(out / "results.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["lens"], r["field"]) for r in rows] == [
        ("fused", "none"), ("unfused", "none"), ("fused", "mode=view kernel_sizes=(5, 9)"),
    ]  # fmt: skip
    slack = rss_resolution_mb()  # a 40x24 step touches almost nothing: its extra peak is 0 to the counters' resolution
    for row in rows:
        assert row["status"] == "ok" and float(row["extra_peak_mb"]) >= -slack and float(row["forward_s"]) > 0, row
        assert float(row["extra_peak_mb"]) < 64, row
        assert row["method"] in ("VmHWM after clear_refs", "ru_maxrss")
    markdown = (out / "results.md").read_text()
    assert "gsmsdr-bench memory --lens fused --sizes 40x24" in markdown and markdown.count("| 40x24 |") == 3
    with pytest.raises(SystemExit, match="no blur-field or degradation option 'nope'"):
        entrypoint(["memory", "--set", "nope=1", "--out", str(out)])


def test_extra_peak_memory_counts_what_the_span_touched_from_the_resident_set_at_the_reset():
    import numpy as np

    from gsmsdr_ns.bench.timing import PeakMemory

    peak = PeakMemory()
    for _ in range(20):  # nothing allocated: 0 to the resolution (the baseline and the peak share one counter)
        peak.reset()
        assert abs(peak.extra_rss_mb()) <= rss_resolution_mb(), (peak.baseline_mb, peak.peak_rss_mb())
    peak.reset()
    touched = np.ones(64 * 2**20 // 8)  # 64 MiB, every page written
    assert peak.extra_rss_mb() >= 60, (peak.baseline_mb, peak.peak_rss_mb())
    del touched


def test_the_table_shows_a_read_within_the_counters_resolution_below_zero_as_zero():
    row = dict(size="40x24", lens="fused", field="none", status="ok", extra_peak_mb="-0.23828125", forward_s="0.01",
               backward_s="0.02", setup_rss_mb="400", setup_vm_mb="3000", limit_gb="10")  # fmt: skip
    over = dict(row, status="> limit", extra_peak_mb="")
    table = format_table([row, dict(row, lens="unfused", extra_peak_mb="12.6"), over])
    assert "| 40x24 | fused | none | 0 | 0.01 |" in table and "| 40x24 | unfused | none | 13 |" in table
    assert "| 40x24 | fused | none | > 10 GB |" in table
    assert 0.25 <= rss_resolution_mb() < 64
