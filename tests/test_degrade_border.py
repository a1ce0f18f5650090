"""gsmsdr-degrade on photos (a scene it cannot re-render): a blur near the border reads pixels from outside the
photo, which only reflection can supply. Every image is cropped by the widest band that happened, so the degraded
photos hold only what a camera could have recorded: shown on real fern photos, against a blur of a wider view."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import fern_capture, shared_fern

from gsmsdr_ns.degrade import DefocusConfig, DegradeConfig, MotionConfig, degrade_scene
from gsmsdr_ns.degrade.kernels import rotational_shake_blur
from gsmsdr_ns.degrade.trajectory import border_reach_px, calibrated_shake
from gsmsdr_ns.io.colmap import read_colmap
from gsmsdr_ns.io.images import read_image, read_image_float


@pytest.fixture(scope="module")
def photos(tmp_path_factory) -> Path:
    """6 real fern photos (252x189) with their LLFF poses as a pinhole transforms.json capture (no scene.json)."""
    fern = fern_capture(6)
    root = tmp_path_factory.mktemp("photos") / "capture"
    (root / "images").mkdir(parents=True)
    (w, h), focal = fern.size, fern.focal
    frames = []
    for name, c2w in zip(fern.names, fern.c2w_opengl):
        (root / "images" / name).write_bytes((fern.folder / name).read_bytes())
        frames.append({"file_path": f"images/{name}", "transform_matrix": c2w.tolist()})
    meta = {"camera_model": "PINHOLE", "w": w, "h": h, "fl_x": focal, "fl_y": focal, "cx": w / 2, "cy": h / 2,
            "frames": frames}  # fmt: skip
    (root / "transforms.json").write_text(json.dumps(meta), encoding="utf8")
    return root


def _config(effect: str, crop: bool = True) -> DegradeConfig:
    return DegradeConfig(effects=(effect,), hold=3, seed=2, workers=1, px_reference_width=0, crop_border=crop,
                         motion=MotionConfig(min_blur_px=8.0, max_blur_px=12.0),
                         defocus=DefocusConfig(min_coc_px=6.0, max_coc_px=9.0))  # fmt: skip


def _reaches(doc: dict, effect: str) -> list:
    return [r["effects"][effect]["border_reach_px"] for r in doc["images"].values() if r["effects"]]


def test_border_reach_bounds_what_a_shake_reads_from_outside_the_photo():
    """Blur a wide real photo, and its centre as a photo of its own, with the same shake: the two agree exactly
    inside the crop the reach gives (nothing there came from outside), and differ in the band outside it."""
    wide = read_image_float(shared_fern() / "images_16" / "IMG_4029.png")
    wide = torch.from_numpy(wide).permute(2, 0, 1)[None].double()
    H, W = wide.shape[-2:]
    m, f = 30, 200.0
    w, h = W - 2 * m, H - 2 * m
    K_wide = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    rng = np.random.default_rng(3)
    for _ in range(3):
        trajectory, extent = calibrated_shake(rng, K, w, h, 12.0, 13, 0.5, 0.3)
        R, _ = trajectory.reference_to_camera()
        reach = border_reach_px(K, trajectory, w, h)
        assert extent / 2 <= reach <= extent + 1e-9  # the reference pose lies on the path
        c = math.ceil(reach)
        photo = rotational_shake_blur(wide[..., m:-m, m:-m], torch.as_tensor(K), R)
        truth = rotational_shake_blur(wide, torch.as_tensor(K_wide), R)[..., m:-m, m:-m]
        assert (photo - truth)[..., c:-c, c:-c].abs().max() < 1e-9
        assert (photo - truth).abs().max() > 0.02  # the band outside the crop did read reflected pixels


def test_shaken_photos_are_cropped_by_the_widest_reach(photos, tmp_path):
    out = degrade_scene(photos, tmp_path / "cropped", _config("motion"))
    whole = degrade_scene(photos, tmp_path / "whole", _config("motion", crop=False))
    doc = json.loads((out / "degradation.json").read_text())
    reaches = _reaches(doc, "motion")
    m = doc["border_crop_px"]
    assert len(reaches) == 4 and m == math.ceil(max(reaches)) and m >= 4
    assert json.loads((whole / "degradation.json").read_text())["border_crop_px"] == 0
    for name in doc["images"]:
        original = read_image(photos / "images" / name)
        h, w = original.shape[:2]
        for folder in ("images", "images_test"):
            image = read_image(out / folder / name)
            assert image.shape[:2] == (h - 2 * m, w - 2 * m)
            # the same seed draws the same shake: the crop is the uncropped scene's interior, pixel for pixel
            np.testing.assert_array_equal(image, read_image(whole / folder / name)[m:-m, m:-m])
        np.testing.assert_array_equal(read_image(out / "images_test" / name), original[m:-m, m:-m])
    cropped, uncropped = read_colmap(out / "sparse" / "0"), read_colmap(whole / "sparse" / "0")
    np.testing.assert_allclose(cropped.w2c, uncropped.w2c)
    np.testing.assert_allclose(cropped.Ks[:, :2, 2], uncropped.Ks[:, :2, 2] - m)
    np.testing.assert_allclose(cropped.Ks[:, 0, 0], uncropped.Ks[:, 0, 0])
    assert [tuple(s) for s in cropped.sizes] == [(w - 2 * m, h - 2 * m) for w, h in uncropped.sizes]
    hwf = np.load(out / "poses_bounds.npy")[:, :15].reshape(-1, 3, 5)[:, :, 4]
    np.testing.assert_allclose(hwf[:, :2], [[h - 2 * m, w - 2 * m] for w, h in uncropped.sizes])


def test_defocused_photos_are_cropped_by_the_widest_disk(photos, tmp_path):
    doc = json.loads((degrade_scene(photos, tmp_path / "defocus", _config("defocus")) / "degradation.json").read_text())
    disks = [r["effects"]["defocus"] for r in doc["images"].values() if r["effects"]]
    assert all(d["model"] == "disk" and d["border_reach_px"] == d["radius_px"] for d in disks)
    assert doc["border_crop_px"] == math.ceil(max(d["radius_px"] for d in disks)) >= 3


def test_a_crop_that_would_leave_less_than_half_a_photo_is_refused(photos, tmp_path):
    config = _config("motion")
    config.motion = MotionConfig(min_blur_px=120.0, max_blur_px=130.0)
    with pytest.raises(ValueError, match=r"reaches \d+ px into the photos' borders.*--no-crop-border"):
        degrade_scene(photos, tmp_path / "too-much", config)
    assert not (tmp_path / "too-much").exists()


def test_depth_maps_of_photos_are_cropped_with_them(photos, tmp_path):
    """Photos with depth maps are defocused by the thin lens; its widest circle sets the crop, and the depth maps
    are cropped alike (they must keep matching their images)."""
    scene = tmp_path / "with-depth"
    shutil.copytree(photos, scene)
    (scene / "depth").mkdir()
    depths = {}
    for k, name in enumerate(sorted(p.name for p in (scene / "images").iterdir())):
        h, w = read_image(scene / "images" / name).shape[:2]
        depths[name] = 2.0 + np.linspace(0.0, 3.0 + k, w)[None, :] + np.linspace(0.0, 1.0, h)[:, None]
        np.save(scene / "depth" / (Path(name).stem + ".npy"), depths[name])
    out = degrade_scene(scene, tmp_path / "defocus", _config("defocus"))
    doc = json.loads((out / "degradation.json").read_text())
    lenses = [r["effects"]["defocus"] for r in doc["images"].values() if r["effects"]]
    m = doc["border_crop_px"]
    assert all(d["model"] == "thin_lens" for d in lenses) and m == math.ceil(max(d["border_reach_px"] for d in lenses))
    assert m >= 2
    for name, depth in depths.items():
        np.testing.assert_array_equal(np.load(out / "depth" / (Path(name).stem + ".npy")), depth[m:-m, m:-m])
        assert read_image(out / "images" / name).shape[:2] == depth[m:-m, m:-m].shape


def test_mixres_records_give_the_cropped_views_low_resolution_size(photos, tmp_path):
    config = _config("motion")
    config.effects = ("motion", "mixres")
    out = degrade_scene(photos, tmp_path / "mixed", config)
    doc = json.loads((out / "degradation.json").read_text())
    m = doc["border_crop_px"]
    assert m > 0
    for name, record in doc["images"].items():
        if "mixres" in record["effects"]:
            h, w = read_image(out / "images" / name).shape[:2]
            f = record["effects"]["mixres"]["factor"]
            assert record["effects"]["mixres"]["size"] == [max(1, round(w / f)), max(1, round(h / f))]
