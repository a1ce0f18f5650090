"""Bilinear splatting of weighted points onto a square grid: how a path of positions becomes a blur kernel."""

from __future__ import annotations

from torch import Tensor


def splat_bilinear(points: Tensor, weights: Tensor, size: int) -> Tensor:
    """Each point's weight shared among its four nearest grid cells by bilinear interpolation.

    Args:
        points: [N, 2] positions (x, y) in cell units, cell (0, 0) at the origin; clamped to [0, size - 1] first, so
            a point beyond the grid lands on its border.
        weights: [N] the points' weights.
        size: the grid's side (>= 1).
    Returns:
        [size * size] (row-major, index y * size + x) in the points' dtype and device; sums to ``weights.sum()``.
    """
    if points.dim() != 2 or points.shape[1] != 2 or weights.shape != points.shape[:1]:
        raise ValueError(f"expected points [N, 2] and weights [N], got {list(points.shape)}, {list(weights.shape)}")
    if size < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    pos = points.clamp(0.0, size - 1.0)
    low = pos.floor().clamp(max=max(size - 2, 0))  # a point on the last row or column keeps a cell after it
    frac = pos - low
    low = low.long()
    weights = weights.to(points.dtype)
    grid = points.new_zeros(size * size)
    for dy in (0, 1):
        for dx in (0, 1):
            wx = frac[:, 0] if dx else 1.0 - frac[:, 0]
            wy = frac[:, 1] if dy else 1.0 - frac[:, 1]
            ix = (low[:, 0] + dx).clamp(max=size - 1)
            iy = (low[:, 1] + dy).clamp(max=size - 1)
            grid.index_add_(0, iy * size + ix, wx * wy * weights)
    return grid
