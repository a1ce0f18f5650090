"""The C++/OpenMP rasterize_to_pixels kernel against an independent brute-force reference.

The reference below walks every tile list front to back with the spec's literal rules (float64, autograd does
its backward). Scenes and tile lists are built here, so nothing depends on projection.py or tiles.py.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from gsmsdr_ns.render.pixels_cpp import (
    cpp_backend_available,
    cpp_backend_error,
    load_cpu_extension,
    rasterize_to_pixels_cpp,
)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module", autouse=True)
def extension():
    # builds once per session; a missing compiler must FAIL these tests, not skip them
    return load_cpu_extension()


# --------------------------------------------------------------------------------------------------------------
# scenes and tile lists
# --------------------------------------------------------------------------------------------------------------


def make_scene(
    seed,
    C=2,
    N=40,
    W=29,
    H=21,
    D=3,
    tile_size=8,
    dtype=torch.float64,
    scale=(0.8, 3.5),
    opacity=(0.05, 0.95),
    margin=3.0,
    region=None,
):
    """Random 2D Gaussians. region=(x0, x1, y0, y1) confines the centres (to leave tiles empty)."""
    g = torch.Generator().manual_seed(seed)
    x0, x1, y0, y1 = region if region is not None else (-margin, W + margin, -margin, H + margin)
    u = torch.rand(C, N, 2, generator=g, dtype=torch.float64)
    means2d = torch.stack([x0 + (x1 - x0) * u[..., 0], y0 + (y1 - y0) * u[..., 1]], dim=-1)
    s = scale[0] + (scale[1] - scale[0]) * torch.rand(C, N, 2, generator=g, dtype=torch.float64)
    theta = math.pi * torch.rand(C, N, generator=g, dtype=torch.float64)
    cos, sin = torch.cos(theta), torch.sin(theta)
    rot = torch.stack([torch.stack([cos, -sin], -1), torch.stack([sin, cos], -1)], -2)  # [C, N, 2, 2]
    cov = rot @ torch.diag_embed(s**2) @ rot.transpose(-1, -2)
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[..., 0, 0], inv[..., 0, 1], inv[..., 1, 1]], dim=-1)
    # radius from the largest eigenvalue of the covariance, like 3-sigma culling
    radii = torch.ceil(3.0 * s.max(dim=-1).values).to(torch.int32)
    depths = torch.rand(C, N, generator=g, dtype=torch.float64)
    colors = torch.rand(C, N, D, generator=g, dtype=torch.float64)
    opacities = opacity[0] + (opacity[1] - opacity[0]) * torch.rand(C, N, generator=g, dtype=torch.float64)
    backgrounds = torch.rand(C, D, generator=g, dtype=torch.float64)
    offsets, flatten_ids = build_isects(means2d, radii, depths, W, H, tile_size)
    return dict(
        means2d=means2d.to(dtype),
        conics=conics.to(dtype),
        colors=colors.to(dtype),
        opacities=opacities.to(dtype),
        backgrounds=backgrounds.to(dtype),
        W=W,
        H=H,
        tile_size=tile_size,
        isect_offsets=offsets,
        flatten_ids=flatten_ids,
    )


def build_isects(means2d, radii, depths, W, H, tile_size):
    """Tile lists sorted by (camera, tile, depth); returns isect_offsets [C, th, tw] and flatten_ids [M] int32."""
    C, N = means2d.shape[:2]
    th, tw = -(-H // tile_size), -(-W // tile_size)
    entries = []  # (camera, tile, depth, flat id)
    for c in range(C):
        for n in range(N):
            r = int(radii[c, n])
            if r <= 0:
                continue
            mx, my = float(means2d[c, n, 0]), float(means2d[c, n, 1])
            tx0, tx1 = max(0, math.floor((mx - r) / tile_size)), min(tw, math.ceil((mx + r) / tile_size))
            ty0, ty1 = max(0, math.floor((my - r) / tile_size)), min(th, math.ceil((my + r) / tile_size))
            for ty in range(ty0, ty1):
                for tx in range(tx0, tx1):
                    entries.append((c, ty * tw + tx, float(depths[c, n]), c * N + n))
    entries.sort()
    counts = torch.zeros(C * th * tw, dtype=torch.int64)
    for c, t, _, _ in entries:
        counts[c * th * tw + t] += 1
    offsets = (torch.cumsum(counts, 0) - counts).to(torch.int32).reshape(C, th, tw)
    flatten_ids = torch.tensor([e[3] for e in entries], dtype=torch.int32)
    return offsets, flatten_ids


def tile_range(offsets, n_isects, c, t):
    flat = offsets.reshape(-1)
    ct = c * offsets[0].numel() + t
    end = int(flat[ct + 1]) if ct + 1 < flat.numel() else n_isects
    return int(flat[ct]), end


# --------------------------------------------------------------------------------------------------------------
# brute-force reference
# --------------------------------------------------------------------------------------------------------------


def reference_rasterize(
    means2d,
    conics,
    colors,
    opacities,
    W,
    H,
    tile_size,
    offsets,
    flatten_ids,
    backgrounds=None,
    stats=None,
    per_pixel=None,
):
    """Spec semantics, literally: every pixel walks its tile's list front to back. Returns colors [C,H,W,D],
    alphas [C,H,W,1]. per_pixel: a list that receives (flat id, offsets leaf [P, 2]) for every tile entry; the
    leaves are zero shifts of the centre seen by each pixel, so their .grad is the per-pixel d loss / d means2d.
    stats: a dict counting early stops and clamped alphas."""
    C, N, D = colors.shape
    th, tw = offsets.shape[1:]
    M = flatten_ids.numel()
    results, pixel_index = [], []
    for c in range(C):
        for ty in range(th):
            for tx in range(tw):
                ys = torch.arange(ty * tile_size, min((ty + 1) * tile_size, H))
                xs = torch.arange(tx * tile_size, min((tx + 1) * tile_size, W))
                yy, xx = torch.meshgrid(ys, xs, indexing="ij")
                yy, xx = yy.reshape(-1), xx.reshape(-1)
                px, py = xx.to(colors.dtype) + 0.5, yy.to(colors.dtype) + 0.5
                P = px.numel()
                T = torch.ones(P, dtype=colors.dtype)
                acc = torch.zeros(P, D, dtype=colors.dtype)
                active = torch.ones(P, dtype=torch.bool)
                start, end = tile_range(offsets, M, c, ty * tw + tx)
                for i in range(start, end):
                    flat = int(flatten_ids[i])
                    cc, g = divmod(flat, N)
                    assert cc == c
                    mean = means2d[c, g].expand(P, 2)
                    if per_pixel is not None:
                        shift = torch.zeros(P, 2, dtype=colors.dtype, requires_grad=True)
                        per_pixel.append((flat, shift))
                        mean = mean + shift
                    a, b, cz = conics[c, g]
                    dx, dy = mean[:, 0] - px, mean[:, 1] - py
                    sigma = 0.5 * (a * dx * dx + cz * dy * dy) + b * dx * dy
                    alpha = torch.clamp(opacities[c, g] * torch.exp(-sigma), max=0.999)
                    use = active & (sigma >= 0) & (alpha >= 1.0 / 255.0)
                    next_T = T * (1.0 - alpha)
                    stop = use & (next_T <= 1e-4)
                    if stats is not None:
                        stats["stops"] = stats.get("stops", 0) + int(stop.sum())
                        stats["clamped"] = stats.get("clamped", 0) + int((use & (alpha >= 0.999)).sum())
                    active = active & ~stop
                    use = use & ~stop
                    acc = acc + torch.where(use[:, None], colors[c, g] * alpha[:, None] * T[:, None], 0.0)
                    T = torch.where(use, next_T, T)
                res = acc + T[:, None] * backgrounds[c] if backgrounds is not None else acc
                results.append(torch.cat([res, (1.0 - T)[:, None]], dim=1))
                pixel_index.append((c * H + yy) * W + xx)
    # one gather puts the tiles' pixels back in image order
    inverse = torch.argsort(torch.cat(pixel_index))
    out = torch.cat(results)[inverse].reshape(C, H, W, D + 1)
    return out[..., :D], out[..., D:]


def run_cpp(scene, requires_grad=False, with_bg=True, absgrad=False, dtype=None):
    dtype = dtype or scene["means2d"].dtype
    names = ["means2d", "conics", "colors", "opacities"] + (["backgrounds"] if with_bg else [])
    leaves = {k: scene[k].detach().to(dtype).clone().requires_grad_(requires_grad) for k in names}
    out = rasterize_to_pixels_cpp(
        leaves["means2d"],
        leaves["conics"],
        leaves["colors"],
        leaves["opacities"],
        scene["W"],
        scene["H"],
        scene["tile_size"],
        scene["isect_offsets"],
        scene["flatten_ids"],
        backgrounds=leaves.get("backgrounds"),
        absgrad=absgrad,
    )
    return out, leaves


def run_ref(scene, with_bg=True, stats=None, per_pixel=None):
    names = ["means2d", "conics", "colors", "opacities"] + (["backgrounds"] if with_bg else [])
    leaves = {k: scene[k].detach().to(torch.float64).clone().requires_grad_(True) for k in names}
    out = reference_rasterize(
        leaves["means2d"],
        leaves["conics"],
        leaves["colors"],
        leaves["opacities"],
        scene["W"],
        scene["H"],
        scene["tile_size"],
        scene["isect_offsets"],
        scene["flatten_ids"],
        leaves.get("backgrounds"),
        stats,
        per_pixel,
    )
    return out, leaves


def psnr(a, b):
    mse = torch.mean((a.double() - b.double()) ** 2).item()
    return float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)


def upstream(out, seed):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(o.shape, generator=g, dtype=torch.float64) for o in out]


def backprop(out, grads):
    loss = sum((o.double() * g).sum() for o, g in zip(out, grads))
    loss.backward()


# --------------------------------------------------------------------------------------------------------------
# tests
# --------------------------------------------------------------------------------------------------------------


def test_backend_reports_available():
    assert cpp_backend_available()
    assert cpp_backend_error() is None


@pytest.mark.parametrize("D", [1, 3, 4, 5])
@pytest.mark.parametrize("with_bg", [False, True])
def test_forward_matches_reference(D, with_bg):
    scene = make_scene(seed=D, D=D)
    assert scene["flatten_ids"].numel() > 100
    (ref_c, ref_a), _ = run_ref(scene, with_bg=with_bg)
    (c64, a64), _ = run_cpp(scene, with_bg=with_bg)
    assert c64.shape == (2, scene["H"], scene["W"], D) and a64.shape == (2, scene["H"], scene["W"], 1)
    assert c64.dtype == torch.float64
    torch.testing.assert_close(c64, ref_c.detach(), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(a64, ref_a.detach(), rtol=1e-12, atol=1e-12)
    assert a64.max() > 0.5  # the scene really covers pixels

    (c32, a32), _ = run_cpp(scene, with_bg=with_bg, dtype=torch.float32)
    assert c32.dtype == torch.float32
    assert psnr(c32, ref_c.detach()) >= 40 and psnr(a32, ref_a.detach()) >= 40
    torch.testing.assert_close(c32.double(), ref_c.detach(), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(a32.double(), ref_a.detach(), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("D", [1, 3, 5])
def test_backward_matches_reference(D):
    scene = make_scene(seed=10 + D, D=D)
    ref_out, ref_leaves = run_ref(scene)
    grads = upstream(ref_out, seed=D)
    backprop(ref_out, grads)
    for dtype, rtol, atol in ((torch.float64, 1e-9, 1e-11), (torch.float32, 2e-3, 2e-4)):
        out, leaves = run_cpp(scene, requires_grad=True, dtype=dtype)
        backprop(out, grads)
        for name, ref_leaf in ref_leaves.items():
            got = leaves[name].grad
            assert got is not None and got.dtype == dtype, name
            scale = ref_leaf.grad.abs().max().item()
            torch.testing.assert_close(
                got.double(),
                ref_leaf.grad,
                rtol=rtol,
                atol=atol * max(scale, 1.0),
                msg=lambda m, n=name, d=dtype: f"{n} ({d}): {m}",
            )


def test_saturated_scene_early_stop_and_clamp():
    # dense, opaque scene: many pixels stop at T <= 1e-4 and alphas clamp at 0.999
    scene = make_scene(seed=3, N=60, scale=(2.0, 5.0), opacity=(0.9, 1.0))
    # opacity 1 at a centre sitting on a pixel centre: op * exp(-0) = 1 is clamped to 0.999
    scene["opacities"][:, ::3] = 1.0
    scene["means2d"][:, ::3] = torch.floor(scene["means2d"][:, ::3]) + 0.5
    stats = {}
    ref_out, ref_leaves = run_ref(scene, stats=stats)
    n_pix = 2 * scene["H"] * scene["W"]
    assert stats["stops"] > 0.2 * n_pix and stats["clamped"] > 10, stats  # both paths really happen
    grads = upstream(ref_out, seed=7)
    backprop(ref_out, grads)
    out, leaves = run_cpp(scene, requires_grad=True)
    for o, r in zip(out, ref_out):
        torch.testing.assert_close(o.detach(), r.detach(), rtol=1e-12, atol=1e-12)
    backprop(out, grads)
    for name, ref_leaf in ref_leaves.items():
        torch.testing.assert_close(leaves[name].grad, ref_leaf.grad, rtol=1e-9, atol=1e-11, msg=name)


def min_threshold_margin(scene):
    """Smallest relative distance, over every (pixel, tile entry), of alpha to 1/255 and 0.999 and of the
    transmittance to 1e-4. Finite differences must not flip those decisions."""
    C, N = scene["opacities"].shape
    m2, con, op = scene["means2d"], scene["conics"], scene["opacities"]
    H, W, ts = scene["H"], scene["W"], scene["tile_size"]
    offsets, ids = scene["isect_offsets"], scene["flatten_ids"]
    tw = offsets.shape[2]
    margin = float("inf")
    for c in range(C):
        for y in range(H):
            for x in range(W):
                start, end = tile_range(offsets, ids.numel(), c, (y // ts) * tw + x // ts)
                T = 1.0
                for i in range(start, end):
                    g = int(ids[i]) % N
                    dx, dy = float(m2[c, g, 0]) - x - 0.5, float(m2[c, g, 1]) - y - 0.5
                    a, b, cz = (float(v) for v in con[c, g])
                    raw = float(op[c, g]) * math.exp(-(0.5 * (a * dx * dx + cz * dy * dy) + b * dx * dy))
                    margin = min(margin, abs(raw * 255 - 1), abs(raw / 0.999 - 1))
                    alpha = min(raw, 0.999)
                    if alpha < 1 / 255:
                        continue
                    margin = min(margin, abs(T * (1 - alpha) / 1e-4 - 1))
                    T *= 1 - alpha
    return margin


@pytest.mark.parametrize("with_bg", [False, True])
def test_gradcheck_tiny_scene(with_bg):
    for seed in range(100, 200):  # first scene whose decisions are safely away from the thresholds
        scene = make_scene(seed=seed, C=2, N=5, W=10, H=9, D=3, tile_size=4, scale=(0.7, 2.0), opacity=(0.2, 0.8))
        if scene["flatten_ids"].numel() >= 10 and min_threshold_margin(scene) > 1e-3:
            break
    else:
        pytest.fail("no safe scene found")
    inputs = [scene[k].clone().requires_grad_(True) for k in ("means2d", "conics", "colors", "opacities")]
    bg = scene["backgrounds"].clone().requires_grad_(True) if with_bg else None

    def fn(means2d, conics, colors, opacities, *maybe_bg):
        return rasterize_to_pixels_cpp(
            means2d,
            conics,
            colors,
            opacities,
            scene["W"],
            scene["H"],
            scene["tile_size"],
            scene["isect_offsets"],
            scene["flatten_ids"],
            backgrounds=maybe_bg[0] if maybe_bg else None,
        )

    args = tuple(inputs) + ((bg,) if with_bg else ())
    assert torch.autograd.gradcheck(fn, args, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_absgrad_is_sum_of_abs_per_pixel_grads():
    scene = make_scene(seed=21, D=3)
    per_pixel = []
    ref_out, ref_leaves = run_ref(scene, per_pixel=per_pixel)
    grads = upstream(ref_out, seed=1)
    backprop(ref_out, grads)
    C, N = scene["opacities"].shape
    expected = torch.zeros(C * N, 2, dtype=torch.float64)
    for flat, shift in per_pixel:
        expected[flat] += shift.grad.abs().sum(dim=0)
    expected = expected.reshape(C, N, 2)
    # sanity of the reference itself: the per-pixel parts sum to the plain gradient
    total = torch.zeros(C * N, 2, dtype=torch.float64)
    for flat, shift in per_pixel:
        total[flat] += shift.grad.sum(dim=0)
    torch.testing.assert_close(total.reshape(C, N, 2), ref_leaves["means2d"].grad, rtol=1e-10, atol=1e-12)
    assert (expected > total.abs().reshape(C, N, 2) + 1e-6).any()  # signs really cancel somewhere

    # the pipeline hands a non-leaf, possibly non-contiguous means2d: absgrad must land on that very object
    base = scene["means2d"].detach().transpose(0, 1).contiguous().requires_grad_(True)  # [N, C, 2]
    means2d = base.transpose(0, 1)  # [C, N, 2] view, non-contiguous, non-leaf
    assert not means2d.is_contiguous()
    means2d.retain_grad()
    out = rasterize_to_pixels_cpp(
        means2d,
        scene["conics"],
        scene["colors"],
        scene["opacities"],
        scene["W"],
        scene["H"],
        scene["tile_size"],
        scene["isect_offsets"],
        scene["flatten_ids"],
        backgrounds=scene["backgrounds"],
        absgrad=True,
    )
    backprop(out, grads)
    assert hasattr(means2d, "absgrad") and means2d.absgrad.shape == means2d.shape
    torch.testing.assert_close(means2d.absgrad, expected, rtol=1e-9, atol=1e-11)
    # and the plain gradient still matches the reference
    torch.testing.assert_close(means2d.grad, ref_leaves["means2d"].grad, rtol=1e-9, atol=1e-11)
    assert (means2d.absgrad >= means2d.grad.abs() - 1e-12).all()

    # a leaf works the same way; absgrad=False sets nothing
    out, leaves = run_cpp(scene, requires_grad=True, absgrad=True)
    backprop(out, grads)
    torch.testing.assert_close(leaves["means2d"].absgrad, expected, rtol=1e-9, atol=1e-11)
    out, leaves = run_cpp(scene, requires_grad=True, absgrad=False)
    backprop(out, grads)
    assert not hasattr(leaves["means2d"], "absgrad")


def test_two_cameras_are_independent():
    scene = make_scene(seed=5, C=2)
    (c2, a2), _ = run_cpp(scene)
    for c in range(2):
        N = scene["means2d"].shape[1]
        sub = dict(scene)
        for k in ("means2d", "conics", "colors", "opacities", "backgrounds"):
            sub[k] = scene[k][c : c + 1]
        start = int(scene["isect_offsets"][c].reshape(-1)[0])
        end = int(scene["isect_offsets"][1].reshape(-1)[0]) if c == 0 else scene["flatten_ids"].numel()
        sub["flatten_ids"] = scene["flatten_ids"][start:end] - c * N
        sub["isect_offsets"] = scene["isect_offsets"][c : c + 1] - start
        (c1, a1), _ = run_cpp(sub)
        torch.testing.assert_close(c1[0], c2[c], rtol=0, atol=0)
        torch.testing.assert_close(a1[0], a2[c], rtol=0, atol=0)


def test_empty_tiles_and_zero_intersections():
    # centres confined to the left part: the right tiles have empty lists
    scene = make_scene(seed=8, W=33, H=17, region=(0, 8, 0, 17), scale=(0.8, 1.5))
    tw = scene["isect_offsets"].shape[2]
    counts = torch.diff(
        torch.cat([scene["isect_offsets"].reshape(-1).long(), torch.tensor([scene["flatten_ids"].numel()])])
    )
    assert (counts.reshape(2, -1, tw)[..., -1] == 0).all()
    ref_out, ref_leaves = run_ref(scene)
    grads = upstream(ref_out, seed=2)
    backprop(ref_out, grads)
    out, leaves = run_cpp(scene, requires_grad=True)
    torch.testing.assert_close(out[0].detach(), ref_out[0].detach(), rtol=1e-12, atol=1e-12)
    backprop(out, grads)
    for name, ref_leaf in ref_leaves.items():
        torch.testing.assert_close(leaves[name].grad, ref_leaf.grad, rtol=1e-9, atol=1e-11, msg=name)

    # no intersections at all: background everywhere, zero alpha, gradient only to the background
    C, N, D = 2, 4, 3
    bg = torch.rand(C, D, dtype=torch.float64, requires_grad=True)
    means2d = torch.rand(C, N, 2, dtype=torch.float64, requires_grad=True)
    conics = torch.ones(C, N, 3, dtype=torch.float64, requires_grad=True)
    colors = torch.rand(C, N, D, dtype=torch.float64, requires_grad=True)
    opac = torch.rand(C, N, dtype=torch.float64, requires_grad=True)
    offsets = torch.zeros(C, 2, 3, dtype=torch.int32)
    ids = torch.zeros(0, dtype=torch.int32)
    img, alpha = rasterize_to_pixels_cpp(
        means2d, conics, colors, opac, 40, 20, 16, offsets, ids, backgrounds=bg, absgrad=True
    )
    assert torch.equal(img, bg[:, None, None].expand(C, 20, 40, D)) and torch.equal(alpha, torch.zeros_like(alpha))
    v = torch.randn_like(img)
    (img * v).sum().backward()
    torch.testing.assert_close(bg.grad, v.sum(dim=(1, 2)))
    for t in (means2d, conics, colors, opac):
        assert torch.equal(t.grad, torch.zeros_like(t))
    assert torch.equal(means2d.absgrad, torch.zeros_like(means2d))

    # no Gaussians at all
    empty = torch.zeros(C, 0, 2, dtype=torch.float32, requires_grad=True)
    img, alpha = rasterize_to_pixels_cpp(
        empty, torch.zeros(C, 0, 3), torch.zeros(C, 0, D), torch.zeros(C, 0), 40, 20, 16, offsets, ids
    )
    assert torch.equal(img, torch.zeros(C, 20, 40, D)) and torch.equal(alpha, torch.zeros(C, 20, 40, 1))
    img.sum().backward()
    assert empty.grad.shape == (C, 0, 2)


def test_noncontiguous_inputs_match_contiguous():
    scene = make_scene(seed=13, D=4)
    (ref_c, ref_a), leaves = run_cpp(scene, requires_grad=True)
    grads = upstream((ref_c, ref_a), seed=4)
    backprop((ref_c, ref_a), grads)

    def strided(t):  # same values, every other element of a doubled buffer
        big = torch.zeros(*t.shape[:-1], 2 * t.shape[-1], dtype=t.dtype)
        big[..., ::2] = t
        leaf = big.requires_grad_(True)
        return leaf, leaf[..., ::2]

    views = {k: strided(scene[k]) for k in ("means2d", "conics", "colors", "backgrounds")}
    opac_leaf = scene["opacities"].t().contiguous().requires_grad_(True)  # [N, C]
    assert not any(v.is_contiguous() for _, v in views.values()) and not opac_leaf.t().is_contiguous()
    ids_big = torch.stack([scene["flatten_ids"], scene["flatten_ids"]], dim=1)
    out = rasterize_to_pixels_cpp(
        views["means2d"][1],
        views["conics"][1],
        views["colors"][1],
        opac_leaf.t(),
        scene["W"],
        scene["H"],
        scene["tile_size"],
        scene["isect_offsets"].transpose(1, 2).contiguous().transpose(1, 2),
        ids_big[:, 0],
        backgrounds=views["backgrounds"][1],
    )
    torch.testing.assert_close(out[0], ref_c, rtol=0, atol=0)
    torch.testing.assert_close(out[1], ref_a, rtol=0, atol=0)
    backprop(out, grads)
    for k, (leaf, _) in views.items():
        torch.testing.assert_close(leaf.grad[..., ::2], leaves[k].grad, rtol=0, atol=0)
        assert torch.equal(leaf.grad[..., 1::2], torch.zeros_like(leaf.grad[..., 1::2]))
    torch.testing.assert_close(opac_leaf.grad.t(), leaves["opacities"].grad, rtol=0, atol=0)


def test_backward_is_deterministic():
    scene = make_scene(seed=17, N=80)
    results = []
    for _ in range(3):
        out, leaves = run_cpp(scene, requires_grad=True, dtype=torch.float32, absgrad=True)
        backprop(out, upstream(out, seed=0))
        results.append([leaves[k].grad for k in leaves] + [leaves["means2d"].absgrad])
    for other in results[1:]:
        for a, b in zip(results[0], other):
            assert torch.equal(a, b)


def test_int64_index_tensors_are_accepted():
    scene = make_scene(seed=19)
    (c32, _), _ = run_cpp(scene)
    scene["isect_offsets"] = scene["isect_offsets"].long()
    scene["flatten_ids"] = scene["flatten_ids"].long()
    (c64, _), _ = run_cpp(scene)
    assert torch.equal(c32, c64)


def _bad_call(**overrides):
    scene = make_scene(seed=0, C=2, N=6, W=12, H=10, tile_size=4)
    kw = dict(
        means2d=scene["means2d"],
        conics=scene["conics"],
        colors=scene["colors"],
        opacities=scene["opacities"],
        image_width=12,
        image_height=10,
        tile_size=4,
        isect_offsets=scene["isect_offsets"],
        flatten_ids=scene["flatten_ids"],
        backgrounds=scene["backgrounds"],
    )
    if isinstance(overrides.get("flatten_ids"), str):
        overrides["flatten_ids"] = scene["flatten_ids"].clone()
        overrides["flatten_ids"][-1] = 12
    kw.update(overrides)
    return rasterize_to_pixels_cpp(**kw)


@pytest.mark.parametrize(
    "overrides, pattern",
    [
        (
            dict(means2d=torch.zeros(2, 6, 3, dtype=torch.float64)),
            r"means2d: expected shape \[C, N, 2\], got \[2, 6, 3\]",
        ),
        (
            dict(conics=torch.zeros(2, 5, 3, dtype=torch.float64)),
            r"conics: expected shape \[2, 6, 3\], got \[2, 5, 3\]",
        ),
        (dict(colors=torch.zeros(2, 6, dtype=torch.float64)), r"colors: expected shape \[C=2, N=6, D>=1\]"),
        (dict(opacities=torch.zeros(2, 6, 1, dtype=torch.float64)), r"opacities: expected shape \[2, 6\]"),
        (dict(backgrounds=torch.zeros(2, 4, dtype=torch.float64)), r"backgrounds: expected shape \[2, 3\]"),
        (dict(colors=torch.zeros(2, 6, 3, dtype=torch.float32)), r"colors: expected dtype torch.float64"),
        (dict(means2d=torch.zeros(2, 6, 2, dtype=torch.int64)), r"means2d: expected dtype float32 or float64"),
        (
            dict(isect_offsets=torch.zeros(2, 3, 4, dtype=torch.int32)),
            r"isect_offsets: expected shape .*\[2, 3, 3\], got \[2, 3, 4\]",
        ),
        (dict(image_width=13), r"isect_offsets: expected shape .*\[2, 3, 4\]"),
        (dict(flatten_ids="out_of_range"), r"flatten_ids: expected values in \[0, C\*N=12\), got range \[0, 12\]"),
        (dict(flatten_ids=torch.tensor([0.0, 1.0])), r"flatten_ids: expected dtype int32"),
        (dict(flatten_ids=torch.zeros(2, 2, dtype=torch.int32)), r"flatten_ids: expected shape \[n_isects\]"),
        (dict(tile_size=0), r"expected positive"),
    ],
)
def test_bad_inputs_raise_value_error(overrides, pattern):
    with pytest.raises(ValueError, match=pattern):
        _bad_call(**overrides)


def run_python(code: str, tmp_path, timeout: float, **env_overrides: str) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter that imports this checkout, with extensions built under ``tmp_path``."""
    env = dict(os.environ, TORCH_EXTENSIONS_DIR=str(tmp_path / "ext"), **env_overrides)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=tmp_path, capture_output=True, text=True, timeout=timeout
    )


