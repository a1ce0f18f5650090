"""What the thin lens learns on a defocused scene with true records (prints a table). Run from the repository root::

    python -m tools.defocus.lens_report --data scene --steps 1500 --every 250 [--init random]

Trains one bench method (default ``full``, the default gsmsdr) on ``--data`` with the bench schedule and, every
``--every`` steps, prints the test PSNR and, over the defocused training views, what the lens does against what the
photos went through (``degradation.json``'s ``max_coc_px`` / 2 at the image width: a disk's radius, or a thin
lens's largest circle-of-confusion radius):

* ``true r``: the mean over views of that largest true radius; ``lens r50`` / ``lens r90``: the mean over views of
  the median and 90th percentile of the learnt circle-of-confusion radius over the view's rendered depth (full-size
  pixels);
* ``r50/true``: the mean ratio of the learnt median radius to the true one (1: right on average; a uniform disk
  wants r50 = r90 = true r);
* ``aperture``, ``focus q``: the shared aperture (px per unit of inverse depth) and where each view's focus sits in
  its depth (the quantile of its rendered inverse depth; a disk has no focus);
* ``gain %``: how much better the lens explains the photos than the sharp render, ``1 - L1(lens(render), photo) /
  L1(render, photo)`` averaged over the views (full resolution, the window the schedule gives at this step);
  ``gain < 0`` views: how many photos the lens explains worse than no lens at all;
* ``in use``: how many of the measured training views train through their degradation model (the rest fall back to
  plain steps, :class:`~gsmsdr_ns.blur.fallback.ExplanationGate`; ``-`` without the fallback).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import torch
import tyro


@dataclass
class LensReport:
    data: Path
    """Scene folder with degradation.json (e.g. written by gsmsdr-synth --variant defocus-disk)."""
    steps: int = 1500
    """Training steps (the bench schedule scaled to them)."""
    every: int = 250
    """Report every this many steps (and at the end)."""
    method: str = "full"
    """Bench method (gsmsdr_ns.bench.methods.METHODS)."""
    init: str = "points"
    """points (the scene's sparse points) or random (Gaussians from random points)."""
    seed: int = 0
    """Training seed."""
    num_downscales: int = 1
    """Resolution schedule of the bench schedule."""
    blur_warmup: float = 0.05
    """Fraction of the steps before the degradation models (lens included) start (the bench schedule's)."""
    work: Path = Path("/tmp/gsmsdr-lens-report")
    """Trainer output folder (only nerfstudio's config is written)."""

    def main(self) -> None:
        from gsmsdr_ns.bench.evaluation import evaluate_test_views
        from gsmsdr_ns.bench.methods import METHODS
        from gsmsdr_ns.bench.training import InProcessRun
        from gsmsdr_ns.plugin.schedule import TrainingSchedule

        torch.set_num_threads(1)
        config = METHODS[self.method].make_config(self.data, self.work)
        schedule = TrainingSchedule.bench(self.steps, num_downscales=self.num_downscales,
                                          blur_warmup_fraction=self.blur_warmup)  # fmt: skip
        schedule.apply(config)
        config.pipeline.model.random_init = self.init == "random"
        run = InProcessRun(config, seed=self.seed)
        truth = true_radii(self.data)
        print(f"{self.method} on {self.data} ({self.init} init), {self.steps} steps, degradation from step "
              f"{int(self.blur_warmup * self.steps)}")  # fmt: skip
        print(
            "| step | test PSNR | Gaussians | views | true r | lens r50 | lens r90 | r50/true | aperture | focus q | "
            "gain % | gain < 0 views | in use |"
        )
        print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
        try:
            targets = sorted({*range(self.every, self.steps, self.every), self.steps})
            for target in targets:
                run.train(target - run.step)
                psnr = evaluate_test_views(run)["psnr"]
                row = lens_rows(run, truth)
                cells = f"{run.step} | {psnr:.2f} | {int(run.model.num_points)} | {row} {models_in_use(run)}"
                print(f"| {cells} |", flush=True)
        finally:
            run.close()


def true_radii(scene: Path) -> Dict[str, float]:
    """{image name: largest true defocus radius in pixels at the image width} of the defocused training images."""
    doc = json.loads((Path(scene) / "degradation.json").read_text(encoding="utf8"))
    radii = {}
    for name, entry in doc["images"].items():
        defocus = entry.get("effects", {}).get("defocus")
        if isinstance(defocus, dict) and "max_coc_px" in defocus:
            radii[name] = float(defocus["max_coc_px"]) / 2
    return radii


def models_in_use(run) -> str:
    """``"<views training through their model> / <views measured>"`` of the fallback gate; ``-`` without one."""
    gate = getattr(getattr(run.model, "degradation", None), "fallback", None)
    if gate is None:
        return "-"
    return f"{int(gate.views_using_model().sum())} / {int(gate.views_measured().sum())}"


@torch.no_grad()
def lens_rows(run, truth: Dict[str, float]) -> str:
    """The table cells after the Gaussian count for the current state of ``run``'s lens (see the module)."""
    model = run.model
    lens = getattr(model.degradation, "thin_lens", None) if getattr(model, "degradation", None) else None
    if lens is None:
        return "0 | - | - | - | - | - | - | - | - |"
    datamanager = run.pipeline.datamanager
    dataset = datamanager.train_dataset
    names = [Path(p).name for p in dataset._dataparser_outputs.image_filenames]
    was_training = model.training
    model.eval()
    stats: List[List[float]] = []
    try:
        for index, name in enumerate(names):
            if name not in truth:
                continue
            camera = dataset.cameras[index : index + 1].to(model.device)
            camera.metadata = {"cam_idx": index}
            outputs = model.get_outputs(camera)
            depth = outputs["depth"].permute(2, 0, 1)[None].float()  # [1, 1, H, W]
            ids = torch.tensor([index], device=depth.device)
            radius = lens.radius(depth, ids).flatten()
            inverse = 1.0 / depth.flatten().clamp_min(1e-6)
            focus = float(lens.inverse_focus[index])
            quantile = float((inverse < focus).float().mean())
            r50, r90 = float(radius.median()), float(torch.quantile(radius, 0.9))
            rgb = outputs["rgb"].permute(2, 0, 1)[None].float()
            photo = dataset[index]["image"][..., :3].to(rgb.device).float().permute(2, 0, 1)[None]
            photo = photo / 255.0 if photo.max() > 1.5 else photo
            window = model.degradation.plan(index, 1, run.step).blur_scale
            size = window.kernel_size if window is not None else 17
            through = lens.blur(rgb, depth, ids, size, 1.0, model.degradation.config.linear_light)
            gain = 1.0 - float((through - photo).abs().mean()) / max(float((rgb - photo).abs().mean()), 1e-9)
            stats.append([truth[name], r50, r90, r50 / max(truth[name], 1e-6), quantile, gain])
    finally:
        model.train(was_training)
    if not stats:
        return "0 | - | - | - | - | - | - | - | - |"
    table = np.asarray(stats)
    mean = table.mean(axis=0)
    aperture = float(torch.exp(lens.log_aperture))
    return (f"{len(stats)} | {mean[0]:.2f} | {mean[1]:.2f} | {mean[2]:.2f} | {mean[3]:.2f} | {aperture:.3g} | "
            f"{mean[4]:.2f} | {100 * mean[5]:.1f} | {int((table[:, 5] < 0).sum())} |")  # fmt: skip


def entrypoint(argv: Optional[List[str]] = None) -> None:
    tyro.cli(LensReport, args=argv).main()


if __name__ == "__main__":
    entrypoint()
