"""Degradation kernels as pure functions on image tensors, with thin `nn.Module` twins (kornia style).

Conventions:
    images are float tensors [B, C, H, W] with values in [0, 1];
    pixel coordinates follow COLMAP: the top-left pixel centre is (0.5, 0.5), x right, y down;
    intrinsics K are [3, 3] pinhole matrices in that convention (kornia's warps use integer pixel centres, the
    conversion happens inside `homography_blur`);
    a rotation R / translation t "from the reference camera to camera t" maps camera coordinates X_ref of the
    reference (sharp) view to X_t = R X_ref + t.
PSFs are applied as convolutions: a delta at pixel p blurred with kernel k ends up on p + offsets of k, where
the kernel centre (k // 2, k // 2) is offset (0, 0).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache

import numpy as np
import torch
from kornia.filters import filter2d
from kornia.geometry.transform import warp_perspective
from torch import Tensor, nn

from ..ops.checks import check_image
from ..ops.splat import splat_bilinear

__all__ = [
    "disk_kernel",
    "motion_kernel_from_trajectory",
    "convolve_psf",
    "plane_homography",
    "homography_blur",
    "rotational_shake_blur",
    "path_extent",
    "defocus_radius",
    "disk_blur",
    "radius_levels",
    "apply_defocus",
    "add_noise",
    "PSFBlur",
    "RotationalShakeBlur",
    "LayeredDefocus",
]


def _as_tensor(x: Tensor | np.ndarray | Sequence, dtype: torch.dtype = torch.float64) -> Tensor:
    return x.to(dtype) if isinstance(x, Tensor) else torch.as_tensor(np.asarray(x), dtype=dtype)


# ------------------------------------------------------------------------------------------------- PSF kernels


@lru_cache(maxsize=256)
def _disk_kernel_np(radius: float, oversample: int) -> np.ndarray:
    half = max(0, math.ceil(radius + 0.5) - 1)
    k = 2 * half + 1
    sub = (np.arange(k * oversample) + 0.5) / oversample - 0.5 - half  # sub-sample offsets from the centre
    yy, xx = np.meshgrid(sub, sub, indexing="ij")
    inside = (xx * xx + yy * yy <= radius * radius).reshape(k, oversample, k, oversample)
    w = inside.mean(axis=(1, 3))
    if w.sum() <= 0:  # radius below the sub-sample spacing: a delta
        w = np.zeros((k, k))
        w[half, half] = 1.0
    return w / w.sum()


def disk_kernel(radius: float, oversample: int = 8, dtype: torch.dtype = torch.float32) -> Tensor:
    """Normalised disk PSF of the given radius in pixels (area coverage of each pixel, anti-aliased).

    Returns [k, k] with k = 2 * (ceil(radius + 0.5) - 1) + 1 (k = 1, a delta, for radius <= 0.5), summing to 1.
    """
    if not math.isfinite(radius) or radius < 0:
        raise ValueError(f"disk radius must be finite and >= 0, got {radius}")
    return torch.from_numpy(_disk_kernel_np(round(float(radius), 6), int(oversample))).to(dtype)


def motion_kernel_from_trajectory(
    trajectory: Tensor | np.ndarray,  # [T, 2]
    kernel_size: int | None = None,
    step_px: float = 0.25,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """Motion-blur PSF of a pixel path sampled at equal time steps.

    Args:
        trajectory: [T, 2] pixel offsets (dx, dy) of the image during the exposure, at equally spaced times;
            the path between samples is linear at constant speed (so each segment holds 1 / (T - 1) of the energy).
        kernel_size: odd side of the kernel; default the smallest odd size that holds the path.
        step_px: spacing of the points splatted along each segment (bilinear splatting).
    Returns:
        kernel [k, k] summing to 1; entry [k//2 + dy, k//2 + dx] holds the time fraction spent at offset (dx, dy).
    """
    traj = _as_tensor(trajectory)
    if traj.dim() != 2 or traj.shape[1] != 2 or traj.shape[0] < 1:
        raise ValueError(f"trajectory must be [T, 2] with T >= 1, got {tuple(traj.shape)}")
    if not torch.isfinite(traj).all():
        raise ValueError("trajectory has non-finite offsets")
    need = 2 * math.ceil(float(traj.abs().max()) + 1.0) + 1
    k = need if kernel_size is None else int(kernel_size)
    if k % 2 == 0 or k < need:
        raise ValueError(f"kernel_size must be odd and >= {need} for this trajectory, got {kernel_size}")
    if traj.shape[0] == 1:
        pts, wts = traj, torch.ones(1, dtype=traj.dtype)
    else:
        seg = traj[1:] - traj[:-1]  # [T-1, 2]
        pts_list, wts_list = [], []
        for a, d in zip(traj[:-1], seg):
            n = max(1, math.ceil(float(d.norm()) / step_px))
            s = (torch.arange(n, dtype=traj.dtype) + 0.5) / n  # midpoints: equal time per point
            pts_list.append(a + s[:, None] * d)
            wts_list.append(torch.full((n,), 1.0 / n, dtype=traj.dtype))
        pts, wts = torch.cat(pts_list), torch.cat(wts_list)
    c = k // 2
    kernel = splat_bilinear(pts + c, wts, k)  # k >= need keeps every point and its four cells inside
    kernel = kernel.reshape(k, k)
    return (kernel / kernel.sum()).to(dtype)


def convolve_psf(
    image: Tensor,  # [B, C, H, W]
    kernel: Tensor,  # [k, k] or [B, k, k]
    border_type: str = "reflect",
) -> Tensor:
    """Spatially uniform blur: convolution (not correlation) of every channel with a PSF. -> [B, C, H, W]."""
    check_image(image)
    if kernel.dim() == 2:
        kernel = kernel[None]
    if kernel.dim() != 3 or kernel.shape[0] not in (1, image.shape[0]) or kernel.shape[-1] % 2 == 0:
        raise ValueError(f"kernel must be [k, k] or [B, k, k] with odd k, got {tuple(kernel.shape)}")
    return filter2d(image, kernel.to(image), border_type=border_type, behaviour="conv")


# --------------------------------------------------------------------------------- camera shake (homographies)


def plane_homography(
    K_src: Tensor,  # [3, 3]
    K_dst: Tensor,  # [3, 3]
    R: Tensor,  # [..., 3, 3]
    t: Tensor | None = None,  # [..., 3]
    plane_depth: float | Tensor = 1.0,
) -> Tensor:
    """Homography from src pixels to dst pixels induced by the fronto-parallel plane z = plane_depth of src.

    X_dst = R X_src + t for points with X_src,z = plane_depth gives H = K_dst (R + t n^T / d) K_src^-1, n = e_z.
    t = None (or a plane at infinity) is a pure rotation: H = K_dst R K_src^-1. -> [..., 3, 3]
    """
    R = _as_tensor(R)
    K_src, K_dst = _as_tensor(K_src), _as_tensor(K_dst)
    if R.shape[-2:] != (3, 3) or K_src.shape != (3, 3) or K_dst.shape != (3, 3):
        raise ValueError(f"need R [..., 3, 3] and K [3, 3], got {tuple(R.shape)}, {tuple(K_src.shape)}")
    M = R.clone()
    if t is not None:
        t = _as_tensor(t)
        M[..., :, 2] = M[..., :, 2] + t / _as_tensor(plane_depth)[..., None]
    return K_dst @ M @ torch.linalg.inv(K_src)


_COLMAP_TO_INDEX = torch.tensor([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]], dtype=torch.float64)


def homography_blur(
    image: Tensor,  # [B, C, H, W]
    homographies: Tensor,  # [T, 3, 3]
    dsize: tuple[int, int] | None = None,
    padding_mode: str = "reflection",
    chunk: int = 16,
) -> Tensor:
    """Average of the image warped by T homographies (src pixel -> dst pixel, COLMAP pixel convention).

    Output pixel x is mean_t image(H_t^-1 x), i.e. what a sensor sees while the image moves through H_t.
    Bilinear sampling; pixels mapped from outside the source use `padding_mode` (kornia / grid_sample).
    dsize: (H_out, W_out), default the input size. -> [B, C, H_out, W_out]
    """
    check_image(image)
    H = _as_tensor(homographies)
    if H.dim() != 3 or H.shape[1:] != (3, 3) or H.shape[0] < 1:
        raise ValueError(f"homographies must be [T, 3, 3] with T >= 1, got {tuple(H.shape)}")
    B, C, h, w = image.shape
    dsize = (h, w) if dsize is None else (int(dsize[0]), int(dsize[1]))
    S = _COLMAP_TO_INDEX
    M = (S @ H @ torch.linalg.inv(S)).to(image.dtype)  # index-coordinate homographies for kornia
    out = torch.zeros(B, C, *dsize, dtype=image.dtype, device=image.device)
    for s in range(0, M.shape[0], chunk):
        m = M[s : s + chunk].to(image.device)
        n = m.shape[0]
        src = image[:, None].expand(B, n, C, h, w).reshape(B * n, C, h, w)
        warped = warp_perspective(src, m.repeat(B, 1, 1), dsize, padding_mode=padding_mode, align_corners=True)
        out += warped.reshape(B, n, C, *dsize).sum(dim=1)
    return out / M.shape[0]


def rotational_shake_blur(
    image: Tensor,  # [B, C, H, W]
    K: Tensor,  # [3, 3]
    rotations: Tensor,  # [T, 3, 3]
    padding_mode: str = "reflection",
) -> Tensor:
    """Spatially varying blur of a camera rotating during the exposure (exact for rotation about the centre).

    rotations[t] maps reference-camera coordinates to camera-t coordinates; the image seen at time t is the
    sharp image warped by K R_t K^-1, and the exposure averages them. -> [B, C, H, W]
    """
    R = _as_tensor(rotations)
    if R.dim() != 3 or R.shape[1:] != (3, 3):
        raise ValueError(f"rotations must be [T, 3, 3], got {tuple(R.shape)}")
    return homography_blur(image, plane_homography(K, K, R), padding_mode=padding_mode)


def path_extent(paths: Tensor) -> Tensor:
    """Blur extent of pixel paths: for each point the largest distance between two of its positions.

    paths: [T, N, 2] positions over time of N points -> [N] (pixels). The max over N is a view's blur extent.
    """
    if paths.dim() != 3 or paths.shape[-1] != 2:
        raise ValueError(f"paths must be [T, N, 2], got {tuple(paths.shape)}")
    p = paths.transpose(0, 1)  # [N, T, 2]
    return torch.cdist(p, p).amax(dim=(1, 2))


# ----------------------------------------------------------------------------------------------------- defocus


def defocus_radius(
    depth: Tensor,  # [...]
    focal_px: float,
    aperture: float,
    focus_distance: float,
    signed: bool = False,
) -> Tensor:
    """Thin-lens circle-of-confusion RADIUS in pixels for z-depths (same units as aperture and focus_distance).

    A thin lens of aperture diameter A focused at distance d_f images a point at depth d as a disk of diameter
    c = A f |d - d_f| / (d (d_f - f)) on a sensor at v = f d_f / (d_f - f); in pixels of a pinhole camera with
    focal length f_px = v / pixel_pitch this is c_px = f_px A |1/d_f - 1/d|, independent of f. Returns c_px / 2:
    0 on the focal plane, growing with the distance from it (in inverse depth); +inf depth is the limit 1/d -> 0.
    signed=True keeps the sign of (1/d_f - 1/d): negative in front of the focal plane, positive behind. -> [...]
    """
    if focal_px <= 0 or aperture < 0 or not focus_distance > 0:
        raise ValueError(
            f"need focal_px > 0, aperture >= 0, focus_distance > 0; got {focal_px}, {aperture}, {focus_distance}"
        )
    if torch.any(~(depth > 0)):
        raise ValueError("depth must be > 0 (inf allowed) everywhere")
    r = 0.5 * focal_px * aperture * (1.0 / focus_distance - 1.0 / depth)
    return r if signed else r.abs()


def disk_blur(image: Tensor, radius: float, border_type: str = "reflect") -> Tensor:
    """Uniform defocus: convolution with a disk PSF of `radius` pixels. image [B, C, H, W] -> [B, C, H, W]."""
    return convolve_psf(image, disk_kernel(radius, dtype=image.dtype), border_type)


def radius_levels(max_radius: float, step_px: float = 0.5, rel_step: float = 0.15) -> Tensor:
    """Quantisation levels for per-pixel blur radii: 0, step, 2 step, ... then steps of rel_step * r.

    -> [L] ascending, from 0 to the first level >= max_radius.
    """
    levels = [0.0]
    while levels[-1] < max_radius - 1e-9:
        levels.append(levels[-1] + max(step_px, rel_step * levels[-1]))
    return torch.tensor(levels, dtype=torch.float64)


def apply_defocus(
    image: Tensor,  # [B, C, H, W]
    signed_radius: Tensor,  # [B, 1, H, W]
    step_px: float = 0.5,
    rel_step: float = 0.15,
) -> Tensor:
    """Depth-layered defocus: per-pixel disk blur with occlusion-aware compositing.

    signed_radius: CoC radius per pixel in pixels, signed as in `defocus_radius(signed=True)` (negative in front
    of the focal plane); it is monotone in depth, so it also orders the layers. Pixels are binned into layers of
    equal quantised signed radius (`radius_levels`); each layer is blurred as a premultiplied RGBA image with its
    disk (so a blurred foreground spreads over what lies behind it, and an in-focus foreground does not bleed
    into a blurred background), and layers are composited back to front with "over". The result is normalised by
    the accumulated alpha (renormalising at the image border and at layer seams). -> [B, C, H, W]
    """
    check_image(image)
    B, C, H, W = image.shape
    if signed_radius.shape != (B, 1, H, W):
        raise ValueError(f"signed_radius must be [B, 1, H, W] = {(B, 1, H, W)}, got {tuple(signed_radius.shape)}")
    if not torch.isfinite(signed_radius).all():
        raise ValueError("signed_radius has non-finite values")
    out = torch.empty_like(image)
    for b in range(B):
        r = signed_radius[b, 0].detach().cpu().to(torch.float64).numpy()
        levels = radius_levels(float(np.abs(r).max()), step_px, rel_step).numpy()
        mids = 0.5 * (levels[1:] + levels[:-1])
        level = np.searchsorted(mids, np.abs(r)) * np.sign(r).astype(np.int64)  # signed level index [H, W]
        offset = int(level.min())
        counts = np.bincount((level - offset).ravel())
        acc_rgb = torch.zeros(C, H, W, dtype=image.dtype, device=image.device)
        acc_a = torch.zeros(1, H, W, dtype=image.dtype, device=image.device)
        for lv in (np.flatnonzero(counts)[::-1] + offset).tolist():  # far (large signed radius) to near
            mask_np = level == lv
            kernel = disk_kernel(float(levels[abs(lv)]), dtype=image.dtype)
            half = kernel.shape[-1] // 2
            rows = np.flatnonzero(mask_np.any(axis=1))
            cols = np.flatnonzero(mask_np.any(axis=0))
            y0, y1 = max(0, int(rows[0]) - half), min(H, int(rows[-1]) + half + 1)
            x0, x1 = max(0, int(cols[0]) - half), min(W, int(cols[-1]) + half + 1)
            m = torch.from_numpy(mask_np[y0:y1, x0:x1]).to(image.device, image.dtype)[None]
            layer = torch.cat([image[b, :, y0:y1, x0:x1] * m, m])[None]  # premultiplied RGBA [1, C+1, h, w]
            if half > 0:
                layer = filter2d(layer, kernel[None], border_type="constant")
            l_rgb, l_a = layer[0, :C], layer[0, C:]
            keep = 1.0 - l_a
            acc_rgb[:, y0:y1, x0:x1].mul_(keep).add_(l_rgb)
            acc_a[:, y0:y1, x0:x1].mul_(keep).add_(l_a)
        out[b] = acc_rgb / acc_a.clamp_min(1e-8)
    return out


# ------------------------------------------------------------------------------------------ mixed resolution


# ------------------------------------------------------------------------------------------------------- noise


def add_noise(image: Tensor, sigma: float, gain: float = 0.0, generator: torch.Generator | None = None) -> Tensor:
    """Poisson-Gaussian sensor noise (Gaussian approximation): x + sqrt(gain * x + sigma^2) * n, n ~ N(0, 1).

    gain = 0 is plain Gaussian noise of std sigma. The result is clipped to [0, 1]. [B, C, H, W] -> same.
    """
    check_image(image)
    if sigma < 0 or gain < 0:
        raise ValueError(f"sigma and gain must be >= 0, got {sigma}, {gain}")
    n = torch.randn(image.shape, generator=generator, dtype=image.dtype)
    std = torch.sqrt(gain * image.clamp_min(0.0) + sigma**2)
    return (image + std * n.to(image.device)).clamp(0.0, 1.0)


# ------------------------------------------------------------------------------------------------ module twins


class PSFBlur(nn.Module):
    """Module twin of `convolve_psf` holding a fixed kernel (e.g. from `motion_kernel_from_trajectory`)."""

    def __init__(self, kernel: Tensor, border_type: str = "reflect") -> None:
        super().__init__()
        self.register_buffer("kernel", kernel)
        self.border_type = border_type

    def forward(self, image: Tensor) -> Tensor:
        return convolve_psf(image, self.kernel, self.border_type)


class RotationalShakeBlur(nn.Module):
    """Module twin of `rotational_shake_blur` for one camera (K) and one shake (rotations [T, 3, 3])."""

    def __init__(self, K: Tensor, rotations: Tensor, padding_mode: str = "reflection") -> None:
        super().__init__()
        self.register_buffer("K", _as_tensor(K))
        self.register_buffer("rotations", _as_tensor(rotations))
        self.padding_mode = padding_mode

    def forward(self, image: Tensor) -> Tensor:
        return rotational_shake_blur(image, self.K, self.rotations, self.padding_mode)


class LayeredDefocus(nn.Module):
    """Module twin of `defocus_radius` + `apply_defocus`: thin-lens defocus of an image given its depth."""

    def __init__(
        self, focal_px: float, aperture: float, focus_distance: float, step_px: float = 0.5, rel_step: float = 0.15
    ) -> None:
        super().__init__()
        self.focal_px, self.aperture, self.focus_distance = focal_px, aperture, focus_distance
        self.step_px, self.rel_step = step_px, rel_step

    def forward(self, image: Tensor, depth: Tensor) -> Tensor:
        """image [B, C, H, W], depth [B, 1, H, W] -> [B, C, H, W]."""
        r = defocus_radius(depth, self.focal_px, self.aperture, self.focus_distance, signed=True)
        return apply_defocus(image, r, self.step_px, self.rel_step)
