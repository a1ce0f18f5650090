"""EWA projection of 3D Gaussians to screen-space ellipses (pinhole cameras), pure PyTorch.

Semantics follow gsplat 1.4.0's `fully_fused_projection` (unpacked layout), so the CPU path and the CUDA path
cull, dilate and size Gaussians identically.
"""

from __future__ import annotations

from typing import NamedTuple, Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor

MAX_RADIUS = float(2**30)  # pixel radii are stored as int32; larger footprints are clamped to this


class Projection(NamedTuple):
    """Per-camera screen-space Gaussians; entries with radii == 0 are culled and carry no meaning."""

    radii: Tensor  # [C, N] int32, 3-sigma pixel radius
    means2d: Tensor  # [C, N, 2] pixel coordinates
    depths: Tensor  # [C, N] camera-space z
    conics: Tensor  # [C, N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]]
    compensations: Optional[Tensor]  # [C, N] opacity factor of the antialiased mode, or None


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices from quaternions.

    Args:
        quats: [..., 4] quaternions (w, x, y, z), any norm.

    Returns:
        [..., 3, 3] rotation matrices.
    """
    w, x, y, z = F.normalize(quats, dim=-1).unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def covariance_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """World-space covariances R S S^T R^T.

    Args:
        quats: [N, 4] quaternions (w, x, y, z).
        scales: [N, 3] standard deviations along the local axes.

    Returns:
        [N, 3, 3] covariances.
    """
    m = quat_to_rotmat(quats) * scales[..., None, :]
    return m @ m.transpose(-1, -2)


def _ewa(
    means_c: Tensor,  # [C, N, 3]
    covars_c: Tensor,  # [C, N, 3, 3]
    in_depth: Tensor,  # [C, N] bool
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    eps2d: float,
) -> Tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Pinhole EWA projection (gsplat's ``persp_proj`` + ``add_blur``) of camera-space Gaussians.

    Returns:
        means2d [C, N, 2]; dilated 2D covariance entries c00, c01, c11 [C, N]; det of the dilated covariance and
        det_raw of the undilated one [C, N]. Entries outside ``in_depth`` are evaluated at depth 1 (finite, unused).
    """
    x, y, z = means_c.unbind(-1)
    # divide by a safe depth so culled Gaussians (behind the camera) stay finite in forward and backward
    tz = torch.where(in_depth, z, torch.ones_like(z))

    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]  # [C, 1]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    # the Jacobian is evaluated at a point clamped to 1.3x the field of view, as 3D-GS does, so Gaussians far
    # off-screen do not get huge, degenerate footprints
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    tx = tz * torch.minimum(torch.maximum(x / tz, -lim_x_neg), lim_x_pos)
    ty = tz * torch.minimum(torch.maximum(y / tz, -lim_y_neg), lim_y_pos)

    zeros = torch.zeros_like(tz)
    J = torch.stack([fx / tz, zeros, -fx * tx / (tz * tz), zeros, fy / tz, -fy * ty / (tz * tz)], dim=-1).reshape(
        tz.shape + (2, 3)
    )  # [C, N, 2, 3]
    cov2d = J @ covars_c @ J.transpose(-1, -2)  # [C, N, 2, 2]
    means2d = torch.stack([fx * x / tz + cx, fy * y / tz + cy], dim=-1)  # [C, N, 2]

    c00, c01, c11 = cov2d[..., 0, 0], cov2d[..., 0, 1], cov2d[..., 1, 1]
    det_raw = c00 * c11 - c01 * c01
    c00, c11 = c00 + eps2d, c11 + eps2d
    det = c00 * c11 - c01 * c01
    return means2d, c00, c01, c11, det, det_raw


