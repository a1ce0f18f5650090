"""The dataparser's estimate judges the full-size copies of the training images when training reads a downscaled
``images_N/`` folder (real fern photos, a few blurred on disk, and their 2x smaller copies)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from conftest import shaken_photo, shared_fern
from PIL import Image

from gsmsdr_ns.io.images import write_image
from gsmsdr_ns.plugin.auto_dataparser import GSMSDRAutoDataParserConfig, estimate_folder

SHAKEN = ("image004.png", "image011.png", "image014.png")


def _scene(root: Path) -> Path:
    fern = shared_fern()
    scene = root / "scene"
    shutil.copytree(fern / "images_8", scene / "images")
    shutil.copy(fern / "poses_bounds.npy", scene / "poses_bounds.npy")
    (scene / "images_2").mkdir()
    for name in sorted(p.name for p in (scene / "images").iterdir()):
        if name in SHAKEN:
            write_image(scene / "images" / name, shaken_photo(scene / "images" / name, 16.0, samples=33))
        with Image.open(scene / "images" / name) as image:
            half = image.resize((image.width // 2, image.height // 2), Image.Resampling.LANCZOS)
            half.save(scene / "images_2" / name)
    return scene


def test_estimate_reads_the_full_size_copies_of_downscaled_training_images(tmp_path):
    scene = _scene(tmp_path)
    names = sorted(p.name for p in (scene / "images_2").iterdir())
    assert estimate_folder(scene / "images_2", names) == scene / "images"
    assert estimate_folder(scene / "images", names) == scene / "images"
    assert estimate_folder(scene / "images_2", [*names, "missing.png"]) == scene / "images_2"  # not all there

    config = GSMSDRAutoDataParserConfig(data=scene)
    config.deblur.downscale_factor = 2
    outputs = config.setup().get_dataparser_outputs("train")
    assert {Path(f).parent.name for f in outputs.image_filenames} == {"images_2"}  # training reads the small copies
    cache = json.loads((scene / "degradation.estimated.json").read_text(encoding="utf8"))
    assert Path(cache["source"]) == scene / "images"
    by_name = {r["name"]: r for r in outputs.metadata["degradations"]}
    for name in SHAKEN:
        assert by_name[name]["degraded"] is True, by_name[name]
    assert sum(r["degraded"] is False for r in by_name.values()) >= len(by_name) - len(SHAKEN) - 1
