"""The depthwise convolution (ops/depthwise_conv.py) and the feature network layers built on it."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from reference_checks import assert_matches_reference

from gsmsdr_ns.blur.maan import ChannelLayerNorm, DepthwiseConv2d
from gsmsdr_ns.ops.depthwise_conv import depthwise_conv2d, depthwise_conv_cpp_available

needs_cpp = pytest.mark.skipif(not depthwise_conv_cpp_available(), reason="no C++ compiler for the depthwise op")

# (B, C, H, W, k, dilation): the feature network's kernels (3, 5, 7; dilations 1-3), a padding wider than the image, a
# single pixel, and rows of several 64-value column groups with a partial last one
CASES = [(2, 3, 7, 9, 3, 1), (1, 4, 13, 37, 5, 2), (1, 2, 5, 4, 7, 3), (1, 1, 1, 1, 3, 1), (1, 3, 6, 131, 7, 1),
         (2, 2, 9, 70, 1, 1)]  # fmt: skip


@pytest.mark.parametrize("backend", [pytest.param("cpp", marks=needs_cpp), "torch"])
@pytest.mark.parametrize("B, C, H, W, k, dilation", CASES)
def test_matches_grouped_conv2d_in_float64(backend, B, C, H, W, k, dilation):
    gen = torch.Generator().manual_seed(H * 1000 + W)
    image = torch.rand(B, C, H, W, dtype=torch.float64, generator=gen, requires_grad=True)
    weight = torch.rand(C, 1, k, k, dtype=torch.float64, generator=gen, requires_grad=True)
    bias = torch.rand(C, dtype=torch.float64, generator=gen, requires_grad=True)
    out = depthwise_conv2d(image, weight, bias, dilation, backend=backend)
    ref = F.conv2d(image, weight, bias, padding=(k // 2) * dilation, dilation=dilation, groups=C)
    assert_matches_reference(out, ref, (image, weight, bias), gen)


@needs_cpp
def test_cpp_gradcheck_and_float32():
    gen = torch.Generator().manual_seed(1)
    image = torch.rand(1, 2, 6, 9, dtype=torch.float64, generator=gen, requires_grad=True)
    weight = torch.rand(2, 1, 5, 5, dtype=torch.float64, generator=gen, requires_grad=True)
    assert torch.autograd.gradcheck(lambda i, w: depthwise_conv2d(i, w, None, 2, backend="cpp"), (image, weight))
    single = depthwise_conv2d(image.float(), weight.float(), None, 2, backend="cpp")
    torch.testing.assert_close(single.double(), depthwise_conv2d(image, weight, None, 2), rtol=0, atol=1e-5)


def test_bad_shapes_and_dilations_are_named():
    image = torch.rand(1, 3, 8, 8)
    with pytest.raises(ValueError, match=r"expected image \[B, C, H, W\] and weight \[C, 1, k, k\]"):
        depthwise_conv2d(image, torch.rand(4, 1, 3, 3))
    with pytest.raises(ValueError, match="square with an odd size"):
        depthwise_conv2d(image, torch.rand(3, 1, 4, 4))
    with pytest.raises(ValueError, match="dilation must be an integer >= 1"):
        depthwise_conv2d(image, torch.rand(3, 1, 3, 3), dilation=0)


def test_other_dtypes_take_torchs_convolution():
    """bfloat16 (what autocast hands over) runs torch's convolution; mixed dtypes never reach the C++ kernel."""
    image = torch.rand(1, 2, 5, 6).bfloat16()
    weight = torch.rand(2, 1, 3, 3).bfloat16()
    torch.testing.assert_close(depthwise_conv2d(image, weight), F.conv2d(image, weight, padding=1, groups=2))
    with pytest.raises(RuntimeError):  # conv2d refuses mixed dtypes itself: nothing is silently converted
        depthwise_conv2d(image.double(), weight.float())


def test_the_feature_networks_layers_keep_nn_conv2d_and_the_layer_norm_formula():
    torch.manual_seed(0)
    layer = DepthwiseConv2d(4, 5, dilation=2).double()
    x = torch.rand(2, 4, 11, 13, dtype=torch.float64, requires_grad=True)
    conv = torch.nn.Conv2d(4, 4, 5, padding=4, dilation=2, groups=4).double()
    conv.load_state_dict(layer.state_dict())
    torch.testing.assert_close(layer(x), conv(x), rtol=1e-12, atol=1e-12)

    norm = ChannelLayerNorm(4).double()
    with torch.no_grad():
        norm.weight.uniform_(0.5, 1.5)
        norm.bias.uniform_(-0.5, 0.5)
    mean = x.mean(dim=1, keepdim=True)
    var = (x - mean).pow(2).mean(dim=1, keepdim=True)
    want = (x - mean) * torch.rsqrt(var + norm.eps) * norm.weight[:, None, None] + norm.bias[:, None, None]
    got = norm(x)
    assert got.is_contiguous()
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    grad_out = torch.rand_like(x)
    torch.testing.assert_close(torch.autograd.grad(got, x, grad_out)[0], torch.autograd.grad(want, x, grad_out)[0])
