"""Apply per-pixel K x K blur kernels to an image (the BAGS / HPKO kernel application step) without unfold.

Convention, shared by every implementation here. With ``p = K // 2`` and the row-major kernel index
``k = i * K + j`` (``i`` the kernel row, ``j`` the kernel column, both in ``[0, K)``)::

    out[b, c, y, x] = sum_{i, j} weights[b, i * K + j, y, x]
                      * image[b, c, clamp(y + i - p, 0, H - 1), clamp(x + j - p, 0, W - 1)]

that is, kernel entry (i, j) weighs the pixel ``(i - p)`` rows below and ``(j - p)`` columns right of the output
pixel (a correlation, not a flipped convolution), and pixels outside the image take the value of the nearest border
pixel (replicate padding, ``F.pad(image, (p, p, p, p), mode="replicate")``). This is exactly the channel order of
``F.unfold(padded, K)`` viewed as ``[B, C, K*K, H*W]``, which is how BAGS applies its blur proposal network's kernels
(`apply_pixel_kernels_unfold`). Weights are used as given: no normalisation, any sign.

Cost. The unfold version materialises all K*K shifted copies of the image (17 x 17 at 600x400 RGB: 832 MB of
patches, plus as much again for the product and twice more in the backward). `apply_pixel_kernels` never allocates
anything of size K*K x image beyond the gradient of ``weights`` itself: the forward accumulates one shifted row at a
time and the backward recomputes the shifts. On CPU (float32 / float64) it runs a C++/OpenMP kernel with one
parallel region per call (`gsmsdr_ns.ops.pixel_kernels_cpp`); elsewhere (CUDA, half precision, no compiler) a PyTorch
twin that loops over the K*K offsets, one shifted view of the padded image at a time. `gsmsdr-bench kernels` measures
both against the unfold version.
"""

from __future__ import annotations

import math
from typing import Literal, Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from gsmsdr_ns.ops.fft_length import fast_fft_length

PixelKernelBackend = Literal["auto", "cpp", "torch"]


def pixel_kernel_size(num_channels: int) -> int:
    """The odd kernel size K with ``K * K == num_channels``.

    Raises:
        ValueError: ``num_channels`` is not the square of an odd positive integer.
    """
    K = math.isqrt(num_channels) if num_channels > 0 else 0
    if K * K != num_channels or K % 2 == 0:
        raise ValueError(
            f"weights: expected K*K channels for an odd kernel size K (1, 9, 25, 49, ...), got {num_channels}"
            + (f" (= {K}*{K}, K is even)" if K > 0 and K * K == num_channels else " (not a square)")
        )
    return K


def _check_inputs(image: Tensor, weights: Tensor) -> int:
    """Validate shapes, dtypes and devices; return K. Errors name the expected and the actual shapes."""
    if not isinstance(image, Tensor) or not isinstance(weights, Tensor):
        raise TypeError(f"image and weights must be tensors, got {type(image).__name__}, {type(weights).__name__}")
    if image.dim() != 4:
        raise ValueError(f"image: expected shape [B, C, H, W], got {list(image.shape)}")
    if weights.dim() != 4:
        raise ValueError(f"weights: expected shape [B, K*K, H, W], got {list(weights.shape)}")
    B, C, H, W = image.shape
    if H < 1 or W < 1:
        raise ValueError(f"image: expected H >= 1 and W >= 1, got shape {list(image.shape)}")
    K = pixel_kernel_size(weights.shape[1])
    if weights.shape[0] != B or tuple(weights.shape[2:]) != (H, W):
        raise ValueError(
            f"weights: expected shape [B, K*K, H, W] = {[B, K * K, H, W]} to match image {list(image.shape)}, "
            f"got {list(weights.shape)}"
        )
    if not image.is_floating_point() or weights.dtype != image.dtype:
        raise ValueError(
            f"image and weights: expected the same floating-point dtype, got {image.dtype} and {weights.dtype}"
        )
    if weights.device != image.device:
        raise ValueError(f"image and weights: expected the same device, got {image.device} and {weights.device}")
    return K


