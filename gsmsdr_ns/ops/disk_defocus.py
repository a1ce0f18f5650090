"""Thin-lens defocus applied to an image without materialising its K*K per-pixel kernels.

``apply_occluding_defocus(image, radius, inverse_depth, K, softness)`` is
``apply_pixel_kernels(image, occluding_disk_kernels(radius, inverse_depth, K, softness))`` and
``apply_soft_disk_defocus(image, radius, K, softness)`` is ``apply_pixel_kernels(image, soft_disk_kernels(radius, K,
softness))`` (equal up to float rounding), fused: the kernels' weights are computed tap by tap where they are used
and recomputed in the backward, so no [B, K*K, H, W] tensor exists (the unfused occluding kernels keep about six of
them for the backward). Gradients reach ``image`` and ``radius``; ``inverse_depth`` is only compared.

On CPU (float32 / float64) a C++/OpenMP kernel with one parallel region per call (`gsmsdr_ns.ops.disk_defocus_cpp`);
elsewhere (CUDA, half precision, no compiler) a PyTorch twin that loops over the K*K offsets with [B, 1, H, W]
temporaries and recomputes them in its backward.
"""

from __future__ import annotations

import math
from typing import Literal, Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.function import once_differentiable

from gsmsdr_ns.ops.pixel_kernels import _replicate_pad_adjoint

__all__ = ["apply_occluding_defocus", "apply_soft_disk_defocus", "DefocusBackend"]

DefocusBackend = Literal["auto", "cpp", "torch"]


def _check(image: Tensor, radius: Tensor, inverse_depth: Tensor, kernel_size: int, softness: float) -> None:
    """Shapes, dtypes and devices; errors name the expected and the actual values."""
    if kernel_size < 1 or kernel_size % 2 == 0:
        raise ValueError(f"kernel_size must be a positive odd integer, got {kernel_size}")
    if not softness > 0:
        raise ValueError(f"softness must be > 0, got {softness}")
    if image.dim() != 4:
        raise ValueError(f"image: expected shape [B, C, H, W], got {list(image.shape)}")
    B, _, H, W = image.shape
    if H < 1 or W < 1:
        raise ValueError(f"image: expected H >= 1 and W >= 1, got shape {list(image.shape)}")
    for name, x in (("radius", radius), ("inverse_depth", inverse_depth)):
        if tuple(x.shape) != (B, 1, H, W):
            raise ValueError(f"{name}: expected shape [B, 1, H, W] = {[B, 1, H, W]} to match image "
                             f"{list(image.shape)}, got {list(x.shape)}")  # fmt: skip
        if x.dtype != image.dtype or not image.is_floating_point():
            raise ValueError(
                f"image and {name}: expected the same floating-point dtype, got {image.dtype} and {x.dtype} "
                f"(cast {name} with .to(image.dtype))"
            )
        if x.device != image.device:
            raise ValueError(f"image and {name}: expected the same device, got {image.device} and {x.device}")


def _tap_constants(K: int, softness: float, dtype: torch.dtype, device: torch.device) -> Tuple[Tensor, Tensor]:
    """[K*K] distance of every window offset from the centre and the coverage of an empty disk there, built on the
    device (a tensor made from Python numbers would be a host-to-device copy per call)."""
    offsets = torch.arange(K, dtype=dtype, device=device) - K // 2
    distance = torch.hypot(offsets[:, None], offsets[None, :]).reshape(-1)
    return distance, torch.sigmoid(-distance / softness)


class _Tap:
    """One window offset (i, j) of the fused op in PyTorch: its distance and empty-disk coverage (0-dim views of
    :func:`_tap_constants`)."""

    def __init__(self, K: int, i: int, j: int, constants: Tuple[Tensor, Tensor]) -> None:
        p = K // 2
        self.centre = i == p and j == p
        self.distance = constants[0][i * K + j]
        self.base = constants[1][i * K + j]  # subtracted from the coverage: radius 0 is sharp


def _tap_terms(
    r_q: Tensor, z_q: Tensor, radius: Tensor, inverse_depth: Tensor, tap: _Tap, softness: float, occlusion: bool,
    need_grad: bool,
) -> Tuple[Tensor, Tensor, Optional[Tensor], Optional[Tensor], Optional[Tensor], Optional[Tensor]]:  # fmt: skip
    """(u, cov, sig, area, dreach_q, dreach_p) of one tap; u is the unnormalised weight. The reach derivatives follow
    torch.minimum's rule (half to each side on a tie)."""
    dreach_q = dreach_p = None
    if not occlusion:
        reach = radius
    else:
        behind = z_q < inverse_depth
        reach = torch.where(behind, torch.minimum(r_q, radius), r_q)
        if need_grad:
            half = torch.where(r_q == radius, 0.5, 0.0).to(radius.dtype)
            dreach_q = torch.where(behind, (r_q < radius).to(radius.dtype) + half, torch.ones_like(half))
            dreach_p = torch.where(behind, (radius < r_q).to(radius.dtype) + half, torch.zeros_like(half))
    if tap.centre:
        sig = None
        cov = torch.ones_like(reach)
    else:
        sig = torch.sigmoid((reach - tap.distance) / softness)
        cov = sig - tap.base
    if occlusion:
        area = 1.0 / (1.0 + math.pi * r_q**2)
        u = cov / (1.0 + math.pi * r_q**2)
    else:
        area = None
        u = cov
    return u, cov, sig, area, dreach_q, dreach_p


