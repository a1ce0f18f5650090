"""`apply_pixel_kernels` (C++ and PyTorch backends) against the F.unfold version (BAGS) and a brute-force loop.

The brute-force reference below spells the convention out pixel by pixel, so the index ordering is pinned
independently of both F.unfold and our kernels. The C++ extension is built once per session; a missing compiler
must FAIL the "cpp" cases, not skip them.
"""

from __future__ import annotations

import re

import pytest
import torch

from gsmsdr_ns.ops.pixel_kernels import (
    ApplyPixelKernels,
    apply_pixel_kernels,
    apply_pixel_kernels_unfold,
    pixel_kernel_size,
)
from gsmsdr_ns.ops.pixel_kernels_cpp import load_pixel_kernels_extension

BACKENDS = ["cpp", "torch"]
TOL64 = dict(rtol=0.0, atol=1e-9)


@pytest.fixture(scope="module", autouse=True)
def extension():
    return load_pixel_kernels_extension()


def make_inputs(B, C, H, W, K, dtype=torch.float64, seed=0, normalised=False):
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(B, C, H, W, generator=g, dtype=dtype)
    weights = torch.randn(B, K * K, H, W, generator=g, dtype=dtype)
    if normalised:
        weights = torch.softmax(weights, dim=1)
    grad = torch.randn(B, C, H, W, generator=g, dtype=dtype)
    return image, weights, grad


def brute_force(image, weights):
    """out[b, c, y, x] = sum_{i,j} weights[b, i*K+j, y, x] * image[b, c, clamp(y+i-p), clamp(x+j-p)], literally."""
    B, C, H, W = image.shape
    K = int(round(weights.shape[1] ** 0.5))
    p = K // 2
    out = torch.zeros_like(image)
    for y in range(H):
        for x in range(W):
            for i in range(K):
                for j in range(K):
                    ys, xs = min(max(y + i - p, 0), H - 1), min(max(x + j - p, 0), W - 1)
                    out[:, :, y, x] += weights[:, i * K + j, y, x, None] * image[:, :, ys, xs]
    return out


def grads(fn, image, weights, grad):
    image = image.detach().clone().requires_grad_(True)
    weights = weights.detach().clone().requires_grad_(True)
    out = fn(image, weights)
    gi, gw = torch.autograd.grad(out, (image, weights), grad)
    return out.detach(), gi, gw


# ---------------------------------------------------------------------------------------------------------------
# smoke / cardinality / convention
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
def test_smoke_and_cardinality(backend):
    image, weights, _ = make_inputs(2, 3, 6, 7, 3, dtype=torch.float32)
    out = apply_pixel_kernels(image, weights, backend=backend)
    assert out.shape == (2, 3, 6, 7)
    assert out.dtype == torch.float32 and out.is_contiguous()


@pytest.mark.parametrize("K", [1, 3, 5])
def test_unfold_reference_matches_brute_force(K):
    image, weights, _ = make_inputs(2, 2, 5, 4, K, seed=K)
    torch.testing.assert_close(apply_pixel_kernels_unfold(image, weights), brute_force(image, weights), **TOL64)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("K", [1, 3, 5])
def test_matches_brute_force(backend, K):
    image, weights, _ = make_inputs(2, 3, 5, 4, K, seed=10 + K)
    out = apply_pixel_kernels(image, weights, backend=backend)
    torch.testing.assert_close(out, brute_force(image, weights), **TOL64)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("i, j", [(0, 0), (0, 4), (3, 1), (4, 4), (2, 2)])
def test_one_hot_kernel_is_clamped_shift(backend, i, j):
    """Kernel entry (i, j) reads the pixel (i - p) rows below and (j - p) columns right, border replicated."""
    K, p, H, W = 5, 2, 6, 7
    image = torch.arange(H * W, dtype=torch.float64).reshape(1, 1, H, W)
    weights = torch.zeros(1, K * K, H, W, dtype=torch.float64)
    weights[:, i * K + j] = 1.0
    ys = (torch.arange(H) + i - p).clamp(0, H - 1)
    xs = (torch.arange(W) + j - p).clamp(0, W - 1)
    expected = image[:, :, ys][:, :, :, xs]
    assert torch.equal(apply_pixel_kernels(image, weights, backend=backend), expected)


# ---------------------------------------------------------------------------------------------------------------
# against the unfold version: forward and gradients, float64 to 1e-9
# ---------------------------------------------------------------------------------------------------------------

SHAPES = [  # B, C, H, W, K
    (1, 1, 1, 1, 3),
    (1, 3, 7, 9, 1),
    (2, 3, 7, 9, 3),
    (3, 4, 5, 11, 5),
    (2, 1, 13, 3, 5),  # kernel wider than the image: margins larger than the width
    (1, 3, 2, 2, 5),  # margins larger than both sizes
    (2, 4, 9, 8, 3),
]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("B, C, H, W, K", SHAPES)
def test_forward_and_grads_match_unfold(backend, B, C, H, W, K):
    image, weights, grad = make_inputs(B, C, H, W, K, seed=B * 1000 + C * 100 + H * 10 + K)
    out, gi, gw = grads(lambda a, b: apply_pixel_kernels(a, b, backend=backend), image, weights, grad)
    ref, gi_ref, gw_ref = grads(apply_pixel_kernels_unfold, image, weights, grad)
    torch.testing.assert_close(out, ref, **TOL64)
    torch.testing.assert_close(gi, gi_ref, **TOL64)
    torch.testing.assert_close(gw, gw_ref, **TOL64)


