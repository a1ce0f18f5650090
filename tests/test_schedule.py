"""The one training schedule (``gsmsdr_ns.plugin.schedule.TrainingSchedule``): its bench and demo presets set the
step-dependent settings of a real gsmsdr TrainerConfig to the values the bench suites and the demo have always used,
and the demo's config is exactly the demo preset applied to the gsmsdr-lite preset."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from gsmsdr_ns.bench.methods import method_spec
from gsmsdr_ns.demo import demo_trainer_config
from gsmsdr_ns.plugin.method_config import (
    CPU_SCHEDULE,
    LITE_MAX_STEPS,
    gsmsdr_cpu_trainer_config,
    gsmsdr_lite_trainer_config,
    gsmsdr_trainer_config,
)
from gsmsdr_ns.plugin.schedule import TrainingSchedule


def _settings(config) -> dict:
    model = config.pipeline.model
    names = ("num_downscales", "resolution_schedule", "stop_split_at", "refine_every", "warmup_length",
             "stop_screen_size_at", "reset_alpha_every", "densify_grad_thresh", "sh_degree_interval")  # fmt: skip
    out = {name: getattr(model, name) for name in names}
    out["blur_warmup"] = model.degradation_model.warmup
    out["max_num_iterations"] = config.max_num_iterations
    out["steps_per_save"] = config.steps_per_save
    for group in ("means", "camera_opt", "bilateral_grid"):
        scheduler = config.optimizers[group]["scheduler"]
        out[f"{group}_lr"] = (scheduler.max_steps, scheduler.warmup_steps)
    return out


def test_bench_preset_values() -> None:
    config = gsmsdr_trainer_config()
    TrainingSchedule.bench(1000).apply(config)
    assert _settings(config) == dict(
        num_downscales=1, resolution_schedule=500, stop_split_at=500, refine_every=33, warmup_length=33,
        stop_screen_size_at=133, reset_alpha_every=10**6, densify_grad_thresh=0.002, sh_degree_interval=250,
        blur_warmup=50, max_num_iterations=1000, steps_per_save=1000, means_lr=(1000, 0), camera_opt_lr=(1000, 100),
        bilateral_grid_lr=(1000, 100),
    )  # fmt: skip


def test_demo_preset_values(tmp_path: Path) -> None:
    config = demo_trainer_config(tmp_path, tmp_path / "out", 1500, "cpu")
    preset = gsmsdr_lite_trainer_config()
    assert _settings(config) == dict(
        num_downscales=2, resolution_schedule=500, stop_split_at=750, refine_every=100, warmup_length=150,
        stop_screen_size_at=preset.pipeline.model.stop_screen_size_at, reset_alpha_every=1000,
        densify_grad_thresh=0.002, sh_degree_interval=375, blur_warmup=75, max_num_iterations=1500,
        steps_per_save=1500, means_lr=(1500, 0), camera_opt_lr=(LITE_MAX_STEPS, 1000),
        bilateral_grid_lr=(LITE_MAX_STEPS, 1000),
    )  # fmt: skip
    assert config.machine.device_type == "cpu" and config.experiment_name == "demo"


def test_cpu_preset_is_mode_view_on_the_real_size_suites_schedule(tmp_path: Path) -> None:
    """gsmsdr-cpu = the gsmsdr preset with one kernel per view (9 / 17 / 33 px) after a camera path (with the
    render margin; rotations, and translations relative to the median depth), trained on the real-size suite's
    schedule at 6000 steps with an SH degree every 1000 steps; so a suite with that schedule trains the preset as
    ns-train does in its `gsmsdr-cpu` rows (`view-k33`'s field, `cpu-shake-parallax`'s model)."""
    assert CPU_SCHEDULE.steps == 6000 and CPU_SCHEDULE.sh_degree_fraction * CPU_SCHEDULE.steps == 1000
    from gsmsdr_ns.bench.suite_config import find_suite_file, load_suite

    config = gsmsdr_cpu_trainer_config()
    field, degradation = config.pipeline.model.blur_field, config.pipeline.model.degradation_model
    assert config.method_name == "gsmsdr-cpu" and field.mode == "view" and field.kernel_sizes == (9, 17, 33)
    assert degradation.camera_shake and degradation.render_margin
    assert degradation.shake_translation and degradation.shake_parallax
    expected = gsmsdr_trainer_config()
    expected.pipeline.model.blur_field = field
    expected.pipeline.model.degradation_model = degradation
    suite = load_suite(find_suite_file("real-size"))
    schedule = dataclasses.replace(suite.schedule_for(CPU_SCHEDULE.steps), sh_degree_fraction=1 / 6)
    schedule.apply(expected)
    assert _settings(config) == _settings(expected)
    assert repr(config.pipeline.model) == repr(expected.pipeline.model)
    as_bench = method_spec("gsmsdr-cpu").make_config(tmp_path, tmp_path / "out")
    schedule.apply(as_bench)
    assert _settings(as_bench) == _settings(config) and as_bench.pipeline.model.blur_field == field
    view = method_spec("view-k33").make_config(tmp_path, tmp_path / "out")
    assert view.pipeline.model.blur_field == field
    shake = method_spec("cpu-shake-parallax").make_config(tmp_path, tmp_path / "out")
    schedule.apply(shake)
    assert repr(as_bench.pipeline.model) == repr(shake.pipeline.model)


@pytest.mark.parametrize("steps", [2, 7, 100, 999, 1000, 1500, 3001, 7000])
def test_demo_config_is_the_demo_preset(tmp_path: Path, steps: int) -> None:
    """Only the preset's fields separate the demo's schedule from the bench's: applying the demo preset to the
    gsmsdr-lite preset gives the demo's model and optimizers."""
    demo = demo_trainer_config(tmp_path, tmp_path / "out", steps, "auto")
    config = gsmsdr_lite_trainer_config()
    TrainingSchedule.demo(steps).apply(config)
    assert repr(config.pipeline.model) == repr(demo.pipeline.model)
    assert repr(sorted(config.optimizers.items())) == repr(sorted(demo.optimizers.items()))
    bench = gsmsdr_lite_trainer_config()
    TrainingSchedule.bench(steps).apply(bench)
    if steps >= 30:
        assert repr(bench.pipeline.model) != repr(demo.pipeline.model)


