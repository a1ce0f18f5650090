"""`rasterization`: gsplat 1.4.0's entry point, with a CPU implementation.

CUDA tensors go to gsplat unchanged (its speed, its kernels). CPU tensors go through our projection, tile
sorting and either the compiled C++/OpenMP kernel or the pure-PyTorch reference, with the same semantics and the
same `meta` keys that gsplat's DefaultStrategy reads, so densification and pruning work on CPU too.
"""

from __future__ import annotations

import math
from typing import Dict, Literal, Optional, Tuple

import torch
from torch import Tensor

from gsmsdr_ns.render.pixels_torch import rasterize_to_pixels_torch
from gsmsdr_ns.render.projection import covariance_3d, project_gaussians
from gsmsdr_ns.render.sh import eval_sh_colors
from gsmsdr_ns.render.tiles import isect_offset_encode, isect_tiles

CpuBackend = Literal["auto", "cpp", "torch"]


def resolve_cpu_backend(requested: CpuBackend = "auto") -> Literal["cpp", "torch"]:
    """Pick the CPU pixel kernel: "cpp" when it builds, else "torch" (one warning says why).

    Asking for "cpp" explicitly raises if the extension cannot be built.
    """
    if requested == "torch":
        return "torch"
    if requested not in ("auto", "cpp"):
        raise ValueError(f"cpu_backend must be 'auto', 'cpp' or 'torch', got {requested!r}")
    from gsmsdr_ns.render.pixels_cpp import EXTENSION

    return EXTENSION.choose_backend(
        requested, unavailable="C++ CPU rasterizer", fallback="the slower PyTorch rasterizer", stacklevel=3
    )


def rasterize_to_pixels(
    means2d: Tensor,  # [C, N, 2]
    conics: Tensor,  # [C, N, 3]
    colors: Tensor,  # [C, N, D]
    opacities: Tensor,  # [C, N]
    image_width: int,
    image_height: int,
    tile_size: int,
    isect_offsets: Tensor,  # [C, th, tw]
    flatten_ids: Tensor,  # [M]
    backgrounds: Optional[Tensor] = None,  # [C, D]
    absgrad: bool = False,
    backend: CpuBackend = "auto",
) -> Tuple[Tensor, Tensor]:
    """Composite sorted screen-space Gaussians on the CPU; see `pixels_torch.rasterize_to_pixels_torch`.

    Returns:
        render_colors: [C, H, W, D]. render_alphas: [C, H, W, 1].
    """
    args = (means2d, conics, colors, opacities, image_width, image_height, tile_size, isect_offsets, flatten_ids)
    if resolve_cpu_backend(backend) == "cpp":
        from gsmsdr_ns.render.pixels_cpp import rasterize_to_pixels_cpp

        return rasterize_to_pixels_cpp(*args, backgrounds=backgrounds, absgrad=absgrad)
    return rasterize_to_pixels_torch(*args, backgrounds=backgrounds, absgrad=absgrad)


def _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, sh_degree, covars) -> None:
    N, C = means.shape[0], viewmats.shape[0]
    expected = {"means": (means, (N, 3)), "opacities": (opacities, (N,)), "viewmats": (viewmats, (C, 4, 4))}
    expected["Ks"] = (Ks, (C, 3, 3))
    if covars is None:
        expected.update(quats=(quats, (N, 4)), scales=(scales, (N, 3)))
    else:
        expected["covars"] = (covars, (N, 3, 3))
    for name, (tensor, shape) in expected.items():
        if tuple(tensor.shape) != shape:
            raise ValueError(f"rasterization: {name} must have shape {list(shape)}, got {list(tensor.shape)}")
    if sh_degree is None:
        ok = (colors.dim() == 2 and colors.shape[0] == N) or (colors.dim() == 3 and colors.shape[:2] == (C, N))
        if not ok:
            raise ValueError(
                f"rasterization: colors must be [N, D] or [C, N, D] (N={N}, C={C}), got {list(colors.shape)}"
            )
    else:
        ok = (colors.dim() == 3 and colors.shape[0] == N) or (colors.dim() == 4 and colors.shape[:2] == (C, N))
        if not ok or colors.shape[-1] != 3:
            raise ValueError(
                f"rasterization: SH colors must be [N, K, 3] or [C, N, K, 3] (N={N}, C={C}), got {list(colors.shape)}"
            )
        if (sh_degree + 1) ** 2 > colors.shape[-2]:
            raise ValueError(f"rasterization: sh_degree={sh_degree} needs {(sh_degree + 1) ** 2} SH coefficients")


