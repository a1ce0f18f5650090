"""gsmsdr-degrade on a capture with lens distortion: real fern photos, distorted on disk with a known OPENCV camera
(k1 = 0.06) and described by a transforms.json, are undistorted to pinhole first (pycolmap's undistorter), then
degraded; the undistorted pixels match the photos before distortion, and the log says what happened."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
import torch.nn.functional as F
from conftest import fern_capture

from gsmsdr_ns.degrade import DegradeConfig, MotionConfig, degrade_scene
from gsmsdr_ns.degrade.cli import parse as degrade_parse
from gsmsdr_ns.degrade.source import load_source
from gsmsdr_ns.degrade.undistort import describe_distortion
from gsmsdr_ns.io.colmap import read_colmap
from gsmsdr_ns.io.errors import InputError
from gsmsdr_ns.io.images import read_image_float, write_image

K1 = 0.06


def sample(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` [H, W, 3] at COLMAP pixel coordinates ``xy`` [N, 2] (pixel centres at +0.5)."""
    h, w = image.shape[:2]
    grid = torch.from_numpy(np.stack([(xy[:, 0] / w) * 2 - 1, (xy[:, 1] / h) * 2 - 1], -1)).float()
    out = F.grid_sample(torch.from_numpy(image).permute(2, 0, 1)[None].float(), grid[None, None], mode="bilinear",
                        padding_mode="border", align_corners=False)  # fmt: skip
    return out[0, :, 0].T.numpy()


def pixel_grid(width: int, height: int) -> np.ndarray:
    ys, xs = np.mgrid[0:height, 0:width]
    return np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], -1).astype(np.float64)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> dict:
    """6 fern photos (252x189) distorted with k1 = 0.06 and their transforms.json (LLFF poses, OPENCV camera)."""
    fern = fern_capture(6)
    root = tmp_path_factory.mktemp("distorted") / "capture"
    (root / "images").mkdir(parents=True)
    names, (w, h), focal = fern.names, fern.size, fern.focal
    camera = pycolmap.Camera(model="OPENCV", width=w, height=h, params=[focal, focal, w / 2, h / 2, K1, 0, 0, 0])
    # the distorted photo at pixel x shows the pinhole photo at K cam_from_img(x)
    rays = camera.cam_from_img(pixel_grid(w, h))
    source_xy = rays * focal + np.array([w / 2, h / 2])
    frames, originals = [], {}
    for name, c2w in zip(names, fern.c2w_opengl):
        pinhole = read_image_float(fern.folder / name)
        originals[name] = pinhole
        distorted = sample(pinhole, source_xy).reshape(h, w, 3)
        write_image(root / "images" / name, (np.clip(distorted, 0, 1) * 255 + 0.5).astype(np.uint8))
        frames.append({"file_path": f"images/{name}", "transform_matrix": c2w.tolist()})
    meta = {"camera_model": "OPENCV", "w": w, "h": h, "fl_x": focal, "fl_y": focal, "cx": w / 2, "cy": h / 2,
            "k1": K1, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames}  # fmt: skip
    (root / "transforms.json").write_text(json.dumps(meta), encoding="utf8")
    return {"root": root, "names": names, "originals": originals, "focal": focal, "size": (w, h)}


def test_load_source_still_refuses_distortion_and_names_the_fix(capture):
    with pytest.raises(InputError, match=r"non-zero distortion .*degrade_scene.* undistort"):
        load_source(capture["root"])
    assert "k1 k2 k3 k4 p1 p2 = 0.06 0 0 0 0 0" in describe_distortion(capture["root"])


