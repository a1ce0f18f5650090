"""Tests of gsmsdr_ns.degrade: pixel-level checks of every kernel, the degraded-scene layout and its metadata,
COLMAP and transforms.json inputs, bad inputs, atomic writes, the CLIs and the synth variants.

Scenes are tiny (10 views, 64x48) and degraded in-process (workers=1) except in the one worker-pool test.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from conftest import run_cli
from PIL import Image

from gsmsdr_ns.degrade import (
    DefocusConfig,
    DegradeConfig,
    LayeredDefocus,
    MotionConfig,
    NoiseConfig,
    PSFBlur,
    RotationalShakeBlur,
    add_noise,
    apply_defocus,
    apply_mixres,
    calibrated_shake,
    convolve_psf,
    defocus_radius,
    degrade_scene,
    disk_blur,
    disk_kernel,
    homography_blur,
    load_preset,
    mixres_factors,
    motion_kernel_from_trajectory,
    path_extent,
    pixel_paths,
    plane_homography,
    rotational_shake_blur,
)
from gsmsdr_ns.degrade import pipeline as pipe_mod
from gsmsdr_ns.degrade.cli import entrypoint as degrade_entrypoint
from gsmsdr_ns.degrade.cli import parse as degrade_parse
from gsmsdr_ns.degrade.synth_cli import parse as synth_parse
from gsmsdr_ns.degrade.trajectory import rotvec_to_matrix
from gsmsdr_ns.degrade.variants import BUILTIN_PRESETS
from gsmsdr_ns.io.colmap import read_colmap
from gsmsdr_ns.io.errors import InputError

REPO = Path(__file__).resolve().parents[1]

# Pixel values below are absolute (px_reference_width=0): blur of a few pixels on 64x48 images.
MOTION = MotionConfig(min_blur_px=3.0, max_blur_px=6.0, keyframe_spacing_px=3.0)
DEFOCUS = DefocusConfig(min_coc_px=3.0, max_coc_px=5.0)


def cfg(*effects: str, **kw) -> DegradeConfig:
    base = dict(effects=effects, px_reference_width=0, workers=1, motion=MOTION, defocus=DEFOCUS)
    return DegradeConfig(**{**base, **kw})


def load_png(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255.0


def delta_image(h: int, w: int, y: int, x: int) -> torch.Tensor:
    img = torch.zeros(1, 1, h, w, dtype=torch.float64)
    img[0, 0, y, x] = 1.0
    return img


def leftovers(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if ".partial-" in p.name or ".sharp-" in p.name or ".old-" in p.name)


# ------------------------------------------------------------------------------------------------ PSF kernels


def test_disk_kernel_is_normalised_symmetric_and_sized():
    assert disk_kernel(0.0).shape == (1, 1) and float(disk_kernel(0.4)[0, 0]) == 1.0
    for r in (1.0, 2.5, 6.0):
        k = disk_kernel(r, dtype=torch.float64)
        assert k.shape[-1] == 2 * (int(np.ceil(r + 0.5)) - 1) + 1
        torch.testing.assert_close(k.sum(), torch.tensor(1.0, dtype=torch.float64))
        torch.testing.assert_close(k, k.flip(0))
        torch.testing.assert_close(k, k.T)
        c = k.shape[-1] // 2
        yy, xx = torch.meshgrid(torch.arange(k.shape[0]) - c, torch.arange(k.shape[1]) - c, indexing="ij")
        assert k[(xx.abs() - 0.5) ** 2 + (yy.abs() - 0.5) ** 2 > r * r].sum() == 0  # nothing beyond the disk
    with pytest.raises(ValueError, match="radius"):
        disk_kernel(-1.0)


def test_motion_kernel_integrates_to_one_and_lies_on_a_straight_path():
    k = motion_kernel_from_trajectory(np.array([[-5.0, 0.0], [5.0, 0.0]]), dtype=torch.float64)
    c = k.shape[-1] // 2
    torch.testing.assert_close(k.sum(), torch.tensor(1.0, dtype=torch.float64))
    nz = torch.nonzero(k > 1e-12)
    assert set(nz[:, 0].tolist()) == {c}  # only the centre row
    assert nz[:, 1].min() == c - 5 and nz[:, 1].max() == c + 5
    row = k[c, c - 4 : c + 5]
    assert float(row.max() / row.min()) < 1.3  # constant speed -> near-uniform energy along the path


def test_motion_kernel_energy_follows_a_bent_trajectory():
    traj = np.array([[-4.0, -3.0], [0.0, -3.0], [0.0, 2.0], [3.0, 4.0]])  # L-shape then a diagonal
    k = motion_kernel_from_trajectory(traj, kernel_size=15, dtype=torch.float64)
    assert k.shape == (15, 15)
    torch.testing.assert_close(k.sum(), torch.tensor(1.0, dtype=torch.float64))
    c = 7
    pts = torch.nonzero(k > 1e-9).double() - c  # (dy, dx)
    # every pixel with energy is within a bilinear footprint of the polyline
    seg_d = []
    for a, b in zip(traj[:-1], traj[1:]):
        a, b = torch.tensor(a[::-1].copy()), torch.tensor(b[::-1].copy())
        s = ((pts - a) @ (b - a) / ((b - a) @ (b - a))).clamp(0, 1)
        seg_d.append((pts - (a + s[:, None] * (b - a))).norm(dim=1))
    assert float(torch.stack(seg_d).min(0).values.max()) <= np.sqrt(2)  # bilinear splatting: 2x2 footprint
    # the centroid is the time average of the path (each segment has equal time, constant speed within it)
    mids = 0.5 * (traj[:-1] + traj[1:])
    dy, dx = torch.meshgrid(torch.arange(15.0) - c, torch.arange(15.0) - c, indexing="ij")
    cx, cy = float((k * dx.double()).sum()), float((k * dy.double()).sum())
    np.testing.assert_allclose([cx, cy], mids.mean(0), atol=1e-6)


def test_psf_blur_of_a_point_light_lands_on_the_trajectory_pixels():
    traj = np.array([[-6.0, 0.0], [6.0, 0.0]])
    kernel = motion_kernel_from_trajectory(traj, dtype=torch.float64)
    img = delta_image(32, 40, 16, 20)
    out = convolve_psf(img, kernel)[0, 0]
    torch.testing.assert_close(out.sum(), torch.tensor(1.0, dtype=torch.float64))
    ys, xs = torch.nonzero(out > 1e-12).T
    assert set(ys.tolist()) == {16} and xs.min() == 14 and xs.max() == 26
    # a one-sided path shows the direction: convolution moves energy to p + offset, not p - offset
    one_sided = motion_kernel_from_trajectory(np.array([[0.0, 0.0], [0.0, 5.0]]), dtype=torch.float64)
    ys, xs = torch.nonzero(convolve_psf(img, one_sided)[0, 0] > 1e-12).T
    assert ys.min() == 16 and ys.max() == 21 and set(xs.tolist()) == {20}


def test_plane_homography_matches_projection_of_plane_points():
    rng = np.random.default_rng(0)
    K = np.array([[80.0, 0.0, 32.0], [0.0, 80.0, 24.0], [0.0, 0.0, 1.0]])
    R = rotvec_to_matrix(rng.normal(size=3) * 0.05)
    t = torch.as_tensor(rng.normal(size=3) * 0.1)
    d = 3.0
    uv = rng.uniform([0, 0], [64, 48], size=(20, 2))
    X = np.c_[(uv - K[:2, 2]) / K[0, 0], np.ones(20)] * d  # points on the plane z = d of the source camera
    Xd = X @ R.numpy().T + t.numpy()
    proj = Xd @ K.T
    expected = proj[:, :2] / proj[:, 2:]
    H = plane_homography(K, K, R, t, d).numpy()
    got = np.c_[uv, np.ones(20)] @ H.T
    np.testing.assert_allclose(got[:, :2] / got[:, 2:], expected, atol=1e-9)


def test_rotational_shake_spreads_a_point_light_along_the_predicted_arc():
    W, H = 64, 48
    K = np.array([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])
    angles = np.linspace(0.0, 0.25, 26)  # roll about the optical axis: points move on circles around (cx, cy)
    R = rotvec_to_matrix(np.stack([np.zeros_like(angles), np.zeros_like(angles), angles], -1))
    py, px = 10, 50  # pixel centre (50.5, 10.5) in COLMAP coordinates
    out = rotational_shake_blur(delta_image(H, W, py, px), K, R)[0, 0]
    assert abs(float(out.sum()) - 1.0) < 0.02
    assert float(out.max()) < 0.25  # spread out, not a point any more
    p = np.array([px + 0.5, py + 0.5, 1.0])
    pred = (plane_homography(K, K, R).numpy() @ p)[:, :2]  # predicted image positions over the exposure
    ys, xs = torch.nonzero(out > 1e-4).T.numpy()
    centres = np.c_[xs + 0.5, ys + 0.5]
    dist = np.linalg.norm(centres[:, None] - pred[None], axis=-1).min(1)
    assert dist.max() < 1.5  # energy only on pixels along the arc
    r0 = np.linalg.norm(p[:2] - K[:2, 2])
    w = out.numpy()[ys, xs]
    radius = (np.linalg.norm(centres - K[:2, 2], axis=1) * w).sum() / w.sum()
    assert abs(radius - r0) < 0.6  # an arc around the principal point, not a chord
    swept = np.arctan2(pred[-1, 1] - 24, pred[-1, 0] - 32) - np.arctan2(pred[0, 1] - 24, pred[0, 0] - 32)
    assert abs(abs(swept) - 0.25) < 1e-6
    # every pixel on the arc got energy: the path is continuous, not a few ghost copies
    seen = {(int(round(x - 0.5)), int(round(y - 0.5))) for x, y in pred}
    assert all(out[y, x] > 0 for x, y in seen)


def test_rotational_shake_pan_shifts_by_focal_times_tan():
    K = np.array([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])
    theta = 8.0 / 60.0
    # camera t rotated about its y axis: X_t = R X_ref moves the image point at the centre to +x by f tan(theta)
    R = rotvec_to_matrix(np.array([[0.0, theta, 0.0]]))
    out = rotational_shake_blur(delta_image(48, 64, 24, 32), K, R)[0, 0]
    ys, xs = torch.nonzero(out > 1e-3).T
    x_mean = float((out[ys, xs] * (xs.double() + 0.5)).sum() / out[ys, xs].sum())
    assert abs(x_mean - (32.5 + 60 * np.tan(theta))) < 0.1


def test_calibrated_shake_hits_the_requested_extent_and_passes_through_the_reference():
    K = np.array([[55.0, 0.0, 32.0], [0.0, 55.0, 24.0], [0.0, 0.0, 1.0]])
    depth = np.full((48, 64), 4.0)
    for trans in (0.0, 0.4):
        traj, ext = calibrated_shake(np.random.default_rng(1), K, 64, 48, 7.0, 21, 0.5, 0.3, trans, depth)
        assert abs(ext - 7.0) < 0.05
        assert np.abs(traj.rotvecs[10]).max() < 1e-12 and np.abs(traj.translations[10]).max() < 1e-12  # t = 0.5
        assert (np.abs(traj.translations).max() > 0) == (trans > 0)
        paths = pixel_paths(K, traj, np.array([[10.0, 10.0]]), np.array([0.25]))
        assert paths.shape == (21, 1, 2) and float(path_extent(paths).max()) <= ext + 1e-9


def test_trajectory_subframe_interpolation_matches_rendering_every_sample(tiny_scene):
    from gsmsdr_ns.degrade.effects import ViewContext, motion_effect
    from gsmsdr_ns.degrade.source import load_depth, load_source

    src = load_source(tiny_scene, check_images=False)
    ctx = ViewContext(src.Ks[3], 64, 48, np.linalg.inv(src.w2cs[3]), load_depth(src.depth_paths[3], (64, 48)),
                      src.synth_config, 1.0)  # fmt: skip
    outs = []
    for spacing in (0.5, 6.0):  # a re-render per exposure sample vs one sub-frame warped by plane homographies
        mc = MotionConfig(
            min_blur_px=6.0, max_blur_px=6.0, keyframe_spacing_px=spacing, render_supersample=3
        )  # anti-aliased sub-frames: compare geometry, not sampling noise
        img, rec = motion_effect(torch.zeros(1, 3, 48, 64), ctx, mc, np.random.default_rng(7))
        outs.append((img.clamp(0, 1), rec))
    (exact, r_exact), (fast, r_fast) = outs
    assert r_exact["keyframes"] == r_exact["samples"] == 7 and r_fast["keyframes"] == 1
    assert r_exact["rotvecs"] == r_fast["rotvecs"]  # same shake, only the rendering differs
    assert float((exact - fast).abs().mean()) < 0.01  # measured 0.007, mostly bilinear resampling of the warps


# ----------------------------------------------------------------------------------------------------- defocus


def test_defocus_radius_is_zero_on_the_focal_plane_and_grows_away_from_it():
    d = torch.tensor([0.5, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0, float("inf")], dtype=torch.float64)
    r = defocus_radius(d, focal_px=100.0, aperture=0.1, focus_distance=2.0)
    assert float(r[3]) == 0.0
    assert torch.all(r[:3].diff() < 0) and torch.all(r[3:].diff() > 0)  # decreasing towards, increasing beyond
    assert abs(float(r[4]) - 0.5 * 100 * 0.1 * abs(1 / 2.0 - 1 / 3.0)) < 1e-12
    assert abs(float(r[-1]) - 0.5 * 100 * 0.1 / 2.0) < 1e-12  # the limit at infinity
    s = defocus_radius(d, 100.0, 0.1, 2.0, signed=True)
    assert torch.all(s[:3] < 0) and torch.all(s[4:] > 0) and torch.allclose(s.abs(), r)
    with pytest.raises(ValueError, match="depth must be > 0"):
        defocus_radius(torch.tensor([1.0, 0.0]), 100.0, 0.1, 2.0)


def test_apply_defocus_constant_radius_equals_disk_blur_and_zero_is_identity():
    img = torch.rand(1, 3, 40, 48, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    zero = torch.zeros(1, 1, 40, 48, dtype=torch.float64)
    torch.testing.assert_close(apply_defocus(img, zero), img)
    out = apply_defocus(img, zero + 2.0)
    ref = disk_blur(img, 2.0)
    torch.testing.assert_close(out[..., 3:-3, 3:-3], ref[..., 3:-3, 3:-3])  # borders renormalise instead of reflect


def _two_layer_scene(fg_radius: float, bg_radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    img = torch.zeros(1, 3, 40, 40, dtype=torch.float64)
    img[0, 2] = 1.0  # blue background
    img[0, :, 14:26, 14:26] = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)[:, None, None]  # red square
    r = torch.full((1, 1, 40, 40), bg_radius, dtype=torch.float64)
    r[..., 14:26, 14:26] = fg_radius
    return img, r


def test_apply_defocus_in_focus_foreground_does_not_bleed_into_blurred_background():
    img, r = _two_layer_scene(fg_radius=0.0, bg_radius=3.0)  # background behind the focal plane
    out = apply_defocus(img, r)[0]
    torch.testing.assert_close(out[:, 14:26, 14:26], img[0, :, 14:26, 14:26])  # sharp square stays sharp
    ring = torch.ones(40, 40, dtype=torch.bool)
    ring[14:26, 14:26] = False
    torch.testing.assert_close(out[:, ring], img[0][:, ring])  # no red halo around it
    # a naive per-pixel (gather) blur would mix red into the background next to the square:
    naive = disk_blur(img, 3.0)[0]
    assert float(naive[0, 20, 12]) > 0.1


def test_apply_defocus_blurred_foreground_spreads_over_the_background():
    img, r = _two_layer_scene(fg_radius=-3.0, bg_radius=0.0)  # foreground in front of the focal plane
    out = apply_defocus(img, r)[0]
    assert float(out[0, 20, 12]) > 0.1 and float(out[0, 20, 27]) > 0.1  # red spills 2 px beyond the edges
    torch.testing.assert_close(out[:, 2, 2], img[0, :, 2, 2])  # far from the square: untouched background
    torch.testing.assert_close(out.sum(0), torch.ones(40, 40, dtype=torch.float64))  # a convex mix of red and blue


# --------------------------------------------------------------------------------------- mixed res and noise


def test_mixres_factors_split_equally_and_follow_the_seed():
    f = mixres_factors(40, seed=0)
    assert sorted(np.unique(f).tolist()) == [1, 2, 3, 4] and np.all(np.bincount(f)[1:] == 10)
    for n in (1, 7, 10, 13):
        counts = np.bincount(mixres_factors(n, seed=5), minlength=5)[1:]
        assert counts.sum() == n and counts.max() - counts.min() <= 1
    np.testing.assert_array_equal(mixres_factors(40, 3), mixres_factors(40, 3))
    assert any(not np.array_equal(mixres_factors(40, 3), mixres_factors(40, s)) for s in range(4, 8))
    assert len(mixres_factors(0, 0)) == 0


def test_apply_mixres_removes_detail_finer_than_the_factor():
    checker = ((torch.arange(48)[:, None] + torch.arange(64)[None]) % 2).double().expand(1, 3, 48, 64)
    torch.testing.assert_close(apply_mixres(checker, 1), checker)
    out = apply_mixres(checker, 4)
    assert out.shape == checker.shape
    assert float((out[..., 4:-4, 4:-4] - 0.5).abs().max()) < 0.1  # the 1-px checker averages to grey
    flat = torch.full((1, 3, 48, 64), 0.3, dtype=torch.float64)
    torch.testing.assert_close(apply_mixres(flat, 3), flat)
    smooth = torch.linspace(0, 1, 64, dtype=torch.float64).expand(1, 3, 48, 64)
    assert float((apply_mixres(smooth, 2) - smooth)[..., 4:-4].abs().max()) < 0.02  # smooth content survives


def test_noise_statistics():
    g = lambda s: torch.Generator().manual_seed(s)  # noqa: E731
    x = torch.full((1, 3, 256, 256), 0.5, dtype=torch.float64)
    y = add_noise(x, 0.05, generator=g(0))
    assert abs(float(y.mean()) - 0.5) < 0.002 and abs(float(y.std()) - 0.05) < 0.002
    torch.testing.assert_close(add_noise(x, 0.05, generator=g(0)), y)
    assert not torch.equal(add_noise(x, 0.05, generator=g(1)), y)
    for level in (0.25, 0.64):  # Poisson-Gaussian: variance gain * x + sigma^2
        y = add_noise(torch.full_like(x, level), 0.02, gain=0.01, generator=g(2))
        assert abs(float(y.var()) - (0.01 * level + 0.02**2)) < 0.05 * (0.01 * level + 0.02**2)
    clipped = add_noise(torch.zeros(1, 1, 64, 64), 0.1, generator=g(3))
    assert float(clipped.min()) == 0.0 and float(clipped.max()) <= 1.0
    torch.testing.assert_close(add_noise(x, 0.0), x)


def test_module_twins_equal_the_functions():
    img = torch.rand(1, 3, 24, 32, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    kernel = motion_kernel_from_trajectory(np.array([[-2.0, 1.0], [3.0, -1.0]]), dtype=torch.float64)
    torch.testing.assert_close(PSFBlur(kernel)(img), convolve_psf(img, kernel))
    K = torch.tensor([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]], dtype=torch.float64)
    R = rotvec_to_matrix(np.array([[0.0, 0.0, 0.0], [0.01, 0.02, 0.03]]))
    torch.testing.assert_close(RotationalShakeBlur(K, R)(img), rotational_shake_blur(img, K, R))
    depth = torch.linspace(1.0, 6.0, 32, dtype=torch.float64).expand(1, 1, 24, 32)
    mod = LayeredDefocus(30.0, 0.2, 2.0)(img, depth)
    fn = apply_defocus(img, defocus_radius(depth, 30.0, 0.2, 2.0, signed=True))
    torch.testing.assert_close(mod, fn)


def test_kernels_check_shapes_and_are_differentiable():
    with pytest.raises(ValueError, match=r"\[B, C, H, W\]"):
        convolve_psf(torch.zeros(3, 8, 8), disk_kernel(1.0))
    with pytest.raises(ValueError, match=r"\[T, 3, 3\]"):
        homography_blur(torch.zeros(1, 1, 8, 8), torch.eye(3))
    with pytest.raises(ValueError, match="signed_radius"):
        apply_defocus(torch.zeros(1, 3, 8, 8), torch.zeros(1, 8, 8))
    with pytest.raises(ValueError, match=r"\[T, 2\]"):
        motion_kernel_from_trajectory(np.zeros((3, 3)))
    img = torch.rand(1, 1, 8, 9, dtype=torch.float64, requires_grad=True)
    K = torch.tensor([[9.0, 0, 4.5], [0, 9.0, 4.0], [0, 0, 1]], dtype=torch.float64)
    R = rotvec_to_matrix(np.array([[0.0, 0.03, 0.0], [0.02, 0.0, 0.05]]))
    assert torch.autograd.gradcheck(lambda x: rotational_shake_blur(x, K, R), (img,))
    assert torch.autograd.gradcheck(lambda x: convolve_psf(x, disk_kernel(1.5, dtype=torch.float64)), (img,))


# ----------------------------------------------------------------------------------------- degraded scenes


@pytest.fixture(scope="module")
def motion_scene(tiny_scene, tmp_path_factory) -> Path:
    """tiny_scene degraded with motion (re-rendered trajectory) + Gaussian noise."""
    out = tmp_path_factory.mktemp("degraded") / "motion"
    return degrade_scene(tiny_scene, out, cfg("motion", noise=NoiseConfig(sigma=0.01)))


def test_degraded_layout_and_metadata(tiny_scene, motion_scene):
    names = sorted(p.name for p in (tiny_scene / "images").iterdir())
    assert sorted(p.name for p in (motion_scene / "images").iterdir()) == names
    assert sorted(p.name for p in (motion_scene / "images_test").iterdir()) == names
    assert (motion_scene / "hold=8").is_file() and (motion_scene / "hold=8").stat().st_size == 0
    assert sorted(p.name for p in (motion_scene / "depth").iterdir()) == [Path(n).stem + ".npy" for n in names]
    assert (motion_scene / "scene.json").is_file()
    doc = json.loads((motion_scene / "degradation.json").read_text())
    assert doc["version"] == 1 and doc["generator"].startswith("gsmsdr-degrade ")
    assert doc["source"] == str(tiny_scene) and doc["seed"] == 0 and doc["hold"] == 8 and doc["preset"] is None
    assert doc["effects"] == ["motion", "noise"] and list(doc["images"]) == names
    assert doc["border_crop_px"] == 0  # a generated scene re-renders its margins: nothing to crop
    for i, name in enumerate(names):
        rec = doc["images"][name]
        sharp = load_png(tiny_scene / "images" / name)
        np.testing.assert_array_equal(load_png(motion_scene / "images_test" / name), sharp)
        img = load_png(motion_scene / "images" / name)
        if i % 8 == 0:
            assert rec == {"split": "test", "degraded": False, "effects": {}}
            np.testing.assert_array_equal(img, sharp)
        else:
            assert rec["split"] == "train" and rec["degraded"] is True
            assert set(rec["effects"]) == {"motion", "noise"}
            m = rec["effects"]["motion"]
            assert m["model"] == "trajectory" and 3.0 <= m["blur_px"] <= 6.0
            assert abs(m["max_displacement_px"] - m["blur_px"]) < 0.05
            assert len(m["times"]) == len(m["rotvecs"]) == len(m["translations"]) == m["samples"]
            assert rec["effects"]["noise"]["model"] == "gaussian" and rec["effects"]["noise"]["sigma"] == 0.01
            assert np.abs(img - sharp).mean() > 0.02  # visibly degraded


def test_degraded_scene_model_and_llff_poses(tiny_scene, motion_scene):
    src = read_colmap(tiny_scene / "sparse" / "0")
    out = read_colmap(motion_scene / "sparse" / "0")
    assert out.names == src.names and np.array_equal(out.sizes, src.sizes)
    np.testing.assert_allclose(out.w2c, src.w2c, atol=1e-9)
    np.testing.assert_allclose(out.Ks, src.Ks)
    rec_in = pycolmap.Reconstruction(str(tiny_scene / "sparse" / "0"))
    rec = pycolmap.Reconstruction(str(motion_scene / "sparse" / "0"))
    assert {c.model.name for c in rec.cameras.values()} == {"PINHOLE"}
    assert rec.num_points3D() == rec_in.num_points3D()
    pb = np.load(motion_scene / "poses_bounds.npy")
    assert pb.shape == (10, 17)
    c2w = np.linalg.inv(src.w2c)
    for v in range(10):
        P = pb[v, :15].reshape(3, 5)
        # LLFF columns (down, right, back) -> OpenCV (right, down, forward)
        np.testing.assert_allclose(np.c_[P[:, 1], P[:, 0], -P[:, 2]], c2w[v, :3, :3], atol=1e-9)
        np.testing.assert_allclose(P[:, 3], c2w[v, :3, 3], atol=1e-9)
        np.testing.assert_allclose(P[:, 4], [48, 64, src.Ks[v][0, 0]])
        near, far = pb[v, 15:]
        depth = np.load(tiny_scene / "depth" / (Path(src.names[v]).stem + ".npy"))
        assert 0 < near < far and depth.min() * 0.5 < near and far < depth.max() * 2


def test_same_seed_same_bytes_and_streams_are_independent(tiny_scene, motion_scene, tmp_path):
    again = degrade_scene(tiny_scene, tmp_path / "again", cfg("motion", noise=NoiseConfig(sigma=0.01)))
    for name in ("frame_00001.png", "frame_00005.png"):
        assert (again / "images" / name).read_bytes() == (motion_scene / "images" / name).read_bytes()
    only_motion = degrade_scene(tiny_scene, tmp_path / "m", cfg("motion"))
    a = json.loads((motion_scene / "degradation.json").read_text())["images"]
    b = json.loads((only_motion / "degradation.json").read_text())["images"]
    assert all(a[n]["effects"].get("motion") == b[n]["effects"].get("motion") for n in a)  # noise draws apart
    other = degrade_scene(tiny_scene, tmp_path / "s1", cfg("motion", seed=1))
    c = json.loads((other / "degradation.json").read_text())["images"]
    assert c["frame_00001.png"]["effects"]["motion"] != b["frame_00001.png"]["effects"]["motion"]


def test_defocus_and_mixres_scene(tiny_scene, tmp_path):
    out = degrade_scene(tiny_scene, tmp_path / "dm", cfg("defocus", "mixres", hold=5))
    doc = json.loads((out / "degradation.json").read_text())
    assert (out / "hold=5").is_file() and doc["effects"] == ["defocus", "mixres"]
    train = [n for n, r in doc["images"].items() if r["split"] == "train"]
    assert len(train) == 8 and [n for n, r in doc["images"].items() if r["split"] == "test"] == [
        "frame_00000.png", "frame_00005.png"]  # fmt: skip
    factors = [doc["images"][n]["effects"]["mixres"]["factor"] for n in train]
    assert factors == mixres_factors(8, 0).tolist() and sorted(factors) == [1, 1, 2, 2, 3, 3, 4, 4]
    for n in train:
        d = doc["images"][n]["effects"]["defocus"]
        depth = np.load(tiny_scene / "depth" / (Path(n).stem + ".npy"))
        assert d["model"] == "thin_lens" and depth.min() <= d["focus_distance"] <= depth.max()
        r = defocus_radius(torch.as_tensor(depth), d["focal_px"], d["aperture"], d["focus_distance"])
        assert abs(2 * float(r.max()) - d["max_coc_px"]) < 1e-4 and 3.0 <= d["max_coc_px"] <= 5.0


def test_mixres_only_scene_factor_one_is_untouched(tiny_scene, tmp_path):
    out = degrade_scene(tiny_scene, tmp_path / "mx", cfg("mixres"))
    doc = json.loads((out / "degradation.json").read_text())
    for name, rec in doc["images"].items():
        if rec["split"] == "test":
            continue
        f = rec["effects"]["mixres"]["factor"]
        diff = np.abs(load_png(out / "images" / name) - load_png(tiny_scene / "images" / name)).mean()
        assert rec["degraded"] == (f != 1) and (diff == 0) == (f == 1)


def test_one_per_image_assignment(tiny_scene, tmp_path):
    out = degrade_scene(tiny_scene, tmp_path / "mixed", cfg("motion", "defocus", "mixres", assignment="one_per_image"))
    doc = json.loads((out / "degradation.json").read_text())
    kinds = [tuple(r["effects"]) for r in doc["images"].values() if r["split"] == "train"]
    assert all(len(k) == 1 for k in kinds)
    counts = [kinds.count((e,)) for e in ("motion", "defocus", "mixres")]
    assert sum(counts) == 8 and max(counts) - min(counts) <= 1


def _colmap_to_transforms(scene: Path, out: Path) -> Path:
    """A nerfstudio transforms.json copy of a COLMAP scene (OpenGL camera-to-world poses), without sparse/."""
    cams = read_colmap(scene / "sparse" / "0")
    (out / "pics").mkdir(parents=True)
    K, (w, h) = cams.Ks[0], (int(v) for v in cams.sizes[0])
    frames = []
    for name, w2c in zip(cams.names, cams.w2c):
        jpg = Path(name).stem + ".jpg"  # JPEG input: the degraded scene names it <stem>.png
        Image.open(scene / "images" / name).save(out / "pics" / jpg, quality=95)
        c2w_gl = np.linalg.inv(w2c) @ np.diag([1.0, -1.0, -1.0, 1.0])
        frames.append({"file_path": f"pics/{jpg}", "transform_matrix": c2w_gl.tolist()})
    frames.reverse()  # frame order must not matter: views are sorted by name
    meta = {"camera_model": "OPENCV", "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": w, "h": h,
            "frames": frames}  # fmt: skip
    (out / "transforms.json").write_text(json.dumps(meta))
    return out


def test_transforms_json_scene_degraded_and_read_back(tiny_scene, tmp_path):
    src = _colmap_to_transforms(tiny_scene, tmp_path / "ns")
    out = degrade_scene(src, tmp_path / "deg", cfg("motion", "defocus"))
    cams_in = read_colmap(tiny_scene / "sparse" / "0")
    cams = read_colmap(out / "sparse" / "0")
    doc = json.loads((out / "degradation.json").read_text())
    m = doc["border_crop_px"]  # photos: cropped where the blur read outside them (tests/test_degrade_border.py)
    assert m > 0
    assert cams.names == cams_in.names
    np.testing.assert_allclose(cams.w2c, cams_in.w2c, atol=1e-9)
    np.testing.assert_allclose(cams.Ks, cams_in.Ks - m * np.array([[0, 0, 1], [0, 0, 1], [0, 0, 0]]), atol=1e-9)
    rec = doc["images"]["frame_00003.png"]["effects"]
    assert rec["motion"]["model"] == "rotational_shake" and rec["defocus"]["model"] == "disk"  # photos: no depth
    assert "translations" not in rec["motion"]
    for name in cams.names:  # lossless PNG twins of the decoded JPEGs; test views identical to them
        sharp = load_png(src / "pics" / (Path(name).stem + ".jpg"))[m:-m, m:-m]
        np.testing.assert_array_equal(load_png(out / "images_test" / name), sharp)
        if doc["images"][name]["split"] == "test":
            np.testing.assert_array_equal(load_png(out / "images" / name), sharp)
    pb = np.load(out / "poses_bounds.npy")  # no points, no depth: bounds guessed from the camera spread
    assert pb.shape == (10, 17) and np.all(0 < pb[:, 15]) and np.all(pb[:, 15] < pb[:, 16])


# ----------------------------------------------------------------------------------------------- bad input


def _copy(tiny_scene: Path, dst: Path) -> Path:
    shutil.copytree(tiny_scene, dst)
    return dst


@pytest.mark.parametrize(
    "breakage, message",
    [
        ("no_cameras", r"no COLMAP model \(sparse/0/\) and no transforms.json"),
        ("missing_image", r"frame_00003.png is listed in sparse/0 but missing"),
        ("corrupted_image", r"cannot read image file '.*frame_00004.png'"),
        ("zero_size_image", r"image file '.*frame_00002.png' is empty \(0 bytes\)"),
        ("wrong_size_image", r"frame_00006.png' is 32x24 px but its camera says 64x48 px"),
    ],
)
def test_bad_input_is_refused_with_a_clear_error(tiny_scene, tmp_path, breakage, message):
    scene = _copy(tiny_scene, tmp_path / "in")
    if breakage == "no_cameras":
        shutil.rmtree(scene / "sparse")
    elif breakage == "missing_image":
        (scene / "images" / "frame_00003.png").unlink()
    elif breakage == "corrupted_image":
        data = (scene / "images" / "frame_00004.png").read_bytes()
        (scene / "images" / "frame_00004.png").write_bytes(data[:40] + b"\x00garbage" * 20)
    elif breakage == "zero_size_image":
        (scene / "images" / "frame_00002.png").write_bytes(b"")
    else:
        Image.new("RGB", (32, 24)).save(scene / "images" / "frame_00006.png")
    with pytest.raises(InputError, match=message):
        degrade_scene(scene, tmp_path / "out", cfg("motion"))
    assert not (tmp_path / "out").exists() and leftovers(tmp_path) == []


def test_bad_config_is_refused(tiny_scene, tmp_path):
    with pytest.raises(ValueError, match="hold must be >= 2"):
        cfg("motion", hold=0)
    with pytest.raises(ValueError, match=r"unknown effect\(s\) \['blurry'\]; valid effects"):
        cfg("motion,blurry")
    with pytest.raises(ValueError, match="noise.sigma > 0"):
        degrade_scene(tiny_scene, tmp_path / "o", cfg("noise"))
    with pytest.raises(ValueError, match="must not be"):
        degrade_scene(tiny_scene, tiny_scene, cfg("motion"), overwrite=True)
    with pytest.raises(ValueError, match="unknown motion keys"):
        bad = tmp_path / "bad.yaml"
        bad.write_text("effects: [motion]\nmotion:\n  blur: 3\n")
        load_preset(bad)
    with pytest.raises(InputError, match="already a degraded scene"):
        (tmp_path / "deg").mkdir()
        (tmp_path / "deg" / "degradation.json").write_text("{}")
        degrade_scene(tmp_path / "deg", tmp_path / "o2", cfg("motion"))
    assert not (tmp_path / "o").exists()


def test_injected_failure_leaves_no_partial_output(tiny_scene, tmp_path, monkeypatch):
    calls = {"n": 0}
    real = pipe_mod.degrade_view

    def flaky(job):
        calls["n"] += 1
        if calls["n"] == 6:
            raise RuntimeError("injected failure in view 6")
        return real(job)

    monkeypatch.setattr(pipe_mod, "degrade_view", flaky)
    with pytest.raises(RuntimeError, match="injected"):
        degrade_scene(tiny_scene, tmp_path / "out", cfg("mixres"))
    assert not (tmp_path / "out").exists() and leftovers(tmp_path) == []
    # an existing output is left exactly as it was when the replacement fails late (while writing metadata)
    monkeypatch.setattr(pipe_mod, "degrade_view", real)
    first = degrade_scene(tiny_scene, tmp_path / "out", cfg("mixres"))
    before = {p.relative_to(first): p.read_bytes() for p in first.rglob("*") if p.is_file()}

    def broken_metadata(*args, **kwargs):
        raise OSError("disk full (injected)")

    monkeypatch.setattr(pipe_mod, "_write_metadata", broken_metadata)
    with pytest.raises(OSError, match="injected"):
        degrade_scene(tiny_scene, tmp_path / "out", cfg("motion"), overwrite=True)
    after = {p.relative_to(first): p.read_bytes() for p in first.rglob("*") if p.is_file()}
    assert after == before and leftovers(tmp_path) == []


def test_refuses_to_overwrite_without_flag(tiny_scene, motion_scene):
    with pytest.raises(FileExistsError, match="overwrite"):
        degrade_scene(tiny_scene, motion_scene, cfg("mixres"))


def test_worker_pool_gives_the_same_scene(tiny_scene, tmp_path):
    one = degrade_scene(tiny_scene, tmp_path / "one", cfg("mixres", "noise", noise=NoiseConfig(sigma=0.02)))
    two = degrade_scene(tiny_scene, tmp_path / "two", cfg("mixres", "noise", noise=NoiseConfig(sigma=0.02), workers=2))
    for p in sorted((one / "images").iterdir()):
        assert p.read_bytes() == (two / "images" / p.name).read_bytes()
    a, b = (json.loads((d / "degradation.json").read_text()) for d in (one, two))
    assert a["images"] == b["images"]


# ------------------------------------------------------------------------------------------------------ CLIs


def test_presets_parse_and_match_the_builtin_ones():
    files = sorted((REPO / "configs" / "degrade").glob("*.yaml"))
    assert {p.stem for p in files} == set(BUILTIN_PRESETS)
    for p in files:
        assert load_preset(p) == BUILTIN_PRESETS[p.stem], p.name


def test_degrade_cli_precedence(tmp_path):
    preset = REPO / "configs" / "degrade" / "mixed.yaml"
    cli = degrade_parse(["--input", "a", "--out", str(tmp_path / "o"), "--preset", str(preset)])
    assert cli.config.effects == ("motion", "defocus", "mixres") and cli.config.assignment == "one_per_image"
    cli = degrade_parse(["--data", "a", "--out", "o", "--preset", str(preset), "--effect", "motion",
                         "--effect", "defocus,mixres", "--noise-sigma", "0.02", "--seed", "4", "--hold", "5",
                         "--motion.max-blur-px", "20"])  # fmt: skip
    c = cli.config
    assert c.effects == ("motion", "defocus,mixres")
    assert c.resolved_effects() == ("motion", "defocus", "mixres", "noise")
    assert (c.noise.sigma, c.seed, c.hold, c.motion.max_blur_px, c.assignment) == (0.02, 4, 5, 20.0, "one_per_image")
    cli = degrade_parse(["--input", "a", "--out", "o"])
    assert cli.config.effects == () and cli.config == DegradeConfig()


def test_degrade_cli_end_to_end(tiny_scene, tmp_path, monkeypatch, capsys):
    ok = run_cli("gsmsdr-degrade", ["--input", tiny_scene, "--out", tmp_path / "o", "--effect", "mixres"], cwd=tmp_path)
    assert ok.returncode == 0, ok.stdout + ok.stderr
    assert json.loads((tmp_path / "o" / "degradation.json").read_text())["effects"] == ["mixres"]
    for args, message in [
        (["--effect", "blurry"], "unknown effect(s) ['blurry']"),
        (["--effect", "motion", "--hold", "0"], "hold must be >= 2"),
        (["--effect", "motion", "--input", str(tmp_path)], "no COLMAP model"),
    ]:
        argv = ["gsmsdr-degrade", "--input", str(tiny_scene), "--out", str(tmp_path / "p"), *args]
        monkeypatch.setattr("sys.argv", argv)
        with pytest.raises(SystemExit) as exit_info:
            degrade_entrypoint()
        out = capsys.readouterr()
        assert exit_info.value.code == 1 and message in " ".join((out.out + out.err).split())
        assert not (tmp_path / "p").exists()


def test_synth_variants(tmp_path):
    small = ["--num-views", "10", "--width", "48", "--height", "32", "--supersample", "1", "--num-points", "200"]
    out = synth_parse(["--out", str(tmp_path / "motion"), "--variant", "motion", *small]).main()
    doc = json.loads((out / "degradation.json").read_text())
    assert doc["generator"].startswith("gsmsdr-synth") and doc["source"] == "procedural"
    assert doc["preset"] == "motion-mild" and doc["effects"] == ["motion"] and doc["seed"] == 0
    assert all(r["effects"]["motion"]["model"] == "trajectory" for r in doc["images"].values() if r["split"] == "train")
    assert (out / "hold=8").is_file() and (out / "sparse" / "0").is_dir() and (out / "scene.json").is_file()
    sharp = synth_parse(["--out", str(tmp_path / "sharp"), "--variant", "sharp", "--hold", "4", *small]).main()
    assert (sharp / "hold=4").is_file()
    for p in (sharp / "images").iterdir():
        assert p.read_bytes() == (sharp / "images_test" / p.name).read_bytes()
    assert leftovers(tmp_path) == []
    plain = synth_parse(["--out", str(tmp_path / "plain"), *small]).main()  # default: unchanged behaviour
    assert not (plain / "degradation.json").exists() and not (plain / "images_test").exists()
