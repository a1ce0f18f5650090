"""How far the camera-shake paths a bench run learnt are from a generated scene's true paths (prints a table). Run
from the repository root::

    python -m tools.shake.path_error --run runs/<run id>.json --data <generated shaken scene>

``--run`` is a suite run's record with ``train_fit`` on (it then keeps ``shake_paths``, what
:func:`gsmsdr_ns.bench.evaluation.learnt_shake_paths` writes); ``--data`` the scene it trained on, whose
``degradation.json`` keeps each training view's true exposure path and ``depth/`` each view's depth. Per shaken
training view, every pixel of the view (every ``--stride``-th row and column) at its true depth is moved along the
learnt path and along the true one read at the learnt path's time samples (:func:`gsmsdr_ns.blur.shake.
shake_splat_positions`), and the table gives, in pixels:

* ``true extent``: the RMS distance of the true positions from the pixel (how far the shake moves it);
* ``error``: the RMS distance between the learnt and the true positions, the learnt path read forwards or backwards
  in time, whichever is closer (a path and its reverse blur alike);
* ``offset``: the length of the mean difference (a shift of the whole blur, which the scene can absorb in this view
  only by moving against the other views);
* ``error without offset``: the RMS distance once that shift is taken out (the blur's shape).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Dict

import numpy as np
import torch
import tyro
from torch import Tensor

from gsmsdr_ns.blur.recorded_shake import recorded_path
from gsmsdr_ns.blur.shake import path_basis, path_coefficients, shake_splat_positions
from tools.shake.shake_fit import scene_intrinsics

COLUMNS = ("true extent", "error", "offset", "error without offset")
"""The table's columns after the view's name."""


def path_distances(K: Tensor, depth: Tensor, times: Tensor, learnt: Dict[str, Tensor], record: Dict,
                   pose_scale: float) -> Dict[str, float]:  # fmt: skip
    """The table's columns for one view: ``K`` [3, 3], ``depth`` [H, W] (the scene's units times ``pose_scale``, the
    units the learnt translations are in), ``times`` [T] the learnt samples, ``learnt`` its ``rotvecs`` and
    ``translations`` [T, 3], ``record`` the view's motion record."""
    record_times, rotvecs, translations = recorded_path(record, pose_scale)
    basis = path_basis(times)
    true_rot = basis @ path_coefficients(record_times, rotvecs)
    true_move = basis @ path_coefficients(record_times, translations) if translations is not None else 0 * true_rot
    K, depth = K.double(), depth.double()
    truth, _ = shake_splat_positions(K, true_rot, true_move, depth)  # [T, H, W, 2]
    H, W = depth.shape
    ys, xs = torch.meshgrid(torch.arange(H, dtype=K.dtype), torch.arange(W, dtype=K.dtype), indexing="ij")
    extent = float(((truth - torch.stack([xs, ys], dim=-1)) ** 2).sum(-1).mean().sqrt())
    best = None
    for order in (1, -1):  # forwards, then backwards in time
        rot, move = learnt["rotvecs"].double(), learnt["translations"].double()
        positions, _ = shake_splat_positions(K, rot.flip(0) if order < 0 else rot, move.flip(0) if order < 0 else move,
                                             depth)  # fmt: skip
        difference = positions - truth
        error = float((difference**2).sum(-1).mean().sqrt())
        if best is None or error < best[0]:
            shift = difference.mean(dim=(0, 1, 2))
            shape = float(((difference - shift) ** 2).sum(-1).mean().sqrt())
            best = (error, float(shift.norm()), shape)
    assert best is not None
    return dict(zip(COLUMNS, (extent, *best)))


@dataclass
class PathError:
    run: Path
    """A suite run's record (runs/<id>.json) with ``shake_paths`` (the suite had ``train_fit`` on)."""
    data: Path
    """The generated shaken scene it trained on (degradation.json with the true paths, depth/, scene.json)."""
    stride: int = 4
    """Every stride-th row and column of each view is compared."""

    def main(self) -> None:
        torch.set_num_threads(1)
        paths = json.loads(self.run.read_text()).get("shake_paths")
        if not paths:
            raise SystemExit(f"{self.run}: no shake_paths (a run of a shake model with the suite's train_fit on)")
        if paths.get("pose_scale") is None:
            raise SystemExit(f"{self.run}: shake_paths has no pose_scale (its dataparser gave none)")
        K = scene_intrinsics(self.data, torch.float64)
        records = json.loads((self.data / "degradation.json").read_text())["images"]
        scale, times = float(paths["pose_scale"]), torch.tensor(paths["times"], dtype=torch.float64)
        print(f"{self.run.name} against the true paths of {self.data}: pixel distances (RMS over the view's pixels at "
              f"their true depth and the {len(times)} time samples)")  # fmt: skip
        print("| view | " + " | ".join(COLUMNS) + " |")
        print("| --- | " + " | ".join("---:" for _ in COLUMNS) + " |")
        rows = []
        for view in paths["views"]:
            record = records.get(view["name"], {}).get("effects", {}).get("motion")
            if not view["motion"] or record is None or "rotvecs" not in record:
                continue
            depth = np.load(self.data / "depth" / f"{Path(view['name']).stem}.npy").astype(np.float64) * scale
            s = max(int(self.stride), 1)
            K_view = K.clone()
            K_view[:2] /= s  # every s-th pixel: the intrinsics of the subsampled grid
            learnt = {k: torch.tensor(view[k], dtype=torch.float64) for k in ("rotvecs", "translations")}
            distances = path_distances(K_view, torch.from_numpy(depth[::s, ::s].copy()), times, learnt, record, scale)
            distances = {k: v * s for k, v in distances.items()}  # back to full-resolution pixels
            rows.append(distances)
            print(f"| {view['name']} | " + " | ".join(f"{distances[c]:.2f}" for c in COLUMNS) + " |", flush=True)
        if not rows:
            raise SystemExit(f"{self.data}: none of the run's views has a recorded shake path")
        print("| mean | " + " | ".join(f"{np.mean([r[c] for r in rows]):.2f}" for c in COLUMNS) + " |")


def entrypoint(argv=None) -> None:
    tyro.cli(PathError, args=argv).main()


if __name__ == "__main__":
    entrypoint()
