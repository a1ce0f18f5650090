"""Bad input gives a clear error naming the file or value (or, for an empty point cloud, a warning)."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli
from nerfstudio.data.utils import colmap_parsing_utils as colmap_io
from PIL import Image

from gsmsdr_ns.io.errors import InputError
from gsmsdr_ns.plugin.dataparser import GSMSDRDataParserConfig
from gsmsdr_ns.plugin.method_config import gsmsdr_trainer_config
from gsmsdr_ns.plugin.model import GSMSDRWarning


@pytest.fixture
def scene(tiny_scene: Path, tmp_path: Path) -> Path:
    """A private copy of the tiny scene that the test may corrupt."""
    return Path(shutil.copytree(tiny_scene, tmp_path / "scene"))


def parse(data: Path, split: str = "train"):
    return GSMSDRDataParserConfig(data=data).setup().get_dataparser_outputs(split=split)


def first_image(scene: Path) -> Path:
    return sorted((scene / "images").iterdir())[1]  # view 1 is a training view (0 and 8 are eval views)


def rewrite_model_as_text(scene: Path, edit_images=None, edit_points=None) -> None:
    """Re-write sparse/0 in COLMAP's text format, optionally editing images / points on the way."""
    model = scene / "sparse" / "0"
    cameras, images, points = colmap_io.read_model(str(model), ext=".bin")
    images = edit_images(images) if edit_images else images
    points = edit_points(points) if edit_points else points
    for file in model.iterdir():
        file.unlink()
    colmap_io.write_model(cameras, images, points, str(model), ext=".txt")


def test_valid_scene_parses(tiny_scene):
    outputs = parse(tiny_scene)
    assert len(outputs.image_filenames) == 8
    assert outputs.metadata["points3D_xyz"].shape[0] > 0


def test_missing_data_path(tmp_path):
    missing = tmp_path / "no-such-scene"
    with pytest.raises(InputError, match=rf"'{missing}' does not exist.*--data"):
        parse(missing)


def test_directory_without_colmap_model(tmp_path):
    (tmp_path / "images").mkdir()
    with pytest.raises(InputError, match=r"no COLMAP model in '.*sparse/0'"):
        parse(tmp_path)


def test_truncated_image_names_the_file(scene):
    image = first_image(scene)
    data = image.read_bytes()
    image.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=rf"cannot read image file '{image}'.*truncated"):
        parse(scene)


def test_unreadable_image_names_the_file(scene):
    image = first_image(scene)
    image.write_bytes(b"this is not a png")
    with pytest.raises(InputError, match=rf"cannot read image file '{image}'"):
        parse(scene)


def test_missing_image_names_the_file(scene):
    image = first_image(scene)
    image.unlink()
    with pytest.raises(InputError, match=rf"'{image}' is listed in the COLMAP model but does not exist"):
        parse(scene)


def test_image_size_differs_from_camera(scene):
    image = first_image(scene)
    Image.open(image).resize((32, 24)).save(image)
    with pytest.raises(InputError, match=rf"'{image}' is 32x24 px but its COLMAP camera says 64x48 px"):
        parse(scene)


@pytest.mark.parametrize("field", ["qvec", "tvec", "zero-qvec"])
def test_non_finite_camera_pose_names_the_image(scene, field):
    def corrupt(images):
        image_id = sorted(images)[2]
        image = images[image_id]
        if field == "zero-qvec":
            images[image_id] = image._replace(qvec=np.zeros(4))
        else:
            value = getattr(image, field).copy()
            value[0] = np.nan if field == "qvec" else np.inf
            images[image_id] = image._replace(**{field: value})
        return images

    rewrite_model_as_text(scene, edit_images=corrupt)
    name = sorted((scene / "images").iterdir())[2].name
    with pytest.raises(InputError, match=rf"image '{name}' .* non-finite or degenerate camera pose"):
        parse(scene)


@pytest.mark.parametrize("how", ["empty", "missing"])
def test_empty_point_cloud_initialises_randomly_with_warning(scene, how):
    if how == "empty":
        rewrite_model_as_text(scene, edit_points=lambda points: {})
    else:
        (scene / "sparse" / "0" / "points3D.bin").unlink()
    config = gsmsdr_trainer_config()
    config.pipeline.datamanager.data = scene
    config.pipeline.model.num_random = 321
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pipeline = config.pipeline.setup(device="cpu", test_mode="val")
    messages = [str(w.message) for w in caught if issubclass(w.category, GSMSDRWarning)]
    assert any("0 usable points" in m and "321 random Gaussians" in m for m in messages), messages
    assert pipeline.model.num_points == 321


def test_ns_train_reports_a_truncated_image_by_name(scene, tmp_path):
    """Through the real CLI: the error reaches the user, names the file, and nothing trains."""
    image = first_image(scene)
    image.write_bytes(image.read_bytes()[:200])
    args = [
        "gsmsdr",
        "--data",
        scene,
        "--output-dir",
        tmp_path / "out",
        "--vis",
        "tensorboard",
        "--max-num-iterations",
        5,
    ]
    proc = run_cli("ns-train", args, cwd=tmp_path)
    assert proc.returncode != 0
    assert f"InputError: gsmsdr: cannot read image file '{image}'" in proc.stderr
    assert not list((tmp_path / "out").rglob("*.ckpt"))