def test_degrade_undistorts_a_distorted_capture_first(capture, tmp_path):
    notices, logs = [], []
    config = DegradeConfig(effects=("motion",), hold=3, seed=1, workers=1, px_reference_width=0,
                           motion=MotionConfig(min_blur_px=3.0, max_blur_px=5.0))  # fmt: skip
    out = degrade_scene(capture["root"], tmp_path / "out", config, log=logs.append, notice=notices.append)
    assert len(notices) == 1 and "lens distortion" in notices[0] and "undistorting it to pinhole" in notices[0]
    model = read_colmap(out / "sparse" / "0")
    assert set(model.camera_models) == {"PINHOLE"} and np.all(model.distortion == 0)
    assert model.names == [Path(n).stem + ".png" for n in capture["names"]]
    doc = json.loads((out / "degradation.json").read_text(encoding="utf8"))
    assert [doc["images"][n]["split"] for n in model.names] == ["test", "train", "train", "test", "train", "train"]
    assert all("motion" in doc["images"][n]["effects"] for n in model.names[1:3])
    assert not list(tmp_path.glob(".out.*")), "the undistortion scratch folder is removed"

    # the sharp twins are the undistorted photos: pixel p' of the pinhole camera K' shows the original photo at
    # K K'^-1 p' (original pinhole K: the photo before the synthetic distortion)
    w, h = (int(x) for x in model.sizes[0])
    fx, fy, cx, cy = model.intrinsics[0]
    ow, oh = capture["size"]
    xy = pixel_grid(w, h)
    original_xy = (xy - [cx, cy]) / [fx, fy] * capture["focal"] + [ow / 2, oh / 2]
    inside = np.all((original_xy > 4) & (original_xy < [ow - 4, oh - 4]), axis=1)
    for name in model.names:
        twin = read_image_float(out / "images_test" / name).reshape(-1, 3)
        expected = sample(capture["originals"][name], original_xy)
        mse = float(np.mean((twin[inside] - expected[inside]) ** 2))
        assert -10 * np.log10(mse) > 28.0, f"{name}: undistorted photo differs from the original"
        # without undistortion the same comparison is far off (the test can fail)
        distorted = read_image_float(capture["root"] / "images" / name)
        if distorted.shape[:2] == (h, w):
            assert np.mean((distorted.reshape(-1, 3)[inside] - expected[inside]) ** 2) > 4 * mse


def test_degrade_cli_prints_the_undistortion_line(capture, tmp_path, capsys):
    cli = degrade_parse(["--input", str(capture["root"]), "--out", str(tmp_path / "cli"), "--effect", "sharp",
                         "--hold", "3", "--workers", "1"])  # fmt: skip
    cli.main()
    printed = capsys.readouterr().out
    assert "lens distortion" in printed and "undistorting" in printed
    assert (tmp_path / "cli" / "degradation.json").is_file()


def test_degrade_undistorts_a_distorted_colmap_scene(capture, tmp_path):
    """The same photos as a COLMAP scene (images/ + sparse/0 with one OPENCV camera, k1 = 0.06)."""
    root = tmp_path / "colmap"
    (root / "sparse" / "0").mkdir(parents=True)
    root_images = root / "images"
    root_images.mkdir()
    w, h = capture["size"]
    focal = capture["focal"]
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="OPENCV", width=w, height=h, camera_id=1,
                                                    params=[focal, focal, w / 2, h / 2, K1, 0, 0, 0]))  # fmt: skip
    frames = json.loads((capture["root"] / "transforms.json").read_text(encoding="utf8"))["frames"]
    for i, frame in enumerate(frames):
        name = Path(frame["file_path"]).name
        (root_images / name).write_bytes((capture["root"] / frame["file_path"]).read_bytes())
        c2w = np.asarray(frame["transform_matrix"]) @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL -> OpenCV axes
        image = pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(np.linalg.inv(c2w)[:3, :4]))
    rec.write(root / "sparse" / "0")
    with pytest.raises(InputError, match=r"OPENCV camera with distortion"):
        load_source(root)
    notices = []
    out = degrade_scene(root, tmp_path / "out", DegradeConfig(effects=(), hold=3, workers=1), notice=notices.append)
    assert len(notices) == 1 and "OPENCV" in notices[0]
    model = read_colmap(out / "sparse" / "0")
    assert set(model.camera_models) == {"PINHOLE"} and len(model.names) == len(capture["names"])
    # the same undistortion as for the transforms.json capture: identical cameras and pixels
    from_transforms = degrade_scene(capture["root"], tmp_path / "tj", DegradeConfig(effects=(), hold=3, workers=1))
    other = read_colmap(from_transforms / "sparse" / "0")
    np.testing.assert_allclose(model.intrinsics, other.intrinsics, rtol=1e-6)
    np.testing.assert_allclose(model.w2c, other.w2c, atol=1e-9)
    for name in model.names:
        a = read_image_float(out / "images_test" / name)
        b = read_image_float(from_transforms / "images_test" / name)
        assert np.abs(a - b).max() <= 1.0 / 255 + 1e-6
