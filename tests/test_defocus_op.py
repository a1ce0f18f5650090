"""The fused thin-lens defocus ops (gsmsdr_ns.ops.disk_defocus) against the unfused kernels they replace.

Reference: ``apply_pixel_kernels(image, occluding_disk_kernels(...))`` (and ``soft_disk_kernels``), in float64, values
and gradients; the C++ kernel and the PyTorch twin both; and what is saved for the backward (no K*K maps).
"""

from __future__ import annotations

import pytest
import torch

from gsmsdr_ns.ops.disk_defocus import apply_occluding_defocus, apply_soft_disk_defocus
from gsmsdr_ns.ops.disk_defocus_cpp import disk_kernels_cpp_error
from gsmsdr_ns.ops.disk_kernels import occluding_disk_kernels, soft_disk_kernels
from gsmsdr_ns.ops.pixel_kernels import apply_pixel_kernels

BACKENDS = ("cpp", "torch")


@pytest.fixture(scope="module", autouse=True)
def _cpp_builds():
    error = disk_kernels_cpp_error()
    assert error is None, f"the C++ defocus op must build for these tests: {error}"


def _scene(B=2, C=3, H=7, W=9, max_radius=3.0, dtype=torch.float64, seed=0):
    """Random image, radius (some beyond the window: truncated) and inverse depth with a radius tie behind a
    pixel (torch.minimum's half-half rule), all leaves."""
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(B, C, H, W, generator=g, dtype=dtype)
    radius = torch.rand(B, 1, H, W, generator=g, dtype=dtype) * max_radius
    inverse_depth = torch.rand(B, 1, H, W, generator=g, dtype=dtype)
    y = H // 2
    radius[0, 0, y, 3] = radius[0, 0, y, 4]
    inverse_depth[0, 0, y, 3] = inverse_depth[0, 0, y, 4] + 0.1  # (y, 4) is behind (y, 3) with the same radius
    grad = torch.randn(B, C, H, W, generator=g, dtype=dtype)
    return image.requires_grad_(True), radius.requires_grad_(True), inverse_depth, grad


def _value_and_grads(fn, image, radius, grad):
    out = fn()
    return (out, *torch.autograd.grad(out, (image, radius), grad))


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("K", [1, 3, 7])
def test_occluding_defocus_is_the_unfused_lens_in_float64(backend, K):
    image, radius, inverse_depth, grad = _scene()
    ref = _value_and_grads(
        lambda: apply_pixel_kernels(image, occluding_disk_kernels(radius, inverse_depth, K)), image, radius, grad
    )
    got = _value_and_grads(
        lambda: apply_occluding_defocus(image, radius, inverse_depth, K, backend=backend), image, radius, grad
    )
    for name, a, b in zip(("out", "grad image", "grad radius"), got, ref):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12, msg=lambda m: f"{name}: {m}")


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("K", [1, 5])
def test_soft_disk_defocus_is_the_unfused_soft_disk_in_float64(backend, K):
    image, radius, _, grad = _scene(seed=1)
    ref = _value_and_grads(lambda: apply_pixel_kernels(image, soft_disk_kernels(radius, K, 0.4)), image, radius, grad)
    got = _value_and_grads(lambda: apply_soft_disk_defocus(image, radius, K, 0.4, backend=backend), image, radius,
                           grad)  # fmt: skip
    for name, a, b in zip(("out", "grad image", "grad radius"), got, ref):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12, msg=lambda m: f"{name}: {m}")


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradcheck_on_a_tiny_lens(backend):
    image, radius, inverse_depth, _ = _scene(B=1, C=2, H=4, W=5, max_radius=2.0, seed=2)
    torch.autograd.gradcheck(
        lambda im, r: apply_occluding_defocus(im, r, inverse_depth, 3, 0.3, backend=backend), (image, radius)
    )
    torch.autograd.gradcheck(lambda im, r: apply_soft_disk_defocus(im, r, 3, 0.3, backend=backend), (image, radius))