def rasterization(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [(C,) N, D] or [(C,) N, K, 3]
    viewmats: Tensor,  # [C, 4, 4]
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: Optional[int] = None,
    packed: bool = True,
    tile_size: int = 16,
    backgrounds: Optional[Tensor] = None,
    render_mode: Literal["RGB", "D", "ED", "RGB+D", "RGB+ED"] = "RGB",
    sparse_grad: bool = False,
    absgrad: bool = False,
    rasterize_mode: Literal["classic", "antialiased"] = "classic",
    channel_chunk: int = 32,
    distributed: bool = False,
    camera_model: Literal["pinhole", "ortho", "fisheye"] = "pinhole",
    covars: Optional[Tensor] = None,
    cpu_backend: CpuBackend = "auto",
) -> Tuple[Tensor, Tensor, Dict]:
    """Rasterize N 3D Gaussians into C images; gsplat 1.4.0's signature and return value.

    Args:
        means: [N, 3]. quats: [N, 4] (w, x, y, z, normalised here). scales: [N, 3]. opacities: [N].
        colors: [N, D] / [C, N, D] post-activation colours, or [N, K, 3] / [C, N, K, 3] SH coefficients when
            `sh_degree` is given (then colours are clamp_min(SH + 0.5, 0), as in 3D-GS).
        viewmats: [C, 4, 4] world-to-camera. Ks: [C, 3, 3]. width, height: pixels.
        backgrounds: [C, D] or None. render_mode: "RGB", "D", "ED", "RGB+D" or "RGB+ED" (depth appended last).
        absgrad: set `meta["means2d"].absgrad` after backward. rasterize_mode: "classic" or "antialiased".
        cpu_backend: CPU pixel kernel, "auto" (C++ when it builds), "cpp" or "torch". Ignored on CUDA.
        packed: on CPU the images are the same either way; packed=True returns gsplat's packed `meta` (the
            visible camera-Gaussian pairs only, with `camera_ids` and `gaussian_ids`), packed=False the [C, N]
            layout. packed=True with absgrad=True is CUDA-only.
        The other arguments are gsplat's; on CPU, `sparse_grad`, `distributed` and non-pinhole camera models are
        not supported and raise.

    Returns:
        render_colors: [C, H, W, D']. render_alphas: [C, H, W, 1]. meta: dict with gsplat's keys (radii,
        means2d, depths, conics, opacities, tiles_per_gauss, isect_ids, flatten_ids, isect_offsets, width,
        height, tile_size, n_cameras, ...) plus "backend". Packed: radii [nnz], means2d [nnz, 2], depths [nnz],
        conics [nnz, 3], opacities [nnz], camera_ids [nnz], gaussian_ids [nnz], flatten_ids into those nnz rows.
    """
    if means.is_cuda:
        from gsplat.rendering import rasterization as gsplat_rasterization

        from gsmsdr_ns.render.gsplat_backend import require_gsplat_cuda

        require_gsplat_cuda()  # cached after the first call: no cost per render

        colors_out, alphas, meta = gsplat_rasterization(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane=near_plane,
            far_plane=far_plane, radius_clip=radius_clip, eps2d=eps2d, sh_degree=sh_degree, packed=packed,
            tile_size=tile_size, backgrounds=backgrounds, render_mode=render_mode, sparse_grad=sparse_grad,
            absgrad=absgrad, rasterize_mode=rasterize_mode, channel_chunk=channel_chunk, distributed=distributed,
            camera_model=camera_model, covars=covars,
        )  # fmt: skip
        meta["backend"] = "gsplat"
        return colors_out, alphas, meta

    unsupported = {"sparse_grad=True": sparse_grad, "distributed=True": distributed}
    unsupported["packed=True with absgrad=True"] = packed and absgrad
    unsupported[f"camera_model={camera_model!r}"] = camera_model != "pinhole"
    for what, used in unsupported.items():
        if used:
            raise ValueError(f"rasterization on CPU does not support {what}; it is CUDA-only")
    if render_mode not in ("RGB", "D", "ED", "RGB+D", "RGB+ED"):
        raise ValueError(f"rasterization: unknown render_mode {render_mode!r}")
    if rasterize_mode not in ("classic", "antialiased"):
        raise ValueError(f"rasterization: unknown rasterize_mode {rasterize_mode!r}")
    if width <= 0 or height <= 0:
        raise ValueError(f"rasterization: image size must be positive, got {width}x{height}")
    _check_inputs(means, quats, scales, opacities, colors, viewmats, Ks, sh_degree, covars)

    # gsplat's CUDA kernels compute in float32 whatever torch.autocast says; so does the CPU path (a bfloat16
    # projection would move centres by pixels, and the C++ kernel needs one dtype)
    dtype = torch.float64 if means.dtype == torch.float64 else torch.float32

    def cast(t: Tensor) -> Tensor:
        return t.to(dtype)  # the same tensor when it already has that dtype

    def cast_optional(t: Optional[Tensor]) -> Optional[Tensor]:
        return None if t is None else t.to(dtype)

    with torch.autocast(device_type="cpu", enabled=False):
        return _rasterization_cpu(
            cast(means), cast_optional(quats), cast_optional(scales), cast(opacities), cast(colors), cast(viewmats),
            cast(Ks), width, height, near_plane, far_plane, radius_clip, eps2d, sh_degree, tile_size,
            cast_optional(backgrounds), render_mode, absgrad, rasterize_mode, cast_optional(covars), cpu_backend,
            packed,
        )  # fmt: skip


