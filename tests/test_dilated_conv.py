"""The dilated "same" convolution on polyphase components equals PyTorch's dilated convolution, values and gradients,
and the blur field's modules that use it keep nn.Conv2d's parameters."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from gsmsdr_ns.blur.maan import LKA, MCA, SameDilatedConv2d
from gsmsdr_ns.ops.dilated_conv import dilated_conv2d_same


@pytest.mark.parametrize("size, k, d, groups, c_in, c_out", [
    ((13, 17), 7, 3, 6, 6, 6),   # depthwise, sizes not multiples of the dilation
    ((12, 9), 3, 2, 1, 4, 5),    # a full convolution
    ((5, 4), 5, 4, 2, 4, 2),     # the dilated kernel wider than the image
    ((8, 8), 3, 1, 1, 3, 3),     # no dilation
])  # fmt: skip
def test_equals_the_dilated_convolution_and_its_gradients(size, k, d, groups, c_in, c_out):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, c_in, *size, dtype=torch.float64, generator=g, requires_grad=True)
    w = torch.randn(c_out, c_in // groups, k, k, dtype=torch.float64, generator=g, requires_grad=True)
    b = torch.randn(c_out, dtype=torch.float64, generator=g, requires_grad=True)
    ours = dilated_conv2d_same(x, w, b, d, groups)
    ref = F.conv2d(x, w, b, padding=(k // 2) * d, dilation=d, groups=groups)
    torch.testing.assert_close(ours, ref, rtol=0, atol=1e-12)
    seed = torch.randn(ref.shape, dtype=torch.float64, generator=g)
    for a, e in zip(torch.autograd.grad(ours, (x, w, b), seed), torch.autograd.grad(ref, (x, w, b), seed)):
        torch.testing.assert_close(a, e, rtol=0, atol=1e-10)


def test_rejects_an_even_kernel_and_a_dilation_below_one():
    x = torch.zeros(1, 2, 6, 6)
    with pytest.raises(ValueError, match="odd square kernel"):
        dilated_conv2d_same(x, torch.zeros(2, 2, 4, 4), None, 2)
    with pytest.raises(ValueError, match="dilation"):
        dilated_conv2d_same(x, torch.zeros(2, 2, 3, 3), None, 0)


def test_the_field_modules_keep_nn_conv2d_parameters_and_outputs():
    torch.manual_seed(0)
    conv = SameDilatedConv2d(4, 4, 7, 3, groups=4)
    plain = torch.nn.Conv2d(4, 4, 7, padding=9, dilation=3, groups=4)
    plain.load_state_dict(conv.state_dict())  # the same keys and shapes: checkpoints load either way
    x = torch.randn(1, 4, 11, 14)
    torch.testing.assert_close(conv(x), plain(x), rtol=1e-5, atol=1e-5)
    lka, mca = LKA.lka5(8), MCA(8)
    assert set(lka.state_dict()) == {"dw.weight", "dw.bias", "dwd.weight", "dwd.bias", "pw.weight", "pw.bias"}
    assert mca.branches[3][0].dilation == (4, 4) and mca(torch.randn(1, 8, 9, 10)).shape == (1, 8, 9, 10)