def project_gaussians(
    means: Tensor,  # [N, 3]
    covars: Tensor,  # [N, 3, 3]
    viewmats: Tensor,  # [C, 4, 4]
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    calc_compensations: bool = False,
) -> Projection:
    """Project 3D Gaussians into C pinhole cameras with the EWA (local affine) approximation.

    Args:
        means: [N, 3] world-space centres.
        covars: [N, 3, 3] world-space covariances.
        viewmats: [C, 4, 4] world-to-camera transforms (OpenCV axes: x right, y down, z forward).
        Ks: [C, 3, 3] pinhole intrinsics.
        width, height: image size in pixels.
        eps2d: screen-space dilation added to the 2D covariance diagonal (pixels^2).
        near_plane, far_plane: depth range kept (inclusive, as gsplat; depths <= 0 are always culled).
        radius_clip: Gaussians whose pixel radius is <= this are culled.
        calc_compensations: also return sqrt(det(cov2d) / det(cov2d + eps2d I)) (antialiased mode).

    Returns:
        A `Projection`. Culled entries have radii 0 and zero placeholder values with exactly zero gradient. Besides
        gsplat's culling (depth range, det <= 0, radius <= radius_clip, off-screen), entries whose projection is
        not finite (covariances or centres that overflow float32, NaN inputs) are culled too.
    """
    # A non-finite centre or covariance is culled in every camera; it is swapped for a finite stand-in before the
    # world-to-camera transform so that its NaN / inf cannot reach the viewmats' gradient (camera optimisation).
    with torch.no_grad():
        world_ok = means.isfinite().all(-1) & covars.isfinite().all(-1).all(-1)  # [N]
    means = torch.where(world_ok[:, None], means, torch.zeros_like(means))
    covars = torch.where(world_ok[:, None, None], covars, torch.eye(3, dtype=covars.dtype, device=covars.device))

    R = viewmats[:, :3, :3]  # [C, 3, 3]
    t = viewmats[:, :3, 3]  # [C, 3]
    means_c = torch.einsum("cij,nj->cni", R, means) + t[:, None, :]  # [C, N, 3]
    covars_c = R[:, None] @ covars[None] @ R[:, None].transpose(-1, -2)  # [C, N, 3, 3]
    z = means_c[..., 2]
    # gsplat keeps near_plane <= z <= far_plane; z > 0 also guards the perspective division for near_plane <= 0
    in_depth = (z >= near_plane) & (z <= far_plane) & (z > 0) & world_ok

    with torch.no_grad():
        # Culling pass on the raw values. The differentiable pass below sees only the kept entries' values (the
        # culled ones are swapped for a unit Gaussian at depth 1), so an overflowing or NaN entry cannot leak
        # 0 * inf = NaN into the gradients of the others' shared inputs or of its own parameters.
        m2d, c00, c01, c11, det, det_raw = _ewa(means_c, covars_c, in_depth, Ks, width, height, eps2d)
        mid = 0.5 * (c00 + c11)
        lambda_max = mid + torch.sqrt((mid * mid - det).clamp_min(0.01))
        radius = torch.ceil(3.0 * torch.sqrt(lambda_max.clamp_min(0.0)))
        on_screen = (
            (m2d[..., 0] + radius > 0)
            & (m2d[..., 0] - radius < width)
            & (m2d[..., 1] + radius > 0)
            & (m2d[..., 1] - radius < height)
        )
        safe = torch.where(det > 0, det, torch.ones_like(det))
        finite = torch.stack([c11 / safe, c01 / safe, c00 / safe, det, radius], dim=-1).isfinite().all(-1)
        finite &= m2d.isfinite().all(-1)
        if calc_compensations:
            finite &= det_raw.isfinite()
        keep = in_depth & finite & (det > 0) & (radius > radius_clip) & on_screen
        # int32 like gsplat; clamped so that a huge (but finite) footprint cannot wrap around to a negative radius
        radii = torch.where(keep, radius.clamp_max(MAX_RADIUS), torch.zeros_like(radius)).to(torch.int32)

    keep2 = keep[..., None]
    unit_mean = means_c.new_tensor([0.0, 0.0, 1.0])
    unit_covar = torch.eye(3, dtype=covars_c.dtype, device=covars_c.device)
    means_c = torch.where(keep2, means_c, unit_mean)
    covars_c = torch.where(keep2[..., None], covars_c, unit_covar)
    means2d, c00, c01, c11, det, det_raw = _ewa(means_c, covars_c, keep, Ks, width, height, eps2d)
    safe_det = torch.where(keep, det, torch.ones_like(det))
    conics = torch.stack([c11 / safe_det, -c01 / safe_det, c00 / safe_det], dim=-1)  # [C, N, 3]

    compensations = None
    if calc_compensations:
        # clamp_min passes no gradient at exactly 0, so sqrt's infinite slope there is never used
        compensations = torch.sqrt((det_raw / safe_det).clamp_min(0.0))

    # culled entries: zero placeholders, gradient-free, so nothing downstream can turn them into NaN
    means2d = torch.where(keep2, means2d, torch.zeros_like(means2d))
    conics = torch.where(keep2, conics, torch.zeros_like(conics))
    depths = torch.where(keep, z, torch.zeros_like(z))
    if compensations is not None:
        compensations = torch.where(keep, compensations, torch.zeros_like(compensations))
    return Projection(radii, means2d, depths, conics, compensations)
