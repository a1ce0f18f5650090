"""The grid an image upsampled from a lower resolution keeps: periodicity of its second and third differences.

Pure functions on grey images ``gray: [H, W]`` (float, values in [0, 1]).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def _line_periodicity(profile: Tensor, freq: float) -> float:
    """Power of profile [L] at `freq` cycles per sample, over its mean power per frequency (noise: about 1)."""
    p = profile - profile.mean()
    total = float((p**2).sum())
    if total <= 0:
        return 0.0
    x = torch.arange(len(p), dtype=p.dtype)
    phase = 2 * math.pi * freq * x
    re, im = float((p * torch.cos(phase)).sum()), float((p * torch.sin(phase)).sum())
    return (re * re + im * im) / total


def grid_scores(gray: Tensor, factors: tuple[int, ...] = (2, 3, 4)) -> dict[int, float]:
    """Periodicity of |second| and |third differences| at the knot spacing of an upsampling by f, per f in `factors`.

    An image interpolated from a low-resolution grid (bilinear, bicubic) bends only at (or changes its curvature
    pattern at) the low-resolution samples, so the column (row) profile of its |d2/dx2| (|d2/dy2|) repeats every
    W / w_low (H / h_low) pixels. The low size may have been rounded either way, so both roundings are tried.
    -> {f: min over the two axes of the best score}; an image without such a grid scores about 1. A grid every
    4 px also repeats every 2 px (it scores at f = 2 as well); a 2 px grid does not score at f = 4.
    """
    H, W = gray.shape
    # Second differences vanish inside a bilinear segment; with f = 2 every output pixel sits at the same
    # distance from a knot, and only the third differences (zero between the two pixels of a segment) show it.
    profiles = {
        "x": [torch.diff(gray, n, dim=1).abs().mean(0) for n in (2, 3)],  # [W - n]
        "y": [torch.diff(gray, n, dim=0).abs().mean(1) for n in (2, 3)],  # [H - n]
    }
    scores = {}
    for f in factors:
        axis_scores = []
        for axis, size in (("x", W), ("y", H)):
            lows = {max(1, math.floor(size / f)), max(1, math.ceil(size / f))}
            axis_scores.append(max(_line_periodicity(p, low / size) for low in lows for p in profiles[axis]))
        scores[f] = min(axis_scores)
    return scores


__all__ = ["grid_scores"]
