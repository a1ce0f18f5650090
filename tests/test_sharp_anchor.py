"""The sharp anchor: on steps through the thin lens, a share of splatfacto's loss on the sharp render."""

from __future__ import annotations

import pytest
import torch
from test_plugin_blur import build, records
from test_plugin_model import look_from, make_camera

from gsmsdr_ns.blur import DegradationConfig


def _losses(weight: float, kind: str = "defocus"):
    options = DegradationConfig(
        warmup=0, thin_lens_initial_aperture=20.0, sharp_anchor_weight=weight, thin_lens_start="warmup"
    )
    model = build({"degradations": records(kind, 2)}, n=2, degradation_model=options, background_color="black",
                  num_downscales=0)  # fmt: skip
    model.train()
    model.optimizers = None
    model.step = 1
    camera = make_camera(look_from([2.0, 0.5, 1.0]), width=48, height=36)
    camera.metadata = {"cam_idx": 0}
    outputs = model.get_outputs(camera)
    photo = torch.rand(36, 48, 3, generator=torch.Generator().manual_seed(0))
    return model, outputs, model.get_loss_dict(outputs, {"image": photo}), photo


def test_the_anchor_adds_the_sharp_renders_loss_times_its_weight():
    model, outputs, losses, photo = _losses(0.5)
    assert outputs["rgb"] is outputs["rgb_degraded"]  # trained through the lens
    sharp = outputs["rgb_sharp"]
    l1 = (sharp - photo).abs().mean()
    ssim = model.ssim(photo.permute(2, 0, 1)[None], sharp.permute(2, 0, 1)[None])
    lam = model.config.ssim_lambda
    torch.testing.assert_close(losses["sharp_anchor"], 0.5 * ((1 - lam) * l1 + lam * (1 - ssim)))
    means = model.gauss_params["means"]
    (grad,) = torch.autograd.grad(losses["sharp_anchor"], means)
    assert float(grad.abs().sum()) > 0  # it trains the Gaussians


def test_no_anchor_by_default_nor_on_views_without_the_lens():
    assert DegradationConfig().sharp_anchor_weight == 0.0
    assert "sharp_anchor" not in _losses(0.0)[2]
    assert "sharp_anchor" not in _losses(0.5, kind="sharp")[2]
    assert "sharp_anchor" not in _losses(0.5, kind="motion")[2]  # the field alone: no lens
    with pytest.raises(ValueError, match="sharp_anchor_weight"):
        DegradationConfig(sharp_anchor_weight=-1.0)
