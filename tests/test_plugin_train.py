"""The real nerfstudio CLI on CPU: ns-train lists and trains gsmsdr, ns-eval and resume load its checkpoints."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys

import pytest
import torch
from conftest import TRAIN_FLAGS, TrainedRun, run_cli

import gsmsdr_ns.plugin  # noqa: F401  (allow-lists the checkpoint's numpy scalars for torch.load)


def checkpoint_of(run_dir_or_models, step: int):
    return run_dir_or_models / f"step-{step:09d}.ckpt"


def scalars(run: TrainedRun, tag: str):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run.run_dir))
    events.Reload()
    return [(event.step, event.value) for event in events.Scalars(tag)]


def test_ns_train_help_lists_gsmsdr(monkeypatch, capsys):
    """ns-train's entry point (what the console script calls) in this process: one interpreter start fewer; the
    session's ``trained_run`` already runs the console script itself."""
    from nerfstudio.scripts.train import entrypoint

    monkeypatch.setenv("COLUMNS", "200")
    monkeypatch.setattr(sys, "argv", ["ns-train", "--help"])
    with pytest.raises(SystemExit) as exited:
        entrypoint()
    out = capsys.readouterr().out
    assert exited.value.code == 0, out[-3000:]
    assert re.search(r"\bgsmsdr\b", out)
    assert "GS-MSDR" in out


def test_training_reduces_the_loss(trained_run):
    losses = [value for _, value in scalars(trained_run, "Train Loss")]
    assert len(losses) >= 10 and all(math.isfinite(v) for v in losses)
    first, last = sum(losses[:3]) / 3, sum(losses[-3:]) / 3
    assert last < 0.8 * first, losses


def test_ns_train_logs_the_schedule_aware_time_estimate(trained_run):
    """The "ETA (time)" scalar is GSMSDRTrainer's estimate (plugin/time_estimate.py), not nerfstudio's (the steps
    left times the logged mean step time) at the logged steps, and falls as the run goes on."""
    eta = scalars(trained_run, "ETA (time)")
    iter_time = dict(scalars(trained_run, "Train Iter (time)"))
    assert len(eta) >= 10 and all(math.isfinite(v) and v >= 0 for _, v in eta), eta
    nerfstudio = {step: (trained_run.steps - step) * iter_time[step] for step, _ in eta if step in iter_time}
    assert sum(1 for step, v in eta if step in nerfstudio and v != pytest.approx(nerfstudio[step])) >= len(eta) // 2
    assert eta[-1][1] < eta[1][1]


def test_training_densifies_and_prunes(trained_run):
    """gsplat's DefaultStrategy logs each refinement; both growth and pruning must have happened."""
    grown = [int(a) + int(b) for a, b in re.findall(r"(\d+) GSs duplicated, (\d+) GSs split", trained_run.log)]
    pruned = [int(n) for n in re.findall(r"(\d+) GSs pruned", trained_run.log)]
    assert sum(grown) > 0, trained_run.log[-3000:]
    assert sum(pruned) > 0, trained_run.log[-3000:]
    final_count = int(re.findall(r"Now having (\d+) GSs", trained_run.log)[-1])
    state = torch.load(checkpoint_of(trained_run.checkpoint_dir, trained_run.steps - 1), map_location="cpu")
    assert state["pipeline"]["_model.gauss_params.means"].shape[0] == final_count
    counts = {value for _, value in scalars(trained_run, "Train Metrics Dict/gaussian_count")}
    assert len(counts) > 1


def test_checkpoint_loads_with_weights_only(trained_run):
    """In a fresh interpreter: what torch's default weights_only=True refuses, and that the plugin import fixes it."""
    ckpt = checkpoint_of(trained_run.checkpoint_dir, trained_run.steps - 1)
    code = f"""
import json, torch
unsafe = torch.serialization.get_unsafe_globals_in_checkpoint({str(ckpt)!r})
try:
    torch.load({str(ckpt)!r}); without_plugin = "loaded"
except Exception as err:
    without_plugin = type(err).__name__
import gsmsdr_ns.plugin
print(json.dumps({{"unsafe": unsafe, "without_plugin": without_plugin, "step": torch.load({str(ckpt)!r})["step"]}}))
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    # nerfstudio's LR schedulers leave numpy float64 scalars in the optimizer / scheduler state: nothing else
    assert result["unsafe"] and all(name.startswith("numpy.") for name in result["unsafe"]), result
    assert result["without_plugin"] == "UnpicklingError"
    assert result["step"] == trained_run.steps - 1


def test_ns_eval_writes_psnr_and_ssim(trained_run, tmp_path):
    output = tmp_path / "eval.json"
    proc = run_cli("ns-eval", ["--load-config", trained_run.config, "--output-path", output], cwd=tmp_path)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    report = json.loads(output.read_text())
    assert report["method_name"] == "gsmsdr"
    results = report["results"]
    assert 10.0 < results["psnr"] < 60.0
    assert 0.0 < results["ssim"] <= 1.0
    assert results["fps"] > 0


def test_resume_keeps_training_the_loaded_gaussians(trained_run, tmp_path):
    """--load-dir: the optimizers must step the loaded parameters (refinement is off, so nothing re-links them)."""
    extra = 10
    args = ["gsmsdr", "--data", trained_run.scene, "--output-dir", tmp_path / "outputs", "--timestamp", "resumed",
            "--load-dir", trained_run.checkpoint_dir, "--max-num-iterations", extra, "--steps-per-save", 1000,
            *TRAIN_FLAGS, "--pipeline.model.stop-split-at", 0]  # fmt: skip
    proc = run_cli("ns-train", args, cwd=tmp_path)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]
    assert "Done loading Nerfstudio checkpoint" in log
    before = torch.load(checkpoint_of(trained_run.checkpoint_dir, trained_run.steps - 1), map_location="cpu")
    models = tmp_path / "outputs" / trained_run.scene.name / "gsmsdr" / "resumed" / "nerfstudio_models"
    after = torch.load(checkpoint_of(models, trained_run.steps - 1 + extra), map_location="cpu")
    means_before = before["pipeline"]["_model.gauss_params.means"]
    means_after = after["pipeline"]["_model.gauss_params.means"]
    assert means_after.shape == means_before.shape
    assert not torch.equal(means_after, means_before), "resumed training did not update the loaded Gaussians"
    assert torch.isfinite(means_after).all()
