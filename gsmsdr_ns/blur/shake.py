"""Camera shake as a learnt rotation path per training view: the sharp render warped along it and averaged.

A handheld photo's motion blur is mostly the camera turning during the exposure. A camera rotation R moves every
pixel by the homography ``K R K^-1`` whatever its depth, so the blurred photo is the average of the sharp image
warped by the homographies of the rotations the camera went through (Whyte et al., "Non-uniform deblurring for
shaken images"). Roll makes that blur vary across the image, which one kernel per view cannot represent.

Each view's path is a cubic polynomial in the exposure time ``tau`` in [-1/2, 1/2] per rotation axis::

    r(tau) = sum_k c_k b_k(tau),   b = (tau, tau^2, tau^3)            (the path passes through the pose at tau 0)
                                   b = (tau, tau^2 - 1/12, tau^3)     (zero mean: the pose is the path's centre)

The first basis fits poses known to be the mid-exposure pose (simulated shake); the second fits poses estimated
from the blurred photo itself, which structure-from-motion puts near the centre of the blur. Pure functions below,
one module (:class:`CameraShake`) holding the coefficients.
"""

from __future__ import annotations

from typing import Callable, Optional, Tuple

import torch
from kornia.color import linear_rgb_to_rgb, rgb_to_linear_rgb
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from kornia.geometry.transform import warp_perspective
from torch import Tensor, nn
from torch.nn.functional import grid_sample

from gsmsdr_ns.ops.splat import splat_bilinear

__all__ = [
    "CameraShake",
    "apply_camera_shake",
    "apply_camera_shake_occluding",
    "apply_camera_shake_with_depth",
    "parallax_rotvecs",
    "path_basis",
    "path_coefficients",
    "rotation_homographies",
    "shake_basis",
    "shake_mean_kernel",
    "shake_sample_grid",
    "shake_sample_times",
    "shake_splat_positions",
    "visible_sample_depths",
]

RADIANS_PER_UNIT = 0.01
"""The coefficients are stored in hundredths of a radian: Adam's steps (about the learning rate) then move a path
by a fraction of a pixel at the focal lengths of photos."""

SCENE_UNITS_PER_UNIT = 0.01
"""Translation coefficients are stored in hundredths of a scene unit (nerfstudio scales the cameras into [-1, 1]):
at a depth of one unit a translation moves a pixel as far as the same number of rotation units."""


def shake_sample_times(num_samples: int) -> Tensor:
    """Times a path is sampled at, the midpoints of ``num_samples`` equal bins of the exposure [-1/2, 1/2] -> [T]
    (float64)."""
    if num_samples < 2:
        raise ValueError(f"a shake path needs at least 2 samples, got {num_samples}")
    return (torch.arange(num_samples, dtype=torch.float64) + 0.5) / num_samples - 0.5


def path_basis(times: Tensor) -> Tensor:
    """The cubic path basis through the pose, ``tau``, ``tau^2``, ``tau^3``, at ``times`` [S] in [-1/2, 1/2] -> [S, 3]
    (a path's coefficients [3, D] times it give the path [S, D])."""
    return torch.stack([times, times**2, times**3], dim=1)


def shake_basis(num_samples: int, centred: bool, dtype: torch.dtype = torch.float32) -> Tensor:
    """Polynomial basis of a path sampled at :func:`shake_sample_times` -> [T, 3].

    ``centred``: columns of zero mean over the samples (the pose is the path's centre); else each column is 0 at
    mid-exposure (the pose lies on the path).
    """
    basis = path_basis(shake_sample_times(num_samples))
    if centred:
        basis = basis - basis.mean(dim=0, keepdim=True)
    return basis.to(dtype)


