"""Bad scene data fails while the scene is parsed, with one message naming the file, the image / row and the fix.

Rows of issue 16 covered here: degradation.json checked against its schema (degradation.json and the estimate's
cache), poses that are not rotations (poses_bounds.npy, transforms.json, COLMAP), a transforms.json scene with a
missing or truncated image, a half-size image in a Deblur-NeRF scene. Scenes are copies of the 10-view 64x48
``tiny_scene`` (real PNGs, a pycolmap model), rearranged and corrupted on disk.
"""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from conftest import write_transforms_json
from nerfstudio.data.utils import colmap_parsing_utils as colmap_io
from PIL import Image

from gsmsdr_ns.data.cameras import cameras_from_colmap, write_poses_bounds
from gsmsdr_ns.data.degradation import load_degradation_json
from gsmsdr_ns.data.degradation_schema import check_entry
from gsmsdr_ns.data.poses import ROTATION_TOLERANCE
from gsmsdr_ns.io.colmap import read_colmap
from gsmsdr_ns.io.errors import InputError
from gsmsdr_ns.plugin.auto_dataparser import GSMSDRAutoDataParserConfig
from gsmsdr_ns.plugin.dataparser import GSMSDRDataParserConfig
from gsmsdr_ns.plugin.deblur_dataparser import DeblurNerfDataParserConfig

TRAIN_VIEW = "frame_00003.png"  # index 3: a training view under hold=8 (views 0 and 8 are held out)


def make_deblur_scene(src: Path, dst: Path, colmap: bool = True) -> Path:
    """``src`` (a COLMAP scene) in the Deblur-NeRF layout: images/, images_test/, hold=8, poses_bounds.npy and a
    degradation.json saying every training view is defocused (the pixels are left sharp: only parsing is tested)."""
    shutil.copytree(src / "images", dst / "images")
    shutil.copytree(src / "images", dst / "images_test")
    if colmap:
        shutil.copytree(src / "sparse", dst / "sparse")
    (dst / "hold=8").touch()
    write_poses_bounds(dst / "poses_bounds.npy", cameras_from_colmap(read_colmap(src / "sparse" / "0")))
    names = sorted(p.name for p in (src / "images").iterdir())
    images = {
        name: {"split": "train", "degraded": True, "effects": {"defocus": {"model": "disk", "radius_px": 2.0}}}
        if i % 8
        else {"split": "test", "degraded": False, "effects": {}}
        for i, name in enumerate(names)
    }
    doc = {"version": 1, "generator": "test", "source": str(src), "seed": 0, "hold": 8, "effects": ["defocus"],
           "preset": None, "images": images}  # fmt: skip
    (dst / "degradation.json").write_text(json.dumps(doc))
    return dst


@pytest.fixture
def deblur(tiny_scene: Path, tmp_path: Path) -> Path:
    return make_deblur_scene(tiny_scene, tmp_path / "deblur")


def parse_deblur(data: Path, split: str = "train", **options):
    return DeblurNerfDataParserConfig(data=data, **options).setup().get_dataparser_outputs(split=split)


def parse_auto(data: Path, split: str = "train"):
    return GSMSDRAutoDataParserConfig(data=data).setup().get_dataparser_outputs(split=split)


def edit_json(path: Path, edit: Callable[[dict], None]) -> None:
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))


# ------------------------------------------------------------------------------------ degradation.json schema


def set_field(*keys, value):
    """An edit of the training view's entry: ``entry[k0][k1]... = value``."""

    def edit(doc: dict) -> None:
        node = doc["images"][TRAIN_VIEW]
        for key in keys[:-1]:
            node = node.setdefault(key, {})
        node[keys[-1]] = value

    return edit


