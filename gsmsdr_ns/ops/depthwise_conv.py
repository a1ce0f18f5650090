"""Depthwise k x k convolution (one filter per channel, zero padding that keeps the size), the blur field's feature
network's most frequent layer::

    depthwise_conv2d(image, weight, bias, dilation)
        == F.conv2d(image, weight, bias, padding=(k // 2) * dilation, dilation=dilation, groups=C)

On the CPU (float32 / float64) a C++/OpenMP kernel (``csrc/depthwise_conv.cpp``) computes it and its gradients: on
the feature network's small maps (16-32 channels of about 100 x 100 cells) oneDNN's depthwise backward costs several
times its forward. Elsewhere (CUDA, half precision, no compiler) PyTorch's convolution runs, on a channels-last copy
of the input on the CPU, where oneDNN's depthwise kernels are faster than in the default layout.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.function import once_differentiable

from gsmsdr_ns._cpp_ext import CppExtension

__all__ = ["depthwise_conv2d", "depthwise_conv_cpp_available"]

EXTENSION = CppExtension(
    name="gsmsdr_depthwise_cpu",
    source=Path(__file__).resolve().parent / "csrc" / "depthwise_conv.cpp",
    namespace="gsmsdr_depthwise",
    what="C++ depthwise convolution",
)
depthwise_conv_cpp_available = EXTENSION.available


class _DepthwiseConvCpp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, image: Tensor, weight: Tensor, dilation: int) -> Tensor:
        image_c, weight_c = image.contiguous(), weight.reshape(weight.shape[0], *weight.shape[-2:]).contiguous()
        ctx.dilation = dilation
        ctx.weight_shape = weight.shape
        ctx.save_for_backward(image_c, weight_c)
        return EXTENSION.load().depthwise_conv_fwd(image_c, weight_c, dilation)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor) -> Tuple[Optional[Tensor], Optional[Tensor], None]:
        image, weight = ctx.saved_tensors
        need_image, need_weight = ctx.needs_input_grad[:2]
        grad_image, grad_weight = EXTENSION.load().depthwise_conv_bwd(
            grad_out.contiguous(), image, weight, ctx.dilation, need_image, need_weight
        )
        if grad_weight is not None:
            grad_weight = grad_weight.reshape(ctx.weight_shape)
        return grad_image, grad_weight, None


def depthwise_conv2d(
    image: Tensor,  # [B, C, H, W]
    weight: Tensor,  # [C, 1, k, k]
    bias: Optional[Tensor] = None,  # [C]
    dilation: int = 1,
    backend: str = "auto",
) -> Tensor:  # [B, C, H, W]
    """Depthwise convolution with zero padding ``(k // 2) * dilation`` (the output has the input's size).

    Args:
        image: [B, C, H, W] floating-point image.
        weight: [C, 1, k, k] filters, odd k (``nn.Conv2d(C, C, k, groups=C).weight``), same dtype and device.
        bias: [C] or None.
        dilation: spacing of the filter taps, >= 1.
        backend: "cpp" (CPU float32/float64), "torch" (``F.conv2d``) or "auto".
    Returns:
        [B, C, H, W]; differentiable in ``image``, ``weight`` and ``bias``.
    """
    if image.dim() != 4 or weight.dim() != 4 or weight.shape[1] != 1 or weight.shape[0] != image.shape[1]:
        raise ValueError(f"depthwise_conv2d: expected image [B, C, H, W] and weight [C, 1, k, k], got "
                         f"{list(image.shape)} and {list(weight.shape)}")  # fmt: skip
    k = weight.shape[-1]
    if weight.shape[-2] != k or k % 2 == 0:
        raise ValueError(f"depthwise_conv2d: the filters must be square with an odd size, got {list(weight.shape)}")
    if int(dilation) != dilation or dilation < 1:
        raise ValueError(f"depthwise_conv2d: dilation must be an integer >= 1, got {dilation}")
    same_kind = weight.dtype == image.dtype and weight.device == image.device
    chosen = "torch" if backend == "auto" and not same_kind else backend
    chosen = EXTENSION.backend_for(
        image, chosen, unavailable="C++ depthwise convolution", fallback="torch's convolution"
    )
    if chosen == "cpp":
        out = _DepthwiseConvCpp.apply(image, weight, int(dilation))
        return out if bias is None else out + bias.view(1, -1, 1, 1)
    pad = (k // 2) * int(dilation)
    source = image.contiguous(memory_format=torch.channels_last) if image.device.type == "cpu" else image
    out = F.conv2d(source, weight, bias, padding=pad, dilation=int(dilation), groups=image.shape[1])
    return out.contiguous()