def _rasterization_cpu(
    means: Tensor,
    quats: Optional[Tensor],
    scales: Optional[Tensor],
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float,
    far_plane: float,
    radius_clip: float,
    eps2d: float,
    sh_degree: Optional[int],
    tile_size: int,
    backgrounds: Optional[Tensor],
    render_mode: str,
    absgrad: bool,
    rasterize_mode: str,
    covars: Optional[Tensor],
    cpu_backend: CpuBackend,
    packed: bool = False,
) -> Tuple[Tensor, Tensor, Dict]:
    """The CPU path of `rasterization` (arguments checked, one floating dtype, autocast off)."""
    C, N = viewmats.shape[0], means.shape[0]
    if covars is None:
        assert quats is not None and scales is not None  # _check_inputs checked their shapes when covars is None
        covars = covariance_3d(quats, scales)
    proj = project_gaussians(
        means, covars, viewmats, Ks, width, height, eps2d=eps2d, near_plane=near_plane, far_plane=far_plane,
        radius_clip=radius_clip, calc_compensations=rasterize_mode == "antialiased",
    )  # fmt: skip
    opacities_c = opacities.expand(C, N)
    if proj.compensations is not None:
        opacities_c = opacities_c * proj.compensations

    if sh_degree is None:
        colors_c = colors.expand(C, N, colors.shape[-1]) if colors.dim() == 2 else colors
    else:
        cam_centres = torch.linalg.inv(viewmats)[:, :3, 3]  # [C, 3]
        # a non-finite centre (culled by the projection) must not send NaN to the cameras' gradient through dirs
        finite_means = torch.where(means.isfinite().all(-1, keepdim=True), means, torch.zeros_like(means))
        dirs = finite_means[None, :, :] - cam_centres[:, None, :]  # [C, N, 3]
        coeffs = colors.expand(C, *colors.shape) if colors.dim() == 3 else colors
        colors_c = torch.clamp_min(eval_sh_colors(sh_degree, dirs, coeffs) + 0.5, 0.0)

    if render_mode in ("RGB+D", "RGB+ED"):
        colors_c = torch.cat([colors_c, proj.depths[..., None]], dim=-1)
        if backgrounds is not None:
            backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(C, 1)], dim=-1)
    elif render_mode in ("D", "ED"):
        colors_c = proj.depths[..., None]
        if backgrounds is not None:
            backgrounds = backgrounds.new_zeros(C, 1)

    means2d = proj.means2d
    if packed:
        camera_ids, gaussian_ids = torch.nonzero(proj.radii > 0, as_tuple=True)  # [nnz] each
        packed_means2d = proj.means2d[camera_ids, gaussian_ids]  # [nnz, 2]: its .grad is the densification signal
        # render from the packed rows scattered back, so the image's gradient reaches packed_means2d
        means2d = proj.means2d.detach().index_put((camera_ids, gaussian_ids), packed_means2d)

    tile_width, tile_height = math.ceil(width / tile_size), math.ceil(height / tile_size)
    tiles_per_gauss, isect_ids, flatten_ids = isect_tiles(
        proj.means2d, proj.radii, proj.depths, tile_size, tile_width, tile_height
    )
    isect_offsets = isect_offset_encode(isect_ids, C, tile_width, tile_height)
    backend = resolve_cpu_backend(cpu_backend)
    render_colors, render_alphas = rasterize_to_pixels(
        means2d, proj.conics, colors_c.contiguous(), opacities_c.contiguous(), width, height, tile_size,
        isect_offsets, flatten_ids, backgrounds=backgrounds, absgrad=absgrad, backend=backend,
    )  # fmt: skip
    if render_mode in ("ED", "RGB+ED"):
        depth = render_colors[..., -1:] / render_alphas.clamp_min(1e-10)
        render_colors = torch.cat([render_colors[..., :-1], depth], dim=-1)

    meta = {
        "camera_ids": None,
        "gaussian_ids": None,
        "radii": proj.radii,
        "means2d": proj.means2d,
        "depths": proj.depths,
        "conics": proj.conics,
        "opacities": opacities_c,
        "tile_width": tile_width,
        "tile_height": tile_height,
        "tiles_per_gauss": tiles_per_gauss,
        "isect_ids": isect_ids,
        "flatten_ids": flatten_ids,
        "isect_offsets": isect_offsets,
        "width": width,
        "height": height,
        "tile_size": tile_size,
        "n_cameras": C,
        "backend": backend,
    }
    if packed:
        meta.update(_packed_meta(meta, camera_ids, gaussian_ids, packed_means2d, N))
    return render_colors, render_alphas, meta