@pytest.mark.parametrize(
    "kwargs,message",
    [
        (dict(steps=0), "steps"),
        (dict(steps=10, refinements=0), "refinements"),
        (dict(steps=10, resolution_fraction=1.5), "resolution_fraction"),
        (dict(steps=10, densify_warmup_fraction=-0.1), "densify_warmup_fraction"),
        (dict(steps=10, num_downscales=-1), "num_downscales"),
        (dict(steps=10, lr_decay_fraction=0.0), "lr_decay_fraction"),
        (dict(steps=10, sh_degree_fraction=1.5), "sh_degree_fraction"),
    ],
)
def test_invalid_schedule_names_the_field(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        TrainingSchedule(**kwargs)


def test_decay_fraction_reaches_the_final_rate_early_and_holds_it() -> None:
    """``lr_decay_fraction`` 0.75: the means' rate (nerfstudio's scheduler, as the trainer builds it) is at its
    final value from three quarters of the steps on, and above it before; the SH degrees unlock at
    ``sh_degree_fraction`` of the steps."""
    import torch

    config = gsmsdr_trainer_config()
    TrainingSchedule.bench(1000, lr_decay_fraction=0.75, sh_degree_fraction=0.1).apply(config)
    assert config.pipeline.model.sh_degree_interval == 100
    group = config.optimizers["means"]
    assert group["scheduler"].max_steps == 750 and config.optimizers["camera_opt"]["scheduler"].warmup_steps == 75
    optimizer = torch.optim.Adam([torch.zeros(1, requires_grad=True)], lr=group["optimizer"].lr)
    scheduler = group["scheduler"].setup().get_scheduler(optimizer, group["optimizer"].lr)
    rates = []
    for _ in range(1000):
        rates.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    final = group["scheduler"].lr_final
    assert rates[0] == pytest.approx(group["optimizer"].lr)
    assert rates[700] > 1.2 * final
    assert rates[750] == pytest.approx(final) and rates[999] == pytest.approx(final)


def test_late_decay_holds_the_rate_then_decays_to_its_final_one(tmp_path: Path) -> None:
    """``cpu-late-decay`` at a 1000-step suite schedule: the shake paths' rate (the scheduler as nerfstudio's
    optimizers build it) stays at the preset's for 0.6 of the steps, then falls exponentially to 1 / 100 of it at
    the last step, and a hold outside [0, 1) is refused."""
    import torch

    from gsmsdr_ns.plugin.lr_schedulers import HeldExponentialDecaySchedulerConfig

    config = method_spec("cpu-late-decay").make_config(tmp_path, tmp_path / "out")
    TrainingSchedule.bench(1000).apply(config)
    group = config.optimizers["blur_shake"]
    lr = group["optimizer"].lr
    optimizer = torch.optim.Adam([torch.zeros(1, requires_grad=True)], lr=lr)
    scheduler = group["scheduler"].setup().get_scheduler(optimizer, lr)
    rates = []
    for _ in range(1100):
        rates.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    assert rates[0] == rates[600] == pytest.approx(lr)
    assert rates[601] < lr and rates[800] == pytest.approx(lr / 10, rel=1e-6)
    assert all(a > b for a, b in zip(rates[600:1000], rates[601:1001]))
    assert rates[1000] == rates[1099] == pytest.approx(lr / 100)
    with pytest.raises(ValueError, match="hold_fraction"):
        HeldExponentialDecaySchedulerConfig(hold_fraction=1.0)
