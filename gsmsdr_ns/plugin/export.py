"""`gsmsdr-export`: a trained ``gsmsdr`` run -> the standard 3D Gaussian Splatting PLY of its sharp Gaussians.

    gsmsdr-export --load-config outputs/scene/gsmsdr/<timestamp>/config.yml --output scene.ply

The file matches nerfstudio's ``ns-export gaussian-splat`` (which cannot run where open3d cannot load): binary
little-endian vertices with ``x y z nx ny nz``, then ``f_dc_0..2`` and ``f_rest_*`` (SH coefficients, the rest
ordered channel-major as the Inria 3DGS files are) or ``red green blue`` (``--ply-color-mode rgb``), then
``opacity`` (logit), ``scale_0..2`` (log) and ``rot_0..3`` (quaternion w, x, y, z, as trained); positions in the
world frame of the nerfstudio run (the dataparser's oriented and scaled frame); all floats written as float32.
Gaussians with a non-finite value or an opacity below 1/255 are left out, an optional oriented box crops them.

Only the Gaussians are exported: they are the sharp scene; the blur field and thin lens model the degradation of
the training photos and are not part of it. One difference from ``ns-export``: a model trained with ``sh_degree``
0 stores logit colours in ``features_dc``; they are converted to SH DC coefficients so that 3DGS viewers show the
right colours. Non-finite values are filtered per Gaussian.
"""

from __future__ import annotations

import sys
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path
from typing import Literal, Optional, Tuple

import numpy as np
import torch
import tyro
from rich.console import Console

from gsmsdr_ns._cli import run_entrypoint
from gsmsdr_ns.io.atomic import write_bytes_atomic

CONSOLE = Console()

LOW_OPACITY_LOGIT = -5.5373  # logit(1/255): such Gaussians are skipped by the rasterizer anyway
SH_C0 = 0.28209479177387814  # the degree-0 real spherical harmonic


def gaussian_ply_fields(
    means: torch.Tensor, features_dc: torch.Tensor, features_rest: torch.Tensor, opacities: torch.Tensor,
    scales: torch.Tensor, quats: torch.Tensor, sh_degree: int, color_mode: Literal["sh_coeffs", "rgb"] = "sh_coeffs",
) -> "OrderedDict[str, np.ndarray]":  # fmt: skip
    """The PLY vertex fields of raw splatfacto parameters, in ``ns-export gaussian-splat`` order, each [N].

    means: [N, 3]; features_dc: [N, 3] (SH DC, or logit RGB when ``sh_degree`` is 0); features_rest: [N, K, 3];
    opacities: [N, 1] logits; scales: [N, 3] log; quats: [N, 4] (w, x, y, z).
    """
    n = means.shape[0]
    fields: "OrderedDict[str, np.ndarray]" = OrderedDict()
    positions = means.detach().cpu().float().numpy()
    for i, axis in enumerate("xyz"):
        fields[axis] = positions[:, i]
    for axis in ("nx", "ny", "nz"):
        fields[axis] = np.zeros(n, dtype=np.float32)
    dc = features_dc.detach().cpu().float()
    if sh_degree == 0:  # logit colours -> the SH DC coefficients viewers expect
        dc = (torch.sigmoid(dc) - 0.5) / SH_C0
    if color_mode == "rgb":
        rgb = torch.clamp(dc * SH_C0 + 0.5, 0.0, 1.0).numpy()
        for i, name in enumerate(("red", "green", "blue")):
            fields[name] = (rgb[:, i] * 255).astype(np.uint8)
    else:
        dc = dc.numpy()
        for i in range(dc.shape[1]):
            fields[f"f_dc_{i}"] = dc[:, i]
        if sh_degree > 0:
            # [N, K, 3] -> [N, 3, K] -> [N, 3K]: all red coefficients, then green, then blue (the Inria order)
            rest = features_rest.detach().cpu().float().transpose(1, 2).reshape(n, -1).numpy()
            for i in range(rest.shape[1]):
                fields[f"f_rest_{i}"] = rest[:, i]
    fields["opacity"] = opacities.detach().cpu().float().reshape(n).numpy()
    for name, tensor, width in (("scale", scales, 3), ("rot", quats, 4)):
        values = tensor.detach().cpu().float().numpy()
        for i in range(width):
            fields[f"{name}_{i}"] = values[:, i]
    return fields


def exported_mask(fields: "OrderedDict[str, np.ndarray]") -> np.ndarray:
    """[N] bool: the Gaussians with only finite values and an opacity of at least 1/255."""
    keep = np.ones(len(fields["x"]), dtype=bool)
    for values in fields.values():
        if values.dtype.kind == "f":
            keep &= np.isfinite(values)
    return keep & ~(fields["opacity"] < LOW_OPACITY_LOGIT)


