"""results.md of a suite trained with several seeds: seed means, each method's lowest and highest PSNR over the
seeds, and the per-seed gap to plain (paired by seed). Records written by hand in the runner's format."""

from __future__ import annotations

from pathlib import Path

from test_bench_suite import TINY_SUITE

from gsmsdr_ns.bench.report import aggregate, format_markdown
from gsmsdr_ns.bench.suite_config import load_suite

SUITE = TINY_SUITE.replace("name: tiny", "name: seeds") + "seeds: [0, 1, 2]\n"  # plain and full, 20 steps

# (method, seed) -> PSNR: full gains +1.0, +2.0 and +0.5 over plain at seeds 0, 1, 2
PSNR = {("plain", 0): 20.0, ("plain", 1): 21.0, ("plain", 2): 22.0,
        ("full", 0): 21.0, ("full", 1): 23.0, ("full", 2): 22.5}  # fmt: skip


def _record(method: str, seed: int) -> dict:
    return {"suite": "seeds", "scene": "motion", "method": method, "steps": 20, "seed": seed,
            "psnr": PSNR[(method, seed)], "ssim": 0.5, "lpips": float("nan"), "train_seconds": 1.0, "step_ms": 50.0,
            "peak_rss_mb": 100.0, "peak_cuda_mb": float("nan"), "num_gaussians": 400, "eval_seconds": 0.1,
            "breakdown": {}}  # fmt: skip


def test_seed_spread_and_paired_gaps(tmp_path: Path) -> None:
    path = tmp_path / "seeds.yaml"
    path.write_text(SUITE, encoding="utf8")
    suite = load_suite(path)
    records = [_record(m, s) for (m, s) in PSNR]
    agg = aggregate(records)
    full = agg[(20, "motion", "full")]
    assert full["seeds"] == 3 and abs(full["psnr"] - 22.1666667) < 1e-6
    assert (full["psnr_min"], full["psnr_max"]) == (21.0, 23.0)

    text = format_markdown(suite, records)
    full_row = next(line for line in text.splitlines() if line.startswith("| GS-MSDR (full) | 22.17"))
    assert full_row.rstrip(" |").endswith("| 3 | 21.00 - 23.00")
    gaps = text[text.index("## Gaps") :].splitlines()
    gap_row = next(line for line in gaps if line.startswith("| motion | GS-MSDR (full) |"))
    cells = [c.strip() for c in gap_row.strip("|").split("|")]
    assert cells[2] == "+1.17"  # difference of the seed means
    assert cells[-1] == "+0.50 .. +2.00"  # paired by seed, not the spread of the means


def test_the_header_names_a_packaged_suite_by_its_configs_path_from_any_working_directory(tmp_path, monkeypatch):
    from gsmsdr_ns.bench.suite_config import find_suite_file

    packaged = load_suite(find_suite_file("quick"))
    records = [_record(m, s) for (m, s) in PSNR]
    monkeypatch.chdir(tmp_path)  # outside the checkout: the packaged file is not under the working directory
    assert "- suite: `configs/bench/quick.yaml`" in format_markdown(packaged, records)
    own = tmp_path / "mine" / "seeds.yaml"  # a suite file of the user's: relative to the working directory
    own.parent.mkdir()
    own.write_text(SUITE, encoding="utf8")
    assert "- suite: `mine/seeds.yaml`" in format_markdown(load_suite(own), records)
    elsewhere = tmp_path.parent / f"{tmp_path.name}-other"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)  # neither: the path as given
    assert f"- suite: `{own}`" in format_markdown(load_suite(own), records)


def test_the_header_says_at_which_commits_reused_records_were_trained(tmp_path):
    path = tmp_path / "seeds.yaml"
    path.write_text(SUITE, encoding="utf8")
    suite = load_suite(path)
    machine = {"cpu": "AMD EPYC", "cores": 2, "torch": "2.14.1", "torch_threads": 1, "device": "cpu", "git": "bbbbbbb"}
    records = [dict(_record(m, s), machine=dict(machine, git="aaaaaaa" if s else "bbbbbbb")) for (m, s) in PSNR]
    text = format_markdown(suite, records, machine=machine)
    assert "git bbbbbbb" in text and "- runs trained at git aaaaaaa (4), bbbbbbb (2)" in text
    same = [dict(r, machine=machine) for r in records]  # every run trained by the code that writes the table
    assert "runs trained at git" not in format_markdown(suite, same, machine=machine)


def test_records_name_the_commit_the_process_imported(monkeypatch):
    """A suite imports its code once: a checkout that moves on while it trains does not change its records' commit."""
    import gsmsdr_ns.bench.machine as machine

    monkeypatch.setattr(machine, "git_revision", lambda: "moved-on")
    assert machine.machine_info()["git"] == machine.GIT_AT_IMPORT != "moved-on"


def test_against_wall_time_compares_with_plain_after_the_same_training_time(tmp_path: Path) -> None:
    """plain reaches 20 dB at 10 s and 22 at 20 s; full trains 15 s to 23 dB: plain after 15 s is 21 dB (+2.00). A
    method training longer than plain is compared with plain's last value, marked *. The last quarter of the steps
    (15 -> 20) gained 1.0 dB. view's first half of the steps took a quarter of its time: its last quarter of the steps
    gained 1.25 dB, of the time (30 s -> 40 s) 0.83 dB."""
    path = tmp_path / "time.yaml"
    path.write_text(TINY_SUITE.replace("methods: [plain, full]", "methods: [plain, full, view]"), encoding="utf8")
    suite = load_suite(path)

    def record(method: str, seconds: float, curve) -> dict:
        points = [{"step": st, "seconds": sec, "psnr": p} for st, sec, p in curve]
        return {**_record("plain", 0), "suite": "tiny", "method": method, "psnr": curve[-1][2],
                "train_seconds": seconds, "setup_seconds": 3.0, "eval_seconds": 6.0, "curve": points}  # fmt: skip

    records = [record("plain", 20.0, [(0, 0.0, 10.0), (10, 10.0, 20.0), (20, 20.0, 22.0)]),
               record("full", 15.0, [(0, 0.0, 10.0), (10, 7.5, 21.0), (20, 15.0, 23.0)]),
               record("view", 40.0, [(0, 0.0, 10.0), (10, 10.0, 21.0), (20, 40.0, 23.5)])]  # fmt: skip
    text = format_markdown(suite, records)
    rows = text[text.index("## Against wall time") :].splitlines()
    full = [c.strip() for c in next(r for r in rows if "| GS-MSDR (full) |" in r).strip("|").split("|")]
    assert full[2:] == ["0.2", "0.4", "23.00", "21.00", "+2.00", "+1.00", "+1.00"]
    view = [c.strip() for c in next(r for r in rows if "(mode view) |" in r).strip("|").split("|")]
    assert view[5:] == ["22.00 *", "+1.50", "+1.25", "+0.83"]
    assert "## Against wall time" not in format_markdown(suite, [_record("plain", 0)])  # no curves: no table
