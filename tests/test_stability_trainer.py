"""Numerical stability of a real nerfstudio ``Trainer``: it stops with ``NonFiniteLossError`` naming the step when
a NaN reaches the loss (a NaN pixel in a training image, a NaN opacity) or the Gaussian parameters, and survives a
one-step learning-rate spike with finite parameters. (``test_plugin_model`` covers the model-level NaN guard on a
bare model.)
"""

from __future__ import annotations

from pathlib import Path
from typing import List

import pytest
import torch
from conftest import cpu_trainer_config
from stability_common import all_finite, single_thread  # noqa: F401  (single_thread: autouse fixture)


@pytest.fixture(scope="module")
def tiny_training_scene(tmp_path_factory) -> Path:
    from conftest import make_tiny_scene

    return make_tiny_scene(tmp_path_factory.mktemp("stability") / "scene", num_views=4, width=32, height=24,
                           num_points=120)  # fmt: skip


@pytest.fixture
def trainer_factory(tiny_training_scene, tmp_path):
    """Builds a nerfstudio Trainer for ``gsmsdr`` through its TrainerConfig (what ``ns-train gsmsdr`` runs) on the
    tiny scene: CPU, images cached as float32 (so a NaN can be written into one), blur field on from step 0."""
    from nerfstudio.utils import writer  # after the configs: importing it first is a circular import

    import gsmsdr_ns.plugin.method_config  # noqa: F401  (our configs load before nerfstudio's writer, below)

    saved_writers = list(writer.EVENT_WRITERS)

    def build(max_steps: int):
        config = cpu_trainer_config(tiny_training_scene, tmp_path / "outputs", max_steps)
        config.pipeline.datamanager.cache_images_type = "float32"
        model = config.pipeline.model
        model.refine_every = 2
        model.finite_check_every = 1  # stop at the bad step itself (test_step_syncs covers the deferred check)
        trainer = config.setup(local_rank=0, world_size=1)
        trainer.setup()
        return trainer

    yield build
    writer.EVENT_WRITERS[:] = saved_writers


def add_callback(trainer, where: str, func, first: bool = True) -> None:
    """Run ``func(step)`` before / after each training iteration, ahead of (or after) the model's callbacks."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

    callback = TrainingCallback([getattr(TrainingCallbackLocation, where)], func)
    trainer.callbacks.insert(0 if first else len(trainer.callbacks), callback)


@pytest.mark.parametrize("poison", ["image", "opacities", "means", "scales", "quats"])
def test_trainer_stops_on_a_nan_naming_the_step(trainer_factory, poison):
    from gsmsdr_ns.plugin.finite_check import NonFiniteLossError

    trainer = trainer_factory(max_steps=12)
    model = trainer.pipeline.model
    assert model.degradation.blur_field is not None, (
        "the tiny scene should train the blur field (nothing known about it)"
    )
    bad_step = 5

    def inject(step: int) -> None:
        if step != bad_step:
            return
        if poison == "image":  # one NaN pixel in every cached training image
            for item in trainer.pipeline.datamanager.cached_train:
                item["image"][3, 4, 1] = float("nan")
        else:  # a NaN position / scale / rotation only culls its Gaussian: the loss alone would stay finite
            with torch.no_grad():
                model.gauss_params[poison][0] = float("nan")

    steps_done: List[int] = []
    add_callback(trainer, "BEFORE_TRAIN_ITERATION", inject)
    add_callback(trainer, "AFTER_TRAIN_ITERATION", lambda step: steps_done.append(step))
    with pytest.raises(NonFiniteLossError) as caught:
        trainer.train()
    message = str(caught.value)
    assert f"step {bad_step} " in message, message
    if poison in ("image", "opacities"):
        assert "main_loss=nan" in message, message
    assert (f"non-finite Gaussian parameters: {poison}" if poison != "image" else "parameters: none") in message
    assert steps_done == list(range(bad_step)), "training went on after the non-finite loss"


def test_trainer_survives_a_learning_rate_spike(trainer_factory):
    """Every learning rate x1e4 for one step (log-scales jump by ~50, opacity logits by ~500), with refinement
    every 2 steps: parameters and Adam states stay finite and training goes on. Regression: the overflowing
    covariances turned the means, quaternions and scales of the whole scene into NaN within one step, silently
    (NaN Gaussians are culled, so the loss stayed finite)."""
    trainer = trainer_factory(max_steps=10)
    model = trainer.pipeline.model
    optimizers = trainer.optimizers.optimizers
    base = {name: [group["lr"] for group in opt.param_groups] for name, opt in optimizers.items()}
    spike_step, checked = 3, []
    assert model.degradation.blur_field is not None
    blur_before = [param.detach().clone() for param in model.degradation.blur_field.parameters()]

    def set_lrs(step: int) -> None:
        for name, opt in optimizers.items():
            for group, lr in zip(opt.param_groups, base[name]):
                group["lr"] = lr * (1e4 if step == spike_step else 1.0)

    def check(step: int) -> None:
        for name, param in model.named_parameters():
            assert all_finite(param.data), f"step {step}: {name} is not finite"
        for name, opt in optimizers.items():
            for param_state in opt.state.values():
                for key, value in param_state.items():
                    if isinstance(value, torch.Tensor):
                        assert all_finite(value), f"step {step}: Adam {key} of {name} is not finite"
        checked.append(step)

    add_callback(trainer, "BEFORE_TRAIN_ITERATION", set_lrs)
    add_callback(trainer, "AFTER_TRAIN_ITERATION", check, first=False)  # after refinement
    trainer.train()
    assert checked == list(range(10))
    assert float(model.scales.max()) > 20.0, "the spike did not reach the scales: the test lost its point"
    moved = [not torch.equal(a, b) for a, b in zip(blur_before, model.degradation.blur_field.parameters())]
    assert any(moved), "the blur field was not trained: the spike did not go through the degradation path"
