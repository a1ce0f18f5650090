"""The Gaussians' side of a ``gsmsdr`` step (pure functions over splatfacto's parameters): the seed point cloud
checked before splatfacto builds from it, the parameters inside the viewer's crop box, and their activation and
rasterization by :func:`gsmsdr_ns.render.rasterization` (gsplat for CUDA tensors, our CPU rasterizer otherwise)."""

from __future__ import annotations

import warnings
from typing import Dict, Mapping, Optional, Tuple, Type

import torch
from nerfstudio.models.splatfacto import RGB2SH
from torch import Tensor

__all__ = [
    "GAUSSIAN_PARAM_NAMES",
    "MIN_SEED_POINTS",
    "usable_seed_points",
    "write_seed_colours",
    "gaussians_in_crop",
    "colours_and_sh_degree",
    "rasterize_gaussians",
    "expected_depth",
]

GAUSSIAN_PARAM_NAMES = ("means", "scales", "quats", "features_dc", "features_rest", "opacities")
MIN_SEED_POINTS = 4  # splatfacto sizes each Gaussian from its 3 nearest neighbours


def usable_seed_points(
    seed_points: Optional[Tuple[Tensor, Tensor]], num_random: int, random_scale: float, category: Type[Warning]
) -> Optional[Tuple[Tensor, Tensor]]:
    """The seed cloud (xyz [N, 3], rgb [N, 3] or [0, 3]) without its non-finite points, or None with a warning of
    ``category`` naming the random initialisation (``num_random`` Gaussians in a cube of side ``random_scale``)
    that takes its place."""
    if seed_points is None:
        problem = "no point cloud was provided"
    else:
        xyz, rgb = seed_points
        finite = torch.isfinite(xyz).all(dim=-1)
        rgb = rgb[finite] if rgb.shape[0] == xyz.shape[0] else rgb[:0]
        xyz = xyz[finite]
        if xyz.shape[0] >= MIN_SEED_POINTS:
            return xyz, rgb
        problem = f"the point cloud has {xyz.shape[0]} usable points (need at least {MIN_SEED_POINTS})"
    warnings.warn(
        f"gsmsdr: {problem}; initialising {num_random} random Gaussians in a cube of side {random_scale} instead. "
        "Training will converge more slowly; set --pipeline.model.num-random / --pipeline.model.random-scale to "
        "tune it.",
        category,
        stacklevel=4,
    )
    return None


@torch.no_grad()
def write_seed_colours(features_dc: Tensor, rgb: Tensor, sh_degree: int) -> None:
    """Set each Gaussian's base colour ``features_dc`` [N, 3] from its seed point's 0-255 ``rgb`` [N, 3], in place
    (nothing when the counts differ: a cloud without colours)."""
    if rgb.shape[0] != features_dc.shape[0]:
        return
    rgb = rgb.to(device=features_dc.device, dtype=features_dc.dtype) / 255.0
    features_dc.copy_(RGB2SH(rgb) if sh_degree > 0 else torch.logit(rgb, eps=1e-10))


def gaussians_in_crop(params: Mapping[str, Tensor], crop_box, training: bool) -> Optional[Dict[str, Tensor]]:
    """The raw Gaussian parameters, restricted to the viewer's ``crop_box`` at evaluation; None if it is empty."""
    gaussians = {name: params[name] for name in GAUSSIAN_PARAM_NAMES}
    if crop_box is None or training:
        return gaussians
    inside = crop_box.within(gaussians["means"]).reshape(-1)
    if not bool(inside.any()):
        return None
    return {name: value[inside] for name, value in gaussians.items()}


def colours_and_sh_degree(
    gaussians: Mapping[str, Tensor], sh_degree: int, step: int, sh_degree_interval: int
) -> Tuple[Tensor, Optional[int]]:
    """SH coefficients [N, K, 3] and the degree unlocked at ``step``, or plain RGB [N, 3] when ``sh_degree`` is 0."""
    coefficients = torch.cat([gaussians["features_dc"][:, None, :], gaussians["features_rest"]], dim=1)
    if sh_degree == 0:
        return torch.sigmoid(coefficients[:, 0, :]), None
    return coefficients, min(step // sh_degree_interval, sh_degree)


def rasterize_gaussians(
    gaussians: Mapping[str, Tensor],
    colours: Tensor,
    sh_degree: Optional[int],
    viewmats: Tensor,
    K: Tensor,
    width: int,
    height: int,
    with_depth: bool,
    absgrad: bool,
    rasterize_mode: str,
) -> Tuple[Tensor, Tensor, Dict]:
    """Activate the raw parameters and rasterize one camera (viewmats [1, 4, 4], K [1, 3, 3]): render
    [1, H, W, 3 or 4] (expected depth last ``with_depth``), alpha [1, H, W, 1], and the rasterizer's info."""
    from gsmsdr_ns.render import rasterization  # imported on first render: keeps method discovery light

    return rasterization(
        means=gaussians["means"],
        quats=gaussians["quats"],  # normalised by the rasterizer
        scales=torch.exp(gaussians["scales"]),
        opacities=torch.sigmoid(gaussians["opacities"]).squeeze(-1),
        colors=colours,
        viewmats=viewmats,
        Ks=K,
        width=width,
        height=height,
        near_plane=0.01,
        far_plane=1e10,
        sh_degree=sh_degree,
        packed=False,
        render_mode="RGB+ED" if with_depth else "RGB",
        sparse_grad=False,
        absgrad=absgrad,
        rasterize_mode=rasterize_mode,
    )


def expected_depth(render: Tensor, alpha: Tensor) -> Tensor:
    """[H, W, 1] expected depth from render [1, H, W, 4] and alpha [1, H, W, 1]; empty pixels get the farthest
    rendered depth."""
    depth = render[..., 3:4]
    return torch.where(alpha > 0, depth, depth.detach().max()).squeeze(0)