def test_missing_compiler_gives_clear_message(tmp_path):
    code = (
        "from gsmsdr_ns.render.pixels_cpp import cpp_backend_available, cpp_backend_error\n"
        "ok = cpp_backend_available()\n"
        "print('AVAILABLE', ok)\n"
        "print('ERROR', cpp_backend_error())\n"
        "print('AGAIN', cpp_backend_available())\n"
    )
    proc = run_python(code, tmp_path, 120, CXX="/nonexistent")
    assert proc.returncode == 0, proc.stderr
    assert "AVAILABLE False" in proc.stdout and "AGAIN False" in proc.stdout
    assert "ERROR no C++ compiler found (set CXX or install g++)" in proc.stdout
    assert "/nonexistent" in proc.stdout
    assert "Traceback" not in proc.stderr


@pytest.mark.slow  # builds an extension (about 30 s)
def test_extensions_build_for_the_cpu_instruction_set_and_the_baseline_build_agrees(tmp_path):
    """Builds are kept per instruction-set level; ``ATEN_CPU_CAPABILITY=default`` (what torch's own kernels then use
    too) builds the x86-64 baseline, whose column blocks of one SSE register give the same blur as the PyTorch
    twin."""
    from gsmsdr_ns._cpp_ext import ISA_FLAGS, cpu_isa
    from gsmsdr_ns.ops.grid_kernels import EXTENSION

    assert cpu_isa() in ISA_FLAGS
    assert EXTENSION.build_directory().name == f"gsmsdr_grid_kernels_cpu_{cpu_isa()}"
    code = (
        "import torch\n"
        "from gsmsdr_ns._cpp_ext import cpu_isa\n"
        "from gsmsdr_ns.ops.grid_kernels import EXTENSION, apply_grid_kernels, grid_size\n"
        "print('ISA', cpu_isa(), EXTENSION.build_directory().name)\n"
        "g = torch.Generator().manual_seed(0)\n"
        "image = torch.rand(1, 3, 21, 37, generator=g, requires_grad=True)\n"
        "grid = torch.rand(1, 81, *grid_size((21, 37), 4), generator=g, requires_grad=True)\n"
        "outs = [apply_grid_kernels(image, grid, 4, backend=b) for b in ('cpp', 'torch')]\n"
        "grads = [torch.autograd.grad(o.square().sum(), (image, grid)) for o in outs]\n"
        "err = max((outs[0] - outs[1]).abs().max().item(),\n"
        "          *[(a - b).abs().max().item() / b.abs().max().item() for a, b in zip(*grads)])\n"
        "print('ERR', err)\n"
    )
    proc = run_python(code, tmp_path, 600, ATEN_CPU_CAPABILITY="default")
    assert proc.returncode == 0, proc.stderr
    assert "ISA generic gsmsdr_grid_kernels_cpu_generic" in proc.stdout, proc.stdout
    assert (tmp_path / "ext" / "gsmsdr_grid_kernels_cpu_generic").is_dir()
    err = float(proc.stdout.split("ERR")[1])
    assert err < 1e-5, proc.stdout


