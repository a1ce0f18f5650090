"""Images deeper than 8 bits train on what is in the file: 16-bit PNGs (RGB and grey) and float TIFFs are scaled to
8 bits, not truncated to their low byte (nerfstudio's own loader keeps ``v & 0xFF`` of a 16-bit value); palette
PNGs give their colours; floats outside [0, 1] are refused naming the file."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import skimage.io
from PIL import Image

from gsmsdr_ns.io.errors import InputError
from gsmsdr_ns.io.images import read_image


def _scaled(v16: np.ndarray) -> np.ndarray:
    return np.round(v16.astype(np.float64) * 255.0 / 65535.0).astype(np.uint8)


def _write16(path: Path, rgb16: np.ndarray) -> None:
    """A 16-bit RGB PNG (OpenCV writes BGR)."""
    import cv2

    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb16[..., ::-1]))


def _read16(path: Path) -> np.ndarray:
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image.dtype == np.uint16
    return image[..., ::-1]


def _deep(image8: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A 16-bit version of an 8-bit image whose low bytes are noise (not a copy of the high bytes)."""
    return image8.astype(np.uint16) * 256 + rng.integers(0, 256, image8.shape, dtype=np.uint16)


@pytest.fixture(scope="module")
def deep_scene(tiny_scene: Path, tmp_path_factory) -> Path:
    """The tiny scene with every image rewritten as a 16-bit RGB PNG (same names)."""
    scene = tmp_path_factory.mktemp("deep") / "scene"
    shutil.copytree(tiny_scene, scene)
    rng = np.random.default_rng(0)
    for path in sorted((scene / "images").iterdir()):
        _write16(path, _deep(np.asarray(Image.open(path).convert("RGB")), rng))
    return scene


def test_16_bit_pngs_are_scaled_not_truncated(tmp_path):
    rng = np.random.default_rng(1)
    rgb = _deep(rng.integers(0, 256, (12, 16, 3), dtype=np.uint8), rng)
    _write16(tmp_path / "rgb.png", rgb)
    grey = _deep(rng.integers(0, 256, (12, 16), dtype=np.uint8), rng)
    Image.fromarray(grey).save(tmp_path / "grey.png")  # PIL mode I;16
    assert np.array(Image.open(tmp_path / "grey.png")).dtype == np.uint16
    decoded = read_image(tmp_path / "rgb.png")
    assert decoded.dtype == np.uint8 and np.array_equal(decoded, _scaled(rgb))
    assert not np.array_equal(decoded, (rgb & 0xFF).astype(np.uint8))  # what a truncating loader trains on
    assert not np.array_equal(decoded, (rgb >> 8).astype(np.uint8))  # Pillow's 8-bit reduction: rounded instead
    grey_decoded = read_image(tmp_path / "grey.png")
    assert grey_decoded.shape == (12, 16, 3) and np.array_equal(grey_decoded[..., 1], _scaled(grey))


def test_float_tiffs_in_0_1_are_scaled_and_the_others_refused_naming_the_file(tmp_path):
    rng = np.random.default_rng(2)
    grey = rng.random((10, 14)).astype(np.float32)
    Image.fromarray(grey, mode="F").save(tmp_path / "ok.tif")  # what Pillow (nerfstudio's loader) can open
    assert np.array_equal(read_image(tmp_path / "ok.tif")[..., 0], np.round(grey * 255).astype(np.uint8))
    Image.fromarray(grey * 4.0, mode="F").save(tmp_path / "hdr.tif")
    with pytest.raises(InputError, match=r"image file '.*hdr.tif' holds floating-point values outside \[0, 1\]"):
        read_image(tmp_path / "hdr.tif")
    skimage.io.imsave(tmp_path / "rgb.tif", rng.random((10, 14, 3)).astype(np.float32), check_contrast=False)
    with pytest.raises(InputError, match=r"cannot read image file '.*rgb.tif'"):  # no decoder of Pillow's reads it
        read_image(tmp_path / "rgb.tif")


def test_palette_pngs_give_their_colours(tmp_path):
    rgb = np.zeros((8, 8, 3), np.uint8)
    rgb[:4] = (200, 30, 10)
    rgb[4:] = (5, 90, 250)
    Image.fromarray(rgb).convert("P", palette=Image.Palette.ADAPTIVE, colors=4).save(tmp_path / "p.png")
    assert Image.open(tmp_path / "p.png").mode == "P"
    assert np.array_equal(read_image(tmp_path / "p.png")[..., :3], rgb)


def test_the_training_datamanager_reads_16_bit_scenes_at_their_depth(deep_scene: Path):
    """What nerfstudio's trainer caches for training and evaluation: the scaled image, for every view."""
    from gsmsdr_ns.plugin.auto_dataparser import GSMSDRAutoDataParserConfig
    from gsmsdr_ns.plugin.datamanager import GSMSDRDatamanagerConfig, GSMSDRInputDataset

    config = GSMSDRDatamanagerConfig(
        dataparser=GSMSDRAutoDataParserConfig(data=deep_scene, estimate_degradations=False),
        cache_images="gpu",
        cache_images_type="uint8",  # as the presets cache them
    )
    config.data = deep_scene
    datamanager = config.setup(device="cpu")
    for dataset in (datamanager.train_dataset, datamanager.eval_dataset):
        assert isinstance(dataset, GSMSDRInputDataset)
        for index in range(len(dataset)):
            path = dataset._dataparser_outputs.image_filenames[index]
            expected = _scaled(_read16(path))
            assert np.array_equal(dataset.get_numpy_image(index), expected), path
    cached = datamanager.cached_train[0]["image"]  # what training steps read
    path = datamanager.train_dataset._dataparser_outputs.image_filenames[0]
    assert np.array_equal(cached.cpu().numpy(), _scaled(_read16(path)))


def test_cmyk_and_grey_alpha_images_become_rgb(tmp_path):
    """A CMYK JPEG's four channels would pass for RGBA (nerfstudio's loader takes them so); grey + alpha has two."""
    rgb = np.zeros((8, 8, 3), np.uint8)
    rgb[:4] = (200, 30, 10)
    rgb[4:] = (5, 90, 250)
    Image.fromarray(rgb).convert("CMYK").save(tmp_path / "cmyk.jpg", quality=100)
    assert Image.open(tmp_path / "cmyk.jpg").mode == "CMYK"
    decoded = read_image(tmp_path / "cmyk.jpg")
    assert decoded.shape == (8, 8, 3) and np.abs(decoded.astype(int) - rgb).max() <= 8  # JPEG's rounding
    grey = np.arange(64, dtype=np.uint8).reshape(8, 8) * 4
    Image.fromarray(grey).convert("LA").save(tmp_path / "la.png")
    decoded = read_image(tmp_path / "la.png")
    assert decoded.shape == (8, 8, 4) and np.array_equal(decoded[..., 0], grey) and (decoded[..., 3] == 255).all()
