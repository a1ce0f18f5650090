"""EWA projection of 3D Gaussians to screen-space ellipses (pinhole cameras), pure PyTorch.

Semantics follow gsplat 1.4.0's `fully_fused_projection` (unpacked layout), so the CPU path and the CUDA path
cull, dilate and size Gaussians identically.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch
import torch.nn.functional as F
from torch import Tensor


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
        near_plane, far_plane: depth range kept.
        radius_clip: Gaussians whose pixel radius is <= this are culled.
        calc_compensations: also return sqrt(det(cov2d) / det(cov2d + eps2d I)) (antialiased mode).

    Returns:
        A `Projection`. Culled entries have radii 0 and finite placeholder values with zero gradient.
    """
    R = viewmats[:, :3, :3]  # [C, 3, 3]
    t = viewmats[:, :3, 3]  # [C, 3]
    means_c = torch.einsum("cij,nj->cni", R, means) + t[:, None, :]  # [C, N, 3]
    covars_c = R[:, None] @ covars[None] @ R[:, None].transpose(-1, -2)  # [C, N, 3, 3]

    x, y, z = means_c.unbind(-1)
    in_depth = (z > near_plane) & (z < far_plane)
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
    J = torch.stack(
        [fx / tz, zeros, -fx * tx / (tz * tz), zeros, fy / tz, -fy * ty / (tz * tz)], dim=-1
    ).reshape(tz.shape + (2, 3))  # [C, N, 2, 3]
    cov2d = J @ covars_c @ J.transpose(-1, -2)  # [C, N, 2, 2]
    means2d = torch.stack([fx * x / tz + cx, fy * y / tz + cy], dim=-1)  # [C, N, 2]

    c00, c01, c11 = cov2d[..., 0, 0], cov2d[..., 0, 1], cov2d[..., 1, 1]
    det_raw = c00 * c11 - c01 * c01
    c00, c11 = c00 + eps2d, c11 + eps2d
    det = c00 * c11 - c01 * c01

    valid = in_depth & (det > 0)
    safe_det = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c11 / safe_det, -c01 / safe_det, c00 / safe_det], dim=-1)  # [C, N, 3]

    compensations = None
    if calc_compensations:
        compensations = torch.sqrt((det_raw / safe_det).clamp_min(0.0))

    with torch.no_grad():
        mid = 0.5 * (c00 + c11)
        lambda_max = mid + torch.sqrt((mid * mid - det).clamp_min(0.01))
        radius = torch.ceil(3.0 * torch.sqrt(lambda_max.clamp_min(0.0)))
        on_screen = (
            (means2d[..., 0] + radius > 0)
            & (means2d[..., 0] - radius < width)
            & (means2d[..., 1] + radius > 0)
            & (means2d[..., 1] - radius < height)
        )
        keep = valid & (radius > radius_clip) & on_screen & torch.isfinite(radius)
        radii = torch.where(keep, radius, torch.zeros_like(radius)).to(torch.int32)

    # culled entries: keep them finite and gradient-free so nothing downstream can turn them into NaN
    keep2 = keep[..., None]
    means2d = torch.where(keep2, means2d, torch.zeros_like(means2d))
    conics = torch.where(keep2, conics, torch.zeros_like(conics))
    depths = torch.where(keep, z, torch.zeros_like(z))
    if compensations is not None:
        compensations = torch.where(keep, compensations, torch.zeros_like(compensations))
    return Projection(radii, means2d, depths, conics, compensations)
