"""Numerical stability of the blur path: ``apply_pixel_kernels``, the blur field's heads with saturated softmax /
sigmoid, ``degrade`` and the resolution-loss model stay finite on 1x1 and one-pixel-thin images and on constant
images.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st
from stability_common import (  # noqa: F401  (single_thread: autouse fixture)
    BACKENDS,
    SETTINGS,
    all_finite,
    saturate_heads,
    single_thread,
)

from gsmsdr_ns.blur.degradation_config import DegradationConfig
from gsmsdr_ns.blur.field import BlurField, BlurFieldConfig
from gsmsdr_ns.blur.losses import mask_regulariser
from gsmsdr_ns.blur.profile import ResolutionLossModel
from gsmsdr_ns.ops.pixel_kernels import apply_pixel_kernels, apply_pixel_kernels_unfold


@settings(max_examples=30, **SETTINGS)
@given(
    hw=st.sampled_from([(1, 1), (1, 7), (7, 1), (2, 3), (5, 6)]),
    K=st.sampled_from([1, 3, 5, 9]),
    backend=st.sampled_from(BACKENDS),
    sign=st.sampled_from([1.0, -1.0]),
    image_kind=st.sampled_from(["black", "white", "constant", "random"]),
    seed=st.integers(0, 2**16),
)
def test_saturated_kernels_and_masks_on_tiny_images(hw, K, backend, sign, image_kind, seed):
    """Kernel logits of +-1e4 (the softmax saturates to one-hot kernels or to a uniform one) and mask logits of
    +-1e4 (masks exactly 0 or 1) on 1x1 / one-row / one-column images: finite values and gradients, the C++ and
    PyTorch kernels agree with the unfold reference."""
    H, W = hw
    gen = torch.Generator().manual_seed(seed)
    image = {
        "black": torch.zeros(2, 3, H, W),
        "white": torch.ones(2, 3, H, W),
        "constant": torch.full((2, 3, H, W), 0.6),
        "random": torch.rand(2, 3, H, W, generator=gen),
    }[image_kind].requires_grad_()
    logits = (sign * 1e4 * torch.randn(2, K * K, H, W, generator=gen).sign()).requires_grad_()
    mask_logits = (1e4 * torch.randn(2, 1, H, W, generator=gen).sign()).requires_grad_()
    weights, mask = F.softmax(logits, dim=1), torch.sigmoid(mask_logits)
    assert all_finite(weights) and bool(((mask == 0) | (mask == 1)).all())
    blurred = apply_pixel_kernels(image, weights, backend=backend)
    degraded = BlurField.degrade(image, weights, mask)
    target = torch.rand(degraded.shape, generator=gen)
    ((degraded - target).abs().mean() + blurred.square().mean()).backward()
    for name, t in (("blurred", blurred), ("degraded", degraded), ("image grad", image.grad),
                    ("logit grad", logits.grad), ("mask logit grad", mask_logits.grad)):  # fmt: skip
        assert all_finite(t), f"{name} is not finite"
    torch.testing.assert_close(blurred, apply_pixel_kernels_unfold(image.detach(), weights.detach()))
    # normalised kernels keep a constant image constant, and stay within the image's range
    assert float(blurred.min()) >= float(image.min()) - 1e-5 and float(blurred.max()) <= float(image.max()) + 1e-5


@pytest.mark.parametrize("backend", BACKENDS)
def test_unnormalised_weights_of_1e4(backend):
    image = torch.rand(1, 3, 1, 9, requires_grad=True)
    weights = torch.full((1, 25, 1, 9), 1e4).requires_grad_()
    out = apply_pixel_kernels(image, weights, backend=backend)
    out.sum().backward()
    assert all_finite(out) and all_finite(image.grad) and all_finite(weights.grad)
    torch.testing.assert_close(out, apply_pixel_kernels_unfold(image.detach(), weights.detach()))


@pytest.mark.parametrize("mode", ["full", "msd_only", "re_only", "view"])
def test_blur_field_saturated_heads_on_tiny_and_constant_images(mode):
    """The MAAN / BAGS feature networks and the HPKO heads on 1x1, one-row and one-column renders of black, white
    and constant images (zero-variance features for every norm layer), with heads saturated to one-hot kernels
    and 0 / 1 masks. Regression: msd_only's InstanceNorm2d raised on a 1x1 render while training."""
    torch.manual_seed(0)
    config = BlurFieldConfig(mode=mode, size="lite", kernel_sizes=(3, 5, 9), feature_dim=8, mid_channels=8)
    sizes = [(1, 1), (1, 6), (6, 1), (4, 5)]
    renders = {"black": 0.0, "white": 1.0, "constant": 0.42}
    for scale in config.setup(num_train_views=2).scales:
        for mask_sign in (1.0, -1.0):
            field = config.setup(num_train_views=2).train()
            K = field.kernel_size(scale)
            hot = (K * K) // 2 + 1  # one pixel to the right: the output is the render shifted left (border clamped)
            saturate_heads(field, scale, hot, mask_sign)
            for H, W in sizes:
                for kind, value in renders.items():
                    render = torch.full((1, 3, H, W), value, requires_grad=True)
                    depth = torch.full((1, 1, H, W), 3.0)  # constant depth: normalises to zeros
                    field.zero_grad(set_to_none=True)
                    kernels, mask = field(render, depth, torch.tensor([1]), scale)
                    degraded = BlurField.degrade(render, kernels, mask, linear_light=True)  # black: sRGB curve at 0
                    loss = (degraded - 0.5).abs().mean() + mask_regulariser(mask, DegradationConfig().mask_reg_weight)
                    loss.backward()
                    what = f"{mode} scale {scale} mask {mask_sign:+g} {H}x{W} {kind}"
                    assert all_finite(kernels) and all_finite(mask) and all_finite(degraded), what
                    assert bool(((mask == 0) | (mask == 1)).all()), what
                    assert torch.equal(kernels.argmax(dim=1), torch.full((1, H, W), hot)), what
                    torch.testing.assert_close(degraded, render.detach(), msg=what)  # constant render, any kernel
                    assert all_finite(render.grad), what
                    bad = [n for n, p in field.named_parameters() if p.grad is not None and not all_finite(p.grad)]
                    assert not bad, f"{what}: non-finite gradients of {bad}"


@pytest.mark.parametrize("factor", [1.0, 2.0, 4.0, 100.0])
def test_resolution_loss_model_on_tiny_and_constant_images(factor):
    model = ResolutionLossModel(num_views=2, kernel_size=3)
    with torch.no_grad():
        model.residual.normal_(0.0, 10.0)  # a far-from-identity residual kernel
    for H, W in [(1, 1), (1, 9), (9, 1), (6, 5)]:
        for value in (0.0, 1.0, 0.3):
            render = torch.full((2, 3, H, W), value, requires_grad=True)
            out = model(render, [factor, 1.0], torch.tensor([0, 1]))
            model.zero_grad(set_to_none=True)
            (out - 0.5).abs().mean().backward()
            assert all_finite(out) and all_finite(render.grad) and all_finite(model.residual.grad), (H, W, value)
            torch.testing.assert_close(out, render.detach())  # residual kernels sum to 1: constants pass through