def _replicate_pad_adjoint(grad_padded: Tensor, p: int) -> Tensor:
    """Adjoint of ``F.pad(x, (p, p, p, p), mode="replicate")``: [B, C, H+2p, W+2p] -> [B, C, H, W].

    The margin rows are summed onto the first / last row, then the margin columns (corners included, as they were
    folded into the margin columns of those rows) onto the first / last column.
    """
    if p == 0:
        return grad_padded
    Hp, Wp = grad_padded.shape[-2:]
    H, W = Hp - 2 * p, Wp - 2 * p
    rows = grad_padded[..., p : p + H, :].clone()  # [B, C, H, W+2p]
    rows[..., 0, :] += grad_padded[..., :p, :].sum(-2)
    rows[..., H - 1, :] += grad_padded[..., p + H :, :].sum(-2)
    out = rows[..., p : p + W].clone()  # [B, C, H, W]
    out[..., 0] += rows[..., :p].sum(-1)
    out[..., W - 1] += rows[..., p + W :].sum(-1)
    return out


def _kernel_row_windows(padded: Tensor, i: int, H: int, W: int, K: int) -> Tensor:
    """[B, C, H, W, K] view (no copy) of the K taps of kernel row ``i`` at every pixel: entry (.., y, x, j) is
    ``padded[.., y + i, x + j]``."""
    return padded[:, :, i : i + H, :].unfold(3, K, 1)


def _kernel_row_weights(weights: Tensor, i: int, K: int) -> Tensor:
    """[B, 1, H, W, K] view of the weights of kernel row ``i`` (entry j: ``weights[:, i * K + j]``)."""
    return weights[:, i * K : (i + 1) * K].permute(0, 2, 3, 1).unsqueeze(1)


class _PixelKernelsTorch(torch.autograd.Function):
    """Device-agnostic twin, one kernel row at a time: a strided [B, C, H, W, K] view of the padded image holds the
    row's K taps at every pixel, so a K x K kernel costs K broadcast products and reductions (a few dozen device
    kernels at K = 17) instead of K*K shifted ones; the backward folds each row's products back with ``F.fold``.

    Extra memory: the padded image and, per kernel row at a time, [B, C, H, W, K] products (K / 3 times the
    [B, K*K, H, W] weights over K rows for RGB); the padded image gradient in the backward. On CPUs, where each op's
    OpenMP barrier can stall on a shared machine, CPU tensors normally take the C++ kernel instead.
    """

    @staticmethod
    def forward(ctx, image: Tensor, weights: Tensor, K: int) -> Tensor:
        H, W = image.shape[-2:]
        p = K // 2
        padded = F.pad(image, (p, p, p, p), mode="replicate")  # [B, C, H+2p, W+2p]
        out = torch.zeros_like(image, memory_format=torch.contiguous_format)
        for i in range(K):
            out += (_kernel_row_windows(padded, i, H, W, K) * _kernel_row_weights(weights, i, K)).sum(-1)
        ctx.K = K
        ctx.save_for_backward(image, weights)
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor) -> Tuple[Optional[Tensor], Optional[Tensor], None]:
        image, weights = ctx.saved_tensors
        K = ctx.K
        B, C, H, W = image.shape
        p = K // 2
        grad_out = grad_out.contiguous()
        grad_image = grad_weights = None
        if ctx.needs_input_grad[1]:
            # grad_weights[:, i*K + j] = sum_c grad_out[:, c] * padded[:, c, y + i, x + j]
            padded = F.pad(image, (p, p, p, p), mode="replicate")
            grad_weights = torch.empty_like(weights, memory_format=torch.contiguous_format)
            for i in range(K):
                row = (grad_out.unsqueeze(-1) * _kernel_row_windows(padded, i, H, W, K)).sum(1)  # [B, H, W, K]
                grad_weights[:, i * K : (i + 1) * K] = row.permute(0, 3, 1, 2)
        if ctx.needs_input_grad[0]:
            # grad_padded[:, :, y + i, x + j] += grad_out[:, :, y, x] * weights[:, i*K + j, y, x]: per kernel row,
            # F.fold sums the K products of every pixel into the K columns they came from
            grad_padded = image.new_zeros(B, C, H + 2 * p, W + 2 * p)
            for i in range(K):
                products = grad_out.unsqueeze(-1) * _kernel_row_weights(weights, i, K)  # [B, C, H, W, K]
                columns = products.permute(0, 1, 4, 2, 3).reshape(B, C * K, H * W)
                grad_padded[:, :, i : i + H, :] += F.fold(columns, (H, W + 2 * p), kernel_size=(1, K))
            grad_image = _replicate_pad_adjoint(grad_padded, p)
        return grad_image, grad_weights, None