def test_cpp_and_torch_agree_at_larger_size():
    image, weights, grad = make_inputs(1, 3, 40, 52, 17, seed=7)
    out_c, gi_c, gw_c = grads(lambda a, b: apply_pixel_kernels(a, b, backend="cpp"), image, weights, grad)
    out_t, gi_t, gw_t = grads(lambda a, b: apply_pixel_kernels(a, b, backend="torch"), image, weights, grad)
    ref, gi_ref, gw_ref = grads(apply_pixel_kernels_unfold, image, weights, grad)
    for ours, theirs in ((out_c, ref), (gi_c, gi_ref), (gw_c, gw_ref), (out_t, ref), (gi_t, gi_ref), (gw_t, gw_ref)):
        torch.testing.assert_close(ours, theirs, **TOL64)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("B, C, H, W, K", [(2, 2, 4, 5, 3), (1, 3, 3, 4, 5), (1, 1, 1, 2, 3)])
def test_gradcheck(backend, B, C, H, W, K):
    image, weights, _ = make_inputs(B, C, H, W, K, seed=3)
    image.requires_grad_(True)
    weights.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: apply_pixel_kernels(a, b, backend=backend), (image, weights))


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradient_to_one_input_only(backend):
    image, weights, grad = make_inputs(2, 3, 6, 5, 3, seed=4)
    _, gi_ref, gw_ref = grads(apply_pixel_kernels_unfold, image, weights, grad)
    a = image.clone().requires_grad_(True)
    (gi,) = torch.autograd.grad(apply_pixel_kernels(a, weights, backend=backend), a, grad)
    torch.testing.assert_close(gi, gi_ref, **TOL64)
    w = weights.clone().requires_grad_(True)
    (gw,) = torch.autograd.grad(apply_pixel_kernels(image, w, backend=backend), w, grad)
    torch.testing.assert_close(gw, gw_ref, **TOL64)


# ---------------------------------------------------------------------------------------------------------------
# properties
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("K", [1, 3, 5, 9])
def test_identity_kernel_reproduces_image_exactly(backend, dtype, K):
    image, _, _ = make_inputs(2, 4, 7, 6, K, dtype=dtype, seed=5)
    weights = torch.zeros(2, K * K, 7, 6, dtype=dtype)
    weights[:, (K * K) // 2] = 1.0  # centre (p, p)
    assert torch.equal(apply_pixel_kernels(image, weights, backend=backend), image)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype, atol", [(torch.float32, 1e-5), (torch.float64, 1e-12)])
def test_normalised_weights_preserve_constant_image(backend, dtype, atol):
    _, weights, _ = make_inputs(2, 3, 8, 9, 5, dtype=dtype, seed=6, normalised=True)
    image = torch.full((2, 3, 8, 9), 0.37, dtype=dtype)
    out = apply_pixel_kernels(image, weights, backend=backend)
    torch.testing.assert_close(out, image, rtol=0.0, atol=atol)


# ---------------------------------------------------------------------------------------------------------------
# strides, dtypes, module twin
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
def test_noncontiguous_inputs(backend):
    image, weights, grad = make_inputs(2, 3, 6, 10, 3, seed=8)
    image_nc = image.permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)  # channels-last strides
    big = torch.randn(2, 9, 6, 20, dtype=torch.float64)
    big[..., ::2] = weights
    weights_nc = big[..., ::2]  # every other column
    assert not image_nc.is_contiguous() and not weights_nc.is_contiguous()
    out, gi, gw = grads(lambda a, b: apply_pixel_kernels(a, b, backend=backend), image_nc, weights_nc, grad)
    ref, gi_ref, gw_ref = grads(apply_pixel_kernels_unfold, image, weights, grad)
    torch.testing.assert_close(out, ref, **TOL64)
    torch.testing.assert_close(gi, gi_ref, **TOL64)
    torch.testing.assert_close(gw, gw_ref, **TOL64)
    # the gradient reaches the caller's own non-contiguous leaves
    a, b = image_nc.detach().requires_grad_(True), weights_nc.detach().requires_grad_(True)
    apply_pixel_kernels(a, b, backend=backend).backward(grad)
    torch.testing.assert_close(a.grad, gi_ref, **TOL64)
    torch.testing.assert_close(b.grad, gw_ref, **TOL64)