BAD_ENTRIES = {
    "effect blurr": (set_field("effects", "blurr", value={}),
                     r"field \"effects\" names unknown degradation effect\(s\) \['blurr'\]; the known effects are mot"),
    "degraded 'no'": (set_field("degraded", value="no"),
                      r"field \"degraded\" is \"no\"; it must be true or false \(a JSON boolean, not a string\)"),
    "negative blur_px": (set_field("effects", "motion", "blur_px", value=-3.0),
                         r"field \"effects.motion.blur_px\" is -3.0; it must be a finite number >= 0"),
    "NaN radius": (set_field("effects", "defocus", "radius_px", value=math.nan),
                   r"field \"effects.defocus.radius_px\" is NaN; it must be a finite number >= 0"),
    "mixres factor 0": (set_field("effects", "mixres", "factor", value=0),
                        r"field \"effects.mixres.factor\" is 0; it must be an integer >= 1"),
    "mixres factor 1.5": (set_field("effects", "mixres", "factor", value=1.5),
                          r"field \"effects.mixres.factor\" is 1.5; it must be an integer >= 1"),
    "upsample nearest": (set_field("effects", "mixres", "upsample", value="nearest"),
                         r"field \"effects.mixres.upsample\" is \"nearest\"; it must be one of \"bilinear\", "),
    "defocus model": (set_field("effects", "defocus", "model", value="gauss"),
                      r"field \"effects.defocus.model\" is \"gauss\"; it must be one of \"thin_lens\", \"disk\", "),
    "effect not an object": (set_field("effects", "noise", value=0.01),
                             r"field \"effects.noise\" is 0.01; it must be an object of the effect's parameters"),
    "split val": (set_field("split", value="val"),
                  r"field \"split\" is \"val\"; it must be one of \"train\", \"test\"\."),
    "degraded null": (set_field("degraded", value=None), r"field \"degraded\" is null; it must be true or false"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(BAD_ENTRIES))
def test_degradation_json_entry_outside_the_schema_names_file_image_and_field(deblur, case):
    edit, message = BAD_ENTRIES[case]
    path = deblur / "degradation.json"
    edit_json(path, edit)
    with pytest.raises(InputError) as err:
        parse_deblur(deblur)
    text = str(err.value)
    assert text.startswith(f"gsmsdr: '{path}': image '{TRAIN_VIEW}', field"), text
    assert re.search(message, text), text
    assert text.endswith("Fix the entry, or re-create the file with gsmsdr-degrade (or gsmsdr-estimate).")


def test_degradation_json_top_level_fields_are_checked(deblur):
    path = deblur / "degradation.json"
    edit_json(path, lambda doc: doc.update(effects=["defocus", "blurr"]))
    with pytest.raises(InputError, match=rf"'{path}': the top-level field \"effects\" names unknown degradation "
                       r"effect\(s\) \['blurr'\]"):  # fmt: skip
        parse_deblur(deblur)
    edit_json(path, lambda doc: doc.update(effects=["defocus"], hold="8"))
    with pytest.raises(InputError, match=r"the top level, field \"hold\" is \"8\"; it must be an integer >= 1 or null"):
        parse_deblur(deblur)


def test_what_the_writers_write_passes_the_schema(tiny_scene, tmp_path):
    """Every field gsmsdr-degrade writes (all four effects, trajectory + thin-lens models) and every estimated
    entry pass; a degraded scene parses."""
    from gsmsdr_ns.degrade import degrade_scene
    from gsmsdr_ns.degrade.config import DefocusConfig, DegradeConfig, MotionConfig, NoiseConfig
    from gsmsdr_ns.estimate.classify import DegradationEstimate
    from gsmsdr_ns.estimate.records import entry_from_estimate

    config = DegradeConfig(
        effects=("motion", "defocus", "mixres", "noise"),
        px_reference_width=0,
        workers=1,
        motion=MotionConfig(min_blur_px=2.0, max_blur_px=3.0, keyframe_spacing_px=3.0),
        defocus=DefocusConfig(min_coc_px=2.0, max_coc_px=3.0),
        noise=NoiseConfig(sigma=0.01),
    )
    out = degrade_scene(tiny_scene, tmp_path / "degraded", config)
    doc = load_degradation_json(out / "degradation.json")
    effects = {name: set(entry["effects"]) for name, entry in doc["images"].items()}
    assert effects[TRAIN_VIEW] == {"motion", "defocus", "mixres", "noise"}
    assert {doc["images"][TRAIN_VIEW]["effects"]["motion"]["model"], doc["images"][TRAIN_VIEW]["effects"]["defocus"]
            ["model"]} == {"trajectory", "thin_lens"}  # fmt: skip
    records = parse_deblur(out).metadata["degradations"]
    assert all(r["degraded"] is True for r in records)

    for label, factor, blurred in [("sharp", 1, False), ("motion", 1, True), ("defocus", 1, True), ("mixres", 2, False),
                                   ("unknown", None, True), ("unknown", None, None)]:  # fmt: skip
        estimate = DegradationEstimate(label, 0.5, 1.0, 1.0, 1.0, 0.1, factor, 0.0, blurred)
        check_entry(Path("degradation.json"), "a.png", entry_from_estimate(estimate), "")


def test_edited_estimate_cache_is_checked_and_named(tiny_scene, tmp_path):
    scene = Path(shutil.copytree(tiny_scene, tmp_path / "colmap"))
    parse_auto(scene)  # estimates the training views and caches them
    cache = scene / "degradation.estimated.json"
    edit_json(cache, lambda doc: doc["images"][TRAIN_VIEW].update(degraded="yes"))
    with pytest.raises(InputError) as err:
        parse_auto(scene)
    assert str(err.value) == (
        f"gsmsdr: '{cache}': image '{TRAIN_VIEW}', field \"degraded\" is \"yes\"; it must be true or false (a JSON "
        f"boolean, not a string). Fix the entry, or delete '{cache}' to estimate again."
    )


def test_bad_degradation_json_stops_the_trainer_pipeline_before_training(deblur):
    """The real ns-train setup path (method config -> pipeline -> datamanager -> dataparser) stops with the message
    before a model exists."""
    from gsmsdr_ns.plugin.method_config import gsmsdr_trainer_config

    path = deblur / "degradation.json"
    edit_json(path, set_field("effects", "blurr", value={}))
    config = gsmsdr_trainer_config()
    config.pipeline.datamanager.data = deblur
    with pytest.raises(InputError) as err:
        config.pipeline.setup(device="cpu", test_mode="val")
    assert str(err.value).startswith(
        f"gsmsdr: '{path}': image '{TRAIN_VIEW}', field \"effects\" names unknown degradation effect(s) ['blurr']; "
        "the known effects are motion, defocus, mixres, noise."
    )


# -------------------------------------------------------------------------------------------------------- poses


def llff_rotation_edits():
    def scaled(r):
        return r * 2

    def zero(r):
        return r * 0

    def reflected(r):
        return r * np.array([1.0, 1.0, -1.0])

    def sheared(r):
        out = r.copy()
        out[:, 0] += 0.01 * r[:, 1]
        return out

    return {"scaled by 2": scaled, "all zero": zero, "reflected": reflected, "sheared 1%": sheared}


@pytest.mark.parametrize("case", list(llff_rotation_edits()))
def test_poses_bounds_rotation_that_is_not_a_rotation_names_the_row(deblur, case):
    shutil.rmtree(deblur / "sparse")  # poses come from poses_bounds.npy
    path = deblur / "poses_bounds.npy"
    array = np.load(path)
    row = array[3, :15].reshape(3, 5)
    row[:, :3] = llff_rotation_edits()[case](row[:, :3])
    array[3, :15] = row.reshape(-1)
    np.save(path, array)
    with pytest.raises(InputError) as err:
        parse_deblur(deblur)
    text = str(err.value)
    assert text.startswith(f"gsmsdr: '{path}' row 3 (image '{TRAIN_VIEW}') has a camera rotation that is not a "
                           "rotation matrix: R = [[")  # fmt: skip
    assert f"(allowed: max |R^T R - I| <= {ROTATION_TOLERANCE:g} and det(R) = 1 within" in text
    assert text.endswith("re-create the file from the COLMAP model (gsmsdr-degrade writes one) or fix that row.")


def test_poses_within_the_tolerance_parse(deblur):
    shutil.rmtree(deblur / "sparse")
    path = deblur / "poses_bounds.npy"
    reference = parse_deblur(deblur).cameras.camera_to_worlds
    array = np.load(path)
    array[:, :15] += np.random.default_rng(0).uniform(-1e-4, 1e-4, size=(len(array), 15)) * np.tile(
        [1, 1, 1, 0, 0], 3
    )  # float32-level noise on the rotations only
    np.save(path, array)
    noisy = parse_deblur(deblur).cameras.camera_to_worlds
    assert np.abs((noisy - reference).numpy()).max() < 1e-3


def test_transforms_json_scaled_rotation_names_the_frame(tiny_scene, tmp_path):
    scene = write_transforms_json(tiny_scene, tmp_path / "ns")
    path = scene / "transforms.json"

    def scale(doc):
        matrix = np.asarray(doc["frames"][4]["transform_matrix"])
        matrix[:3, :3] *= 2
        doc["frames"][4]["transform_matrix"] = matrix.tolist()

    edit_json(path, scale)
    message = (rf"^gsmsdr: '{path}' frame 4 \('images/frame_00004.png'\) has a camera rotation that is not a rotation "
               r"matrix: .* det\(R\) = 8 .*upper-left 3x3 must be a rotation")  # fmt: skip
    with pytest.raises(InputError, match=message):
        parse_auto(scene)


@pytest.mark.parametrize("reader", ["colmap", "deblur-nerf-data"])
def test_colmap_quaternion_that_is_not_unit_names_the_image(tiny_scene, tmp_path, reader):
    """nerfstudio's COLMAP reader and pycolmap use the quaternion as written: a scaled one gives a scaled rotation."""
    scene = Path(shutil.copytree(tiny_scene, tmp_path / "scene"))
    if reader == "deblur-nerf-data":
        scene = make_deblur_scene(tiny_scene, tmp_path / "deblur")
    model = scene / "sparse" / "0"
    cameras, images, points = colmap_io.read_model(str(model), ext=".bin")
    image_id = next(i for i, im in images.items() if im.name == TRAIN_VIEW)
    images[image_id] = images[image_id]._replace(qvec=images[image_id].qvec * 1.5)
    for file in model.iterdir():  # rigs / frames would hold the poses for pycolmap: write a model without them
        file.unlink()
    colmap_io.write_model(cameras, images, points, str(model), ext=".bin")
    with pytest.raises(InputError, match=rf"^gsmsdr: '{model}' image '{TRAIN_VIEW}' has a camera rotation that is "
                       r"not a rotation matrix: .*a pose's quaternion must be a unit quaternion\.$"):  # fmt: skip
        config = GSMSDRDataParserConfig if reader == "colmap" else DeblurNerfDataParserConfig
        config(data=scene).setup().get_dataparser_outputs("train")


# ---------------------------------------------------------------------------------------- transforms.json images


def test_transforms_json_missing_image_is_named_before_nerfstudio_reads(tiny_scene, tmp_path):
    scene = write_transforms_json(tiny_scene, tmp_path / "ns")
    image = scene / "images" / "frame_00000.png"  # the first frame: the one nerfstudio opens itself
    image.unlink()
    with pytest.raises(InputError) as err:
        parse_auto(scene)
    assert str(err.value) == (
        f"gsmsdr: image file '{image}' (frame 0 of '{scene / 'transforms.json'}') does not exist. Restore it, or "
        "remove its frame from the transforms file."
    )


def test_transforms_json_truncated_image_is_named_before_training(tiny_scene, tmp_path):
    scene = write_transforms_json(tiny_scene, tmp_path / "ns")
    image = scene / "images" / TRAIN_VIEW
    data = image.read_bytes()
    image.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=rf"^gsmsdr: cannot read image file '{image}': .*truncated.*re-copy or "
                       r"re-export it\.$"):  # fmt: skip
        parse_auto(scene)