class _DiskDefocusTorch(torch.autograd.Function):
    """Device-agnostic twin: loops over the K*K offsets with [B, 1, H, W] temporaries, recomputed in the backward.

    Extra memory: the padded image, radius and inverse depth, the weight sums, and in the backward the padded
    gradients; one [B, C, H, W] temporary per offset at a time.
    """

    @staticmethod
    def forward(ctx, image: Tensor, radius: Tensor, inverse_depth: Tensor, K: int, softness: float, occlusion: bool):
        H, W = image.shape[-2:]
        p = K // 2
        pad = (p, p, p, p)
        image_p = F.pad(image, pad, mode="replicate")
        radius_p = F.pad(radius, pad, mode="replicate")
        depth_p = F.pad(inverse_depth, pad, mode="replicate")
        total = torch.zeros_like(image, memory_format=torch.contiguous_format)
        weight_sum = torch.zeros_like(radius, memory_format=torch.contiguous_format)
        constants = _tap_constants(K, softness, image.dtype, image.device)
        with torch.no_grad():
            for i in range(K):
                for j in range(K):
                    tap = _Tap(K, i, j, constants)
                    window = (..., slice(i, i + H), slice(j, j + W))
                    u = _tap_terms(radius_p[window], depth_p[window], radius, inverse_depth, tap, softness,
                                   occlusion, False)[0]  # fmt: skip
                    weight_sum += u
                    total.addcmul_(image_p[window], u)
            out = total / weight_sum
        ctx.K, ctx.softness, ctx.occlusion = K, softness, occlusion
        ctx.save_for_backward(image, radius, inverse_depth, out, weight_sum)
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor):
        image, radius, inverse_depth, out, weight_sum = ctx.saved_tensors
        K, softness, occlusion = ctx.K, ctx.softness, ctx.occlusion
        need_image, need_radius = ctx.needs_input_grad[:2]
        B, C, H, W = image.shape
        p = K // 2
        pad = (p, p, p, p)
        image_p = F.pad(image, pad, mode="replicate")
        radius_p = F.pad(radius, pad, mode="replicate")
        depth_p = F.pad(inverse_depth, pad, mode="replicate")
        beta = (grad_out * out).sum(1, keepdim=True)  # [B, 1, H, W]
        grad_image_p = image.new_zeros(B, C, H + 2 * p, W + 2 * p) if need_image else None
        grad_radius_p = radius.new_zeros(B, 1, H + 2 * p, W + 2 * p) if need_radius and occlusion else None
        grad_radius_own = torch.zeros_like(radius) if need_radius else None
        constants = _tap_constants(K, softness, image.dtype, image.device)
        for i in range(K):
            for j in range(K):
                tap = _Tap(K, i, j, constants)
                window = (..., slice(i, i + H), slice(j, j + W))
                r_q = radius_p[window]
                u, cov, sig, area, dreach_q, dreach_p = _tap_terms(
                    r_q, depth_p[window], radius, inverse_depth, tap, softness, occlusion, need_radius
                )
                if grad_image_p is not None:
                    grad_image_p[window].addcmul_(grad_out, u / weight_sum)
                if grad_radius_own is None:
                    continue
                dl_du = ((grad_out * image_p[window]).sum(1, keepdim=True) - beta) / weight_sum
                dcov = None if sig is None else sig * (1.0 - sig) / softness
                if not occlusion:
                    if dcov is not None:
                        grad_radius_own += dl_du * dcov
                    continue
                # occlusion with need_radius: _tap_terms made area and the reach derivatives, and grad_radius_p exists
                assert area is not None and dreach_q is not None and dreach_p is not None and grad_radius_p is not None
                d_u = -2.0 * math.pi * r_q * area * area * cov  # through the area 1 / (1 + pi r_q^2)
                if dcov is not None:
                    grad_radius_own += dl_du * dcov * dreach_p * area
                    d_u = d_u + dcov * dreach_q * area
                grad_radius_p[window] += dl_du * d_u
        grad_image = None if grad_image_p is None else _replicate_pad_adjoint(grad_image_p, p)
        grad_radius = grad_radius_own
        if grad_radius_p is not None:
            assert grad_radius is not None  # grad_radius_p is only made when need_radius
            grad_radius = grad_radius + _replicate_pad_adjoint(grad_radius_p, p)
        return grad_image, grad_radius, None, None, None, None