class _PixelKernelsCpp(torch.autograd.Function):
    """C++ forward / backward (`kernels_cpp`); inputs are made contiguous here so gradients reach the caller's."""

    @staticmethod
    def forward(ctx, image: Tensor, weights: Tensor, K: int) -> Tensor:
        from gsmsdr_ns.ops.pixel_kernels_cpp import pixel_kernels_fwd_cpp

        image_c, weights_c = image.contiguous(), weights.contiguous()
        ctx.K = K
        ctx.save_for_backward(image_c, weights_c)
        return pixel_kernels_fwd_cpp(image_c, weights_c, K)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor) -> Tuple[Optional[Tensor], Optional[Tensor], None]:
        from gsmsdr_ns.ops.pixel_kernels_cpp import pixel_kernels_bwd_cpp

        image, weights = ctx.saved_tensors
        need_image, need_weights = ctx.needs_input_grad[:2]
        grad_image, grad_weights = pixel_kernels_bwd_cpp(
            grad_out.contiguous(), image, weights, ctx.K, need_image, need_weights
        )
        return grad_image, grad_weights, None


def apply_pixel_kernels(
    image: Tensor,  # [B, C, H, W]
    weights: Tensor,  # [B, K*K, H, W]
    backend: PixelKernelBackend = "auto",
) -> Tensor:  # [B, C, H, W]
    """Blur every pixel with its own K x K kernel, replicate border, without materialising K*K image copies.

    ``out[b, c, y, x] = sum_{i,j} weights[b, i*K + j, y, x] * image[b, c, clamp(y+i-p), clamp(x+j-p)]`` with
    ``p = K // 2``: row-major kernel index, entry (i, j) reads the pixel offset by (i - p) rows and (j - p) columns,
    rows / columns outside the image replicate the border (see the module docstring). Identical, up to float
    rounding, to `apply_pixel_kernels_unfold`, the F.unfold formulation used by BAGS.

    Differentiable in ``image`` and ``weights`` (first order; the backward is not itself differentiable). Memory
    beyond the inputs: the output, and in the backward the two gradients (``weights``' is as large as ``weights``).

    Args:
        image: [B, C, H, W] floating-point image, any strides.
        weights: [B, K*K, H, W] per-pixel kernels for an odd K, same dtype and device as ``image``; used as given
            (softmax them beforehand for normalised kernels).
        backend: "cpp" (C++/OpenMP, CPU float32/float64 only), "torch" (a loop of K*K PyTorch ops, any device) or
            "auto": "cpp" when it applies and the extension builds, else "torch".

    Returns:
        [B, C, H, W] blurred image, contiguous, same dtype and device as ``image``.

    Raises:
        ValueError: wrong ranks, K*K not the square of an odd K, batch / height / width mismatch, dtype or device
            mismatch; the message names expected and actual shapes.
    """
    K = _check_inputs(image, weights)
    from gsmsdr_ns.ops.pixel_kernels_cpp import EXTENSION

    chosen = EXTENSION.backend_for(
        image, backend, unavailable="C++ pixel-kernel op", fallback="the PyTorch loop (slower on busy CPUs)"
    )
    if chosen == "cpp":
        return _PixelKernelsCpp.apply(image, weights, K)
    return _PixelKernelsTorch.apply(image, weights, K)


