"""The warm-start diagnostic (``tools.shake.warm_start``): the bound's Gaussians moved into a blur model on the shaken
twin, at a later step of the schedule. A tiny generated scene and its sharp twin on disk, the real nerfstudio
trainer, a few dozen steps."""

from __future__ import annotations

import json
from pathlib import Path

import torch
import yaml

from tools.shake.warm_start import WarmStart, fast_forward_schedulers, with_gaussians

STEPS = 40
START = 30


def write_suite(folder: Path) -> Path:
    suite = {
        "name": "warm-start-test",
        "scene_defaults": {"width": 64, "height": 48, "num_views": 8, "hold": 4, "num_points": 200, "seed": 0},
        "scenes": [{"name": "tiny", "variant": "motion-strong"}],
        "methods": ["cpu-shake-true-paths"],
        "steps": [STEPS],
        "schedule": {"num_downscales": 1, "densify_grad_thresh": 0.002},
        "threads": 1,
        "scene_root": str(folder / "scenes-root"),
    }
    path = folder / "suite.yaml"
    path.write_text(yaml.safe_dump(suite))
    return path


def test_the_warm_start_begins_at_the_bounds_scene_and_reuses_its_gaussians(tmp_path, capsys) -> None:
    suite, out = write_suite(tmp_path), tmp_path / "out"
    WarmStart(suite=suite, out=out, start_step=START, eval_every=5).main()
    bound = torch.load(out / "bound.pt", map_location="cpu")
    result = json.loads((out / "warm_start-cpu-shake-true-paths.json").read_text())
    curve = result["curve"]
    assert [p["step"] for p in curve] == [30, 35, 40]
    first = curve[0]
    # the same Gaussians in the same frame render the same sharp test views
    assert abs(first["psnr"] - bound["psnr"]) < 1e-4
    assert first["psnr_views"] == bound["psnr_views"]
    count = bound["gaussians"]["gauss_params.means"].shape[0]
    assert all(p["num_gaussians"] == count for p in curve)  # past the end of densification
    assert "train_psnr" in first and "train_psnr" in curve[-1]
    assert all(torch.isfinite(torch.tensor([p["psnr"] for p in curve])))

    # a second call trains no bound: it reads bound.pt, and the start is the same
    stamp = (out / "bound.pt").stat().st_mtime_ns
    WarmStart(suite=suite, out=out, start_step=START, eval_every=10).main()
    again = json.loads((out / "warm_start-cpu-shake-true-paths.json").read_text())["curve"]
    assert (out / "bound.pt").stat().st_mtime_ns == stamp
    assert abs(again[0]["psnr"] - first["psnr"]) < 1e-4
    assert "| 30 |" in capsys.readouterr().out


def test_schedulers_fast_forwarded_match_schedulers_stepped() -> None:
    from nerfstudio.engine.optimizers import AdamOptimizerConfig, Optimizers
    from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig

    def make() -> Optimizers:
        config = {"means": {"optimizer": AdamOptimizerConfig(lr=1e-2),
                            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=100)}}  # fmt: skip
        return Optimizers(config, {"means": [torch.nn.Parameter(torch.zeros(3))]})

    stepped, forwarded = make(), make()
    for _ in range(37):
        stepped.optimizers["means"].step()
        stepped.schedulers["means"].step()
    fast_forward_schedulers(forwarded, 37)
    lr = forwarded.optimizers["means"].param_groups[0]["lr"]
    assert abs(lr - stepped.optimizers["means"].param_groups[0]["lr"]) < 1e-12
    assert lr < 1e-2


def test_with_gaussians_replaces_only_the_gaussians_and_names_what_is_missing() -> None:
    state = {"gauss_params.means": torch.zeros(2, 3), "degradation.kernel": torch.ones(1)}
    merged = with_gaussians(state, {"gauss_params.means": torch.ones(5, 3), "other": torch.zeros(1)})
    assert merged["gauss_params.means"].shape == (5, 3) and "other" not in merged
    assert torch.equal(merged["degradation.kernel"], torch.ones(1))
    try:
        with_gaussians(state, {})
    except ValueError as error:
        assert "gauss_params.means" in str(error)
    else:
        raise AssertionError("a bound without means must be refused")
