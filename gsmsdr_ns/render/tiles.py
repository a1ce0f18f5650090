"""Gaussian-to-tile intersection lists, sorted front to back per tile (no gradients flow here)."""

from __future__ import annotations

from typing import Tuple

import torch
from torch import Tensor


@torch.no_grad()
def isect_tiles(
    means2d: Tensor,  # [C, N, 2]
    radii: Tensor,  # [C, N]
    depths: Tensor,  # [C, N]
    tile_size: int,
    tile_width: int,
    tile_height: int,
) -> Tuple[Tensor, Tensor, Tensor]:
    """List every (camera, tile, Gaussian) overlap of the 3-sigma bounding squares.

    Args:
        means2d: [C, N, 2] pixel centres.
        radii: [C, N] pixel radii; 0 means culled.
        depths: [C, N] camera-space depths (positive for every Gaussian with radius > 0).
        tile_size: tile edge in pixels.
        tile_width, tile_height: number of tiles along x and y.

    Returns:
        tiles_per_gauss: [C, N] int32 number of tiles each Gaussian touches.
        isect_ids: [M] int64 keys `(camera * n_tiles + tile) << 32 | float32 bits of depth`, sorted ascending,
            i.e. grouped by camera, then tile, then front to back.
        flatten_ids: [M] int32 index of the Gaussian into the flattened [C * N] arrays.
    """
    C, N = radii.shape
    device = means2d.device
    r = radii.to(means2d.dtype)
    x, y = means2d[..., 0], means2d[..., 1]
    x0 = torch.clamp(torch.floor((x - r) / tile_size), 0, tile_width).long()
    x1 = torch.clamp(torch.ceil((x + r) / tile_size), 0, tile_width).long()
    y0 = torch.clamp(torch.floor((y - r) / tile_size), 0, tile_height).long()
    y1 = torch.clamp(torch.ceil((y + r) / tile_size), 0, tile_height).long()
    span_x = x1 - x0
    counts = torch.where(radii > 0, span_x * (y1 - y0), torch.zeros_like(span_x))  # [C, N]

    flat_counts = counts.reshape(-1)
    total = int(flat_counts.sum())
    owner = torch.repeat_interleave(torch.arange(C * N, device=device), flat_counts)  # [M]
    # position of each intersection inside its Gaussian's tile rectangle
    starts = torch.cumsum(flat_counts, 0) - flat_counts
    local = torch.arange(total, device=device) - starts[owner]
    sx = span_x.reshape(-1)[owner]
    tile_x = x0.reshape(-1)[owner] + local % sx.clamp_min(1)
    tile_y = y0.reshape(-1)[owner] + local // sx.clamp_min(1)
    camera = owner // N
    n_tiles = tile_width * tile_height
    tile_key = camera * n_tiles + tile_y * tile_width + tile_x

    # positive float32 depths order like their bit patterns read as integers
    depth_bits = depths.reshape(-1)[owner].to(torch.float32).view(torch.int32).to(torch.int64)
    keys = (tile_key << 32) | (depth_bits & 0xFFFFFFFF)
    isect_ids, order = torch.sort(keys, stable=True)
    flatten_ids = owner[order].to(torch.int32)
    return counts.to(torch.int32), isect_ids, flatten_ids


@torch.no_grad()
def isect_offset_encode(isect_ids: Tensor, n_cameras: int, tile_width: int, tile_height: int) -> Tensor:
    """First intersection index of every tile.

    Args:
        isect_ids: [M] sorted keys from `isect_tiles`.
        n_cameras, tile_width, tile_height: grid size.

    Returns:
        [C, tile_height, tile_width] int32 offsets; tile t's list ends where the next tile's begins (or at M).
    """
    n_tiles = tile_width * tile_height
    tile_keys = isect_ids >> 32
    queries = torch.arange(n_cameras * n_tiles, device=isect_ids.device, dtype=torch.int64)
    offsets = torch.searchsorted(tile_keys, queries)
    return offsets.to(torch.int32).reshape(n_cameras, tile_height, tile_width)
