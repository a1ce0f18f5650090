"""``gsmsdr-export``: a trained run's Gaussians as the standard 3DGS PLY, read back with plyfile."""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import TrainedRun
from plyfile import PlyData

import gsmsdr_ns.plugin  # noqa: F401  (allow-lists the checkpoint's numpy scalars for torch.load)
from gsmsdr_ns.plugin.export import ExportCLI, exported_mask, gaussian_ply_fields, ply_bytes


def checkpoint_params(run: TrainedRun) -> dict:
    checkpoint = torch.load(run.checkpoint_dir / f"step-{run.steps - 1:09d}.ckpt", map_location="cpu")
    prefix = "_model.gauss_params."
    return {k[len(prefix) :]: v for k, v in checkpoint["pipeline"].items() if k.startswith(prefix)}


def test_export_matches_the_checkpoint(trained_run: TrainedRun, tmp_path: Path):
    output = tmp_path / "nested" / "splat.ply"
    assert ExportCLI(load_config=trained_run.config, output=output).main() == output
    assert sorted(p.name for p in output.parent.iterdir()) == ["splat.ply"]  # no temp file left

    params = checkpoint_params(trained_run)
    rest = params["features_rest"]  # [N, K, 3]
    k = rest.shape[1]
    assert k > 0  # higher SH degrees are exported too
    ply = PlyData.read(str(output))
    assert not ply.text and ply.byte_order == "<"
    vertex = ply["vertex"]
    expected_names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                      + [f"f_rest_{i}" for i in range(3 * k)] + ["opacity", "scale_0", "scale_1", "scale_2"]
                      + ["rot_0", "rot_1", "rot_2", "rot_3"])  # fmt: skip
    assert [p.name for p in vertex.properties] == expected_names
    assert all(vertex[name].dtype == np.float32 for name in expected_names)
    assert "Vertical Axis: z" in ply.comments

    keep = (params["opacities"][:, 0] >= -5.5373) & torch.stack(
        [torch.isfinite(v.reshape(len(v), -1)).all(1) for v in params.values()]
    ).all(0)
    assert 0 < int(keep.sum()) == vertex.count
    kept = {name: value[keep].numpy() for name, value in params.items()}
    np.testing.assert_array_equal(np.stack([vertex["x"], vertex["y"], vertex["z"]], 1), kept["means"])
    np.testing.assert_array_equal(np.stack([vertex[f"f_dc_{i}"] for i in range(3)], 1), kept["features_dc"])
    for channel in range(3):  # channel-major: all red coefficients first
        for j in range(k):
            np.testing.assert_array_equal(vertex[f"f_rest_{channel * k + j}"], kept["features_rest"][:, j, channel])
    np.testing.assert_array_equal(vertex["opacity"], kept["opacities"][:, 0])
    np.testing.assert_array_equal(np.stack([vertex[f"scale_{i}"] for i in range(3)], 1), kept["scales"])
    np.testing.assert_array_equal(np.stack([vertex[f"rot_{i}"] for i in range(4)], 1), kept["quats"])
    assert np.all(vertex["nx"] == 0)

    # rgb mode: the same Gaussians with bytes instead of SH coefficients; exporting again replaces the file
    ExportCLI(load_config=trained_run.config, output=output, ply_color_mode="rgb").main()
    vertex = PlyData.read(str(output))["vertex"]
    names = [p.name for p in vertex.properties]
    assert names[6:9] == ["red", "green", "blue"] and not any(n.startswith("f_") for n in names)
    assert vertex["red"].dtype == np.uint8
    expected_red = (np.clip(kept["features_dc"][:, 0] * 0.28209479177387814 + 0.5, 0, 1) * 255).astype(np.uint8)
    assert np.abs(vertex["red"].astype(int) - expected_red.astype(int)).max() <= 1
    assert sorted(p.name for p in output.parent.iterdir()) == ["splat.ply"]


def test_non_finite_and_transparent_gaussians_are_left_out_one_by_one():
    n = 5
    means = torch.arange(3 * n, dtype=torch.float32).reshape(n, 3)
    means[1, 2] = float("nan")
    scales = torch.zeros(n, 3)
    scales[2, 0] = float("inf")
    opacities = torch.zeros(n, 1)
    opacities[3, 0] = -6.0  # below 1/255
    fields = gaussian_ply_fields(means, torch.zeros(n, 3), torch.zeros(n, 3, 3), opacities, scales,
                                 torch.ones(n, 4), sh_degree=1)  # fmt: skip
    assert exported_mask(fields).tolist() == [True, False, False, False, True]


def test_sh_degree_zero_colours_become_sh_dc():
    """A sh_degree-0 model stores logit colours; the PLY holds the SH DC coefficients of the same colours."""
    rgb = torch.tensor([[0.2, 0.5, 0.9]])
    fields = gaussian_ply_fields(torch.zeros(1, 3), torch.logit(rgb), torch.zeros(1, 0, 3), torch.zeros(1, 1),
                                 torch.zeros(1, 3), torch.ones(1, 4), sh_degree=0)  # fmt: skip
    dc = np.array([fields[f"f_dc_{i}"][0] for i in range(3)])
    np.testing.assert_allclose(dc * 0.28209479177387814 + 0.5, rgb[0].numpy(), atol=1e-6)
    assert not any(name.startswith("f_rest") for name in fields)


def test_ply_bytes_round_trip(tmp_path: Path):
    fields = OrderedDict(x=np.array([1.5, -2.0]), red=np.array([3, 250], dtype=np.uint8))
    path = tmp_path / "a.ply"
    path.write_bytes(ply_bytes(fields, ["hello"]))
    ply = PlyData.read(str(path))
    assert ply.comments == ["hello"]
    assert ply["vertex"]["x"].tolist() == [1.5, -2.0] and ply["vertex"]["red"].tolist() == [3, 250]


def test_missing_config_and_bad_output_are_named(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        ExportCLI(load_config=tmp_path / "nope.yml", output=tmp_path / "a.ply").main()
    config = tmp_path / "config.yml"
    config.write_text("x")
    with pytest.raises(ValueError, match=r"must end in \.ply"):
        ExportCLI(load_config=config, output=tmp_path / "a.txt").main()
