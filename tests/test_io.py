"""gsmsdr_ns.io: the COLMAP reader / writer, image files, atomic writes and the YAML config loader, on real files."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Literal, Optional, Tuple

import numpy as np
import pycolmap
import pytest
from PIL import Image

from gsmsdr_ns.io.atomic import (
    atomic_dir,
    exclusive_lock,
    write_bytes_atomic,
    write_file_atomic,
    write_json_atomic,
    write_text_atomic,
)
from gsmsdr_ns.io.colmap import ColmapPoints, has_colmap_model, read_colmap, write_colmap_model
from gsmsdr_ns.io.config import load_dataclass, read_yaml_mapping
from gsmsdr_ns.io.errors import InputError
from gsmsdr_ns.io.images import (
    list_images,
    read_image,
    read_image_float,
    read_image_size,
    resolve_image,
    write_image,
)

PACKAGE = Path(__file__).resolve().parents[1] / "gsmsdr_ns"
NAMES = ["c.png", "a.png", "b.png"]  # written in this (capture) order; read back sorted by name


def _w2c(angle: float, t: Tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    w2c = np.eye(4)
    w2c[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    w2c[:3, 3] = t
    return w2c


@pytest.fixture
def model_inputs():
    Ks = np.array([[[50.0, 0, 32], [0, 55.0, 24], [0, 0, 1]]] * 2 + [[[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]]])
    sizes = [(64, 48), (64, 48), (32, 24)]
    w2cs = np.stack([_w2c(0.1 * i, (0.5 * i, -0.2, 3.0)) for i in range(3)])
    points = ColmapPoints(
        xyz=np.array([[0.0, 0.0, 1.0], [0.5, 0.1, 2.0]]),
        rgb=np.array([[255, 0, 0], [0, 128, 255]], dtype=np.uint8),
        obs_point=np.array([0, 0, 1, 1, 1]),
        obs_view=np.array([0, 1, 0, 1, 2]),
        obs_uv=np.array([[10.0, 11.0], [12.0, 13.0], [20.0, 21.0], [22.0, 23.0], [5.0, 6.0]]),
    )
    return Ks, sizes, w2cs, points


@pytest.fixture
def model_dir(tmp_path, model_inputs) -> Path:
    Ks, sizes, w2cs, points = model_inputs
    write_colmap_model(tmp_path / "sparse" / "0", NAMES, Ks, sizes, w2cs, points)
    return tmp_path / "sparse" / "0"


# ----------------------------------------------------------------------------------------------------- COLMAP


def test_colmap_round_trip_sorted_by_name(model_dir, model_inputs):
    Ks, sizes, w2cs, points = model_inputs
    model = read_colmap(model_dir, tracks=True)
    order = [1, 2, 0]  # a, b, c
    assert model.names == ["a.png", "b.png", "c.png"] and model.image_ids == [2, 3, 1]
    assert model.camera_models == ["PINHOLE"] * 3 and model.unposed == []
    np.testing.assert_allclose(model.w2c, w2cs[order], atol=1e-12)
    np.testing.assert_allclose(model.c2w @ model.w2c, np.tile(np.eye(4), (3, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(model.Ks, Ks[order])
    np.testing.assert_array_equal(model.sizes, np.array(sizes)[order])
    np.testing.assert_array_equal(model.distortion, np.zeros((3, 6)))
    np.testing.assert_allclose(model.points.xyz, points.xyz)
    np.testing.assert_array_equal(model.points.rgb, points.rgb)
    # observations come back with rows in name order: written view 0 ('c') is row 2, view 2 ('b') is row 1
    row_of_view = np.array([2, 0, 1])
    np.testing.assert_array_equal(model.points.obs_point, points.obs_point)
    np.testing.assert_array_equal(model.points.obs_view, row_of_view[points.obs_view])
    np.testing.assert_allclose(model.points.obs_uv, points.obs_uv)
    assert read_colmap(model_dir).points.obs_view.size == 0  # tracks are read only on request


def test_missing_model_and_missing_points(tmp_path, model_dir):
    assert has_colmap_model(model_dir) and not has_colmap_model(tmp_path)
    with pytest.raises(InputError, match=rf"no COLMAP model in '{re.escape(str(tmp_path))}'.*Run COLMAP"):
        read_colmap(tmp_path)
    (model_dir / "points3D.bin").unlink()
    model = read_colmap(model_dir)
    assert model.points.xyz.shape == (0, 3) and len(model) == 3


@pytest.mark.parametrize("name", ["cameras", "images", "points3D"])
def test_truncated_binary_files_are_named(model_dir, name):
    path = model_dir / f"{name}.bin"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 3])
    with pytest.raises(InputError, match=rf"COLMAP file '{re.escape(str(path))}' is truncated.*Re-export"):
        read_colmap(model_dir)
    path.write_bytes(b"")
    with pytest.raises(InputError, match=rf"COLMAP file '{re.escape(str(path))}' is empty \(0 bytes\)"):
        read_colmap(model_dir)


def test_malformed_rig_file_names_the_model(model_dir):
    (model_dir / "rigs.bin").write_bytes((model_dir / "rigs.bin").read_bytes()[:12])
    with pytest.raises(InputError, match=rf"cannot read the COLMAP model in '{re.escape(str(model_dir))}'"):
        read_colmap(model_dir)


def test_text_model_with_nan_pose_names_the_image(model_dir):
    pycolmap.Reconstruction(str(model_dir)).write_text(str(model_dir))
    for file in model_dir.glob("*.bin"):
        file.unlink()
    model = read_colmap(model_dir)  # the text model reads like the binary one
    assert model.names == ["a.png", "b.png", "c.png"]
    text = (model_dir / "images.txt").read_text()
    lines = text.splitlines()
    i = next(k for k, line in enumerate(lines) if line.endswith(" b.png"))
    fields = lines[i].split()
    fields[1] = "nan"
    lines[i] = " ".join(fields)
    (model_dir / "images.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"image 'b.png' .*non-finite or degenerate camera pose"):
        read_colmap(model_dir)


def _single_camera_model(path: Path, model: str, params: List[float]) -> Path:
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=40, height=30, params=params, camera_id=1))
    for i, name in enumerate(["a.png", "b.png"]):
        image = pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(_w2c(0.2 * i, (i, 0, 2))[:3, :4]))
    path.mkdir(parents=True)
    rec.write(str(path))
    return path


def test_camera_models_and_distortion(tmp_path):
    opencv = read_colmap(_single_camera_model(tmp_path / "opencv", "OPENCV", [30, 31, 20, 15, 0.1, -0.05, 1e-3, 2e-3]))
    np.testing.assert_allclose(opencv.intrinsics[0], [30, 31, 20, 15])
    np.testing.assert_allclose(opencv.distortion[0], [0.1, -0.05, 0, 0, 1e-3, 2e-3])
    zero = read_colmap(_single_camera_model(tmp_path / "fisheye0", "OPENCV_FISHEYE", [30, 31, 20, 15, 0, 0, 0, 0]))
    np.testing.assert_allclose(zero.intrinsics[0], [30, 31, 20, 15])
    fisheye = _single_camera_model(tmp_path / "fisheye", "OPENCV_FISHEYE", [30, 31, 20, 15, 0.1, 0, 0, 0])
    with pytest.raises(InputError, match=r"OPENCV_FISHEYE model with distortion .*colmap image_undistorter"):
        read_colmap(fisheye)
    bad = _single_camera_model(tmp_path / "zero_focal", "PINHOLE", [0, 30, 20, 15])
    with pytest.raises(InputError, match=r"camera 1 .* invalid intrinsics"):
        read_colmap(bad)


def test_only_io_constructs_a_colmap_reconstruction():
    """One COLMAP reader: outside gsmsdr_ns/io nothing builds a pycolmap.Reconstruction or defines a reader."""
    offenders = []
    for file in sorted(PACKAGE.rglob("*.py")):
        if file.parent.name == "io":
            continue
        for number, line in enumerate(file.read_text(encoding="utf8").splitlines(), 1):
            if "Reconstruction(" in line or re.search(r"def \w*read_colmap", line):
                offenders.append(f"{file.relative_to(PACKAGE)}:{number}: {line.strip()}")
    assert offenders == []


# ----------------------------------------------------------------------------------------------------- images


def test_image_round_trip_and_conversions(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 256, (6, 8, 3), dtype=np.uint8)
    write_image(tmp_path / "rgb.png", rgb)
    np.testing.assert_array_equal(read_image(tmp_path / "rgb.png"), rgb)
    np.testing.assert_allclose(read_image_float(tmp_path / "rgb.png", (8, 6)), rgb / 255.0, atol=1e-7)
    assert read_image_size(tmp_path / "rgb.png") == (8, 6)
    rgba = np.concatenate([rgb, np.full((6, 8, 1), 7, np.uint8)], axis=2)
    write_image(tmp_path / "rgba.png", rgba)
    assert read_image(tmp_path / "rgba.png").shape == (6, 8, 4)
    assert read_image_float(tmp_path / "rgba.png").shape == (6, 8, 3)
    Image.fromarray(rgb[:, :, 0]).save(tmp_path / "grey.png")
    np.testing.assert_array_equal(read_image(tmp_path / "grey.png"), np.repeat(rgb[:, :, :1], 3, axis=2))
    deep = (np.arange(48, dtype=np.uint16).reshape(6, 8) * 1000).astype(np.uint16)
    Image.fromarray(deep).save(tmp_path / "deep.png")
    np.testing.assert_allclose(read_image_float(tmp_path / "deep.png")[..., 0], deep / 65535.0, atol=1e-6)
    with pytest.raises(ValueError, match="uint8"):
        write_image(tmp_path / "x.png", rgb.astype(np.float32))


def test_bad_image_files_are_named(tmp_path):
    rgb = np.full((24, 32, 3), 128, np.uint8)
    write_image(tmp_path / "ok.png", rgb)
    data = (tmp_path / "ok.png").read_bytes()
    (tmp_path / "truncated.png").write_bytes(data[: len(data) // 2])
    (tmp_path / "garbage.png").write_bytes(b"not an image at all")
    (tmp_path / "empty.png").write_bytes(b"")
    cases = {
        "missing.png": r"'{}' does not exist",
        "empty.png": r"'{}' is empty \(0 bytes\)",
        "garbage.png": r"cannot read image file '{}'.*not a readable image",
        "truncated.png": r"cannot read image file '{}'.*truncated",
    }
    for name, pattern in cases.items():
        with pytest.raises(InputError, match=pattern.format(re.escape(str(tmp_path / name)))):
            read_image(tmp_path / name)
    with pytest.raises(InputError, match=r"'.*ok.png' is 32x24 px but its camera says 64x48 px"):
        read_image_float(tmp_path / "ok.png", (64, 48))


def test_listing_and_resolving(tmp_path):
    for name in ["b.png", "a.JPG", ".hidden.png", "notes.txt"]:
        (tmp_path / name).write_bytes(b"x")
    assert list_images(tmp_path) == ["a.JPG", "b.png"]
    assert resolve_image(tmp_path, "a.png", "the test") == tmp_path / "a.JPG"  # same stem, other extension
    with pytest.raises(InputError, match=r"image 'z.png' is listed in the test"):
        resolve_image(tmp_path, "z.png", "the test")
    with pytest.raises(InputError, match="does not exist or is not a directory"):
        list_images(tmp_path / "nope")


# ----------------------------------------------------------------------------------------------------- atomic


def test_atomic_files(tmp_path):
    target = tmp_path / "sub" / "doc.json"
    write_json_atomic(target, {"a": [1, 2]})
    assert json.loads(target.read_text()) == {"a": [1, 2]}
    write_text_atomic(target, "replaced")
    assert target.read_text() == "replaced"
    write_bytes_atomic(tmp_path / "raw.bin", b"\x00\x01")
    assert (tmp_path / "raw.bin").read_bytes() == b"\x00\x01"

    with pytest.raises(ValueError):
        write_json_atomic(target, {"x": float("nan")}, allow_nan=False)
    with pytest.raises(TypeError):
        write_json_atomic(target, {"x": object()})
    assert target.read_text() == "replaced"  # a failed write keeps the old file

    def fail(tmp: Path) -> None:
        assert tmp.suffix == ".npy" and tmp.parent == tmp_path
        tmp.write_bytes(b"partial")
        raise RuntimeError("injected")

    with pytest.raises(RuntimeError, match="injected"):
        write_file_atomic(tmp_path / "arr.npy", fail)
    write_file_atomic(tmp_path / "arr.npy", lambda tmp: np.save(tmp, np.arange(3)))
    np.testing.assert_array_equal(np.load(tmp_path / "arr.npy"), np.arange(3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arr.npy", "raw.bin", "sub"]
    assert [p.name for p in (tmp_path / "sub").iterdir()] == ["doc.json"]


def test_atomic_dir_replaces_or_keeps(tmp_path):
    target = tmp_path / "out"
    with atomic_dir(target) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".out.") and not target.exists()
        (tmp / "a.txt").write_text("one")
    assert (target / "a.txt").read_text() == "one"
    with pytest.raises(RuntimeError, match="injected"):
        with atomic_dir(target) as tmp:
            (tmp / "b.txt").write_text("two")
            raise RuntimeError("injected")
    assert [p.name for p in target.iterdir()] == ["a.txt"]  # the old folder is untouched
    with atomic_dir(target) as tmp:
        (tmp / "b.txt").write_text("two")
    assert [p.name for p in target.iterdir()] == ["b.txt"]  # replaced as a whole
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no temp or old folders left


def test_exclusive_lock_makes_a_second_process_wait(tmp_path):
    """A process that wants the lock another holds blocks until it is released, then enters."""
    target = tmp_path / "scene"
    entered = tmp_path / "entered"
    script = (
        "import sys; from pathlib import Path; from gsmsdr_ns.io.atomic import exclusive_lock\n"
        "with exclusive_lock(Path(sys.argv[1])):\n"
        "    Path(sys.argv[2]).write_text('in')\n"
    )
    with exclusive_lock(target) as lock:
        assert lock == tmp_path / ".scene.lock"
        proc = subprocess.Popen([sys.executable, "-c", script, str(target), str(entered)])
        with pytest.raises(subprocess.TimeoutExpired):
            proc.wait(timeout=3)  # still waiting for the lock this process holds
        assert not entered.exists()
    assert proc.wait(timeout=300) == 0 and entered.read_text() == "in"


# ----------------------------------------------------------------------------------------------------- config


@dataclass
class _Inner:
    """Test section."""

    size: int = 3
    """A size."""
    scale: float = 1.0
    """A scale."""
    mode: Literal["a", "b"] = "a"
    """A mode."""

    def __post_init__(self):
        if self.size < 1:
            raise ValueError(f"size must be >= 1, got {self.size}")


@dataclass
class _Entry:
    """Test list item."""

    name: str
    """Required name."""
    seed: int = 0
    """A seed."""


@dataclass
class _Outer:
    """Test config."""

    inner: _Inner = field(default_factory=_Inner)
    """Nested section."""
    factors: Tuple[int, ...] = (4, 2)
    """A tuple."""
    entries: List[_Entry] = field(default_factory=list)
    """A list of sections."""
    root: Optional[Path] = None
    """An optional path."""
    flag: bool = False
    """A flag."""


def test_load_dataclass_nested_lists_and_conversions():
    cfg = load_dataclass(
        _Outer,
        {"inner": {"scale": 2, "mode": "b"}, "factors": [3], "entries": [{"name": "x", "seed": 4}], "root": "d/e"},
        "s.yaml",
    )
    assert cfg == _Outer(_Inner(3, 2.0, "b"), (3,), [_Entry("x", 4)], Path("d/e"), False)
    assert isinstance(cfg.inner.scale, float) and isinstance(cfg.factors, tuple)
    base = _Outer(inner=_Inner(size=7))
    assert load_dataclass(_Outer, {"inner": None, "flag": True}, None, base) == _Outer(_Inner(7), flag=True)


@pytest.mark.parametrize(
    "values, message",
    [
        ({"inenr": {}}, r"s.yaml: unknown _Outer keys: \['inenr'\]; valid keys: \['entries', 'factors'"),
        ({"inner": {"sise": 1}}, r"s.yaml: unknown inner keys: \['sise'\]"),
        ({"inner": {"size": 2.5}}, r"s.yaml: inner.size: must be an integer, got 2.5"),
        ({"inner": {"size": True}}, r"s.yaml: inner.size: must be an integer, got True"),
        ({"inner": {"mode": "c"}}, r"s.yaml: inner.mode: must be one of \['a', 'b'\], got 'c'"),
        ({"inner": {"size": 0}}, r"s.yaml: inner: size must be >= 1, got 0"),
        ({"inner": 3}, r"s.yaml: inner: must be a mapping of _Inner fields, got int"),
        ({"factors": [4, "x"]}, r"s.yaml: factors\[1\]: must be an integer, got 'x'"),
        ({"entries": [{"seed": 1}]}, r"s.yaml: entries\[0\]: missing required keys \['name'\]"),
        ({"entries": [{"name": 3}]}, r"s.yaml: entries\[0\].name: must be a string, got 3"),
        ({"flag": "yes"}, r"s.yaml: flag: must be true or false, got 'yes'"),
        ({"root": 5}, r"s.yaml: root: must be .*path.*, got 5"),
    ],
)
def test_load_dataclass_errors_name_file_and_key(values, message):
    with pytest.raises(InputError, match=message):
        load_dataclass(_Outer, values, "s.yaml")


def test_read_yaml_mapping(tmp_path):
    (tmp_path / "ok.yaml").write_text("a: 1\nb: [x, y]\n")
    assert read_yaml_mapping(tmp_path / "ok.yaml") == {"a": 1, "b": ["x", "y"]}
    (tmp_path / "empty.yaml").write_text("")
    assert read_yaml_mapping(tmp_path / "empty.yaml") == {}
    (tmp_path / "list.yaml").write_text("- 1\n")
    with pytest.raises(InputError, match=r"list.yaml: must be a YAML mapping, got list"):
        read_yaml_mapping(tmp_path / "list.yaml")
    (tmp_path / "bad.yaml").write_text("a: [1\n")
    with pytest.raises(InputError, match=r"bad.yaml: not valid YAML"):
        read_yaml_mapping(tmp_path / "bad.yaml")
    with pytest.raises(InputError, match=r"missing.yaml: file not found"):
        read_yaml_mapping(tmp_path / "missing.yaml")
