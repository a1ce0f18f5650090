"""Tests of the procedural scene generator (gsmsdr_ns.synth): determinism, layout, COLMAP/nerfstudio
round trips, geometric consistency of poses/depth/points, atomic writes and the CLI."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image

from gsmsdr_ns.degrade.synth_cli import parse
from gsmsdr_ns.io.colmap import read_colmap
from gsmsdr_ns.synth import generate as gen_mod
from gsmsdr_ns.synth.cameras import intrinsics, orbit_cameras, project, world_to_camera
from gsmsdr_ns.synth.config import SynthSceneConfig, config_from_dict, load_preset
from gsmsdr_ns.synth.generate import generate_scene
from gsmsdr_ns.synth.geometry import Sphere
from gsmsdr_ns.synth.raycast import render_view
from gsmsdr_ns.synth.scene import WORLD_UP, build_scene

REPO = Path(__file__).resolve().parents[1]

# Small but complete: every code path of the default scene, ~1 s to generate.
SMALL = SynthSceneConfig(seed=3, num_views=8, width=64, height=48, supersample=2, num_points=400)


def _cam_from_world(image) -> np.ndarray:
    cfw = image.cam_from_world
    m = (cfw() if callable(cfw) else cfw).matrix()
    return np.vstack([m, [0.0, 0.0, 0.0, 1.0]])


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample img [H, W, ...] at COLMAP pixel coords uv [N, 2] (pixel centres at +0.5)."""
    h, w = img.shape[:2]
    x = np.clip(uv[:, 0] - 0.5, 0, w - 1.000001)
    y = np.clip(uv[:, 1] - 0.5, 0, h - 1.000001)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    if img.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    top = img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx
    bot = img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bot * fy