def apply_image_kernels(
    image: Tensor,  # [B, C, H, W]
    kernels: Tensor,  # [B, K*K]
) -> Tensor:  # [B, C, H, W]
    """Blur each image with one K x K kernel: ``apply_pixel_kernels`` with the same kernel at every pixel.

    Same convention (row-major index, correlation, replicate border), no per-pixel weights. Float32 / float64 images
    are blurred by a product of 2D real FFTs of the replicate-padded image and the flipped kernel (their circular
    overlap falls in the padding, which is cropped); at K = 17 on a 504x378 image its forward and backward take a
    sixth of a grouped ``F.conv2d``'s time on a CPU. Other dtypes take the grouped convolution. Differentiable in
    both inputs.

    Args:
        image: [B, C, H, W] floating-point image.
        kernels: [B, K*K] for an odd K (cast to the image's dtype).
    Returns:
        [B, C, H, W]
    """
    if image.dim() != 4:
        raise ValueError(f"image: expected shape [B, C, H, W], got {list(image.shape)}")
    if kernels.dim() != 2 or kernels.shape[0] != image.shape[0]:
        raise ValueError(f"kernels: expected shape [{image.shape[0]}, K*K], got {list(kernels.shape)}")
    B, C, H, W = image.shape
    K = pixel_kernel_size(kernels.shape[1])
    p = K // 2
    if image.dtype in (torch.float32, torch.float64):
        padded = F.pad(image, (p, p, p, p), mode="replicate")  # [B, C, H + 2p, W + 2p]
        # a longer transform only moves the circular wrap further into the cropped border; a length with a large
        # prime factor (365 = 5 x 73) transforms several times slower than the next 2-3-5-smooth one (375)
        size = (fast_fft_length(H + 2 * p), fast_fft_length(W + 2 * p))
        flipped = kernels.to(image.dtype).reshape(B, 1, K, K).flip(-2, -1)  # correlation as a convolution
        product = torch.fft.rfft2(padded, s=size) * torch.fft.rfft2(flipped, s=size)
        # output pixel (y, x) of a K x K convolution anchored at the kernel's corner lands at (y + 2p, x + 2p)
        return torch.fft.irfft2(product, s=size)[..., 2 * p : 2 * p + H, 2 * p : 2 * p + W].contiguous()
    padded = F.pad(image.reshape(1, B * C, H, W), (p, p, p, p), mode="replicate")
    weight = kernels.to(image.dtype).reshape(B, 1, K, K).repeat_interleave(C, dim=0)  # [B*C, 1, K, K]
    return F.conv2d(padded, weight, groups=B * C).reshape(B, C, H, W)


def kernel_centroids(weights: Tensor) -> Tensor:
    """Centre of mass of each pixel's kernel, in pixels from the pixel itself (the shift the kernel applies).

    Args:
        weights: [B, K*K, H, W] kernel weights in the row-major convention above (any grid: per pixel, or the blur
            field's coarse grid; each kernel is expected to sum to 1, as softmax kernels do).
    Returns:
        [B, 2, H, W]: (row, column) offsets, ``sum_k w_k * (i_k - p, j_k - p)``; 0 for a centred (symmetric) kernel.
    """
    offsets = kernel_tap_offsets(pixel_kernel_size(weights.shape[1]), weights.device, weights.dtype)
    return torch.einsum("mk,bkhw->bmhw", offsets, weights)


def kernel_tap_offsets(K: int, device=None, dtype=None) -> Tensor:
    """[2, K*K] (row, column) offset in pixels of each kernel entry from the window's centre (row-major index)."""
    offsets = torch.arange(K, device=device, dtype=dtype) - K // 2
    return torch.stack([offsets.repeat_interleave(K), offsets.repeat(K)])  # entry k = i * K + j: row i, column j


def apply_pixel_kernels_unfold(
    image: Tensor,  # [B, C, H, W]
    weights: Tensor,  # [B, K*K, H, W]
) -> Tensor:  # [B, C, H, W]
    """Reference (BAGS-style): replicate-pad, ``F.unfold`` into [B, C, K*K, H, W] patches, weight and sum.

    Same convention and checks as `apply_pixel_kernels`; autograd does the backward. Allocates
    ``B * C * K*K * H * W`` elements for the patches (0.8 GB at 600x400 RGB, K=17) and as much for their product
    with the weights; kept for tests and `gsmsdr-bench kernels` only.
    """
    K = _check_inputs(image, weights)
    B, C, H, W = image.shape
    p = K // 2
    padded = F.pad(image, (p, p, p, p), mode="replicate")  # [B, C, H+2p, W+2p]
    patches = F.unfold(padded, kernel_size=K).view(B, C, K * K, H, W)  # channel c*K*K + i*K + j
    return (patches * weights.unsqueeze(1)).sum(2)


class ApplyPixelKernels(nn.Module):
    """Module twin of `apply_pixel_kernels`; holds only the backend choice.

    Shape:
        - image: [B, C, H, W]
        - weights: [B, K*K, H, W]
        - output: [B, C, H, W]
    """

    def __init__(self, backend: PixelKernelBackend = "auto") -> None:
        super().__init__()
        self.backend = backend

    def forward(self, image: Tensor, weights: Tensor) -> Tensor:
        return apply_pixel_kernels(image, weights, backend=self.backend)

    def extra_repr(self) -> str:
        return f"backend={self.backend!r}"