def ply_bytes(fields: "OrderedDict[str, np.ndarray]", comments: Sequence[str] = ()) -> bytes:
    """A binary little-endian PLY with one ``vertex`` element holding ``fields`` (float -> float32, uint8)."""
    count = len(next(iter(fields.values())))
    dtype = [(name, "<f4" if values.dtype.kind == "f" else "u1") for name, values in fields.items()]
    vertices = np.empty(count, dtype=dtype)
    for name, values in fields.items():
        vertices[name] = values
    header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments), f"element vertex {count}"]
    header += [f"property {'float' if kind == '<f4' else 'uchar'} {name}" for name, kind in dtype]
    header.append("end_header")
    return ("\n".join(header) + "\n").encode() + vertices.tobytes()


@dataclass
class ExportCLI:
    """Write the sharp Gaussians of a trained gsmsdr run as a standard 3D Gaussian Splatting PLY."""

    load_config: Path
    """The run's config.yml (outputs/<scene>/gsmsdr/<timestamp>/config.yml)."""
    output: Path
    """The PLY file to write (its folder is created)."""
    ply_color_mode: Literal["sh_coeffs", "rgb"] = "sh_coeffs"
    """"sh_coeffs": f_dc_* / f_rest_* spherical harmonics (3DGS viewers); "rgb": red / green / blue bytes only."""
    obb_center: Optional[Tuple[float, float, float]] = None
    """Centre of an oriented box to crop to (with --obb-rotation and --obb-scale)."""
    obb_rotation: Optional[Tuple[float, float, float]] = None
    """Rotation of the crop box as roll, pitch, yaw in radians."""
    obb_scale: Optional[Tuple[float, float, float]] = None
    """Size of the crop box along each of its axes."""

    def main(self) -> Path:
        from nerfstudio.models.splatfacto import SplatfactoModel
        from nerfstudio.utils.eval_utils import eval_setup

        import gsmsdr_ns.plugin  # noqa: F401  (allow-lists the checkpoint's numpy scalars for torch.load)

        if not self.load_config.is_file():
            raise FileNotFoundError(f"gsmsdr-export: config '{self.load_config}' does not exist; pass a run's "
                                    "config.yml (outputs/<scene>/<method>/<timestamp>/config.yml).")  # fmt: skip
        if self.output.suffix.lower() != ".ply":
            raise ValueError(f"gsmsdr-export: --output '{self.output}' must end in .ply.")
        _, pipeline, checkpoint, step = eval_setup(self.load_config, test_mode="inference")
        model = pipeline.model
        if not isinstance(model, SplatfactoModel):
            raise ValueError(f"gsmsdr-export: '{self.load_config}' is a {type(model).__name__} run, not a Gaussian "
                             "splatting (gsmsdr / splatfacto) run.")  # fmt: skip
        with torch.no_grad():
            params = model.gauss_params
            fields = gaussian_ply_fields(
                params["means"], params["features_dc"], params["features_rest"], params["opacities"],
                params["scales"], params["quats"], model.config.sh_degree, self.ply_color_mode,
            )  # fmt: skip
            keep = exported_mask(fields)
            if self.obb_center is not None and self.obb_rotation is not None and self.obb_scale is not None:
                from nerfstudio.data.scene_box import OrientedBox

                box = OrientedBox.from_params(self.obb_center, self.obb_rotation, self.obb_scale)
                keep &= box.within(params["means"].detach().cpu().float()).numpy()
        if not keep.any():
            raise ValueError(f"gsmsdr-export: no Gaussian of '{checkpoint}' is finite, visible and inside the box.")
        total = len(keep)
        fields = OrderedDict((name, values[keep]) for name, values in fields.items())
        comments = (f"Generated by gsmsdr-export (nerfstudio {version('nerfstudio')})", "Vertical Axis: z")
        self.output.parent.mkdir(parents=True, exist_ok=True)
        write_bytes_atomic(self.output, ply_bytes(fields, comments))
        CONSOLE.print(f"[bold green]wrote {int(keep.sum())}/{total} Gaussians[/bold green] (step {step}, "
                      f"{len(fields)} fields) to {self.output}")  # fmt: skip
        return self.output


def entrypoint() -> None:
    """Console-script entry point."""
    run_entrypoint(lambda: tyro.cli(ExportCLI, args=sys.argv[1:]), CONSOLE)


if __name__ == "__main__":
    entrypoint()
