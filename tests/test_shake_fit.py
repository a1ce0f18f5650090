"""tools/shake/shake_fit.py on a real generated shaken scene and its sharp twin (tiny, written to disk): the true
6-DoF path explains the shaken photo, the fitted rotation path at least as well as the true rotations alone, the
fitted moving path at least as well as the rotation path it starts from, the true path at two time samples worse than
all of it, and every model better than the sharp image itself."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from gsmsdr_ns.bench.scenes import SceneSpec, ensure_scene
from tools.shake.shake_fit import ShakeFit, _image, view_fits


def test_models_fit_a_shaken_photo_in_the_expected_order(tmp_path: Path, capsys) -> None:
    spec = SceneSpec(variant="motion-strong", width=96, height=72, num_views=6, hold=3, num_points=300, seed=0)
    shaken = ensure_scene(tmp_path, spec)
    sharp = ensure_scene(tmp_path, spec.with_variant("sharp"))
    records = json.loads((shaken / "degradation.json").read_text())["images"]
    name = next(n for n, r in sorted(records.items()) if r["split"] == "train")
    record = records[name]["effects"]["motion"]
    intr = json.loads((shaken / "scene.json").read_text())["intrinsics"]
    K = torch.tensor([[intr["fx"], 0.0, intr["cx"]], [0.0, intr["fy"], intr["cy"]], [0.0, 0.0, 1.0]])
    depth = torch.from_numpy(np.load(shaken / "depth" / f"{Path(name).stem}.npy").astype(np.float32))
    fits = view_fits(_image(sharp / "images" / name), _image(shaken / "images" / name), K, record, depth, 9, 9)
    assert fits["6-DoF"] > 30.0 and fits["6-DoF"] > fits["none"] + 8.0, fits
    assert fits["6-DoF occluding"] > fits["none"] + 8.0, fits
    assert fits["path"] >= fits["rotation"] - 0.05, fits
    assert fits["moving path"] >= fits["path"] - 0.05, fits  # the moving path starts from the rotation path
    assert all(fits[m] > fits["none"] for m in ("kernel", "rotation", "path", "path + kernel", "moving path")), fits
    # two samples of the true path explain the photo worse than all of it; a kernel after them recovers some
    sampled = view_fits(_image(sharp / "images" / name), _image(shaken / "images" / name), K, record, depth, 9, 2,
                        ("sampled 6-DoF occluding", "sampled 6-DoF occluding + kernel"))  # fmt: skip
    assert sampled["sampled 6-DoF occluding"] < fits["6-DoF occluding"] - 1.0, (sampled, fits)
    assert sampled["sampled 6-DoF occluding + kernel"] > sampled["sampled 6-DoF occluding"], sampled

    ShakeFit(data=shaken, sharp=sharp, views=1, kernel_size=9).main()
    table = capsys.readouterr().out
    assert f"| {name} |" in table and "| mean |" in table
    ShakeFit(data=shaken, sharp=sharp, views=1, models=("none", "6-DoF occluding")).main()
    header = capsys.readouterr().out.splitlines()[1]
    assert header == "| view | blur px | none | 6-DoF occluding |", header


def test_midpoint_samples_are_the_bins_centres() -> None:
    from tools.shake.shake_fit import midpoint_samples

    assert midpoint_samples(30, 3).tolist() == [4, 14, 24]  # centres 4.5 / 14.5 / 24.5 round to even
    assert midpoint_samples(9, 9).tolist() == list(range(9))
    assert midpoint_samples(5, 9).min() == 0 and midpoint_samples(5, 9).max() == 4
