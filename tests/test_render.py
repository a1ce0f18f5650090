"""The CPU rasterizer against independent references: brute-force float64 compositing, gsplat's own PyTorch
projection/SH helpers, finite differences (gradcheck), and DefaultStrategy's expectations of `meta`."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from gsmsdr_ns.render import eval_sh_colors, isect_offset_encode, isect_tiles, project_gaussians, rasterization
from gsmsdr_ns.render.projection import covariance_3d

BACKENDS = ["torch", "cpp"]


def look_at(eye, target) -> torch.Tensor:
    """World-to-camera [4, 4] (OpenCV axes) for a camera at `eye` looking at `target`."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, -1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    view = np.eye(4)
    view[:3, :3] = R
    view[:3, 3] = -R @ eye
    return torch.tensor(view)


def random_scene(n, seed, width=48, height=32, dtype=torch.float64, spread=0.6, scale=(0.02, 0.12)):
    """Gaussians in front of one or two cameras, all well inside the frustum."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * spread * torch.tensor([1.5, 1.0, 1.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = scale[0] + (scale[1] - scale[0]) * torch.rand(n, 3, generator=g, dtype=dtype)
    opacities = 0.15 + 0.8 * torch.rand(n, generator=g, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    f = 0.9 * width
    K = torch.tensor([[f, 0, width / 2 + 0.3], [0, f, height / 2 - 0.2], [0, 0, 1]], dtype=dtype)
    viewmats = torch.stack([look_at([0.1, -0.1, -2.5], [0, 0, 0]), look_at([0.8, 0.2, -2.3], [0, 0, 0])])
    return means, quats, scales, opacities, colors, viewmats.to(dtype), torch.stack([K, K]), width, height


def brute_force_render(means, quats, scales, opacities, colors, viewmat, K, width, height, background):
    """Every Gaussian at every pixel, no tiles, float64; projection written independently of the library:
    rotations from scipy, the Jacobian of the perspective map from autograd."""
    means, opacities, colors = means.double(), opacities.double(), colors.double()
    R = torch.tensor(Rotation.from_quat(quats.double().numpy()[:, [1, 2, 3, 0]]).as_matrix())  # scipy is xyzw
    S = torch.diag_embed(scales.double())
    cov3 = R @ S @ S.transpose(1, 2) @ R.transpose(1, 2)
    Rv, tv = viewmat[:3, :3].double(), viewmat[:3, 3].double()
    K = K.double()

    def to_pixels(p_world):
        pc = Rv @ p_world + tv
        uvw = K @ pc
        return uvw[:2] / uvw[2]

    mean2d, cov2d, depth = [], [], []
    for i in range(means.shape[0]):
        J = torch.autograd.functional.jacobian(to_pixels, means[i])  # [2, 3] d pixel / d world
        mean2d.append(to_pixels(means[i]))
        cov2d.append(J @ cov3[i] @ J.T + 0.3 * torch.eye(2, dtype=torch.float64))
        depth.append((Rv @ means[i] + tv)[2])
    mean2d, cov2d, depth = torch.stack(mean2d), torch.stack(cov2d), torch.stack(depth)
    inv = torch.linalg.inv(cov2d)
    order = torch.argsort(depth)
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij"
    )
    pix = torch.stack([xs + 0.5, ys + 0.5], -1).reshape(-1, 2)
    out = torch.zeros(pix.shape[0], 3, dtype=torch.float64)
    T = torch.ones(pix.shape[0], dtype=torch.float64)
    done = torch.zeros(pix.shape[0], dtype=torch.bool)
    for i in order.tolist():
        d = mean2d[i] - pix
        sigma = 0.5 * torch.einsum("pi,ij,pj->p", d, inv[i], d)
        alpha = torch.clamp(opacities[i] * torch.exp(-sigma), max=0.999)
        use = (alpha >= 1 / 255) & ~done
        next_T = T * (1 - alpha)
        stop = use & (next_T <= 1e-4)
        done |= stop
        use &= ~stop
        out[use] += (alpha * T)[use, None] * colors[i]
        T = torch.where(use, next_T, T)
    out = out + T[:, None] * background
    return out.reshape(height, width, 3), (1 - T).reshape(height, width, 1)


def psnr(a, b):
    mse = torch.mean((a.double() - b.double()) ** 2).item()
    return float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_brute_force_reference(backend, seed):
    means, quats, scales, opac, colors, viewmats, Ks, W, H = random_scene(60, seed, dtype=torch.float32)
    bg = torch.tensor([[0.2, 0.5, 0.9], [1.0, 1.0, 1.0]])
    img, alpha, meta = rasterization(
        means, quats, scales, opac, colors, viewmats, Ks, W, H, packed=False, backgrounds=bg, cpu_backend=backend
    )
    assert meta["backend"] == backend
    assert img.shape == (2, H, W, 3) and alpha.shape == (2, H, W, 1)
    for c in range(2):
        ref_img, ref_alpha = brute_force_render(means, quats, scales, opac, colors, viewmats[c], Ks[c], W, H, bg[c])
        assert psnr(img[c], ref_img) >= 40.0
        assert psnr(alpha[c], ref_alpha) >= 40.0
        # most pixels are not affected by tile culling at all: those must agree to float32 precision
        close = (img[c].double() - ref_img).abs().amax(-1) < 1e-4
        assert close.float().mean() > 0.9


@pytest.mark.parametrize("backend", BACKENDS)
def test_backends_agree_on_values_and_gradients(backend):
    torch.manual_seed(3)
    scene = random_scene(200, 7, width=70, height=50, dtype=torch.float32)
    means, quats, scales, opac, colors, viewmats, Ks, W, H = scene
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
    upstream = torch.randn(2, H, W, 4)

    def run(which):
        params = [t.detach().clone().requires_grad_(True) for t in leaves]
        img, alpha, meta = rasterization(
            *params, viewmats.float(), Ks.float(), W, H, packed=False, render_mode="RGB+ED", cpu_backend=which
        )
        out = torch.cat([img[..., :3], alpha], -1)
        grads = torch.autograd.grad((out * upstream).sum(), params)
        return out.detach(), img[..., 3].detach(), grads

    ref_out, ref_depth, ref_grads = run("torch")
    out, depth, grads = run(backend)
    torch.testing.assert_close(out, ref_out, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(depth, ref_depth, atol=1e-4, rtol=1e-4)
    for g, r in zip(grads, ref_grads):
        torch.testing.assert_close(g, r, atol=1e-4, rtol=1e-3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradcheck_float64(backend):
    scene = random_scene(5, 11, width=12, height=10, scale=(0.08, 0.15))
    means, quats, scales, opac, colors, viewmats, Ks, W, H = scene
    opac = torch.full_like(opac, 0.6)  # clear of the 1/255 skip and the 0.999 clamp

    def render(m, q, s, o, c):
        img, alpha, _ = rasterization(
            m,
            q,
            s,
            o,
            c,
            viewmats[:1],
            Ks[:1],
            W,
            H,
            packed=False,
            cpu_backend=backend,
            backgrounds=torch.full((1, 3), 0.3, dtype=torch.float64),
        )
        return img, alpha

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors))
    # thresholds (1/255, 3-sigma tiles) make the function piecewise; a small step keeps us on one piece
    assert torch.autograd.gradcheck(render, inputs, eps=1e-7, atol=1e-5, rtol=1e-3)


def test_projection_matches_gsplat_torch_reference():
    from gsplat.cuda._torch_impl import _fully_fused_projection

    means, quats, scales, *_, viewmats, Ks, W, H = random_scene(300, 5, dtype=torch.float32, spread=4.0)
    covars = covariance_3d(quats, scales)
    ours = project_gaussians(means, covars, viewmats, Ks, W, H, calc_compensations=True)
    radii, means2d, depths, conics, comp = _fully_fused_projection(
        means, covars, viewmats, Ks, W, H, calc_compensations=True
    )
    assert torch.equal(ours.radii, radii.to(torch.int32))
    keep = radii > 0
    assert keep.any() and (~keep).any()  # the scene has both visible and culled Gaussians
    torch.testing.assert_close(ours.means2d[keep], means2d[keep])
    torch.testing.assert_close(ours.conics[keep], conics[keep], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(ours.depths[keep], depths[keep])
    torch.testing.assert_close(ours.compensations[keep], comp[keep])


def test_sh_matches_gsplat_torch_reference():
    from gsplat.cuda._torch_impl import _spherical_harmonics

    g = torch.Generator().manual_seed(0)
    dirs = torch.randn(500, 3, generator=g)
    coeffs = torch.randn(500, 16, 3, generator=g)
    for degree in range(4):
        torch.testing.assert_close(eval_sh_colors(degree, dirs, coeffs), _spherical_harmonics(degree, dirs, coeffs))


def test_tile_lists_match_brute_force_overlap():
    means, quats, scales, *_, viewmats, Ks, W, H = random_scene(150, 9, width=80, height=56, dtype=torch.float32)
    proj = project_gaussians(means, covariance_3d(quats, scales), viewmats, Ks, W, H)
    ts, tw, th = 16, 5, 4
    counts, isect_ids, flatten_ids = isect_tiles(proj.means2d, proj.radii, proj.depths, ts, tw, th)
    offsets = isect_offset_encode(isect_ids, 2, tw, th).reshape(-1).tolist() + [len(flatten_ids)]
    N = means.shape[0]
    for cam in range(2):
        for tile in range(tw * th):
            ty, tx = divmod(tile, tw)
            k = cam * tw * th + tile
            got = flatten_ids[offsets[k] : offsets[k + 1]].long()
            expect = []
            for n in range(N):
                r = int(proj.radii[cam, n])
                if r == 0:
                    continue
                x, y = proj.means2d[cam, n].tolist()
                if (math.floor((x - r) / ts) <= tx < math.ceil((x + r) / ts)) and (
                    math.floor((y - r) / ts) <= ty < math.ceil((y + r) / ts)
                ):
                    expect.append(cam * N + n)
            assert sorted(got.tolist()) == sorted(expect)
            d = proj.depths.reshape(-1)[got]
            assert torch.all(d[1:] >= d[:-1])  # front to back
    assert int(counts.sum()) == len(flatten_ids)


@pytest.mark.parametrize("backend", BACKENDS)
def test_meta_drives_default_strategy_on_cpu(backend):
    """gsplat's DefaultStrategy reads means2d.grad / .absgrad, radii, width, height and n_cameras."""
    from gsplat.strategy import DefaultStrategy

    means, quats, scales, opac, colors, viewmats, Ks, W, H = random_scene(120, 4, dtype=torch.float32)
    params = torch.nn.ParameterDict({
        "means": means, "quats": quats, "scales": torch.log(scales), "opacities": torch.logit(opac),
        "colors": colors,
    })  # fmt: skip
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    strategy = DefaultStrategy(refine_start_iter=0, refine_every=1, grow_grad2d=0.0, absgrad=True, verbose=False)
    state = strategy.initialize_state()
    img, alpha, info = rasterization(
        params["means"],
        params["quats"],
        torch.exp(params["scales"]),
        torch.sigmoid(params["opacities"]),
        params["colors"],
        viewmats[:1].float(),
        Ks[:1].float(),
        W,
        H,
        packed=False,
        absgrad=True,
        cpu_backend=backend,
    )
    strategy.step_pre_backward(params, optimizers, state, 1, info)
    (img - 0.5).square().sum().backward()
    assert info["means2d"].grad is not None
    absgrad = info["means2d"].absgrad
    visible = info["radii"] > 0
    assert torch.all(absgrad >= info["means2d"].grad.abs() - 1e-6)
    assert (absgrad[visible] > 0).any() and torch.all(absgrad[~visible] == 0)
    strategy.step_post_backward(params, optimizers, state, 1, info, packed=False)
    assert params["means"].shape[0] > 120  # grow_grad2d=0 duplicates or splits every visible Gaussian
    assert torch.isfinite(params["means"]).all()


