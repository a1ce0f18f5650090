"""The per-image fallback: a blurred image trains as a plain step until its degradation model explains the photo
better than the sharp render; meanwhile the model learns alone on the detached render."""

from __future__ import annotations

import math

import pytest
import torch
from test_plugin_blur import build, records
from test_plugin_model import look_from, make_camera

from gsmsdr_ns.blur import BlurFieldConfig, DegradationConfig
from gsmsdr_ns.blur.fallback import ExplanationGate, photo_errors
from gsmsdr_ns.blur.state_keys import with_fallback_state


def test_gate_uses_the_model_only_once_measured_better_than_the_sharp_render():
    gate = ExplanationGate(3, decay=0.5)
    assert not any(gate.uses_model(i) for i in range(3))  # nothing measured: plain steps
    assert float(gate.fraction_using_model()) == 0.0
    gate.update(0, torch.tensor([0.10, 0.20]))  # the blur explains view 0 better
    gate.update(1, torch.tensor([0.30, 0.20]))  # and view 1 worse
    assert gate.uses_model(0) and not gate.uses_model(1) and not gate.uses_model(2)
    assert float(gate.fraction_using_model()) == pytest.approx(0.5)  # of the measured views
    gate.update(1, torch.tensor([0.05, 0.20]))  # running mean: (0.30 + 0.05) / 2 = 0.175 < 0.20
    assert gate.errors[1].tolist() == pytest.approx([0.175, 0.20])
    assert gate.uses_model(1)
    strict = ExplanationGate(1, decay=0.0, margin=0.2)
    strict.update(0, torch.tensor([0.17, 0.20]))  # better, but not by 20 %
    assert not strict.uses_model(0)
    strict.update(0, torch.tensor([0.15, 0.20]))  # decay 0: the last step alone
    assert strict.uses_model(0)


@pytest.mark.parametrize("decay, margin", [(1.0, 0.0), (-0.1, 0.0), (0.5, 1.0), (0.5, -0.1)])
def test_gate_rejects_settings_outside_their_range(decay, margin):
    with pytest.raises(ValueError, match="fallback"):
        ExplanationGate(2, decay=decay, margin=margin)
    with pytest.raises(ValueError, match="fallback"):
        DegradationConfig(fallback_decay=decay, fallback_margin=margin)
    with pytest.raises(ValueError, match="fallback_sigma"):
        DegradationConfig(fallback_sigma=-1.0)


def test_photo_errors_are_the_mean_absolute_errors_detached():
    target = torch.zeros(4, 5, 3)
    degraded = torch.full((4, 5, 3), 0.25, requires_grad=True)
    errors = photo_errors(degraded, torch.full((4, 5, 3), -0.5), target)
    assert errors.tolist() == pytest.approx([0.25, 0.5]) and not errors.requires_grad


def test_errors_after_a_small_blur_tell_render_noise_from_photo_blur():
    """A sharp photo with an edge, a render that is the photo plus pixel-scale noise, and that render blurred: as
    they are, the blur seems to explain the photo better (it removes the noise); after a 1-pixel Gaussian blur of all
    three the noise is gone and the render explains the photo better, as it should. A blurred photo stays better
    explained by the blurred render at both scales."""
    from kornia.filters import box_blur

    photo = torch.zeros(32, 32, 3)
    photo[:, 16:] = 0.8
    checker = (torch.arange(32)[:, None] + torch.arange(32)[None, :]) % 2
    render = photo + 0.1 * (2 * checker[..., None].float() - 1)

    def blur(image):
        return box_blur(image.permute(2, 0, 1)[None], (5, 5), border_type="replicate")[0].permute(1, 2, 0)

    degraded, sharp = photo_errors(blur(render), render, photo).tolist()
    assert degraded < sharp  # the noise fools the comparison
    degraded, sharp = photo_errors(blur(render), render, photo, sigma=1.0).tolist()
    assert sharp < 0.1 * degraded  # not after the small blur
    blurred_photo = blur(photo)
    for sigma in (0.0, 1.0):
        degraded, sharp = photo_errors(blur(photo), photo, blurred_photo, sigma=sigma).tolist()
        assert degraded < 0.1 * sharp


def _train_camera(view: int):
    camera = make_camera(look_from([2.0, 0.5, 1.0]), width=48, height=36)
    camera.metadata = {"cam_idx": view}
    return camera


def _gradients(model, loss):
    model.zero_grad(set_to_none=True)
    loss.backward(retain_graph=True)
    means = model.gauss_params["means"].grad
    lens = model.degradation.thin_lens.log_aperture.grad
    return (None if means is None else means.clone()), (None if lens is None else lens.clone())


