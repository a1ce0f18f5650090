"""End-to-end demo (``make demo`` / ``python -m gsmsdr_ns.demo``): blurry scene -> train -> ns-eval -> PNG.

1. generates the default procedural scene with camera-motion blur on its training views (``gsmsdr-synth
   --variant motion``: Deblur-NeRF layout, sharp held-out test views) into ``data/demo-motion`` unless it is there;
2. trains ``gsmsdr-lite`` on the blurry training views with nerfstudio's trainer (CPU here: a few minutes on 2
   cores; CUDA when available), with the HPKO / resolution, refinement and learning-rate schedules shortened to the
   demo's step count;
3. runs ns-eval's ``ComputePSNR`` on the sharp test views, which writes the metrics JSON;
4. saves ``sharp ground truth | render`` of the first test view as a PNG;
5. prints, as its last line, ``demo: psnr=<x> ssim=<y> eval_json=<path>``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import torch
import tyro
from PIL import Image


@dataclass
class Demo:
    """Train gsmsdr on the procedural demo scene and report test-view PSNR / SSIM."""

    scene: Path = Path("data/demo-motion")
    """Scene directory; generated as the default ``gsmsdr-synth --variant motion`` scene when it does not exist."""
    output_dir: Path = Path("outputs/demo")
    """Where the training run, the eval JSON and the comparison PNG go."""
    steps: int = 1500
    """Training steps (about 3-4 minutes on a 2-core CPU)."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Training device; "auto" picks CUDA when available."""

    def main(self) -> str:
        started = time.perf_counter()
        scene = ensure_scene(self.scene)
        run_dir = self.train(scene)
        eval_json = self.output_dir / "eval.json"
        results = run_ns_eval(run_dir / "config.yml", eval_json)
        comparison = save_comparison(run_dir / "config.yml", self.output_dir / "test_view_gt_vs_render.png")
        print(f"demo: run {run_dir}; comparison {comparison}; total {time.perf_counter() - started:.0f} s")
        line = f"demo: psnr={results['psnr']:.2f} ssim={results['ssim']:.4f} eval_json={eval_json}"
        print(line, flush=True)
        return line

    def train(self, scene: Path) -> Path:
        """Run nerfstudio's trainer in-process; returns the run directory (holding config.yml)."""
        from nerfstudio.scripts.train import main as train_main

        config = demo_trainer_config(scene, self.output_dir, self.steps, self.device)
        train_main(config)  # sets the timestamp, saves config.yml, trains, writes the final checkpoint
        return config.get_base_dir()


def ensure_scene(scene: Path) -> Path:
    """Reuse a generated degraded scene (it has degradation.json), or generate the default motion one."""
    if (scene / "degradation.json").is_file() and (scene / "sparse" / "0").is_dir():
        return scene
    from gsmsdr_ns.degrade.variants import generate_variant

    print(f"demo: generating the default procedural scene with motion blur into {scene} ...", flush=True)
    return generate_variant(scene, variant="motion")  # refuses to overwrite a non-empty non-scene directory


def demo_trainer_config(scene: Path, output_dir: Path, steps: int, device: str):
    """The ``gsmsdr-lite`` method config with schedules scaled down to ``steps`` (:meth:`TrainingSchedule.demo`)."""
    from gsmsdr_ns.plugin.method_config import gsmsdr_lite_trainer_config
    from gsmsdr_ns.plugin.schedule import TrainingSchedule

    config = gsmsdr_lite_trainer_config()
    config.data = scene
    config.output_dir = output_dir
    config.experiment_name = "demo"
    config.vis = "tensorboard"  # no viewer server that would keep the process alive after training
    config.steps_per_eval_image = 0
    config.steps_per_eval_all_images = 0
    if device != "auto":
        config.machine.device_type = device
    TrainingSchedule.demo(steps).apply(config)
    return config


def run_ns_eval(config_path: Path, output_json: Path) -> dict:
    """ns-eval (nerfstudio's ``ComputePSNR``) on the test split; returns its ``results``."""
    from nerfstudio.scripts.eval import ComputePSNR

    ComputePSNR(load_config=config_path, output_path=output_json).main()
    return json.loads(output_json.read_text())["results"]


def save_comparison(config_path: Path, png_path: Path, view: int = 0) -> Path:
    """Write ``ground truth | render`` of test view ``view`` as an 8-bit PNG."""
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(config_path, test_mode="test")
    datamanager = pipeline.datamanager
    camera = datamanager.eval_dataset.cameras[view : view + 1]
    batch = datamanager.cached_eval[view]
    with torch.no_grad():
        outputs = pipeline.model.get_outputs_for_camera(camera)
        _, images = pipeline.model.get_image_metrics_and_images(outputs, batch)
    pixels = (images["img"].clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
    png_path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(pixels).save(png_path)
    return png_path


def entrypoint(argv: Optional[list] = None) -> None:
    tyro.cli(Demo, args=argv).main()


if __name__ == "__main__":
    entrypoint()