def test_cpu_rejects_bad_inputs():
    means, quats, scales, opac, colors, viewmats, Ks, W, H = random_scene(10, 0, dtype=torch.float32)
    with pytest.raises(ValueError, match="means must have shape"):
        rasterization(means[:, :2], quats, scales, opac, colors, viewmats, Ks, W, H, packed=False)
    with pytest.raises(ValueError, match="packed=True with absgrad=True"):
        rasterization(means, quats, scales, opac, colors, viewmats, Ks, W, H, packed=True, absgrad=True)
    with pytest.raises(ValueError, match="sh_degree=2 needs 9"):
        rasterization(means, quats, scales, opac, torch.zeros(10, 4, 3), viewmats, Ks, W, H, sh_degree=2, packed=False)


def test_sh_colors_and_render_modes():
    means, quats, scales, opac, _, viewmats, Ks, W, H = random_scene(40, 1, dtype=torch.float32)
    sh = torch.zeros(40, 16, 3)
    sh[:, 0] = 0.3
    img, alpha, meta = rasterization(
        means,
        quats,
        scales,
        opac,
        sh,
        viewmats,
        Ks,
        W,
        H,
        sh_degree=3,
        packed=False,
        render_mode="RGB+D",
        cpu_backend="torch",
    )
    # a constant DC term gives a constant colour 0.3 * C0 + 0.5 wherever the image is opaque
    expected = 0.3 * 0.28209479177387814 + 0.5
    rgb = img[..., :3] / alpha.clamp_min(1e-6)
    solid = alpha[..., 0] > 0.5
    torch.testing.assert_close(rgb[solid], torch.full_like(rgb[solid], expected), atol=1e-4, rtol=0)
    d, _, _ = rasterization(
        means,
        quats,
        scales,
        opac,
        sh,
        viewmats,
        Ks,
        W,
        H,
        sh_degree=3,
        packed=False,
        render_mode="ED",
        cpu_backend="torch",
    )
    depths = meta["depths"][meta["radii"] > 0]
    ed = d[..., 0][solid]
    assert ed.min() >= depths.min() - 1e-4 and ed.max() <= depths.max() + 1e-4