# ----------------------------------------------------------------------------------------- Deblur-NeRF image sizes


@pytest.mark.parametrize("folder, name, split", [("images", TRAIN_VIEW, "train"),
                                                 ("images_test", "frame_00008.png", "test")])  # fmt: skip
def test_half_size_image_in_a_deblur_scene_is_rejected(deblur, folder, name, split):
    image = deblur / folder / name
    Image.open(image).resize((32, 24), Image.BILINEAR).save(image)
    with pytest.raises(InputError) as err:
        parse_deblur(deblur, split)
    assert str(err.value).startswith(
        f"gsmsdr: image file '{image}' is 32x24 px but the other images of '{deblur / folder}' are the size of their "
        f"cameras, so it should be 64x48 px (its camera in '{deblur / 'sparse' / '0'}' is 64x48 px). All "
        "images of a folder must have matching sizes"
    ), str(err.value)


def test_a_folder_at_a_small_scale_of_large_cameras_is_one_scale():
    """1/16 of a 4032x3024 camera is 252x189 exactly: the folder's scale is not rounded (0.062 would expect 250 px)."""
    from gsmsdr_ns.data.cameras import check_same_scale

    files = [Path(f"image{i:03d}.png") for i in range(4)]
    check_same_scale(files, np.array([[4032, 3024]] * 4), [(252, 189)] * 4, "'poses_bounds.npy'")
    with pytest.raises(InputError, match=r"image003\.png' is 126x94 px .* so it should be 252x189 px"):
        check_same_scale(files, np.array([[4032, 3024]] * 4), [(252, 189)] * 3 + [(126, 94)], "'poses_bounds.npy'")


def test_a_whole_folder_at_half_size_still_parses(deblur):
    """images_2/-style copies (every file at the same scale) keep rescaling the intrinsics."""
    for image in (deblur / "images").iterdir():
        Image.open(image).resize((32, 24), Image.BILINEAR).save(image)
    outputs = parse_deblur(deblur)
    assert outputs.cameras.width.unique().tolist() == [32]
