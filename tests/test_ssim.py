"""Our training SSIM equals splatfacto's (pytorch_msssim), values and gradients, and the model trains with it."""

from __future__ import annotations

import pytest
import torch
from pytorch_msssim import SSIM as ReferenceSSIM

from gsmsdr_ns.ops.ssim import SSIM, gaussian_window, ssim


@pytest.mark.parametrize("size", [(37, 52), (9, 30), (6, 7)])  # both dims filtered, rows too short, neither
def test_equals_pytorch_msssim_in_value_and_gradient(size):
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 3, *size, dtype=torch.float64, generator=g, requires_grad=True)
    y = torch.rand(1, 3, *size, dtype=torch.float64, generator=g, requires_grad=True)
    reference = ReferenceSSIM(data_range=1.0, size_average=True, channel=3)
    with pytest.warns(UserWarning) if min(size) < 11 else _no_warning():
        expected = reference(x, y)
    ours = SSIM()(x, y)
    torch.testing.assert_close(ours, expected, rtol=0, atol=1e-12)
    for a, b in zip(torch.autograd.grad(ours, (x, y)), torch.autograd.grad(expected, (x, y))):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    torch.testing.assert_close(gaussian_window().double(), reference.win[0].flatten().double(), rtol=0, atol=1e-7)


def test_identical_images_score_one_and_shapes_are_checked():
    x = torch.rand(1, 3, 20, 24)
    assert float(ssim(x, x, gaussian_window())) == pytest.approx(1.0, abs=1e-6)
    with pytest.raises(ValueError, match="one shape"):
        ssim(x, x[..., :10], gaussian_window())
    assert "window" not in SSIM().state_dict()  # checkpoints unchanged


def test_the_model_uses_it_for_splatfactos_loss():
    from test_plugin_blur import build, records

    model = build({"degradations": records("sharp", 2)}, n=2)
    assert isinstance(model.ssim, SSIM)


class _no_warning:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False
