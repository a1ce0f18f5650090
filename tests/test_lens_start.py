"""When the thin lens starts (``DegradationConfig.thin_lens_start``): with the field, or when densification stops."""

from __future__ import annotations

import pytest
import torch
from test_plugin_blur import build, records
from test_plugin_model import look_from, make_camera

from gsmsdr_ns.blur import DegradationConfig, DegradationModel
from gsmsdr_ns.blur.field import BlurFieldConfig
from gsmsdr_ns.blur.profile import DegradationProfile

DEFOCUS = DegradationProfile(defocus=True)
MOTION = DegradationProfile(motion=True)
UNKNOWN = DegradationProfile.unknown()


def _model(start: str, densify_until=40, **options) -> DegradationModel:
    config = DegradationConfig(warmup=10, thin_lens_start=start, **options)  # type: ignore[arg-type]
    return DegradationModel([DEFOCUS, MOTION, UNKNOWN], BlurFieldConfig(), config, num_downscales=0,
                            resolution_schedule=1000, densify_until=densify_until)  # fmt: skip


def test_a_lens_alone_image_trains_plain_steps_until_densification_stops():
    model = _model("densify_end")
    assert model.lens_start == 40
    assert model.plan(0, 1, step=5).is_plain  # the field's warm-up
    before = model.plan(0, 1, step=39)
    assert before.is_plain and before.has_model and not before.thin_lens
    after = model.plan(0, 1, step=40)
    assert after.thin_lens and not after.blur_field and not after.is_plain
    # the other choice: the lens starts with the field
    early = _model("warmup")
    assert early.lens_start == 10 and early.plan(0, 1, step=10).thin_lens
    assert DegradationConfig().thin_lens_start == "densify_end"  # the default


def test_the_field_keeps_its_warm_up_and_motion_is_untouched():
    late, default = _model("densify_end", thin_lens_for_unknown_kind=True), _model("warmup")
    for step in (10, 39, 40, 500):
        assert late.plan(1, 1, step) == default.plan(1, 1, step)  # motion: the field alone, from its warm-up
    unknown = late.plan(2, 1, step=20)  # the field runs, the lens in front of it waits
    assert unknown.blur_scale is not None and unknown.blur_field and not unknown.thin_lens
    assert late.plan(2, 1, step=40).thin_lens


def test_the_lens_never_starts_before_the_fields_warm_up_nor_without_a_densification_step():
    assert _model("densify_end", densify_until=3).lens_start == 10
    assert _model("densify_end", densify_until=None).lens_start == 10
    with pytest.raises(ValueError, match="thin_lens_start"):
        DegradationConfig(thin_lens_start="never")  # type: ignore[arg-type]


def test_the_plugin_model_starts_the_lens_at_its_stop_split_at():
    options = DegradationConfig(warmup=0, thin_lens_initial_aperture=20.0, thin_lens_start="densify_end")
    model = build({"degradations": records("defocus", 2)}, n=2, degradation_model=options, background_color="black",
                  num_downscales=0, stop_split_at=7)  # fmt: skip
    assert model.degradation.lens_start == 7
    assert "thin lens for defocus from step 7" in model.degradation.describe()  # the log says when it starts
    model.train()
    model.optimizers = None
    camera = make_camera(look_from([2.0, 0.5, 1.0]), width=48, height=36)
    camera.metadata = {"cam_idx": 0}
    photo = torch.rand(36, 48, 3, generator=torch.Generator().manual_seed(0))
    model.step = 6
    outputs = model.get_outputs(camera)
    assert "rgb_sharp" not in outputs and "degradation_plan" not in outputs  # a plain step
    assert torch.isfinite(model.get_loss_dict(outputs, {"image": photo})["main_loss"])
    model.step = 7
    outputs = model.get_outputs(camera)
    assert outputs["rgb"] is outputs["rgb_degraded"]  # through the lens
    assert not torch.equal(outputs["rgb"], outputs["rgb_sharp"])


@pytest.mark.parametrize("on_lens", [True, False])
def test_a_view_the_lens_blurs_takes_the_deconvolved_loss_by_the_lens_mean_disk(on_lens):
    """With ``deconvolved_loss_on_lens`` a defocused view trained through the lens alone gets ``blur_deconvolved``,
    weighted by the lens's mean disk over the image; before the lens starts, or with the option off, it gets none."""
    camera = make_camera(look_from([2.0, 0.5, 1.0]), width=64, height=48)
    camera.metadata = {"cam_idx": 0}
    image = torch.rand(48, 64, 3, generator=torch.Generator().manual_seed(0))
    options = DegradationConfig(warmup=0, thin_lens_initial_aperture=20.0, thin_lens_start="densify_end",
                                fallback=False, deconvolved_loss_on_lens=on_lens)  # fmt: skip
    torch.manual_seed(0)
    model = build({"degradations": records("defocus", 2)}, n=2, degradation_model=options, background_color="black",
                  num_downscales=0, stop_split_at=5)  # fmt: skip
    model.train()
    model.optimizers = None  # no densification step here

    def step(at: int):
        model.step = at
        outputs = model.get_outputs(camera)
        return model.get_loss_dict(outputs, {"image": image}), outputs.get("degradation")

    losses, aux = step(1)  # before the lens starts: a plain step
    assert "blur_deconvolved" not in losses and aux is None
    losses, aux = step(5)
    if not on_lens:
        assert "blur_deconvolved" not in losses and aux.kernel_mean is None
        return
    kernel = aux.kernel_mean
    assert kernel.dim() == 3 and kernel.shape[1] == kernel.shape[2] and not kernel.requires_grad
    torch.testing.assert_close(kernel.sum(), torch.tensor(1.0))
    assert float(kernel[0, kernel.shape[1] // 2, kernel.shape[2] // 2]) < 0.99  # the lens blurs
    assert losses["blur_deconvolved"].requires_grad