def _packed_meta(
    meta: Dict, camera_ids: Tensor, gaussian_ids: Tensor, packed_means2d: Tensor, num_gaussians: int
) -> Dict:
    """gsplat's packed layout of the per-camera entries of an unpacked `meta`.

    Args:
        meta: the unpacked meta ([C, N] per-camera entries, flatten_ids indexing C * N).
        camera_ids, gaussian_ids: [nnz] the visible (radii > 0) pairs, in row-major (camera, Gaussian) order.
        packed_means2d: [nnz, 2] the rows the image was rendered from.

    Returns:
        The entries that differ in packed mode: camera_ids, gaussian_ids, radii, means2d, depths, conics,
        opacities and tiles_per_gauss as [nnz] rows, flatten_ids re-indexed into them.
    """
    rows = {name: meta[name][camera_ids, gaussian_ids] for name in ("radii", "depths", "conics", "opacities")}
    rows["tiles_per_gauss"] = meta["tiles_per_gauss"].reshape(-1, num_gaussians)[camera_ids, gaussian_ids]
    flat = camera_ids * num_gaussians + gaussian_ids
    row_of = torch.full((meta["n_cameras"] * num_gaussians,), -1, dtype=torch.int64, device=flat.device)
    row_of[flat] = torch.arange(flat.shape[0], device=flat.device)
    flatten_ids = row_of[meta["flatten_ids"].long()].to(meta["flatten_ids"].dtype)
    return dict(rows, camera_ids=camera_ids, gaussian_ids=gaussian_ids, means2d=packed_means2d, flatten_ids=flatten_ids)
