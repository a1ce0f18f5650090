"""A model saved by older code (tests/data/legacy-checkpoint, written by its make.py at commit cd4744e: lens, shake,
margin, schedule and loss options in ``BlurFieldConfig``, the thin lens under the blur field) loads with today's
code: its config.yml gives the same options in their new homes, and its checkpoint fills every parameter."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import torch
import yaml
from nerfstudio.data.scene_box import SceneBox

import gsmsdr_ns.plugin  # noqa: F401  (checkpoint globals for torch.load)
from gsmsdr_ns.blur.degradation_config import DegradationConfig
from gsmsdr_ns.blur.field import BlurFieldConfig
from gsmsdr_ns.plugin.model import GSMSDRModelConfig

LEGACY = Path(__file__).resolve().parent / "data" / "legacy-checkpoint"


def legacy_config() -> GSMSDRModelConfig:
    return yaml.load((LEGACY / "config.yml").read_text(), Loader=yaml.Loader)


def test_an_old_config_yml_puts_each_option_where_it_lives_now():
    config = legacy_config()
    assert isinstance(config.degradation_model, DegradationConfig)
    options = config.degradation_model
    assert (options.camera_shake, options.render_margin, options.warmup) == (True, True, 7)
    assert (options.deconvolved_loss_weight, options.thin_lens_initial_aperture) == (3.0, 2.5)
    assert options.resolution_kernel_size == 5 and not hasattr(config, "resolution_kernel_size")
    field = config.blur_field
    assert (field.size, tuple(field.kernel_sizes)) == ("lite", (3, 5))
    assert not hasattr(field, "camera_shake") and not hasattr(field, "warmup")
    assert vars(field).keys() == vars(BlurFieldConfig()).keys()  # nothing left over, nothing missing


def test_an_old_checkpoint_loads_every_parameter_into_todays_modules():
    config = legacy_config()
    records = json.loads((LEGACY / "degradations.json").read_text())
    box = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = config.setup(scene_box=box, num_train_data=len(records), metadata={"degradations": records},
                             seed_points=None)  # fmt: skip
    saved = torch.load(LEGACY / "model.ckpt", map_location="cpu", weights_only=False)["pipeline"]
    saved = {key.removeprefix("_model."): value for key, value in saved.items()}
    model.load_state_dict(saved)  # strict: every key of today's model is filled, none is left over
    lens = model.degradation.thin_lens
    assert lens is not None and model.degradation.camera_shake is not None
    torch.testing.assert_close(lens.log_aperture.detach(), saved["degradation.blur_field.thin_lens.log_aperture"])
    torch.testing.assert_close(
        model.degradation.camera_shake.coefficients.detach(), saved["degradation.camera_shake.coefficients"]
    )
    field_key = next(k for k in saved if k.startswith("degradation.blur_field.heads."))
    torch.testing.assert_close(model.state_dict()[field_key], saved[field_key])
