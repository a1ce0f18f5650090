"""Dense baseline: every Gaussian against every pixel, in PyTorch. Only for measuring what the tiles buy."""

from __future__ import annotations

from typing import Tuple

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from gsmsdr_ns.render.pixels_torch import ALPHA_MAX, ALPHA_MIN, composite_front_to_back


def _pixel_chunk(pix: Tensor, means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor) -> Tensor:
    dx = means2d[None, :, 0] - pix[:, None, 0]  # [P, N]
    dy = means2d[None, :, 1] - pix[:, None, 1]
    a, b, c = conics.unbind(-1)
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = torch.clamp_max(opacities * torch.exp(-sigma), ALPHA_MAX)
    alpha = alpha * ((sigma >= 0) & (alpha >= ALPHA_MIN))
    weights, trans = composite_front_to_back(alpha)
    return torch.cat([weights @ colors, trans[:, None]], dim=-1)


def rasterize_dense(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    colors: Tensor,  # [N, D]
    opacities: Tensor,  # [N]
    depths: Tensor,  # [N]
    radii: Tensor,  # [N]
    width: int,
    height: int,
    chunk: int = 1024,
) -> Tuple[Tensor, Tensor]:
    """One camera, no tiles: sort all visible Gaussians by depth and composite them at every pixel.

    Pixel chunks are recomputed in backward (activation checkpointing) so memory stays at one chunk.

    Returns:
        colors: [H, W, D]. alphas: [H, W, 1].
    """
    visible = torch.nonzero(radii > 0).squeeze(-1)
    order = visible[torch.argsort(depths[visible])]
    m, con, col, opa = means2d[order], conics[order], colors[order], opacities[order]
    ys, xs = torch.meshgrid(torch.arange(height, dtype=m.dtype), torch.arange(width, dtype=m.dtype), indexing="ij")
    pix = torch.stack([xs, ys], dim=-1).reshape(-1, 2) + 0.5
    outs = [
        checkpoint(_pixel_chunk, pix[i : i + chunk], m, con, col, opa, use_reentrant=False)
        for i in range(0, pix.shape[0], chunk)
    ]
    out = torch.cat(outs).reshape(height, width, -1)
    return out[..., :-1], 1.0 - out[..., -1:]
