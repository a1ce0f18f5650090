"""deblur-nerf-data, mixres-data and gsmsdr-data on real files: pycolmap models, PNGs, poses_bounds.npy, caches.

Scenes are 16-view 64x48 ``gsmsdr_ns.synth`` renders, rearranged here into the Deblur-NeRF layout (blurred
training views in images/, sharp twins in images_test/, hold=N, degradation.json, poses_bounds.npy).
"""

from __future__ import annotations

import json
import os
import shutil
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Dict, Optional

import numpy as np
import pytest
import torch
from conftest import TRAIN_FLAGS, make_tiny_scene, run_cli, write_transforms_json
from nerfstudio.data.utils import colmap_parsing_utils as colmap_io
from PIL import Image, ImageFilter

from gsmsdr_ns.data.cameras import cameras_from_colmap, depth_bounds, llff_to_opencv, opencv_to_llff, write_poses_bounds
from gsmsdr_ns.data.layout import detect_layout
from gsmsdr_ns.data.mixres import MIXRES_FACTORS, assign_mixres_factors, downscale_upscale
from gsmsdr_ns.io.colmap import read_colmap
from gsmsdr_ns.io.errors import InputError, InputWarning
from gsmsdr_ns.plugin.auto_dataparser import GSMSDRAutoDataParser, GSMSDRAutoDataParserConfig
from gsmsdr_ns.plugin.dataparser import GSMSDRDataParser, GSMSDRDataParserConfig
from gsmsdr_ns.plugin.deblur_dataparser import DeblurNerfDataParser, DeblurNerfDataParserConfig
from gsmsdr_ns.plugin.mixres_dataparser import MixresDataParserConfig

NUM_VIEWS = 16
TEST_NAMES = ["frame_00000.png", "frame_00008.png"]  # index % 8 == 0 among 16 views sorted by name


def names_of(outputs):
    return [Path(f).name for f in outputs.image_filenames]