def test_cpp_and_twin_agree_in_float32_and_on_a_single_row():
    for shape in ((1, 3, 24, 31), (2, 1, 1, 13)):  # a one-row image: every vertical tap replicates the row
        B, C, H, W = shape
        image, radius, inverse_depth, grad = _scene(B, C, H, W, max_radius=6.0, dtype=torch.float32, seed=3)
        cpp = _value_and_grads(lambda: apply_occluding_defocus(image, radius, inverse_depth, 9, backend="cpp"),
                               image, radius, grad)  # fmt: skip
        twin = _value_and_grads(lambda: apply_occluding_defocus(image, radius, inverse_depth, 9, backend="torch"),
                                image, radius, grad)  # fmt: skip
        for a, b in zip(cpp, twin):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_radius_zero_and_a_one_tap_window_are_the_identity(backend):
    image, radius, inverse_depth, _ = _scene(dtype=torch.float32, seed=4)
    sharp = apply_occluding_defocus(image, torch.zeros_like(radius), inverse_depth, 9, backend=backend)
    assert torch.equal(sharp, image)
    assert torch.equal(apply_soft_disk_defocus(image, torch.zeros_like(radius), 9, backend=backend), image)
    one_tap = apply_occluding_defocus(image, radius, inverse_depth, 1, backend=backend)
    if backend == "cpp":  # normalised weight 1, as the unfused kernels
        assert torch.equal(one_tap, image)
    else:  # the twin divides the weighted sum by the weight (one pass over the taps): within a rounding
        torch.testing.assert_close(one_tap, image, rtol=2e-7, atol=0.0)
    # and nothing moves the radius at a one-tap window: the only weight is 1
    (grad_radius,) = torch.autograd.grad(one_tap.square().sum(), radius)
    assert float(grad_radius.abs().max()) <= (0.0 if backend == "cpp" else 1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_borders_replicate(backend):
    """A uniform disk on a 1-pixel-wide bright left column: the first column's light is counted once per tap that
    falls off the left edge, as replicate padding does."""
    image = torch.zeros(1, 1, 5, 6, dtype=torch.float64)
    image[..., 0] = 1.0
    radius = torch.full((1, 1, 5, 6), 1.0, dtype=torch.float64)
    inverse_depth = torch.ones(1, 1, 5, 6, dtype=torch.float64)
    out = apply_occluding_defocus(image, radius, inverse_depth, 5, backend=backend)
    weights = soft_disk_kernels(radius, 5)[0, :, 2, 0].reshape(5, 5)
    # at column 0 the taps of kernel columns 0..2 read column 0 (two of them replicated past the edge)
    torch.testing.assert_close(out[0, 0, 2, 0], weights[:, :3].sum())
    padded = torch.nn.functional.pad(image, (2, 2, 2, 2), mode="replicate")
    assert float(padded[0, 0, 2, 0]) == 1.0  # the convention the reference uses
    torch.testing.assert_close(out, apply_pixel_kernels(image, soft_disk_kernels(radius, 5)))


def test_nan_radius_flows_into_the_output():
    image, radius, inverse_depth, _ = _scene(dtype=torch.float32, seed=5)
    radius = radius.detach().clone()
    radius[0, 0, 3, 3] = float("nan")
    for backend in BACKENDS:
        out = apply_occluding_defocus(image, radius, inverse_depth, 5, backend=backend)
        assert torch.isnan(out[0, :, 3, 3]).all() and torch.isfinite(out[1]).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_nothing_of_size_k_squared_is_saved_for_the_backward(backend):
    K = 9
    image, radius, inverse_depth, _ = _scene(B=1, C=3, H=12, W=14, dtype=torch.float32, seed=6)
    saved = []
    with torch.autograd.graph.saved_tensors_hooks(lambda t: saved.append(tuple(t.shape)) or t, lambda t: t):
        out = apply_occluding_defocus(image, radius, inverse_depth, K, backend=backend)
    assert saved and all(shape[1] < K * K for shape in saved if len(shape) == 4), saved
    out.sum().backward()
    assert radius.grad is not None and image.grad is not None
    unfused = []
    with torch.autograd.graph.saved_tensors_hooks(lambda t: unfused.append(tuple(t.shape)) or t, lambda t: t):
        apply_pixel_kernels(image, occluding_disk_kernels(radius, inverse_depth, K))
    assert sum(len(s) == 4 and s[1] == K * K for s in unfused) >= 4  # what the fused op saves the memory of


def test_inverse_depth_is_not_differentiated():
    image, radius, inverse_depth, _ = _scene(dtype=torch.float64, seed=7)
    inverse_depth.requires_grad_(True)
    for backend in BACKENDS:
        apply_occluding_defocus(image, radius, inverse_depth, 3, backend=backend).sum().backward()
        assert inverse_depth.grad is None


def test_bad_arguments_name_the_value_and_the_fix():
    image, radius, inverse_depth, _ = _scene(dtype=torch.float32)
    with pytest.raises(ValueError, match=r"radius.*float32.*float64.*\.to\(image\.dtype\)"):
        apply_occluding_defocus(image, radius.double(), inverse_depth, 3)
    with pytest.raises(ValueError, match=r"inverse_depth: expected shape \[B, 1, H, W\] = \[2, 1, 7, 9\]"):
        apply_occluding_defocus(image, radius, inverse_depth[..., :8], 3)
    with pytest.raises(ValueError, match="kernel_size must be a positive odd integer, got 4"):
        apply_occluding_defocus(image, radius, inverse_depth, 4)
    with pytest.raises(ValueError, match="softness must be > 0"):
        apply_soft_disk_defocus(image, radius, 3, 0.0)
    with pytest.raises(ValueError, match="same device"):
        apply_occluding_defocus(image, radius, inverse_depth.to("meta"), 3)
    with pytest.raises(ValueError, match="backend='cpp' needs CPU float32/float64"):
        apply_occluding_defocus(image.half(), radius.half(), inverse_depth.half(), 3, backend="cpp")
    with pytest.raises(ValueError, match="backend: expected"):
        apply_occluding_defocus(image, radius, inverse_depth, 3, backend="cuda")


def test_half_precision_takes_the_twin():
    image, radius, inverse_depth, _ = _scene(dtype=torch.float32, seed=8)
    reference = apply_occluding_defocus(image, radius, inverse_depth, 5)
    half = apply_occluding_defocus(image.bfloat16(), radius.bfloat16(), inverse_depth.bfloat16(), 5)
    assert half.dtype == torch.bfloat16
    torch.testing.assert_close(half.float(), reference, rtol=0.05, atol=0.05)
