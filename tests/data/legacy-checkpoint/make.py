"""Writes this folder's config.yml, model.ckpt and degradations.json: a gsmsdr model as the code of commit cd4744e
saved it (thin lens and camera-shake parameters under ``degradation.blur_field``, the loss weights, lens, shake
and margin options in ``BlurFieldConfig``). Run from the repository root with that commit checked out:

    PYTHONPATH=. python tests/data/legacy-checkpoint/make.py

tests/test_legacy_checkpoint.py loads both with today's code. Kept as it ran; later code need not run it.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import torch
import yaml
from nerfstudio.data.scene_box import SceneBox

from gsmsdr_ns.blur.field import BlurFieldConfig
from gsmsdr_ns.plugin.model import GSMSDRModelConfig

HERE = Path(__file__).resolve().parent
RECORDS = (
    [{"split": "train", "degraded": True, "effects": {"motion": {}}}] * 2
    + [{"split": "train", "degraded": True, "effects": {"defocus": {}}}] * 2
    + [{"split": "train", "degraded": False, "effects": {}}]
    + [{"split": "train", "degraded": True, "effects": {"mixres": {"factor": 2}}, "mixres_factor": 2}]
)


def main() -> None:
    torch.manual_seed(0)
    field = BlurFieldConfig(size="lite", kernel_sizes=(3, 5), camera_shake=True, render_margin=True, warmup=7,
                            deconvolved_loss_weight=3.0, thin_lens_initial_aperture=2.5)  # fmt: skip
    config = GSMSDRModelConfig(num_random=32, num_downscales=1, blur_field=field, resolution_kernel_size=5)
    gen = torch.Generator().manual_seed(0)
    seed = (torch.rand(24, 3, generator=gen) - 0.5, torch.randint(0, 256, (24, 3), generator=gen, dtype=torch.uint8))
    box = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = config.setup(scene_box=box, num_train_data=len(RECORDS), metadata={"degradations": RECORDS},
                             seed_points=seed)  # fmt: skip
    with torch.no_grad():  # values a fresh model would not have, so a load that drops them shows
        for i, param in enumerate(model.degradation.parameters()):
            param.add_(0.01 * (i + 1))
    state = {f"_model.{key}": value for key, value in model.state_dict().items()}
    torch.save({"step": 9, "pipeline": state}, HERE / "model.ckpt")
    (HERE / "config.yml").write_text(yaml.dump(config))
    (HERE / "degradations.json").write_text(json.dumps(RECORDS, indent=1) + "\n")


if __name__ == "__main__":
    main()