def pixels(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"))


def box_blur(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(Image.fromarray(rgb).filter(ImageFilter.BoxBlur(2)))


@pytest.fixture(scope="session")
def synth16(tmp_path_factory) -> Path:
    """16 views, 64x48, COLMAP model in sparse/0 (read-only)."""
    return make_tiny_scene(tmp_path_factory.mktemp("dp") / "synth16", num_views=NUM_VIEWS, num_points=300)


def make_deblur_scene(
    src: Path,
    dst: Path,
    hold: Optional[int] = 8,
    twins: bool = True,
    degradation: bool = True,
    poses_bounds: bool = True,
    colmap: bool = True,
) -> Path:
    """Rearrange a synth scene into the Deblur-NeRF layout (blurred training views, sharp held-out views)."""
    names = sorted(p.name for p in (src / "images").iterdir())
    every = hold or 8
    (dst / "images").mkdir(parents=True)
    entries: Dict[str, dict] = {}
    for index, name in enumerate(names):
        sharp = pixels(src / "images" / name)
        if index % every == 0:
            shutil.copy2(src / "images" / name, dst / "images" / name)
            entries[name] = {"split": "test", "degraded": False, "effects": {}}
        else:
            Image.fromarray(box_blur(sharp)).save(dst / "images" / name)
            effects = {"defocus": {"model": "disk", "radius_px": 2.0}}
            if index % 3 == 0:
                effects["mixres"] = {"factor": 2}
            entries[name] = {"split": "train", "degraded": True, "effects": effects}
    if twins:
        shutil.copytree(src / "images", dst / "images_test")
    if colmap:
        shutil.copytree(src / "sparse", dst / "sparse")
    if hold is not None:
        (dst / f"hold={hold}").touch()
    if poses_bounds:
        model = read_colmap(src / "sparse" / "0")
        cameras = cameras_from_colmap(model)
        bounds = depth_bounds(cameras, model.points.xyz)
        write_poses_bounds(dst / "poses_bounds.npy", cameras, bounds)
    if degradation:
        doc = {"version": 1, "generator": "test", "source": str(src), "seed": 0, "hold": every,
               "effects": ["defocus", "mixres"], "preset": None, "images": entries}  # fmt: skip
        (dst / "degradation.json").write_text(json.dumps(doc))
    return dst


@pytest.fixture
def deblur_scene(synth16, tmp_path) -> Path:
    return make_deblur_scene(synth16, tmp_path / "deblur")


def parse_deblur(data: Path, split: str = "train", **options):
    return DeblurNerfDataParserConfig(data=data, **options).setup().get_dataparser_outputs(split=split)


# --------------------------------------------------------------------------------------------- deblur-nerf-data


def test_degraded_scene_round_trips(deblur_scene, synth16):
    parser = DeblurNerfDataParserConfig(data=deblur_scene).setup()
    train = parser.get_dataparser_outputs("train")
    val = parser.get_dataparser_outputs("val")
    test = parser.get_dataparser_outputs("test")
    all_names = sorted(p.name for p in (synth16 / "images").iterdir())

    assert names_of(train) == [n for n in all_names if n not in TEST_NAMES]
    assert names_of(val) == names_of(test) == TEST_NAMES
    # training views are the blurred files in images/, evaluation views the sharp twins in images_test/
    assert all(Path(f).parent == deblur_scene / "images" for f in train.image_filenames)
    assert all(Path(f).parent == deblur_scene / "images_test" for f in test.image_filenames)
    for f in test.image_filenames:
        np.testing.assert_array_equal(pixels(f), pixels(synth16 / "images" / Path(f).name))
    assert not np.array_equal(pixels(train.image_filenames[0]), pixels(synth16 / "images" / names_of(train)[0]))

    # per-image degradation records, aligned with each split's images
    records = train.metadata["degradations"]
    assert [r["name"] for r in records] == names_of(train)
    assert all(r["degraded"] is True and "defocus" in r["effects"] for r in records)
    assert [r["mixres_factor"] for r in records] == [2 if all_names.index(n) % 3 == 0 else 1 for n in names_of(train)]
    assert [r["name"] for r in test.metadata["degradations"]] == TEST_NAMES
    assert all(r["degraded"] is False and r["ground_truth"] == "images_test" for r in test.metadata["degradations"])
    assert train.metadata["hold"] == 8 and train.metadata["degradation_info"]["effects"] == ["defocus", "mixres"]

    # same world frame for all splits; intrinsics of the synth camera; seed points loaded
    assert torch.equal(train.dataparser_transform, test.dataparser_transform)
    assert train.dataparser_scale == test.dataparser_scale
    K = json.loads((synth16 / "scene.json").read_text())["intrinsics"]
    assert torch.allclose(train.cameras.fx, torch.tensor(K["fx"], dtype=torch.float32))
    assert torch.allclose(test.cameras.cy, torch.tensor(K["cy"], dtype=torch.float32))
    assert train.cameras.width.unique().tolist() == [64] and train.cameras.height.unique().tolist() == [48]
    assert train.metadata["points3D_xyz"].shape == (300, 3) and train.metadata["points3D_rgb"].dtype == torch.uint8


def test_matches_nerfstudio_colmap_normalisation(deblur_scene, synth16):
    """Poses and seed points normalised exactly like the COLMAP reader (nerfstudio's colmap parser) does."""
    ours = parse_deblur(deblur_scene)
    reference = GSMSDRDataParserConfig(data=synth16).setup().get_dataparser_outputs("train")
    assert names_of(reference) == names_of(ours)  # ids are in name order in this model
    torch.testing.assert_close(ours.cameras.camera_to_worlds, reference.cameras.camera_to_worlds)
    torch.testing.assert_close(ours.dataparser_transform, reference.dataparser_transform)
    torch.testing.assert_close(ours.metadata["points3D_xyz"], reference.metadata["points3D_xyz"])


def shuffle_colmap_ids(model: Path, seed: int = 3) -> Dict[str, int]:
    """Rewrite a COLMAP model with image ids permuted relative to the name order; returns name -> new id."""
    cameras, images, points = colmap_io.read_model(str(model), ext=".bin")
    old_ids = sorted(images)
    new_of = dict(zip(old_ids, (np.random.default_rng(seed).permutation(len(old_ids)) + 1).tolist()))
    images = {new_of[i]: im._replace(id=new_of[i]) for i, im in images.items()}
    points = {k: p._replace(image_ids=np.array([new_of[int(i)] for i in p.image_ids])) for k, p in points.items()}
    for file in model.iterdir():
        file.unlink()
    colmap_io.write_model(cameras, images, points, str(model), ext=".bin")
    return {im.name: im.id for im in images.values()}


def test_hold_rule_counts_sorted_file_names_not_colmap_ids(deblur_scene):
    reference = parse_deblur(deblur_scene, "train")
    (deblur_scene / "hold=8").rename(deblur_scene / "hold=5")
    (deblur_scene / "degradation.json").unlink()
    ids = shuffle_colmap_ids(deblur_scene / "sparse" / "0")
    names = sorted(ids)
    by_id = sorted(names, key=ids.get)
    assert by_id != names
    assert [by_id[i] for i in range(0, 16, 5)] != [names[i] for i in range(0, 16, 5)]  # the id rule would differ

    parser = DeblurNerfDataParserConfig(data=deblur_scene).setup()
    test, train = parser.get_dataparser_outputs("test"), parser.get_dataparser_outputs("train")
    assert names_of(test) == ["frame_00000.png", "frame_00005.png", "frame_00010.png", "frame_00015.png"]
    assert len(train.image_filenames) == 12 and not set(names_of(train)) & set(names_of(test))
    # each name keeps its own pose: same normalised poses as the unshuffled model for the shared training views
    pose_of = dict(zip(names_of(reference), reference.cameras.camera_to_worlds))
    for name, pose in zip(names_of(train), train.cameras.camera_to_worlds):
        if name in pose_of:
            torch.testing.assert_close(pose, pose_of[name])


def test_poses_bounds_without_colmap_model(deblur_scene):
    from_colmap = {split: parse_deblur(deblur_scene, split) for split in ("train", "test")}
    shutil.rmtree(deblur_scene / "sparse")
    parser = DeblurNerfDataParserConfig(data=deblur_scene).setup()
    for split, a in from_colmap.items():
        b = parser.get_dataparser_outputs(split)
        assert names_of(a) == names_of(b)
        torch.testing.assert_close(b.cameras.camera_to_worlds, a.cameras.camera_to_worlds, atol=1e-5, rtol=0)
        for attr in ("fx", "fy", "cx", "cy", "width", "height"):
            torch.testing.assert_close(getattr(b.cameras, attr), getattr(a.cameras, attr))
        torch.testing.assert_close(b.dataparser_transform, a.dataparser_transform, atol=1e-5, rtol=0)
        assert b.dataparser_scale == pytest.approx(a.dataparser_scale, rel=1e-6)
        assert a.metadata["pose_source"].endswith("sparse/0") and b.metadata["pose_source"].endswith("poses_bounds.npy")
        assert b.metadata["points3D_xyz"].shape == (0, 3)  # nothing to seed from: random initialisation


def test_llff_axis_convention():
    """LLFF columns are (down, right, backwards): identity rotation in LLFF looks along world -z, x-axis down."""
    llff = np.concatenate([np.eye(3), np.array([[1.0], [2.0], [3.0]])], axis=1)[None]
    c2w = llff_to_opencv(llff)[0]
    np.testing.assert_array_equal(c2w[:3, 0], [0, 1, 0])  # camera right
    np.testing.assert_array_equal(c2w[:3, 1], [1, 0, 0])  # camera down
    np.testing.assert_array_equal(c2w[:3, 2], [0, 0, -1])  # viewing direction
    np.testing.assert_array_equal(c2w[:3, 3], [1, 2, 3])
    np.testing.assert_array_equal(opencv_to_llff(c2w[None]), llff)


def test_images_n_and_camera_size_mismatch_rescale_intrinsics(deblur_scene):
    full = parse_deblur(deblur_scene, "train")
    (deblur_scene / "images_2").mkdir()
    for f in (deblur_scene / "images").iterdir():
        Image.open(f).resize((32, 24), Image.BILINEAR).save(deblur_scene / "images_2" / f.name)
    half = parse_deblur(deblur_scene, "train", downscale_factor=2)
    assert all(Path(f).parent.name == "images_2" for f in half.image_filenames)
    assert half.cameras.width.unique().tolist() == [32]
    for attr in ("fx", "fy", "cx", "cy"):
        torch.testing.assert_close(getattr(half.cameras, attr), getattr(full.cameras, attr) / 2)
    torch.testing.assert_close(half.cameras.camera_to_worlds, full.cameras.camera_to_worlds)

    # a COLMAP camera computed at 128x96 describing 64x48 files: intrinsics follow the files
    model = deblur_scene / "sparse" / "0"
    cameras, images, points = colmap_io.read_model(str(model), ext=".bin")
    cameras = {k: c._replace(width=c.width * 2, height=c.height * 2, params=np.asarray(c.params) * 2)
               for k, c in cameras.items()}  # fmt: skip
    colmap_io.write_model(cameras, images, points, str(model), ext=".bin")
    rescaled = parse_deblur(deblur_scene, "train")
    for attr in ("fx", "fy", "cx", "cy", "width", "height"):
        torch.testing.assert_close(getattr(rescaled.cameras, attr), getattr(full.cameras, attr))

    # a file that is not a rescaled copy of what the camera describes is an error naming it
    bad = deblur_scene / "images" / "frame_00001.png"
    Image.open(bad).resize((64, 64)).save(bad)
    with pytest.raises(InputError, match=rf"image file '{bad}' is 64x64 px but its camera is 128x96 px"):
        parse_deblur(deblur_scene, "train")


def test_missing_hold_file_defaults_to_8_with_warning(synth16, tmp_path):
    scene = make_deblur_scene(synth16, tmp_path / "s", hold=None, degradation=False)
    with pytest.warns(InputWarning, match=r"no 'hold=N' file .* every 8th view"):
        outputs = parse_deblur(scene, "test")
    assert names_of(outputs) == TEST_NAMES
    with pytest.warns(InputWarning):
        records = parse_deblur(scene, "train").metadata["degradations"]
    assert all(r["degraded"] is None and r["mixres_factor"] is None for r in records)  # no degradation.json


def test_degradation_json_names_the_hold_when_the_file_is_missing(synth16, tmp_path):
    scene = make_deblur_scene(synth16, tmp_path / "s", hold=None)  # degradation.json says hold 8
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputWarning)
        assert names_of(parse_deblur(scene, "test")) == TEST_NAMES


def test_degradation_json_that_contradicts_the_hold_is_an_error(deblur_scene):
    (deblur_scene / "hold=8").rename(deblur_scene / "hold=4")
    with pytest.raises(InputError, match=r"holdout interval .* is 4 .*degradation.json' says hold 8"):
        parse_deblur(deblur_scene)
    doc = json.loads((deblur_scene / "degradation.json").read_text())
    del doc["hold"]
    (deblur_scene / "degradation.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"puts image 'frame_00004.png' .* in the train split, but hold=4"):
        parse_deblur(deblur_scene)


def test_gsmsdr_degrade_output_round_trips(synth16, tmp_path):
    """The shared contract: what gsmsdr-degrade writes, deblur-nerf-data (via gsmsdr-data) reads back."""
    from gsmsdr_ns.degrade import DegradeConfig, degrade_scene

    scene = degrade_scene(synth16, tmp_path / "degraded", DegradeConfig(effects=("motion", "mixres")))
    doc = json.loads((scene / "degradation.json").read_text())
    parser = GSMSDRAutoDataParserConfig(data=scene).setup()
    train, test = parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")
    assert isinstance(parser.delegate, DeblurNerfDataParser)
    assert names_of(test) == TEST_NAMES and len(train.image_filenames) == NUM_VIEWS - 2
    for f in test.image_filenames:
        assert Path(f).parent.name == "images_test"
        np.testing.assert_array_equal(pixels(f), pixels(synth16 / "images" / Path(f).name))
    for record in train.metadata["degradations"]:
        entry = doc["images"][record["name"]]
        assert record["degraded"] is True and set(record["effects"]) == {"motion", "mixres"}
        assert record["mixres_factor"] == entry["effects"]["mixres"]["factor"]
    factors = [r["mixres_factor"] for r in train.metadata["degradations"]]
    assert sorted(np.bincount(factors, minlength=5)[1:].tolist()) == [3, 3, 4, 4]
    # its poses_bounds.npy describes the same cameras as its COLMAP model
    llff = DeblurNerfDataParserConfig(data=scene, pose_source="poses_bounds").setup()
    torch.testing.assert_close(
        llff.get_dataparser_outputs("train").cameras.camera_to_worlds, train.cameras.camera_to_worlds, atol=1e-5, rtol=0
    )


# ---------------------------------------------------------------------------------------------- bad input


def _remove_sparse_and_poses_bounds(scene: Path) -> Path:
    shutil.rmtree(scene / "sparse")
    (scene / "poses_bounds.npy").unlink()
    return scene


def _extra_image_with_poses_bounds(scene: Path) -> Path:
    shutil.rmtree(scene / "sparse")
    shutil.copy(scene / "images" / "frame_00003.png", scene / "images" / "frame_00016.png")
    return scene


def _extra_image_with_colmap(scene: Path) -> Path:
    shutil.copy(scene / "images" / "frame_00003.png", scene / "images" / "extra.png")
    return scene


def _delete(name: str):
    def edit(scene: Path) -> Path:
        (scene / "images" / name).unlink()
        return scene

    return edit


def _overwrite(name: str, content):
    def edit(scene: Path) -> Path:
        path = scene / "images" / name
        path.write_bytes(content(path.read_bytes()))
        return scene

    return edit


def _hold(text: str):
    def edit(scene: Path) -> Path:
        (scene / "hold=8").rename(scene / f"hold={text}")
        (scene / "degradation.json").unlink()
        return scene

    return edit


BAD_INPUT = {  # case: (edit of a valid scene, the error it must give)
    "no sparse/0 and no poses_bounds.npy": (
        _remove_sparse_and_poses_bounds,
        r"no camera poses: no COLMAP model in '.*sparse/0' .* and no '.*poses_bounds.npy'",
    ),
    "image count does not match poses_bounds.npy": (
        _extra_image_with_poses_bounds,
        r"poses_bounds.npy' has poses for 16 images but the image folder has 17",
    ),
    "image on disk without a COLMAP pose": (
        _extra_image_with_colmap,
        r"images' has 17 images but '.*sparse/0' has poses for 16; without a pose: \['extra.png'\]",
    ),
    "image listed but missing": (
        _delete("frame_00003.png"),
        r"image 'frame_00003.png' is listed in the COLMAP model '.*' but '.*frame_00003.png' does not exist",
    ),
    "corrupted image file": (
        _overwrite("frame_00003.png", lambda data: b"not an image" + data[:20]),
        r"cannot read image file '.*frame_00003.png'",
    ),
    "truncated image file": (
        _overwrite("frame_00003.png", lambda data: data[: len(data) // 2]),
        r"cannot read image file '.*frame_00003.png'.*truncated",
    ),
    "zero-size image file": (
        _overwrite("frame_00003.png", lambda data: b""),
        r"image file '.*frame_00003.png' is empty \(0 bytes\)",
    ),
    "hold=0": (_hold("0"), r"'.*hold=0' sets the holdout interval to 0; it must be >= 1"),
    "hold=abc": (_hold("abc"), r"'abc' is not an integer"),
    "hold=1 leaves no training views": (_hold("1"), r"the train split of .* is empty: 16 views with hold=1"),
}


@pytest.mark.parametrize("case", list(BAD_INPUT), ids=list(BAD_INPUT))
def test_bad_input_gives_a_clear_error(case, synth16, tmp_path):
    edit, message = BAD_INPUT[case]
    scene = edit(make_deblur_scene(synth16, tmp_path / "s"))
    with pytest.raises(InputError, match=message):
        parse_deblur(scene, "train")


def test_missing_sharp_twin_is_named(deblur_scene):
    (deblur_scene / "images_test" / "frame_00008.png").unlink()
    with pytest.raises(InputError, match=r"image 'frame_00008.png' is listed in .*sharp twin.* does not exist"):
        parse_deblur(deblur_scene, "test")


# ---------------------------------------------------------------------------------------------------- mixres-data


def parse_mixres(data: Path, split: str = "train", **options):
    return MixresDataParserConfig(data=data, **options).setup().get_dataparser_outputs(split=split)


@pytest.fixture
def colmap_scene(synth16, tmp_path) -> Path:
    return Path(shutil.copytree(synth16, tmp_path / "mip360"))


def test_mixres_four_way_split_is_seeded(colmap_scene):
    train = parse_mixres(colmap_scene, seed=0)
    test = parse_mixres(colmap_scene, "test", seed=0)
    assert names_of(test) == TEST_NAMES
    assert all(Path(f).parent == colmap_scene / "images" for f in test.image_filenames)  # untouched originals
    assert [r["mixres_factor"] for r in test.metadata["degradations"]] == [1, 1]

    records = train.metadata["degradations"]
    factors = [r["mixres_factor"] for r in records]
    all_names = sorted(os.listdir(colmap_scene / "images"))
    assert [r["name"] for r in records] == [n for n in all_names if n not in TEST_NAMES]
    assert sorted(np.bincount(factors, minlength=5)[1:].tolist()) == [3, 3, 4, 4]  # 14 views in 4 equal groups
    assert all(r["effects"] == {"mixres": {"factor": r["mixres_factor"]}} for r in records)
    assert all(r["degraded"] == (r["mixres_factor"] > 1) for r in records)
    assert factors == assign_mixres_factors(14, 0).tolist()
    # full-size training images; same cameras as the originals
    assert train.cameras.width.unique().tolist() == [64] and train.cameras.height.unique().tolist() == [48]

    again = [r["mixres_factor"] for r in parse_mixres(colmap_scene, seed=0).metadata["degradations"]]
    other = [r["mixres_factor"] for r in parse_mixres(colmap_scene, seed=1).metadata["degradations"]]
    assert again == factors and other != factors
    assert (colmap_scene / ".gsmsdr_cache" / "mixres_seed1" / "manifest.json").is_file()


def test_mixres_images_are_downscaled_and_upsampled(colmap_scene):
    train = parse_mixres(colmap_scene)
    for path, record in zip(train.image_filenames, train.metadata["degradations"]):
        original = pixels(colmap_scene / "images" / record["name"])
        image = pixels(path)
        assert image.shape == original.shape
        if record["mixres_factor"] == 1:
            assert Path(path) == colmap_scene / "images" / record["name"]
        else:
            assert Path(path).parent == colmap_scene / ".gsmsdr_cache" / "mixres_seed0"
            np.testing.assert_array_equal(image, downscale_upscale(original, record["mixres_factor"]))
    # stronger downscaling loses more detail (high-frequency energy)
    img = pixels(colmap_scene / "images" / "frame_00001.png")

    def detail(image):
        return np.abs(np.diff(image.astype(np.float64), axis=1)).mean()

    energy = [detail(downscale_upscale(img, f)) for f in MIXRES_FACTORS]
    assert energy[0] < energy[1] < energy[2] < energy[3] == pytest.approx(detail(img))


def test_mixres_cache_is_reused_and_rebuilt_when_stale(colmap_scene, capsys):
    first = parse_mixres(colmap_scene)
    cache = colmap_scene / ".gsmsdr_cache" / "mixres_seed0"
    produced = sorted(cache.glob("*.png"))
    assert len(produced) == sum(r["mixres_factor"] > 1 for r in first.metadata["degradations"])
    stamps = {p: p.stat().st_mtime_ns for p in produced}
    assert "building the mixed-resolution cache" in capsys.readouterr().out

    second = parse_mixres(colmap_scene)
    assert "reusing the mixed-resolution cache" in capsys.readouterr().out
    assert second.image_filenames == first.image_filenames
    assert {p: p.stat().st_mtime_ns for p in sorted(cache.glob("*.png"))} == stamps
    assert not [p for p in cache.parent.iterdir() if p.name != "mixres_seed0"]  # no temp dirs left behind

    produced[0].write_bytes(produced[0].read_bytes()[:50])  # a damaged cached file invalidates the cache
    parse_mixres(colmap_scene)
    assert "building the mixed-resolution cache" in capsys.readouterr().out
    source = colmap_scene / "images" / "frame_00002.png"  # so does a changed source image
    Image.fromarray(255 - pixels(source)).save(source)
    parse_mixres(colmap_scene)
    assert "building the mixed-resolution cache" in capsys.readouterr().out
    assert sorted(p.name for p in cache.parent.iterdir()) == ["mixres_seed0"]


def test_mixres_cache_path_option(colmap_scene, tmp_path):
    elsewhere = tmp_path / "cache"
    first = parse_mixres(colmap_scene, seed=2, cache_path=elsewhere)
    assert not (colmap_scene / ".gsmsdr_cache").exists()
    assert (elsewhere / "mixres_seed2" / "manifest.json").is_file()
    assert first.metadata["mixres_cache"] == str(elsewhere / "mixres_seed2")


# ----------------------------------------------------------------------------------------------------- gsmsdr-data


def make_layout(kind: str, synth16: Path, root: Path) -> Path:
    scene = root / kind
    if kind == "deblur-hold":
        return make_deblur_scene(synth16, scene, twins=False, degradation=False, poses_bounds=False)
    if kind == "deblur-images_test":
        return make_deblur_scene(synth16, scene, hold=None, degradation=False, poses_bounds=False)
    if kind == "deblur-degradation.json":
        return make_deblur_scene(synth16, scene, hold=None, twins=False, poses_bounds=False)
    if kind == "llff":
        return make_deblur_scene(synth16, scene, hold=None, twins=False, degradation=False, colmap=False)
    if kind == "colmap-sparse":
        return Path(shutil.copytree(synth16, scene))
    if kind == "ns-process-data":
        write_transforms_json(synth16, scene)
        shutil.copytree(synth16 / "sparse", scene / "colmap" / "sparse")
        return scene
    if kind == "colmap-colmap":
        shutil.copytree(synth16 / "images", scene / "images")
        shutil.copytree(synth16 / "sparse", scene / "colmap" / "sparse")
        return scene
    raise ValueError(kind)


LAYOUTS = {
    "deblur-hold": ("deblur-nerf-data", "found hold=8", DeblurNerfDataParser),
    "deblur-images_test": ("deblur-nerf-data", "found images_test/", DeblurNerfDataParser),
    "deblur-degradation.json": ("deblur-nerf-data", "found degradation.json", DeblurNerfDataParser),
    "llff": ("deblur-nerf-data", "found poses_bounds.npy and no COLMAP model", DeblurNerfDataParser),
    "colmap-sparse": ("colmap", "found sparse/0", GSMSDRDataParser),
    "ns-process-data": ("nerfstudio-data", "found transforms.json", None),
    "colmap-colmap": ("colmap", "found colmap/sparse/0", GSMSDRDataParser),
}


@pytest.mark.parametrize("kind", list(LAYOUTS))
def test_auto_detection_picks_the_reader_and_says_why(kind, synth16, tmp_path, capsys):
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio

    scene = make_layout(kind, synth16, tmp_path)
    reader, reason, parser_type = LAYOUTS[kind]
    parser = GSMSDRAutoDataParserConfig(data=scene).setup()
    assert isinstance(parser, GSMSDRAutoDataParser)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        train = parser.get_dataparser_outputs("train")
        test = parser.get_dataparser_outputs("test")
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("gsmsdr-data:")]
    assert lines[0] == f"gsmsdr-data: reading '{scene}' with {reader} ({lines[0].split('(', 1)[1]}"
    assert all("estimated from the photos" in line for line in lines[1:]) and len(lines) <= 2, lines
    assert reason in lines[0]
    assert isinstance(parser.delegate, parser_type or Nerfstudio)
    assert len(train.image_filenames) + len(test.image_filenames) == NUM_VIEWS
    if reader == "deblur-nerf-data":
        assert names_of(test) == TEST_NAMES


def test_transforms_json_scene_reads_back_through_gsmsdr_data(synth16, tmp_path):
    scene = write_transforms_json(synth16, tmp_path / "ns")
    outputs = GSMSDRAutoDataParserConfig(data=scene).setup().get_dataparser_outputs("train")
    reference = DeblurNerfDataParserConfig(data=synth16, orientation_method="none", center_method="none",
                                           auto_scale_poses=False).setup()  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        reference.get_dataparser_outputs("train")
    scene_cams = reference.load_scene().cameras
    index = {name: i for i, name in enumerate(scene_cams.names)}
    rows = [index[n] for n in names_of(outputs)]
    assert len(rows) >= 12
    fx = torch.tensor(scene_cams.intrinsics[rows, 0], dtype=torch.float32)
    torch.testing.assert_close(outputs.cameras.fx[:, 0], fx)
    # camera centres agree up to nerfstudio's similarity normalisation: compare pairwise distances
    ours = outputs.cameras.camera_to_worlds[:, :3, 3].double()
    truth = torch.from_numpy(scene_cams.c2w[rows, :3, 3])
    d_ours, d_truth = torch.cdist(ours, ours), torch.cdist(truth, truth)
    torch.testing.assert_close(d_ours / d_ours.max(), d_truth / d_truth.max(), atol=1e-5, rtol=0)


def test_unknown_layout_lists_what_was_looked_for(tmp_path):
    (tmp_path / "photos").mkdir()
    with pytest.raises(InputError, match=r"cannot tell what kind of scene .*Looked for: a Deblur-NeRF scene .*"
                       r"sparse/0 or colmap/sparse/0.*transforms.json.*poses_bounds.npy.*Found: photos/"):  # fmt: skip
        GSMSDRAutoDataParserConfig(data=tmp_path).setup().get_dataparser_outputs("train")
    (tmp_path / "x.json").write_text("{}")
    assert detect_layout(tmp_path / "x.json").reader == "nerfstudio-data"


# ------------------------------------------------------------------------------------- the real trainer and ns-eval

E2E_STEPS = 20


def train_and_eval(scene: Path, dataparser: str, work: Path) -> dict:
    """``ns-train gsmsdr ... <dataparser>`` for a few CPU steps, then ``ns-eval`` with rendered images kept."""
    out = work / "outputs"
    proc = run_cli(
        "ns-train",
        [
            "gsmsdr",
            "--data",
            scene,
            "--output-dir",
            out,
            "--timestamp",
            "run",
            "--max-num-iterations",
            E2E_STEPS,
            "--steps-per-save",
            E2E_STEPS,
            *TRAIN_FLAGS,
            dataparser,
        ],  # fmt: skip
        cwd=work,
    )
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"ns-train failed (exit {proc.returncode}):\n{log[-5000:]}"
    config = out / scene.name / "gsmsdr" / "run" / "config.yml"
    proc = run_cli(
        "ns-eval",
        ["--load-config", config, "--output-path", work / "eval.json", "--render-output-path", work / "renders"],
        cwd=work,
    )
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-5000:]
    return {"log": log, "report": json.loads((work / "eval.json").read_text()), "renders": work / "renders"}


def ground_truth_halves(renders: Path, width: int):
    """splatfacto's eval image is [ground truth | render] side by side: the ground-truth halves, in eval order."""
    return [pixels(p)[:, :width] for p in sorted(renders.glob("eval_img_*.png"))]


@pytest.fixture(scope="module")
def e2e_runs(synth16, tmp_path_factory) -> Dict[str, dict]:
    """``ns-train`` then ``ns-eval`` on a degraded Deblur-NeRF scene and under the mixres protocol, the two at once
    (each is mostly interpreter and nerfstudio start-up)."""
    degraded = make_deblur_scene(synth16, tmp_path_factory.mktemp("e2e-deblur") / "blurry")
    for name in TEST_NAMES:  # make images/ differ from the twins: ns-eval must measure against images_test/
        Image.fromarray(255 - pixels(degraded / "images" / name)).save(degraded / "images" / name)
    mixres = Path(shutil.copytree(synth16, tmp_path_factory.mktemp("e2e-mixres") / "mip360"))
    jobs = {"deblur-nerf-data": degraded, "mixres-data": mixres}
    with ThreadPoolExecutor(max_workers=2) as pool:
        futures = {name: pool.submit(train_and_eval, scene, name, scene.parent) for name, scene in jobs.items()}
        return {name: {**future.result(), "scene": jobs[name]} for name, future in futures.items()}


def test_ns_train_and_eval_on_a_degraded_scene(e2e_runs):
    run = e2e_runs["deblur-nerf-data"]
    scene = run["scene"]
    results = run["report"]["results"]
    assert run["report"]["method_name"] == "gsmsdr" and 5.0 < results["psnr"] < 60.0 and 0 < results["ssim"] <= 1
    truth = ground_truth_halves(run["renders"], 64)
    assert len(truth) == len(TEST_NAMES)
    for image, name in zip(truth, TEST_NAMES):
        np.testing.assert_allclose(image.astype(int), pixels(scene / "images_test" / name).astype(int), atol=1)


def test_ns_train_and_eval_under_the_mixres_protocol(e2e_runs):
    run = e2e_runs["mixres-data"]
    scene = run["scene"]
    assert "mixed-resolution training views (seed 0)" in run["log"]
    assert (scene / ".gsmsdr_cache" / "mixres_seed0" / "manifest.json").is_file()
    assert 5.0 < run["report"]["results"]["psnr"] < 60.0
    truth = ground_truth_halves(run["renders"], 64)
    for image, name in zip(truth, TEST_NAMES, strict=True):  # full-resolution untouched originals
        np.testing.assert_allclose(image.astype(int), pixels(scene / "images" / name).astype(int), atol=1)