@pytest.mark.parametrize("backend", BACKENDS)
def test_float32_close_to_float64(backend):
    image, weights, grad = make_inputs(2, 3, 12, 10, 5, seed=9, normalised=True)
    out64, gi64, gw64 = grads(lambda a, b: apply_pixel_kernels(a, b, backend=backend), image, weights, grad)
    out32, gi32, gw32 = grads(lambda a, b: apply_pixel_kernels(a, b, backend=backend), image.float(),
                              weights.float(), grad.float())  # fmt: skip
    assert out32.dtype == gi32.dtype == gw32.dtype == torch.float32
    torch.testing.assert_close(out32.double(), out64, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(gi32.double(), gi64, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(gw32.double(), gw64, rtol=1e-5, atol=1e-5)


def test_half_precision_takes_torch_path():
    image, weights, _ = make_inputs(1, 3, 6, 5, 3, dtype=torch.float64, seed=11, normalised=True)
    out = apply_pixel_kernels(image.bfloat16(), weights.bfloat16())  # auto: the C++ op has no bfloat16
    assert out.dtype == torch.bfloat16
    torch.testing.assert_close(out.double(), apply_pixel_kernels_unfold(image, weights), rtol=0.0, atol=3e-2)
    with pytest.raises(ValueError, match="backend='cpp' needs CPU float32/float64"):
        apply_pixel_kernels(image.bfloat16(), weights.bfloat16(), backend="cpp")


@pytest.mark.parametrize("backend", BACKENDS)
def test_module_equals_function(backend):
    image, weights, _ = make_inputs(2, 3, 5, 6, 3, seed=12)
    module = ApplyPixelKernels(backend=backend)
    assert backend in repr(module)
    assert torch.equal(module(image, weights), apply_pixel_kernels(image, weights, backend=backend))


# ---------------------------------------------------------------------------------------------------------------
# exceptions
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("channels, why", [(8, "not a square"), (16, "K is even"), (4, "K is even"), (0, "")])
def test_kernel_size_must_be_odd_square(channels, why):
    with pytest.raises(ValueError, match=rf"K\*K channels for an odd kernel size K.*got {channels}.*{why}"):
        pixel_kernel_size(channels)
    image = torch.rand(1, 3, 4, 5)
    with pytest.raises(ValueError, match=rf"got {channels}"):
        apply_pixel_kernels(image, torch.rand(1, channels, 4, 5))
    assert [pixel_kernel_size(k * k) for k in (1, 3, 5, 17)] == [1, 3, 5, 17]


@pytest.mark.parametrize(
    "image_shape, weights_shape, message",
    [
        ((1, 3, 4, 5), (2, 9, 4, 5), r"expected shape [B, K*K, H, W] = [1, 9, 4, 5] to match image [1, 3, 4, 5], "
                                     r"got [2, 9, 4, 5]"),
        ((2, 3, 4, 5), (2, 9, 5, 4), r"= [2, 9, 4, 5] to match image [2, 3, 4, 5], got [2, 9, 5, 4]"),
        ((3, 4, 5), (1, 9, 4, 5), r"image: expected shape [B, C, H, W], got [3, 4, 5]"),
        ((1, 3, 4, 5), (9, 4, 5), r"weights: expected shape [B, K*K, H, W], got [9, 4, 5]"),
        ((1, 3, 0, 5), (1, 9, 0, 5), r"expected H >= 1 and W >= 1, got shape [1, 3, 0, 5]"),
    ],
)  # fmt: skip
def test_bad_shapes_raise(image_shape, weights_shape, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        apply_pixel_kernels(torch.rand(*image_shape), torch.rand(*weights_shape))
    with pytest.raises(ValueError, match=re.escape(message)):
        apply_pixel_kernels_unfold(torch.rand(*image_shape), torch.rand(*weights_shape))


def test_bad_dtypes_and_backend_raise():
    image = torch.rand(1, 3, 4, 5)
    with pytest.raises(ValueError, match="same floating-point dtype, got torch.float32 and torch.float64"):
        apply_pixel_kernels(image, torch.rand(1, 9, 4, 5, dtype=torch.float64))
    with pytest.raises(ValueError, match="same floating-point dtype, got torch.int64"):
        apply_pixel_kernels(torch.ones(1, 3, 4, 5, dtype=torch.long), torch.ones(1, 9, 4, 5, dtype=torch.long))
    with pytest.raises(ValueError, match="backend: expected 'auto', 'cpp' or 'torch', got 'cuda'"):
        apply_pixel_kernels(image, torch.rand(1, 9, 4, 5), backend="cuda")


# ---------------------------------------------------------------------------------------------------------------
# the point of it all: memory
# ---------------------------------------------------------------------------------------------------------------


def test_extra_peak_memory_far_below_unfold():
    """Fresh processes, 200x300 RGB, K=17: the unfold version's patches alone are 208 MB."""
    from gsmsdr_ns.bench.kernels import measure_peak_memory

    ours = measure_peak_memory("ours", 17, height=200, width=300)
    unfold = measure_peak_memory("unfold", 17, height=200, width=300)
    weights_grad = 17 * 17 * 200 * 300 * 4  # the one allocation both need
    assert ours["extra_bytes"] < weights_grad + 16 * 2**20, ours
    assert ours["extra_bytes"] <= 0.35 * unfold["extra_bytes"], (ours, unfold)