def _unproject(depth: np.ndarray, c2w: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All pixel centres of a view with their depth -> (world points [H*W, 3], pixel uv [H*W, 2])."""
    h, w = depth.shape
    jj, ii = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    uv = np.stack([ii.ravel(), jj.ravel()], -1)
    cam = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(h * w)], -1)
    cam *= depth.reshape(-1, 1).astype(np.float64)
    return cam @ c2w[:3, :3].T + c2w[:3, 3], uv


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory) -> Path:
    return generate_scene(tmp_path_factory.mktemp("synth") / "scene", SMALL)


def _all_files(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


# ----------------------------------------------------------------------------------------- determinism


def test_same_seed_is_bitwise_identical(small_scene, tmp_path):
    again = generate_scene(tmp_path / "again", SMALL)
    a, b = _all_files(small_scene), _all_files(again)
    assert a.keys() == b.keys()
    assert [k for k in a if a[k] != b[k]] == []


def test_different_seeds_differ(small_scene, tmp_path):
    other = generate_scene(tmp_path / "other", dataclasses.replace(SMALL, seed=SMALL.seed + 1))
    for name in ("frame_00000.png", "frame_00005.png"):
        a = np.asarray(Image.open(small_scene / "images" / name), dtype=np.float64)
        b = np.asarray(Image.open(other / "images" / name), dtype=np.float64)
        assert np.abs(a - b).mean() > 10.0


def test_random_streams_are_independent():
    # Changing the number of sparse points must not move the scene or the cameras.
    more = dataclasses.replace(SMALL, num_points=50)
    assert np.array_equal(orbit_cameras(SMALL), orbit_cameras(more))
    s1, s2 = build_scene(SMALL), build_scene(more)
    assert [p.texture for p in s1.primitives] == [p.texture for p in s2.primitives]


# ----------------------------------------------------------------------------------------------- layout


def test_layout_and_metadata(small_scene):
    names = sorted(p.name for p in (small_scene / "images").iterdir())
    assert names == [f"frame_{i:05d}.png" for i in range(SMALL.num_views)]
    for name in names:
        im = Image.open(small_scene / "images" / name)
        assert im.mode == "RGB" and im.size == (SMALL.width, SMALL.height)
        depth = np.load(small_scene / "depth" / name.replace(".png", ".npy"))
        assert depth.dtype == np.float32 and depth.shape == (SMALL.height, SMALL.width)
        assert np.all(np.isfinite(depth)) and depth.min() > 0.1  # the room box catches every ray
    for f in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (small_scene / "sparse" / "0" / f).is_file()
    meta = json.loads((small_scene / "scene.json").read_text())
    assert meta["seed"] == SMALL.seed
    assert config_from_dict(meta["config"]) == SMALL
    assert meta["num_images"] == SMALL.num_views and meta["num_points3D"] == SMALL.num_points
    # No temp / backup directories left next to the output.
    assert [p.name for p in small_scene.parent.iterdir()] == [small_scene.name]


def test_images_have_high_frequency_detail(small_scene):
    img = np.asarray(Image.open(small_scene / "images" / "frame_00000.png"), dtype=np.float64).mean(-1)
    grad = np.abs(np.diff(img, axis=1))
    assert np.mean(grad > 20) > 0.03  # plenty of strong edges for deblurring to recover
    assert img.std() > 20


# ------------------------------------------------------------------------------------ COLMAP model


def test_pycolmap_reads_cameras_and_poses(small_scene):
    rec = pycolmap.Reconstruction(str(small_scene / "sparse" / "0"))
    assert rec.num_reg_images() == SMALL.num_views
    assert rec.num_cameras() == 1
    K = intrinsics(SMALL.width, SMALL.height, SMALL.fov_deg)
    cam = next(iter(rec.cameras.values()))
    assert cam.model_name == "PINHOLE" and (cam.width, cam.height) == (SMALL.width, SMALL.height)
    np.testing.assert_allclose(cam.calibration_matrix(), K, atol=1e-9)
    c2ws = orbit_cameras(SMALL)
    for image_id in sorted(rec.images.keys()):
        image = rec.images[image_id]
        assert image.name == f"frame_{image_id - 1:05d}.png"  # ids 1..V in capture order
        np.testing.assert_allclose(_cam_from_world(image), world_to_camera(c2ws[image_id - 1]), atol=1e-9)
    cams = read_colmap(small_scene / "sparse" / "0")
    np.testing.assert_allclose(cams.w2c, world_to_camera(c2ws), atol=1e-9)


def test_cameras_look_at_scene_and_are_upright():
    c2ws = orbit_cameras(SMALL)
    for c2w in c2ws:
        R = c2w[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) > 0
        assert abs(R[:, 0] @ WORLD_UP) < 1e-9  # no roll: image x axis is horizontal
        assert R[:, 1] @ WORLD_UP < 0  # image y points down
        assert c2w[:3, 3] @ WORLD_UP > 0  # camera above the floor
        to_centre = -c2w[:3, 3] / np.linalg.norm(c2w[:3, 3])
        assert R[:, 2] @ to_centre > 0.95


def test_pixel_convention_matches_colmap_projection(small_scene):
    """Unproject pixel centres with the saved depth, project back with pycolmap: same pixel centres."""
    rec = pycolmap.Reconstruction(str(small_scene / "sparse" / "0"))
    c2ws = orbit_cameras(SMALL)
    K = intrinsics(SMALL.width, SMALL.height, SMALL.fov_deg)
    depth = np.load(small_scene / "depth" / "frame_00002.npy")
    X, uv = _unproject(depth, c2ws[2], K)
    image = rec.images[3]
    for k in np.random.default_rng(0).choice(len(X), 50, replace=False):
        np.testing.assert_allclose(image.project_point(X[k]), uv[k], atol=2e-3)


def test_sphere_depth_matches_geometry(small_scene):
    """A known 3D point: along the ray through a sphere's projected centre the depth map must show the
    sphere's front surface (or something in front of it, never behind)."""
    scene = build_scene(SMALL)
    spheres = [p for p in scene.primitives if isinstance(p, Sphere)]
    assert spheres, "test seed must produce at least one sphere"
    c2ws = orbit_cameras(SMALL)
    K = intrinsics(SMALL.width, SMALL.height, SMALL.fov_deg)
    n_exact = n_checked = 0
    for v, c2w in enumerate(c2ws):
        depth = np.load(small_scene / "depth" / f"frame_{v:05d}.npy").astype(np.float64)
        for s in spheres:
            uv, z = project(s.center[None], world_to_camera(c2w), K)
            if not (1 <= uv[0, 0] <= SMALL.width - 1 and 1 <= uv[0, 1] <= SMALL.height - 1):
                continue
            dist = np.linalg.norm(s.center - c2w[:3, 3])
            expected = (dist - s.radius) * z[0] / dist  # z-depth of the front surface on the centre ray
            # Inverse depth is affine in pixel coords on planes, so interpolate it, not depth.
            seen = 1.0 / _bilinear(1.0 / depth, uv)[0]
            n_checked += 1
            assert seen <= expected + 0.05 * s.radius
            n_exact += abs(seen - expected) < 0.05 * s.radius
    assert n_checked >= 4 and n_exact >= 0.5 * n_checked


def test_point_tracks_are_valid(small_scene):
    rec = pycolmap.Reconstruction(str(small_scene / "sparse" / "0"))
    assert rec.num_points3D() == SMALL.num_points
    assert rec.compute_mean_reprojection_error() < 1e-6
    depths = {
        iid: np.load(small_scene / "depth" / rec.images[iid].name.replace(".png", ".npy")).astype(np.float64)
        for iid in rec.images.keys()
    }
    n_obs = n_depth_ok = 0
    for pid, point in rec.points3D.items():
        elements = point.track.elements
        assert len(elements) >= SMALL.min_track_length
        assert len({e.image_id for e in elements}) == len(elements)
        for e in elements:
            image = rec.images[e.image_id]
            p2d = image.points2D[e.point2D_idx]
            assert p2d.point3D_id == pid
            xy = np.asarray(p2d.xy)
            assert 0 <= xy[0] <= SMALL.width and 0 <= xy[1] <= SMALL.height
            np.testing.assert_allclose(image.project_point(point.xyz), xy, atol=1e-6)
            z = (_cam_from_world(image) @ np.append(point.xyz, 1.0))[2]
            n_obs += 1
            # Visible in this view: one of the 4 pixel centres around xy shows the same surface (the
            # tolerance covers depth change across a pixel on grazing floor / silhouettes).
            x0 = int(np.clip(np.floor(xy[0] - 0.5), 0, SMALL.width - 2))
            y0 = int(np.clip(np.floor(xy[1] - 0.5), 0, SMALL.height - 2))
            n_depth_ok += np.min(np.abs(depths[e.image_id][y0 : y0 + 2, x0 : x0 + 2] - z)) < 0.05 * z
    assert n_depth_ok > 0.95 * n_obs


def test_point_colours_match_images(small_scene):
    rec = pycolmap.Reconstruction(str(small_scene / "sparse" / "0"))
    images = {
        iid: np.asarray(Image.open(small_scene / "images" / rec.images[iid].name), dtype=np.float64)
        for iid in rec.images.keys()
    }
    diffs = []
    for point in rec.points3D.values():
        e = point.track.elements[0]
        xy = np.asarray(rec.images[e.image_id].points2D[e.point2D_idx].xy)
        diffs.append(np.abs(_bilinear(images[e.image_id], xy[None])[0] - point.color).mean())
    # Textures are high-frequency, so individual samples differ; the typical one must match closely.
    assert np.median(diffs) < 12.0


def test_depth_is_multiview_consistent(small_scene):
    """Unproject view 0 with its depth, reproject into other views: where unoccluded the other view's
    depth agrees (geometry) and the colour agrees (Lambertian, view-independent shading)."""
    c2ws = orbit_cameras(SMALL)
    K = intrinsics(SMALL.width, SMALL.height, SMALL.fov_deg)
    d0 = np.load(small_scene / "depth" / "frame_00000.npy")
    img0 = np.asarray(Image.open(small_scene / "images" / "frame_00000.png"), dtype=np.float64)
    X, uv0 = _unproject(d0, c2ws[0], K)
    for v in (1, SMALL.num_views - 1):  # the neighbours on the orbit (45 deg apart) overlap most
        dv = np.load(small_scene / "depth" / f"frame_{v:05d}.npy").astype(np.float64)
        imgv = np.asarray(Image.open(small_scene / "images" / f"frame_{v:05d}.png"), dtype=np.float64)
        uv, z = project(X, world_to_camera(c2ws[v]), K)
        inside = (
            (z > 0) & (uv[:, 0] > 1) & (uv[:, 0] < SMALL.width - 1) & (uv[:, 1] > 1) & (uv[:, 1] < SMALL.height - 1)
        )
        z_seen = 1.0 / _bilinear(1.0 / dv, uv[inside])  # inverse depth is affine on planes: exact there
        rel = np.abs(z_seen - z[inside]) / z[inside]
        visible = rel < 1e-2
        assert visible.mean() > 0.4
        assert np.median(rel[visible]) < 1e-5
        c0 = img0.reshape(-1, 3)[inside][visible]
        cv = _bilinear(imgv, uv[inside][visible])
        assert np.median(np.abs(c0 - cv).mean(-1)) < 12.0


# ------------------------------------------------------------------------------------ nerfstudio


def test_nerfstudio_colmap_dataparser(small_scene):
    from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParserConfig

    # downscale_factor=1 (explicit) skips the interactive "downscale images?" prompt.
    cfg = ColmapDataParserConfig(
        data=small_scene,
        colmap_path=Path("sparse/0"),
        images_path=Path("images"),
        downscale_factor=1,
        load_3D_points=True,
        eval_mode="all",
    )
    out = cfg.setup().get_dataparser_outputs(split="train")
    assert len(out.image_filenames) == SMALL.num_views
    assert [Path(f).name for f in out.image_filenames] == [f"frame_{i:05d}.png" for i in range(SMALL.num_views)]
    K = intrinsics(SMALL.width, SMALL.height, SMALL.fov_deg)
    assert float(out.cameras.fx[0]) == pytest.approx(K[0, 0], rel=1e-5)
    assert float(out.cameras.cy[0]) == pytest.approx(K[1, 2], rel=1e-5)
    assert int(out.cameras.width[0]) == SMALL.width and int(out.cameras.height[0]) == SMALL.height
    assert out.metadata["points3D_xyz"].shape == (SMALL.num_points, 3)
    assert out.metadata["points3D_rgb"].shape == (SMALL.num_points, 3)
    assert int(out.metadata["points3D_num_points2D"].min()) >= 2


# ----------------------------------------------------------------------------------- renderer API


def test_render_view_arbitrary_intrinsics():
    scene = build_scene(SMALL)
    c2w = orbit_cameras(SMALL)[0]
    K = np.array([[40.0, 0.0, 12.0], [0.0, 44.0, 20.0], [0.0, 0.0, 1.0]])  # off-centre principal point
    rgb, depth = render_view(scene, c2w, K, 30, 25, supersample=1)
    assert rgb.shape == (25, 30, 3) and rgb.dtype == np.float32 and depth.shape == (25, 30)
    assert 0.0 <= rgb.min() and rgb.max() <= 1.0 and np.all(np.isfinite(depth))
    # Supersampling changes colours only; depth is always taken at the exact pixel centre.
    rgb3, depth3 = render_view(scene, c2w, K, 30, 25, supersample=3)
    assert np.array_equal(depth, depth3)
    assert np.abs(rgb3 - rgb).mean() < 0.1


# ------------------------------------------------------------------------------ atomic writes


def test_failure_leaves_nothing(tmp_path, monkeypatch):
    calls = {"n": 0}
    real = gen_mod.write_image

    def flaky(path, rgb):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("injected failure")
        real(path, rgb)

    monkeypatch.setattr(gen_mod, "write_image", flaky)
    target = tmp_path / "out"
    with pytest.raises(RuntimeError, match="injected"):
        generate_scene(target, SMALL)
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []

    # With overwrite, a failure must keep the previous dataset intact.
    target.mkdir()
    (target / "keep.txt").write_text("old")
    calls["n"] = 0
    with pytest.raises(RuntimeError, match="injected"):
        generate_scene(target, SMALL, overwrite=True)
    assert _all_files(target) == {"keep.txt": b"old"}
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_refuses_to_overwrite(tmp_path):
    target = tmp_path / "out"
    target.mkdir()
    generate_scene(target, dataclasses.replace(SMALL, num_views=2, num_points=20))  # empty dir is fine
    before = _all_files(target)
    with pytest.raises(FileExistsError, match="overwrite"):
        generate_scene(target, dataclasses.replace(SMALL, num_views=3, num_points=20))
    assert _all_files(target) == before
    generate_scene(target, dataclasses.replace(SMALL, num_views=3, num_points=20), overwrite=True)
    assert len(list((target / "images").iterdir())) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    (tmp_path / "afile").write_text("x")
    with pytest.raises(FileExistsError):
        generate_scene(tmp_path / "afile", SMALL, overwrite=True)


# ------------------------------------------------------------------------------------ config / CLI


def test_default_preset_matches_dataclass_defaults():
    assert load_preset(REPO / "configs" / "synth" / "default.yaml") == SynthSceneConfig()


def test_invalid_config_is_rejected():
    with pytest.raises(ValueError):
        SynthSceneConfig(num_views=1)
    with pytest.raises(ValueError):
        SynthSceneConfig(orbit_radius=9.0)  # camera outside the room
    with pytest.raises(ValueError, match="unknown"):
        config_from_dict({"num_veiws": 3})


def test_cli_flags_and_preset_precedence(tmp_path):
    cli = parse(["--out", str(tmp_path / "a"), "--seed", "7", "--num-views", "5"])
    assert cli.out == tmp_path / "a" and cli.scene.seed == 7 and cli.scene.num_views == 5
    assert cli.scene.width == SynthSceneConfig().width

    preset = tmp_path / "p.yaml"
    preset.write_text("seed: 5\nnum_views: 3\nwidth: 40\nheight: 30\nnum_points: 30\n")
    cli = parse(["--out", str(tmp_path / "b"), "--preset", str(preset)])
    assert (cli.scene.seed, cli.scene.num_views, cli.scene.width) == (5, 3, 40)
    cli = parse(["--out", str(tmp_path / "b"), "--preset", str(preset), "--seed", "9"])
    assert (cli.scene.seed, cli.scene.num_views) == (9, 3)

    out = cli.main()
    assert out == (tmp_path / "b").absolute()
    assert len(list((out / "images").iterdir())) == 3
    assert json.loads((out / "scene.json").read_text())["seed"] == 9