class _DiskDefocusCpp(torch.autograd.Function):
    """C++ forward / backward (`disk_kernels_cpp`); inputs are made contiguous here so gradients reach the caller's."""

    @staticmethod
    def forward(ctx, image: Tensor, radius: Tensor, inverse_depth: Tensor, K: int, softness: float, occlusion: bool):
        from gsmsdr_ns.ops.disk_defocus_cpp import disk_defocus_fwd_cpp

        image_c, radius_c, depth_c = image.contiguous(), radius.contiguous(), inverse_depth.contiguous()
        out, weight_sum = disk_defocus_fwd_cpp(image_c, radius_c, depth_c, K, softness, occlusion)
        ctx.K, ctx.softness, ctx.occlusion = K, softness, occlusion
        ctx.save_for_backward(image_c, radius_c, depth_c, out, weight_sum)
        ctx.mark_non_differentiable(weight_sum)
        return out, weight_sum

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor, _grad_sum: Optional[Tensor]):
        from gsmsdr_ns.ops.disk_defocus_cpp import disk_defocus_bwd_cpp

        image, radius, inverse_depth, out, weight_sum = ctx.saved_tensors
        need_image, need_radius = ctx.needs_input_grad[:2]
        grad_image, grad_radius = disk_defocus_bwd_cpp(
            grad_out.contiguous(), image, radius, inverse_depth, out, weight_sum, ctx.K, ctx.softness,
            ctx.occlusion, need_image, need_radius,
        )  # fmt: skip
        return grad_image, grad_radius, None, None, None, None


def _apply(image, radius, inverse_depth, kernel_size, softness, occlusion, backend) -> Tensor:
    from gsmsdr_ns.ops.disk_defocus_cpp import EXTENSION

    chosen = EXTENSION.backend_for(
        image, backend, unavailable="C++ thin-lens defocus op", fallback="the PyTorch loop (slower)"
    )
    if chosen == "cpp":
        return _DiskDefocusCpp.apply(image, radius, inverse_depth.detach(), kernel_size, float(softness), occlusion)[0]
    return _DiskDefocusTorch.apply(image, radius, inverse_depth.detach(), kernel_size, float(softness), occlusion)


def apply_occluding_defocus(
    image: Tensor,  # [B, C, H, W]
    radius: Tensor,  # [B, 1, H, W]
    inverse_depth: Tensor,  # [B, 1, H, W]
    kernel_size: int,
    softness: float = 0.25,
    backend: DefocusBackend = "auto",
) -> Tensor:  # [B, C, H, W]
    """``apply_pixel_kernels(image, occluding_disk_kernels(radius, inverse_depth, kernel_size, softness))`` without
    any [B, K*K, H, W] tensor (see :func:`~gsmsdr_ns.blur.defocus.occluding_disk_kernels` for the kernels).

    Args:
        image: [B, C, H, W] floating-point image (differentiable).
        radius: [B, 1, H, W] disk radius in pixels, >= 0, the image's dtype and device (differentiable).
        inverse_depth: [B, 1, H, W] 1 / depth, the image's dtype and device (only compared, never differentiated).
        kernel_size: odd window size K.
        softness: edge width in pixels (> 0).
        backend: "cpp" (C++/OpenMP, CPU float32/float64 only), "torch" (a loop over the K*K offsets, any device)
            or "auto": "cpp" when it applies and the extension builds, else "torch".
    Returns:
        [B, C, H, W] blurred image, contiguous.
    Raises:
        ValueError: wrong shapes, an even or non-positive K, softness <= 0, mismatched dtypes or devices.
    """
    _check(image, radius, inverse_depth, kernel_size, softness)
    return _apply(image, radius, inverse_depth, kernel_size, softness, True, backend)


def apply_soft_disk_defocus(
    image: Tensor,  # [B, C, H, W]
    radius: Tensor,  # [B, 1, H, W]
    kernel_size: int,
    softness: float = 0.25,
    backend: DefocusBackend = "auto",
) -> Tensor:  # [B, C, H, W]
    """``apply_pixel_kernels(image, soft_disk_kernels(radius, kernel_size, softness))`` without any [B, K*K, H, W]
    tensor: every pixel gathers its own soft disk. Arguments as :func:`apply_occluding_defocus`."""
    _check(image, radius, radius, kernel_size, softness)
    return _apply(image, radius, radius, kernel_size, softness, False, backend)
