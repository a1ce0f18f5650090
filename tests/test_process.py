"""``gsmsdr-process`` on real photos: the LLFF fern poses recovered by pycolmap SfM, the clear failure on unrelated
photos, and the written scene trained by ``ns-train``."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import TRAIN_FLAGS, run_cli, shared_fern

from gsmsdr_ns.bench.sfm import llff_cameras_opencv, pose_errors
from gsmsdr_ns.data.layout import detect_layout
from gsmsdr_ns.io.colmap import read_colmap
from gsmsdr_ns.io.errors import InputError, InputWarning
from gsmsdr_ns.io.images import list_images, read_image, write_image
from gsmsdr_ns.process import ProcessConfig, RegistrationError, choose_matching, process_photos
from gsmsdr_ns.process.cli import parse

FERN = shared_fern()
FERN_IMAGES = FERN / "images_8"


@pytest.fixture(scope="module")
def fern_scene(tmp_path_factory: pytest.TempPathFactory):
    """``gsmsdr-process`` (its CLI main) run once on the 20 fern photos."""
    if not FERN_IMAGES.is_dir():
        pytest.fail(f"the fern photos are missing: expected them at {FERN_IMAGES} (set GSMSDR_DATA_DIR)")
    out = tmp_path_factory.mktemp("process") / "fern"
    start = time.perf_counter()
    result = parse(["--images", str(FERN_IMAGES), "--out", str(out), "--hold", "8"]).main()
    print(f"gsmsdr-process on {len(list_images(FERN_IMAGES))} fern photos: {time.perf_counter() - start:.1f}s")
    return out, result


def test_fern_registers_all_photos_with_llff_poses(fern_scene):
    out, result = fern_scene
    names = list_images(FERN_IMAGES)
    assert result.registered == names and result.unregistered == []
    assert result.matching == "exhaustive"
    assert sorted(p.name for p in out.iterdir()) == ["hold=8", "images", "sparse"]
    assert list_images(out / "images") == names
    assert detect_layout(out).reader == "deblur-nerf-data"  # hold=8 makes it a Deblur-NeRF scene

    cameras = read_colmap(out / "sparse" / "0")
    assert cameras.names == names
    assert np.all(cameras.distortion == 0.0)  # undistorted to pinhole
    llff_centres, llff_rotations = llff_cameras_opencv(FERN / "poses_bounds.npy")
    errors = pose_errors(cameras.c2w, llff_centres, llff_rotations)
    print(f"max centre error {errors.max_centre:.4f} of the diameter, max rotation error "
          f"{errors.max_rotation_deg:.3f} deg")  # fmt: skip
    assert errors.max_centre < 0.01
    assert errors.max_rotation_deg < 1.0


def test_unrelated_photos_fail_clearly_and_leave_nothing(tmp_path: Path):
    """Three photos of different, unrelated content cannot form a model: a RegistrationError names them with their
    sharpness, and neither the output nor a temp folder remains."""
    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    fern = read_image(FERN_IMAGES / "image000.png")
    write_image(photos / "a_fern.png", fern)
    write_image(photos / "b_noise.png", rng.integers(0, 256, size=fern.shape, dtype=np.uint8))
    write_image(photos / "c_flat.png", np.full_like(fern, 128))
    out = tmp_path / "scene"
    with pytest.raises(RegistrationError) as info:
        process_photos(photos, out, ProcessConfig())
    message = str(info.value)
    assert "0 of 3 photos" in message and str(photos) in message
    for name in ("a_fern.png", "b_noise.png", "c_flat.png"):
        assert name in message
    assert "(0.00e+00)" in message  # the flat photo's sharpness
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]


def test_existing_output_needs_overwrite(tmp_path: Path):
    out = tmp_path / "scene"
    out.mkdir()
    (out / "keep.txt").write_text("previous scene")
    with pytest.raises(FileExistsError, match="--overwrite"):
        process_photos(FERN_IMAGES, out, ProcessConfig())
    assert (out / "keep.txt").read_text() == "previous scene"


def test_bad_options_and_inputs_are_named(tmp_path: Path):
    with pytest.raises(ValueError, match="min-registered-fraction"):
        process_photos(FERN_IMAGES, tmp_path / "o", ProcessConfig(min_registered_fraction=1.5))
    (tmp_path / "one").mkdir()
    write_image(tmp_path / "one" / "only.png", np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(ValueError, match="at least 2"):
        process_photos(tmp_path / "one", tmp_path / "o", ProcessConfig())
    assert not (tmp_path / "o").exists()


def test_cli_reports_bad_input_as_one_error_line(tmp_path: Path):
    """``python -m gsmsdr_ns.process.cli`` (what the gsmsdr-process script runs): exit status 1, the reason shown."""
    (tmp_path / "one").mkdir()
    write_image(tmp_path / "one" / "only.png", np.zeros((8, 8, 3), np.uint8))
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]), COLUMNS="200")
    argv = [sys.executable, "-m", "gsmsdr_ns.process.cli", "--images", str(tmp_path / "one"),
            "--out", str(tmp_path / "scene")]  # fmt: skip
    proc = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "error:" in proc.stdout and "at least 2" in proc.stdout
    assert not (tmp_path / "scene").exists()


def test_auto_matching_switches_to_sequential_for_many_photos():
    config = ProcessConfig(exhaustive_max_images=50)
    assert choose_matching(50, config) == "exhaustive"
    assert choose_matching(51, config) == "sequential"
    assert choose_matching(10, ProcessConfig(matching="sequential")) == "sequential"


def test_ns_train_starts_on_the_processed_fern(fern_scene, tmp_path: Path):
    """The processed scene trains with ``ns-train gsmsdr-lite`` (a few CPU steps)."""
    out, _ = fern_scene
    args = ["gsmsdr-lite", "--data", out, "--output-dir", tmp_path / "outputs", "--timestamp", "run",
            "--max-num-iterations", 4, "--steps-per-save", 4, *TRAIN_FLAGS]  # fmt: skip
    proc = run_cli("ns-train", args, cwd=tmp_path)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"ns-train failed (exit {proc.returncode}):\n{log[-5000:]}"
    assert list((tmp_path / "outputs").rglob("*.ckpt")), log[-3000:]


def test_photos_share_a_camera_per_image_size(tmp_path: Path):
    """camera_mode "auto" groups photos by size: each group gets one shared camera (one per device)."""
    from gsmsdr_ns.process.sfm import names_by_size

    for name, size in (("a.png", (8, 6)), ("b.png", (4, 3)), ("c.png", (8, 6))):
        write_image(tmp_path / name, np.zeros((size[1], size[0], 3), np.uint8))
    assert names_by_size(tmp_path, ["a.png", "b.png", "c.png"]) == [["a.png", "c.png"], ["b.png"]]


def test_downscaled_copies_have_floor_halved_sizes(tmp_path: Path):
    """images_2/, images_4/ hold every photo at floor(size / factor), the size nerfstudio rescales cameras to."""
    from gsmsdr_ns.io.images import read_image_size
    from gsmsdr_ns.process.sfm import write_downscaled

    (tmp_path / "images").mkdir()
    write_image(tmp_path / "images" / "a.png", np.full((21, 30, 3), 200, np.uint8))
    write_downscaled(tmp_path, 2, ["a.png"])
    assert read_image_size(tmp_path / "images_2" / "a.png") == (15, 10)
    assert read_image_size(tmp_path / "images_4" / "a.png") == (7, 5)
    small = tmp_path / "small"
    (small / "images").mkdir(parents=True)
    write_image(small / "images" / "a.png", np.zeros((3, 3, 3), np.uint8))
    with pytest.raises(ValueError, match="too small"):
        write_downscaled(small, 2, ["a.png"])


def test_mixed_resolution_photos_register_with_a_camera_per_size(tmp_path: Path):
    """Half of the fern photos from a 'lower-resolution phone' (images_16): all register, and each size gets its
    own pinhole camera, the small one with half the focal length."""
    photos = tmp_path / "photos"
    photos.mkdir()
    small = list_images(FERN / "images_16")
    for i, name in enumerate(list_images(FERN_IMAGES)):  # same photos in the same sorted order
        source = FERN_IMAGES / name if i % 2 == 0 else FERN / "images_16" / small[i]
        write_image(photos / name, read_image(source))
    result = process_photos(photos, tmp_path / "scene", ProcessConfig())
    assert len(result.registered) == 20
    cameras = read_colmap(tmp_path / "scene" / "sparse" / "0")
    large = cameras.sizes[:, 0] > 300
    assert large.tolist() == [i % 2 == 0 for i in range(20)]
    for group in (large, ~large):  # one shared camera per size
        assert np.unique(cameras.intrinsics[group], axis=0).shape[0] == 1
    ratio = cameras.intrinsics[~large][0, 0] / cameras.intrinsics[large][0, 0]
    assert abs(ratio - 0.5) < 0.01


def test_a_folder_of_photos_without_poses_is_told_how_to_get_them(tmp_path: Path):
    """ns-train on plain photos (no poses): one error line naming the folder and the gsmsdr-process command."""
    photos = tmp_path / "photos"
    (photos / "images").mkdir(parents=True)
    for name in ("image000.png", "image001.png", "image002.png"):
        write_image(photos / "images" / name, read_image(FERN_IMAGES / name))
    from gsmsdr_ns.io.errors import InputError

    with pytest.raises(InputError, match=r"holds photos .* but no camera poses.*gsmsdr-process --images"):
        detect_layout(photos)
    proc = run_cli("ns-train", ["gsmsdr", "--data", photos, "--output-dir", tmp_path / "out", *TRAIN_FLAGS],
                   cwd=tmp_path, timeout=600)  # fmt: skip
    log = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert f"gsmsdr-process --images {photos / 'images'}" in log.replace("\n", ""), log[-3000:]
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*.ckpt"))


def test_domain_size_pooling_reaches_the_sift_descriptors(tmp_path: Path):
    """``ProcessConfig.domain_size_pooling`` changes the descriptors pycolmap writes (pooled descriptors); it is off
    by default (no consistent effect on the poses of blurred photos, docs/results/sfm)."""
    import pycolmap

    from gsmsdr_ns.process.sfm import extract_and_match

    assert not ProcessConfig().domain_size_pooling
    names = list_images(FERN / "images_16")[:3]
    descriptors = {}
    for pooling in (False, True):
        database = tmp_path / f"pooling-{pooling}.db"
        config = ProcessConfig(domain_size_pooling=pooling, num_threads=1)
        extract_and_match(database, FERN / "images_16", names, config)
        db = pycolmap.Database.open(database)
        image = db.read_image_with_name(names[0])
        descriptors[pooling] = np.asarray(db.read_descriptors(image.image_id).data)  # [K, 128] uint8
        db.close()
    off, on = descriptors[False], descriptors[True]
    assert len(off) > 100 and len(on) > 100 and off.shape[1] == on.shape[1] == 128
    n = min(len(off), len(on))
    assert not np.array_equal(off[:n], on[:n])


def _copies_of_fern(folder: Path, count: int = 6) -> Path:
    """``count`` fern photos plus a byte copy, a JPEG re-encoding and a half-size copy of three of them."""
    from PIL import Image

    folder.mkdir()
    names = list_images(FERN_IMAGES)[:count]
    for name in names:
        shutil.copy(FERN_IMAGES / name, folder / name)
    shutil.copy(FERN_IMAGES / names[0], folder / "zz_byte_copy.png")
    Image.open(FERN_IMAGES / names[1]).convert("RGB").save(folder / "image001_reencoded.jpg", quality=90)
    photo = Image.open(FERN_IMAGES / names[2]).convert("RGB")
    photo.resize((photo.width // 2, photo.height // 2), Image.Resampling.BILINEAR).save(folder / "small_copy.png")
    return folder


def test_copies_of_a_photo_are_found_and_different_photos_are_not(tmp_path: Path):
    from gsmsdr_ns.process.duplicates import find_duplicates

    folder = _copies_of_fern(tmp_path / "photos")
    names = list_images(folder)
    assert find_duplicates(folder, names) == {
        "image001_reencoded.jpg": "image001.png",
        "small_copy.png": "image002.png",
        "zz_byte_copy.png": "image000.png",
    }
    assert find_duplicates(FERN_IMAGES, list_images(FERN_IMAGES)) == {}  # 20 photos of one scene, all different


def test_gsmsdr_process_leaves_copies_out_so_none_becomes_a_test_view(tmp_path: Path):
    folder = _copies_of_fern(tmp_path / "photos")
    with pytest.warns(
        InputWarning, match=r"left out 3 photo\(s\) that copy another one.*zz_byte_copy.png \(= image000"
    ):
        result = process_photos(folder, tmp_path / "scene", ProcessConfig(hold=3))
    assert result.duplicates == {"image001_reencoded.jpg": "image001.png", "small_copy.png": "image002.png",
                                 "zz_byte_copy.png": "image000.png"}  # fmt: skip
    assert result.registered == list_images(FERN_IMAGES)[:6]
    assert list_images(tmp_path / "scene" / "images") == result.registered


def test_photos_that_do_not_register_are_blamed_on_blur_only_when_they_are_blurrier(tmp_path: Path):
    from gsmsdr_ns.process.sfm import check_registration

    sharp_pair = {"a.png": 410.0, "b.png": 395.0}
    with pytest.raises(RegistrationError) as info:
        check_registration(["a.png", "b.png"], [], sharp_pair, ProcessConfig(), tmp_path)
    message = str(info.value)
    assert "blurred" not in message and "--max-image-size" not in message
    assert "with 2 photos, add a few more taken from nearby viewpoints" in message
    names = [f"{i}.png" for i in range(6)]
    scores = {name: 400.0 for name in names} | {"5.png": 60.0}
    with pytest.raises(RegistrationError) as info:
        check_registration(names, names[:2], scores, ProcessConfig(min_registered=4), tmp_path)
    message = str(info.value)
    assert "5.png look blurred next to the others: try a smaller --max-image-size" in message
    assert "2.png look" not in message and "add a few more" not in message


def test_a_scene_whose_test_view_copies_a_training_image_is_refused(tiny_scene: Path, tmp_path: Path):
    """nerfstudio's split of the tiny COLMAP scene holds out views 0 and 8: view 8's file replaced by a JPEG copy
    of view 3 is a test view that training has seen."""
    from PIL import Image

    from gsmsdr_ns.plugin.auto_dataparser import GSMSDRAutoDataParserConfig
    from gsmsdr_ns.plugin.datamanager import GSMSDRDatamanagerConfig

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    copy = Image.open(scene / "images" / "frame_00003.png").convert("RGB")
    copy.save(scene / "images" / "frame_00008.png", format="JPEG", quality=92)  # same name, re-encoded content

    def setup(refuse: bool):
        parser = GSMSDRAutoDataParserConfig(data=scene, estimate_degradations=False, refuse_copied_test_views=refuse)
        config = GSMSDRDatamanagerConfig(dataparser=parser, cache_images="gpu")
        config.data = scene
        return config.setup(device="cpu")

    with pytest.raises(InputError, match=r"test view\(s\) of '.*scene' that copy a training image: 'frame_00008.png' "
                                         r"\(= training image '.*frame_00003.png'\)"):  # fmt: skip
        setup(refuse=True)
    with pytest.warns(InputWarning, match="refuse-copied-test-views False trains anyway"):
        datamanager = setup(refuse=False)
    assert len(datamanager.eval_dataset) == 2