def path_coefficients(times: Tensor, values: Tensor) -> Tensor:
    """Least-squares coefficients of the path through the pose (:func:`path_basis`) closest to a sampled path. A path
    of fewer than 3 samples (a short shake's record) fits the first columns only, the others 0.

    Args:
        times: [S] times of the samples in the exposure [-1/2, 1/2] (0: the pose), S >= 1.
        values: [S, D] the path at those times (rotation vectors or translations, one column per axis).
    Returns:
        [3, D] coefficients, in the units of ``values``.
    """
    if times.ndim != 1 or values.ndim != 2 or values.shape[0] != times.shape[0] or times.shape[0] < 1:
        raise ValueError(
            f"a sampled path needs times [S] and values [S, D] with S >= 1, got {tuple(times.shape)} and "
            f"{tuple(values.shape)}"
        )
    used = min(int(times.shape[0]), 3)
    basis = path_basis(times.to(torch.float64))[:, :used]  # [S, used]
    coefficients = values.new_zeros((3, values.shape[1]), dtype=torch.float64)
    coefficients[:used] = torch.linalg.lstsq(basis, values.to(torch.float64)).solution
    return coefficients


def rotation_homographies(K: Tensor, rotvecs: Tensor) -> Tensor:
    """Pixel homographies of camera rotations: ``K_i R(r) K_i^-1`` in pixel-index coordinates (pixel centres at
    integers), ready for kornia's warps.

    Args:
        K: [3, 3] pinhole intrinsics, principal point in the pixel-edge convention (centres at i + 0.5).
        rotvecs: [T, 3] rotation vectors (axis * angle, radians) in the camera's frame.
    Returns:
        [T, 3, 3].
    """
    K_index = _index_intrinsics(K)
    R = axis_angle_to_rotation_matrix(rotvecs.to(K.dtype))
    return K_index @ R @ torch.linalg.inv(K_index)


def apply_camera_shake(image: Tensor, homographies: Tensor, linear_light: bool = True) -> Tensor:
    """Average of ``image`` warped by each homography: what a sensor records while the view moves through them.

    Args:
        image: [1, C, H, W]; sRGB-encoded in [0, 1] when ``linear_light``.
        homographies: [T, 3, 3] pixel-index homographies (see :func:`rotation_homographies`).
        linear_light: average linear light (decode, warp and average, re-encode).
    Returns:
        [1, C, H, W]. Pixels mapped from outside the image read its border.
    """
    _check_image(image)
    if homographies.dim() != 3 or homographies.shape[1:] != (3, 3):
        raise ValueError(f"homographies must be [T, 3, 3], got {list(homographies.shape)}")

    def warp(source: Tensor) -> Tensor:
        _, C, H, W = source.shape
        stack = source.expand(homographies.shape[0], C, H, W)
        return warp_perspective(stack, homographies.to(source.dtype), (H, W), padding_mode="border", align_corners=True)

    return _average_warps(image, warp, linear_light)


