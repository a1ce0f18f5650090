"""Procedural 2D textures with sharp, high-frequency detail (deblurring needs edges).

All functions are pure numpy on float64 texture coordinates in world units, hash-based (no global RNG),
so the same inputs give bitwise identical outputs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TEXTURE_KINDS = ("checker", "stripes", "grid", "bricks", "noise", "text")

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLD = np.uint64(0x9E3779B97F4A7C15)
_MULTS = [np.uint64(m) for m in (0xD6E8FEB86659FD93, 0xA0761D6478BD642F, 0xE7037ED1A0B428DB, 0x8EBC6AF09C88C6E3)]


@dataclass(frozen=True)
class Texture:
    """A procedural texture: `kind` pattern mixing two colours, at `scale` world units per period."""

    kind: str
    """One of TEXTURE_KINDS."""
    color_a: tuple[float, float, float]
    """Base (background / paper / brick) albedo, linear RGB in [0, 1]."""
    color_b: tuple[float, float, float]
    """Pattern (ink / mortar / stripe) albedo."""
    scale: float
    """Pattern period in world units (text: line height)."""
    seed: int
    """Hash seed of the noise and glyph patterns."""
    angle: float = 0.0
    """Rotation of the pattern in the uv plane (radians)."""
    detail: float = 0.25
    """Amplitude of the multiplicative value-noise detail layered on every pattern."""


def _mix64(h: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser; uint64 arithmetic wraps, which is what we want."""
    h = h ^ (h >> np.uint64(30))
    h = h * _M1
    h = h ^ (h >> np.uint64(27))
    h = h * _M2
    return h ^ (h >> np.uint64(31))


def hash01(seed: int, *coords: np.ndarray) -> np.ndarray:
    """Deterministic hash of integer lattice coordinates to floats in [0, 1). coords: int arrays of one shape."""
    with np.errstate(over="ignore"):
        # One splitmix round over a linear combination with large odd multipliers: plenty for textures,
        # and much cheaper than mixing per coordinate (hashing dominates texture cost).
        h = _mix64(np.array([seed & 0xFFFFFFFFFFFFFFFF], dtype=np.uint64) + _GOLD)
        for k, c in enumerate(coords):
            h = h + np.asarray(c, dtype=np.int64).astype(np.uint64) * _MULTS[k]
        h = _mix64(h)
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


def value_noise(u: np.ndarray, v: np.ndarray, seed: int) -> np.ndarray:
    """Smooth 2D value noise in [0, 1] on the unit lattice. u, v: [N] -> [N]."""
    iu, iv = np.floor(u), np.floor(v)
    fu, fv = u - iu, v - iv
    iu, iv = iu.astype(np.int64), iv.astype(np.int64)
    su, sv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    n00 = hash01(seed, iu, iv)
    n10 = hash01(seed, iu + 1, iv)
    n01 = hash01(seed, iu, iv + 1)
    n11 = hash01(seed, iu + 1, iv + 1)
    return (n00 * (1 - su) + n10 * su) * (1 - sv) + (n01 * (1 - su) + n11 * su) * sv


def fbm(u: np.ndarray, v: np.ndarray, seed: int, octaves: int = 4) -> np.ndarray:
    """Fractal sum of value noise, normalised to [0, 1]. u, v: [N] -> [N]."""
    total = np.zeros_like(u)
    amp, norm = 1.0, 0.0
    for o in range(octaves):
        f = 2.0**o
        # Per-octave offset avoids the lattice origins lining up across octaves.
        total += amp * value_noise(u * f + 17.3 * o, v * f - 9.1 * o, seed + 1013 * o)
        norm += amp
        amp *= 0.5
    return total / norm


def _frac(x: np.ndarray) -> np.ndarray:
    return x - np.floor(x)


def _text_mask(u: np.ndarray, v: np.ndarray, seed: int) -> np.ndarray:
    """Text-like ink mask: lines of 5x7 glyphs from a random 40-glyph font, with word gaps. u,v in line heights."""
    px_u, px_v = u * 10.0, v * 10.0  # a line is 10 glyph pixels tall: 7 glyph rows + 3 rows of leading
    cell_u = np.floor(px_u / 6.0).astype(np.int64)  # a glyph cell is 6 px wide: 5 columns + 1 spacing
    line = np.floor(v).astype(np.int64)
    gx = np.floor(px_u - 6.0 * cell_u).astype(np.int64)
    gy = np.floor(px_v - 10.0 * line).astype(np.int64)
    cell_h = hash01(seed, cell_u, line)
    glyph = np.floor(hash01(seed + 7, cell_u, line) * 40).astype(np.int64)
    bit = hash01(seed + 13, glyph, gx, gy) < 0.45
    # Short lines: lines end at a random length so the block looks like a paragraph.
    line_len = 24 + np.floor(hash01(seed + 29, line) * 40)
    in_line = _frac(cell_u / 64.0) * 64.0 < line_len
    return bit & (gx < 5) & (gy < 7) & (cell_h > 0.18) & in_line


def eval_texture(tex: Texture, uv: np.ndarray) -> np.ndarray:
    """Albedo of `tex` at texture coordinates uv [N, 2] (world units) -> [N, 3] float64 in [0, 1]."""
    c, s = np.cos(tex.angle), np.sin(tex.angle)
    u = (c * uv[:, 0] - s * uv[:, 1]) / tex.scale
    v = (s * uv[:, 0] + c * uv[:, 1]) / tex.scale
    a = np.asarray(tex.color_a, dtype=np.float64)
    b = np.asarray(tex.color_b, dtype=np.float64)
    kind = tex.kind
    shade = np.ones_like(u)  # per-cell brightness variation where the pattern has cells
    if kind == "checker":
        w = ((np.floor(u) + np.floor(v)) % 2).astype(np.float64)
    elif kind == "stripes":
        # Main stripes plus a thin secondary stripe: two edge frequencies.
        w = ((_frac(u) < 0.5) | (_frac(u * 3.0 + 0.25) < 0.12)).astype(np.float64)
    elif kind == "grid":
        w = ((_frac(u) < 0.08) | (_frac(v) < 0.08)).astype(np.float64)
        shade = 0.8 + 0.4 * hash01(tex.seed, np.floor(u).astype(np.int64), np.floor(v).astype(np.int64))
    elif kind == "bricks":
        vr = v * 2.0  # bricks are half as tall as wide
        row = np.floor(vr)
        ub = u + 0.5 * (row % 2)
        w = ((_frac(ub) < 0.06) | (_frac(vr) < 0.12)).astype(np.float64)
        shade = 0.7 + 0.6 * hash01(tex.seed, np.floor(ub).astype(np.int64), row.astype(np.int64))
    elif kind == "noise":
        n = fbm(u, v, tex.seed, octaves=5)
        # A steep ramp turns smooth noise into blobs with crisp (but anti-aliasable) boundaries.
        w = np.clip((n - 0.5) * 12.0 + 0.5, 0.0, 1.0)
    elif kind == "text":
        w = _text_mask(u, v, tex.seed).astype(np.float64)
    else:
        raise ValueError(f"unknown texture kind {kind!r}; expected one of {TEXTURE_KINDS}")
    rgb = a[None] * (shade * (1 - w))[:, None] + b[None] * w[:, None]
    if tex.detail > 0:
        # Fine multiplicative grain at 4x the pattern frequency: no flat regions anywhere.
        g = fbm(u * 4.0, v * 4.0, tex.seed + 99991, octaves=2)
        rgb = rgb * (1.0 - tex.detail * 0.5 + tex.detail * g)[:, None]
    return np.clip(rgb, 0.0, 1.0)
