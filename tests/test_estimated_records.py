"""``gsmsdr-data`` on a scene without degradation records: the real fern photos (LLFF poses), a few of them blurred
on disk; the dataparser estimates a record per training image, so only the degraded photos get a degradation model."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import shaken_photo, shared_fern

from gsmsdr_ns.blur.profile import training_profiles
from gsmsdr_ns.degrade.kernels import disk_blur
from gsmsdr_ns.io.images import read_image, write_image

MOTION = ("image003.png", "image010.png", "image013.png")
DEFOCUS = ("image005.png", "image017.png")


def _blurred(path: Path, effect: str) -> np.ndarray:
    if effect == "motion":
        return shaken_photo(path, 12.0)
    image = torch.from_numpy(read_image(path)[..., :3].astype(np.float32) / 255.0).permute(2, 0, 1)[None]
    image = disk_blur(image, 4.0)
    return (image[0].permute(1, 2, 0).clamp(0, 1).numpy() * 255).round().astype(np.uint8)


@pytest.fixture(scope="module")
def fern_with_blurred_photos(tmp_path_factory) -> Path:
    fern = shared_fern()
    scene = tmp_path_factory.mktemp("fern") / "scene"
    shutil.copytree(fern / "images_8", scene / "images")
    shutil.copy(fern / "poses_bounds.npy", scene / "poses_bounds.npy")
    for name in MOTION:
        write_image(scene / "images" / name, _blurred(scene / "images" / name, "motion"))
    for name in DEFOCUS:
        write_image(scene / "images" / name, _blurred(scene / "images" / name, "defocus"))
    return scene


def _train_outputs(scene: Path, **overrides):
    from gsmsdr_ns.plugin.auto_dataparser import GSMSDRAutoDataParserConfig

    return GSMSDRAutoDataParserConfig(data=scene, **overrides).setup().get_dataparser_outputs("train")


def test_unrecorded_scene_gets_estimated_records_and_only_degraded_images_get_a_model(fern_with_blurred_photos):
    outputs = _train_outputs(fern_with_blurred_photos)
    records = outputs.metadata["degradations"]
    names = [Path(f).name for f in outputs.image_filenames]
    assert [r["name"] for r in records] == names
    blurred = set(MOTION + DEFOCUS)
    by_name = {r["name"]: r for r in records}
    for name in names:
        if name in blurred:
            assert by_name[name]["degraded"] is True, by_name[name]
            assert {"motion", "defocus"} & set(by_name[name]["effects"]), by_name[name]
        else:
            assert by_name[name]["degraded"] is False, by_name[name]
    assert by_name["image003.png"]["effects"].keys() >= {"motion"}
    assert (fern_with_blurred_photos / "degradation.estimated.json").is_file()

    profiles = training_profiles("auto", outputs.metadata, len(records))
    for name, profile in zip(names, profiles):
        assert profile.is_sharp == (name not in blurred), (name, profile)
        assert profile.needs_blur_field == (name in blurred), (name, profile)


def test_estimation_can_be_switched_off(fern_with_blurred_photos):
    records = _train_outputs(fern_with_blurred_photos, estimate_degradations=False).metadata["degradations"]
    assert all(r["degraded"] is None for r in records)