def test_unsorted_offsets_raise_value_error():
    scene = make_scene(seed=0, C=2, N=6, W=12, H=10, tile_size=4)
    n = scene["flatten_ids"].numel()
    for index, value in ((-1, 0), (0, -1), (-1, n + 1)):  # out of order, negative, past the end
        bad = scene["isect_offsets"].clone()
        bad.view(-1)[index] = value
        with pytest.raises(ValueError, match=r"isect_offsets: expected non-decreasing values in \[0, n_isects="):
            _bad_call(isect_offsets=bad)


def test_raw_ops_reject_bad_input_without_crashing(extension):
    scene = make_scene(seed=0, C=2, N=6, W=12, H=10, tile_size=4)
    args = [scene[k] for k in ("means2d", "conics", "colors", "opacities")]
    ids = scene["flatten_ids"].clone()
    ids[0] = 12  # out of [0, C * N)
    with pytest.raises(RuntimeError, match="flatten_ids out of range"):
        extension.rasterize_to_pixels_fwd(*args, None, 12, 10, 4, scene["isect_offsets"], ids, 1)
    with pytest.raises(RuntimeError, match="isect_offsets must be"):
        extension.rasterize_to_pixels_fwd(*args, None, 13, 10, 4, scene["isect_offsets"], scene["flatten_ids"], 1)
    assert load_cpu_extension() is extension  # built once, cached
