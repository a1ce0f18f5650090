"""Readable pure-PyTorch tile rasterizer: the reference and the fallback of the C++ kernel.

Autograd does the backward. Each tile is a dense [pixels, Gaussians-in-tile] block, so the cost follows the real
intersection counts instead of padding every tile to the fullest one.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch
from torch import Tensor

ALPHA_MAX = 0.999  # opacity clamp, keeps 1 - alpha away from 0
ALPHA_MIN = 1.0 / 255.0  # contributions below one 8-bit step are skipped
T_MIN = 1e-4  # compositing stops before transmittance falls to this


def composite_front_to_back(alphas: Tensor) -> Tuple[Tensor, Tensor]:
    """Front-to-back blending weights with 3D-GS's early stop.

    Args:
        alphas: [P, K] per-pixel alphas in depth order, already clamped and with skipped entries set to 0.

    Returns:
        weights: [P, K] alpha_k * T_k for the composited entries, 0 for the rest.
        transmittance: [P] transmittance left after the last composited entry.
    """
    one_minus = 1.0 - alphas
    with torch.no_grad():
        # transmittance only decreases, so the entries kept are a prefix of each row
        keep = torch.cumprod(one_minus, dim=-1) > T_MIN
    kept = alphas * keep
    kept_one_minus = 1.0 - kept
    t_before = torch.cumprod(torch.cat([torch.ones_like(kept[:, :1]), kept_one_minus[:, :-1]], dim=-1), dim=-1)
    weights = kept * t_before
    transmittance = t_before[:, -1] * kept_one_minus[:, -1]
    return weights, transmittance


def _accumulate_abs(buffer: Tensor, rows: Tensor, component: int):
    """Hook adding |d loss / d offset| of every pixel into buffer[rows, component] (gsplat's absgrad)."""

    def hook(grad: Tensor) -> None:
        buffer[:, component].index_add_(0, rows, grad.abs().sum(dim=0).to(buffer.dtype))

    return hook


def rasterize_to_pixels_torch(
    means2d: Tensor,  # [C, N, 2]
    conics: Tensor,  # [C, N, 3]
    colors: Tensor,  # [C, N, D]
    opacities: Tensor,  # [C, N]
    image_width: int,
    image_height: int,
    tile_size: int,
    isect_offsets: Tensor,  # [C, tile_height, tile_width]
    flatten_ids: Tensor,  # [M]
    backgrounds: Optional[Tensor] = None,  # [C, D]
    absgrad: bool = False,
) -> Tuple[Tensor, Tensor]:
    """Alpha-composite sorted screen-space Gaussians tile by tile.

    Args:
        means2d: [C, N, 2] pixel centres. conics: [C, N, 3] inverse 2D covariances (a, b, c).
        colors: [C, N, D] per-camera colours (any D). opacities: [C, N] in [0, 1].
        image_width, image_height, tile_size: raster size.
        isect_offsets: [C, th, tw] int32 first intersection of every tile (see `tiles.isect_offset_encode`).
        flatten_ids: [M] int32 indices into the flattened [C * N] arrays, sorted front to back per tile.
        backgrounds: [C, D] colour behind the Gaussians, or None for black.
        absgrad: after backward, `means2d.absgrad` [C, N, 2] holds the per-Gaussian sum over pixels of
            |d loss / d means2d|.

    Returns:
        render_colors: [C, H, W, D]. render_alphas: [C, H, W, 1].
    """
    C, N, D = colors.shape
    H, W = image_height, image_width
    device, dtype = colors.device, colors.dtype
    m2d = means2d.reshape(C * N, 2)
    con = conics.reshape(C * N, 3)
    col = colors.reshape(C * N, D)
    opa = opacities.reshape(C * N)
    flat_ids = flatten_ids.long()

    abs_buffer = None
    if absgrad and means2d.requires_grad and torch.is_grad_enabled():
        abs_buffer = torch.zeros(C * N, 2, device=device, dtype=means2d.dtype)
        # filled in place by the hooks during backward; gsplat's extra attribute, unknown to torch's stubs
        means2d.absgrad = abs_buffer.view(C, N, 2)  # type: ignore[attr-defined]

    offsets = isect_offsets.reshape(-1).tolist() + [flat_ids.numel()]
    th, tw = isect_offsets.shape[1:]
    pixel_rows, tile_colors, tile_trans = [], [], []
    for tile_index in range(C * th * tw):
        start, end = offsets[tile_index], offsets[tile_index + 1]
        if end <= start:
            continue
        cam, rest = divmod(tile_index, th * tw)
        ty, tx = divmod(rest, tw)
        ys = torch.arange(ty * tile_size, min((ty + 1) * tile_size, H), device=device)
        xs = torch.arange(tx * tile_size, min((tx + 1) * tile_size, W), device=device)
        py, px = torch.meshgrid(ys, xs, indexing="ij")
        py, px = py.reshape(-1), px.reshape(-1)

        ids = flat_ids[start:end]
        g = m2d[ids]
        dx = g[:, 0][None, :] - (px.to(dtype) + 0.5)[:, None]  # [P, K]
        dy = g[:, 1][None, :] - (py.to(dtype) + 0.5)[:, None]
        if abs_buffer is not None:
            dx.register_hook(_accumulate_abs(abs_buffer, ids, 0))
            dy.register_hook(_accumulate_abs(abs_buffer, ids, 1))
        a, b, c = con[ids].unbind(-1)
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        alpha = torch.clamp_max(opa[ids] * torch.exp(-sigma), ALPHA_MAX)
        with torch.no_grad():
            used = (sigma >= 0) & (alpha >= ALPHA_MIN)
        alpha = alpha * used
        weights, trans = composite_front_to_back(alpha)
        pixel_rows.append(cam * H * W + py * W + px)
        tile_colors.append(weights @ col[ids])
        tile_trans.append(trans)

    out_colors = torch.zeros(C * H * W, D, device=device, dtype=dtype)
    out_trans = torch.ones(C * H * W, device=device, dtype=dtype)
    if pixel_rows:
        rows = torch.cat(pixel_rows)
        out_colors = out_colors.index_copy(0, rows, torch.cat(tile_colors))
        out_trans = out_trans.index_copy(0, rows, torch.cat(tile_trans))
    else:
        # nothing intersects any tile: tie the inputs into the graph with an exact zero (a sum over no element),
        # so they still get (zero) gradients, like the C++ kernel and gsplat, instead of None (which breaks
        # DefaultStrategy's `means2d.grad.clone()` and leaves optimizers without a gradient)
        anchor = m2d[:0].sum() + con[:0].sum() + col[:0].sum() + opa[:0].sum()
        out_colors, out_trans = out_colors + anchor, out_trans + anchor
    out_colors = out_colors.reshape(C, H, W, D)
    out_trans = out_trans.reshape(C, H, W, 1)
    if backgrounds is not None:
        out_colors = out_colors + out_trans * backgrounds[:, None, None, :]
    return out_colors, 1.0 - out_trans