def test_a_view_trains_plain_until_its_lens_explains_the_photo_then_through_it():
    """Defocused views with a wide initial lens. First visit: ``rgb`` is the sharp render, the Gaussians get the
    plain loss's gradient alone and the lens only ``degradation_fit``'s. Once the photo is one the lens explains (the
    target is the lens's own blur), the next visit trains through the lens."""
    options = DegradationConfig(
        warmup=0, thin_lens_initial_aperture=20.0, fallback=True, fallback_decay=0.0, thin_lens_start="warmup"
    )
    model = build({"degradations": records("defocus", 2)}, n=2, degradation_model=options, background_color="black",
                  num_downscales=0)  # fmt: skip
    model.train()
    model.optimizers = None  # no densification here
    model.step = 1
    outputs = model.get_outputs(_train_camera(0))
    plan = outputs["degradation_plan"]
    assert plan.fallback and plan.thin_lens
    assert outputs["rgb"] is outputs["rgb_sharp"]
    assert float((outputs["rgb_degraded"] - outputs["rgb_sharp"]).detach().abs().max()) > 1e-3  # the lens blurs
    photo = outputs["rgb_sharp"].detach().clone()  # a sharp photo: the render explains it, the lens's blur less
    losses = model.get_loss_dict(outputs, {"image": photo})
    assert losses["degradation_fit"].requires_grad
    means_grad, lens_grad = _gradients(model, losses["degradation_fit"])
    assert means_grad is None and lens_grad is not None and float(lens_grad.abs()) > 0
    means_grad, lens_grad = _gradients(model, losses["main_loss"])
    assert means_grad is not None and float(means_grad.abs().sum()) > 0 and lens_grad is None
    assert not model.degradation.fallback.uses_model(0)  # measured: the blur does not explain this photo better
    assert not math.isnan(float(model.degradation.fallback.errors[0, 0]))
    assert torch.isnan(model.degradation.fallback.errors[1]).all()  # view 1 not visited

    outputs = model.get_outputs(_train_camera(0))
    lens_blur = outputs["rgb_degraded"].detach().clone()
    losses = model.get_loss_dict(outputs, {"image": lens_blur})  # the lens explains this photo exactly
    assert model.degradation.fallback.uses_model(0)
    outputs = model.get_outputs(_train_camera(0))
    assert not outputs["degradation_plan"].fallback
    assert outputs["rgb"] is outputs["rgb_degraded"]
    losses = model.get_loss_dict(outputs, {"image": lens_blur})
    assert "degradation_fit" not in losses
    means_grad, lens_grad = _gradients(model, losses["main_loss"])
    assert float(means_grad.abs().sum()) > 0 and float(lens_grad.abs()) > 0  # both learn through the lens
    metrics = model.get_metrics_dict(outputs, {"image": lens_blur})
    assert float(metrics["blur_model_in_use"]) == 1.0  # of the one view measured


def test_without_the_fallback_every_blurred_view_trains_through_its_model():
    """Off (the default): no gate, every blurred view trains through its model from the end of the warm-up."""
    assert not DegradationConfig().fallback
    options = DegradationConfig(warmup=0)
    model = build({"degradations": records("motion", 2)}, n=2, degradation_model=options,
                  blur_field=BlurFieldConfig(mode="view"))  # fmt: skip
    assert model.degradation.fallback is None
    model.train()
    model.optimizers = None
    model.step = 1
    outputs = model.get_outputs(_train_camera(1))
    assert not outputs["degradation_plan"].fallback and outputs["rgb"] is outputs["rgb_degraded"]


def test_checkpoints_load_with_and_without_the_fallback():
    """A model without a gate loads a checkpoint that has one (the gate's state dropped), and the reverse (the
    gate starts unmeasured); a gate's measured state survives a save and load."""
    metadata = {"degradations": records("motion", 2)}
    with_gate = build(metadata, n=2, degradation_model=DegradationConfig(fallback=True))
    with_gate.degradation.fallback.update(1, torch.tensor([0.1, 0.2]))
    without = build(metadata, n=2, degradation_model=DegradationConfig(fallback=False))
    without.load_state_dict(with_gate.state_dict())  # strict
    fresh = build(metadata, n=2, degradation_model=DegradationConfig(fallback=True))
    fresh.load_state_dict(without.state_dict())
    assert torch.isnan(fresh.degradation.fallback.errors).all()
    fresh.load_state_dict(with_gate.state_dict())
    assert fresh.degradation.fallback.uses_model(1) and not fresh.degradation.fallback.uses_model(0)
    state = with_gate.state_dict()
    assert with_fallback_state(state, with_gate.state_dict(), "degradation.fallback.") is state  # nothing to change


def test_nerfstudio_trainer_trains_a_defocus_scene_with_the_fallback(tmp_path):
    """The real Trainer on a generated defocus scene with the fallback on: every step finite, each visited view's
    errors measured once its lens runs, ``degradation_fit`` on each view's first step after the warm-up (nothing
    measured yet: a plain step), and the gate's state in the checkpoint the trainer writes."""
    from test_plugin_blur import InProcessTrainer, make_variant

    scene = make_variant(tmp_path / "defocus", "defocus")
    options = DegradationConfig(warmup=2, fallback=True, thin_lens_start="warmup")
    run = InProcessTrainer(scene, tmp_path, warmup=2, degradation_model=options)
    run.train(24)
    gate = run.model.degradation.fallback
    after_warmup = [s for s in run.steps if s["step"] >= 2]
    visited = {s["view"] for s in after_warmup}
    assert visited and not torch.isnan(gate.errors[sorted(visited)]).any()
    first_visits = {}
    for s in after_warmup:
        first_visits.setdefault(s["view"], s)
    assert all("degradation_fit" in s["losses"] for s in first_visits.values())  # nothing measured yet: plain
    run.trainer.save_checkpoint(23)
    checkpoint = torch.load(next((tmp_path / "outputs").rglob("step-*.ckpt")), map_location="cpu")
    saved = checkpoint["pipeline"]["_model.degradation.fallback.errors"]
    torch.testing.assert_close(saved, gate.errors, equal_nan=True)