@torch.no_grad()
def shake_mean_kernel(K: Tensor, rotvecs: Tensor, height: int, width: int, max_size: int, probes: int = 5) -> Tensor:
    """The blur kernel of a rotation path, averaged over the image: what the deconvolved residual loss
    (:func:`~gsmsdr_ns.ops.deconvolved_loss.deconvolved_residual`) weighs by. Detached.

    Each of ``probes`` x ``probes`` pixels spread over the image moves along the path's homographies; its positions,
    centred on their mean (a shift does not change the kernel's spectrum magnitude, which is all the loss reads),
    are splatted bilinearly onto a square grid, and the grids of all probes are averaged.

    Args:
        K: [3, 3] pinhole intrinsics of the image (as :func:`rotation_homographies`).
        rotvecs: [T, 3] the path's rotation vectors (radians).
        height, width: the image's size in pixels.
        max_size: largest kernel side (odd); positions beyond it are clamped to its border.
    Returns:
        [1, max_size, max_size], summing to 1.
    """
    if max_size < 1 or max_size % 2 == 0:
        raise ValueError(f"max_size must be a positive odd integer, got {max_size}")
    homographies = rotation_homographies(K.double(), rotvecs.detach().double())  # [T, 3, 3]
    ys = torch.linspace(0.0, height - 1.0, probes, dtype=torch.float64, device=K.device)
    xs = torch.linspace(0.0, width - 1.0, probes, dtype=torch.float64, device=K.device)
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    points = torch.stack([grid_x.flatten(), grid_y.flatten(), torch.ones_like(grid_x.flatten())], dim=0)  # [3, P]
    moved = homographies @ points  # [T, 3, P]
    xy = moved[:, :2] / moved[:, 2:3]
    offsets = xy - xy.mean(dim=0, keepdim=True)  # [T, 2, P], each probe's path centred
    size = max_size  # fixed, so no device read; zero taps beyond the path leave the spectrum's magnitude alone
    pos = (offsets + size // 2).permute(0, 2, 1).reshape(-1, 2)  # [T * P, 2] (x, y)
    kernel = splat_bilinear(pos, torch.ones_like(pos[:, 0]), size)
    kernel = kernel / kernel.sum()
    return kernel.reshape(1, size, size).to(K.dtype)


def _check_image(image: Tensor) -> None:
    if image.dim() != 4 or image.shape[0] != 1:
        raise ValueError(f"image must be [1, C, H, W], got {list(image.shape)}")


def _average_warps(image: Tensor, warp: Callable[[Tensor], Tensor], linear_light: bool) -> Tensor:
    """Mean over T of ``warp(image)`` [T, C, H, W], in linear light when ``linear_light`` (decode, warp and
    average, re-encode) -> [1, C, H, W]."""
    source = rgb_to_linear_rgb(image) if linear_light else image
    out = warp(source).mean(dim=0, keepdim=True)
    return linear_rgb_to_rgb(out) if linear_light else out


def _index_intrinsics(K: Tensor) -> Tensor:
    """``K`` [3, 3] with the principal point moved to the pixel-index convention (pixel centres at integers)."""
    shift = torch.eye(3, dtype=K.dtype, device=K.device)
    shift[:2, 2] = -0.5
    return shift @ K


def _render_points(K_index: Tensor, depth: Tensor) -> Tensor:
    """Camera-frame points ``z(p) K^-1 p`` of every pixel ``p`` of a depth map [..., H, W] -> [..., H, W, 3]
    (``K_index`` [3, 3] in the pixel-index convention)."""
    H, W = depth.shape[-2:]
    dtype, device = K_index.dtype, K_index.device
    ys, xs = torch.meshgrid(
        torch.arange(H, dtype=dtype, device=device), torch.arange(W, dtype=dtype, device=device), indexing="ij"
    )
    pixels = torch.stack([xs, ys, torch.ones_like(xs)], dim=-1)  # [H, W, 3]
    return (pixels @ torch.linalg.inv(K_index).T) * depth.to(dtype)[..., None]


def shake_sample_grid(K: Tensor, rotvecs: Tensor, translations: Tensor, depth: Tensor) -> Tensor:
    """Where each pixel of a shaken view reads the sharp render at each time sample, given the render's depth.

    The scene point seen at pixel ``x`` lies at ``X = z(x) K^-1 x``; at time sample ``t`` the camera has turned by
    ``R_t`` and moved by ``c_t``, so the pixel reads the render at ``K (R_t^T X + c_t)``. Near points move further
    than far ones under translation; with zero translations this is the rotation homography of
    :func:`rotation_homographies` (depth cancels).

    Args:
        K: [3, 3] pinhole intrinsics, principal point in the pixel-edge convention.
        rotvecs: [T, 3] rotation vectors (radians).
        translations: [T, 3] camera translations (scene units, camera frame).
        depth: [H, W] depth of the render along the optical axis (scene units, > 0), or [T, H, W] a depth per time
            sample (what that sample's camera sees at each pixel, :func:`visible_sample_depths`).
    Returns:
        [T, H, W, 2] sampling grid for ``torch.nn.functional.grid_sample`` (x, y in [-1, 1], ``align_corners=True``).
    """
    H, W = depth.shape[-2:]
    dtype = K.dtype
    K_index = _index_intrinsics(K)
    points = _render_points(K_index, depth)  # [H, W, 3] or [T, H, W, 3]
    R_T = axis_angle_to_rotation_matrix(rotvecs.to(dtype)).transpose(-1, -2)  # [T, 3, 3]
    points = points.expand(rotvecs.shape[0], H, W, 3)  # [T, H, W, 3]
    moved = torch.einsum("tij,thwj->thwi", R_T, points) + translations.to(dtype)[:, None, None, :]
    projected = moved @ K_index.T  # [T, H, W, 3]
    uv = projected[..., :2] / projected[..., 2:].clamp_min(1e-6)
    scale = torch.tensor([2.0 / max(W - 1, 1), 2.0 / max(H - 1, 1)], dtype=dtype, device=K.device)
    return uv * scale - 1.0


def parallax_rotvecs(translations: Tensor, reference_depth: Tensor) -> Tensor:
    """Rotations that undo, to first order, what ``translations`` do to a point at ``reference_depth`` on the
    optical axis: added to a path's rotations, its translations move only points nearer or farther than that.

    A camera moved by ``c`` sees the point ``(0, 0, z)`` at ``(c_x, c_y, z + c_z)``; turned by the small rotation
    ``r`` it sees it at ``(-r_y z, r_x z, z)`` (see :func:`shake_sample_grid`), so ``r = (-c_y / z, c_x / z, 0)``
    cancels the sideways move. Forward motion has no rotation equivalent and is left as it is.

    Args:
        translations: [T, 3] camera translations (scene units, camera frame).
        reference_depth: scalar depth (scene units, > 0).
    Returns:
        [T, 3] rotation vectors (radians).
    """
    inverse = 1.0 / reference_depth.to(translations.dtype)
    zero = torch.zeros_like(translations[:, 0])
    return torch.stack([-translations[:, 1] * inverse, translations[:, 0] * inverse, zero], dim=1)


def shake_splat_positions(K: Tensor, rotvecs: Tensor, translations: Tensor, depth: Tensor) -> Tuple[Tensor, Tensor]:
    """Where each pixel of the sharp render lands at each time sample, and at what depth: the forward counterpart of
    :func:`shake_sample_grid` (the same camera motion).

    The point seen at pixel ``p`` lies at ``X = z(p) K^-1 p``; the camera of time sample ``t``, turned by ``R_t`` and
    moved by ``c_t`` (as in :func:`shake_sample_grid`), sees it at ``R_t (X - c_t)``.

    Args:
        K: [3, 3] pinhole intrinsics, principal point in the pixel-edge convention.
        rotvecs: [T, 3] rotation vectors (radians).
        translations: [T, 3] camera translations (scene units, camera frame).
        depth: [H, W] depth of the render along the optical axis (scene units, > 0).
    Returns:
        positions [T, H, W, 2] (x, y pixel indices, centres at integers) and depths [T, H, W] in each sample's camera.
    """
    dtype = K.dtype
    K_index = _index_intrinsics(K)
    points = _render_points(K_index, depth)  # [H, W, 3]
    KR = K_index @ axis_angle_to_rotation_matrix(rotvecs.to(dtype))  # [T, 3, 3]
    offsets = torch.einsum("tij,tj->ti", KR, translations.to(dtype))  # [T, 3]: K R_t c_t
    projected = torch.einsum("tij,hwj->thwi", KR, points) - offsets[:, None, None, :]  # [T, H, W, 3]
    z = projected[..., 2].clamp_min(1e-6)
    return projected[..., :2] / z[..., None], z


def visible_sample_depths(K: Tensor, rotvecs: Tensor, translations: Tensor, depth: Tensor) -> Tensor:
    """The render's depth as each time sample's camera sees it: every pixel's point projected into that camera
    (:func:`shake_splat_positions`) and, of the points landing on a pixel, the nearest kept (a z-buffer). Not
    differentiable.

    A pixel no point reaches (background the render's near surfaces hide, or a gap where the view stretches) keeps
    the render's own depth there.

    Args:
        K: [3, 3] pinhole intrinsics, principal point in the pixel-edge convention.
        rotvecs: [T, 3] rotation vectors (radians).
        translations: [T, 3] camera translations (scene units, camera frame).
        depth: [H, W] depth of the render (scene units, > 0).
    Returns:
        [T, H, W] depths (scene units, > 0).
    """
    with torch.no_grad():
        H, W = depth.shape
        positions, sample_depth = shake_splat_positions(K, rotvecs.detach(), translations.detach(), depth.detach())
        T = positions.shape[0]
        x, y = positions[..., 0].round(), positions[..., 1].round()
        inside = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
        base = torch.arange(T, device=depth.device)[:, None, None] * (H * W)
        index = (base + y.clamp(0, H - 1).long() * W + x.clamp(0, W - 1).long())[inside]
        visible = depth.new_full((T * H * W,), float("inf"))
        visible.scatter_reduce_(0, index, sample_depth.to(depth.dtype)[inside], reduce="amin", include_self=True)
        visible = visible.reshape(T, H, W)
        return torch.where(torch.isinf(visible), depth.detach().expand_as(visible), visible)


def apply_camera_shake_occluding(
    image: Tensor, K: Tensor, rotvecs: Tensor, translations: Tensor, depth: Tensor, linear_light: bool = True
) -> Tensor:
    """Average of the render moved to each time sample with occlusion: each sample's pixel reads the render along
    the depth that sample's camera sees there (:func:`visible_sample_depths`), not the render's depth at the same
    pixel. A near surface then smears outward over the background behind it, as in a photo, where reading by the
    render's own depth moves every pixel by its own depth and erodes the near surface instead.

    Args:
        image: [1, C, H, W]; sRGB-encoded in [0, 1] when ``linear_light``.
        K: [3, 3] pinhole intrinsics, principal point in the pixel-edge convention.
        rotvecs: [T, 3] rotation vectors (radians).
        translations: [T, 3] camera translations (scene units, camera frame).
        depth: [H, W] the render's depth (scene units, > 0; not differentiated through).
        linear_light: average linear light.
    Returns:
        [1, C, H, W].
    """
    visible = visible_sample_depths(K, rotvecs, translations, depth)
    return apply_camera_shake_with_depth(image, shake_sample_grid(K, rotvecs, translations, visible), linear_light)


def apply_camera_shake_with_depth(image: Tensor, grid: Tensor, linear_light: bool = True) -> Tensor:
    """Average of ``image`` read at each time sample's grid (:func:`shake_sample_grid`).

    Args:
        image: [1, C, H, W]; sRGB-encoded in [0, 1] when ``linear_light``.
        grid: [T, H, W, 2].
        linear_light: average linear light.
    Returns:
        [1, C, H, W]. Reads outside the image take its border.
    """
    _check_image(image)

    def warp(source: Tensor) -> Tensor:
        _, C, H, W = source.shape
        stack = source.expand(grid.shape[0], C, H, W)
        return grid_sample(stack, grid.to(source.dtype), mode="bilinear", padding_mode="border", align_corners=True)

    return _average_warps(image, warp, linear_light)


class CameraShake(nn.Module):
    """One learnt rotation path per training view (cubic in time, see the module docstring).

    Args:
        num_views: training views.
        num_samples: time samples of the exposure the render is warped to.
        initial_radians: standard deviation of the random initial coefficients. A path of exactly zero gets no
            gradient (blur is even in the path), so each starts as a small random curve.
        seed: seed of the initial coefficients' generator (the global random stream is left alone).
        translation: also learn a camera translation path per view (cubic, the same basis): the blur then depends
            on the render's depth, which :meth:`forward` needs.
        parallax: the translations move the image relative to each render's median depth only
            (:func:`parallax_rotvecs` offsets the rotations), so the rotation path carries the blur at that depth.
        occlusion: with ``translation``, each time sample reads the render along the depth its own camera sees
            (:func:`apply_camera_shake_occluding`) instead of the render's depth at the same pixel.
    """

    basis_through_pose: Tensor  # buffers (register_buffer in __init__)
    basis_centred: Tensor

    def __init__(
        self,
        num_views: int,
        num_samples: int = 9,
        initial_radians: float = 1e-3,
        seed: int = 0,
        translation: bool = False,
        parallax: bool = False,
        occlusion: bool = False,
    ) -> None:
        super().__init__()
        self.parallax = bool(parallax)
        self.occlusion = bool(occlusion)
        if num_views < 1:
            raise ValueError(f"num_views must be >= 1, got {num_views}")
        self.num_samples = int(num_samples)
        generator = torch.Generator().manual_seed(seed)
        init = torch.randn(num_views, 3, 3, generator=generator) * (initial_radians / RADIANS_PER_UNIT)
        self.coefficients = nn.Parameter(init)  # [V, basis, axis]
        # starts at rest: the rotation path's random start already gives the translations a gradient
        self.translation_coefficients = nn.Parameter(torch.zeros(num_views, 3, 3)) if translation else None
        self.register_buffer("basis_through_pose", shake_basis(self.num_samples, centred=False), persistent=False)
        self.register_buffer("basis_centred", shake_basis(self.num_samples, centred=True), persistent=False)

    @torch.no_grad()
    def set_path(self, view: int, times: Tensor, rotvecs: Tensor, translations: Optional[Tensor] = None) -> None:
        """Set view ``view``'s path through the pose to the cubic closest to a sampled one (:func:`path_coefficients`):
        ``times`` [S] in [-1/2, 1/2], ``rotvecs`` [S, 3] (radians) and ``translations`` [S, 3] (scene units, camera
        frame; needs ``translation``) as :func:`shake_sample_grid` reads them."""
        self.coefficients[view] = (path_coefficients(times, rotvecs) / RADIANS_PER_UNIT).to(self.coefficients)
        if translations is None:
            return
        if self.translation_coefficients is None:
            raise ValueError("set_path: this camera shake learns no translation path (translation=False)")
        coefficients = path_coefficients(times, translations) / SCENE_UNITS_PER_UNIT
        self.translation_coefficients[view] = coefficients.to(self.translation_coefficients)

    def _basis(self, centred: bool) -> Tensor:
        return self.basis_centred if centred else self.basis_through_pose

    def rotvecs(self, view_ids: Tensor, centred: bool) -> Tensor:
        """Rotation vectors of view ``view_ids[0]``'s path -> [T, 3] (radians)."""
        return RADIANS_PER_UNIT * (self._basis(centred) @ self.coefficients[view_ids[0]])

    def warped_rotvecs(self, view_ids: Tensor, centred: bool, translations: Tensor, depth: Tensor) -> Tensor:
        """The rotations [T, 3] (radians) view ``view_ids[0]``'s render is warped by alongside ``translations``
        [T, 3]: with ``parallax``, its rotation path offset by :func:`parallax_rotvecs` at the median of ``depth``
        (the render's, [H, W], > 0); else the rotation path itself."""
        rotvecs = self.rotvecs(view_ids, centred)
        return rotvecs + parallax_rotvecs(translations, depth.median()) if self.parallax else rotvecs

    def translations(self, view_ids: Tensor, centred: bool) -> Tensor:
        """Camera translations along view ``view_ids[0]``'s path -> [T, 3] (scene units); zeros without
        ``translation``."""
        basis = self._basis(centred)
        if self.translation_coefficients is None:
            return basis.new_zeros(basis.shape[0], 3)
        return SCENE_UNITS_PER_UNIT * (basis @ self.translation_coefficients[view_ids[0]])

    def mean_kernel(self, K: Tensor, view_ids: Tensor, centred: bool, height: int, width: int, max_size: int) -> Tensor:
        """[1, max_size, max_size] detached image-mean kernel of view ``view_ids`` [1]'s rotation path
        (:func:`shake_mean_kernel`; a translation path's depth-dependent part is left out)."""
        return shake_mean_kernel(K, self.rotvecs(view_ids, centred), height, width, max_size)

    def forward(
        self,
        image: Tensor,
        K: Tensor,
        view_ids: Tensor,
        centred: bool,
        linear_light: bool = True,
        depth: Optional[Tensor] = None,
        translate: bool = True,
    ) -> Tensor:
        """The render ``image`` [1, C, H, W] (intrinsics ``K`` [3, 3]) blurred along view ``view_ids`` [1]'s path;
        with ``translation`` and ``translate``, ``depth`` [H, W] is the render's depth (not differentiated through).
        ``translate`` False: the rotation path alone (the translations get no gradient)."""
        if self.translation_coefficients is None or not translate:
            return apply_camera_shake(image, rotation_homographies(K, self.rotvecs(view_ids, centred)), linear_light)
        if depth is None:
            raise ValueError("a camera shake path with translation needs the render's depth")
        depth = depth.detach().clamp_min(1e-3)
        translations = self.translations(view_ids, centred)
        rotvecs = self.warped_rotvecs(view_ids, centred, translations, depth)
        if self.occlusion:
            return apply_camera_shake_occluding(image, K, rotvecs, translations, depth, linear_light)
        grid = shake_sample_grid(K, rotvecs, translations, depth)
        return apply_camera_shake_with_depth(image, grid, linear_light)
