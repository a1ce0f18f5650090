"""The blur field wired into training: built and evaluated only for the images that need it.

Scenes are 10-view 64x48 ``gsmsdr-synth`` variants (motion, mixres, sharp) in the Deblur-NeRF layout, read by the
default ``gsmsdr-data`` parser. In-process tests drive nerfstudio's real ``Trainer.train_iteration`` with the real
datamanager, optimizers and training callbacks (no viewer, no writers); the CLI tests run ``ns-train`` / ``ns-eval``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import warnings
from collections import defaultdict
from pathlib import Path
from typing import Dict, List

import pytest
import torch
import yaml
from conftest import TINY_SCENE, TRAIN_FLAGS, run_cli
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.engine.callbacks import TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer
from test_plugin_model import look_from, make_camera, seed_cloud

import gsmsdr_ns.plugin  # noqa: F401  (checkpoint globals for torch.load)
from gsmsdr_ns.blur import BlurField, BlurFieldConfig, DegradationConfig, ResolutionLossModel
from gsmsdr_ns.blur.preview import coarsen_kernels, kernel_spread, nearest_view, preview_downscale
from gsmsdr_ns.plugin.method_config import gsmsdr_trainer_config
from gsmsdr_ns.plugin.model import GSMSDRModelConfig, GSMSDRWarning

SHARP_TRAIN_VIEWS = ("frame_00002.png", "frame_00005.png", "frame_00009.png")  # training views (hold=8)
CLI_STEPS = 20
BLUR_FLAGS = ("--pipeline.model.degradation-model.warmup", "4")


def make_variant(out: Path, variant: str) -> Path:
    from gsmsdr_ns.degrade import generate_variant
    from gsmsdr_ns.synth.config import SynthSceneConfig

    return generate_variant(out, SynthSceneConfig(**TINY_SCENE), variant)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Dict[str, Path]:
    """motion, defocus, mixres and sharp variants, and ``partly_sharp``: the motion scene with three training views
    replaced by their sharp twins and marked ``degraded: false`` in degradation.json (read-only)."""
    root = tmp_path_factory.mktemp("blur_scenes")
    out = {name: make_variant(root / name, name) for name in ("motion", "defocus", "mixres", "sharp")}
    partly = Path(shutil.copytree(out["motion"], root / "partly_sharp"))
    doc = json.loads((partly / "degradation.json").read_text())
    for name in SHARP_TRAIN_VIEWS:
        shutil.copyfile(partly / "images_test" / name, partly / "images" / name)
        doc["images"][name] = {"split": "train", "degraded": False, "effects": {}}
    (partly / "degradation.json").write_text(json.dumps(doc))
    out["partly_sharp"] = partly
    return out


# -- in-process training with nerfstudio's Trainer ---------------------------------------------------------------


class InProcessTrainer:
    """``Trainer.train_iteration`` with the gsmsdr preset on CPU, without viewer or event writers."""

    def __init__(self, data: Path, tmp: Path, warmup: int = 2, **model_overrides):
        config = gsmsdr_trainer_config()
        config.machine.device_type = "cpu"
        config.vis = "tensorboard"
        config.output_dir = tmp / "outputs"
        config.pipeline.datamanager.data = data
        model = config.pipeline.model
        model.num_downscales, model.warmup_length, model.refine_every = 0, 10, 10
        model.degradation_model = dataclasses.replace(model.degradation_model, warmup=warmup)
        for name, value in model_overrides.items():
            setattr(model, name, value)
        trainer = Trainer(config)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", GSMSDRWarning)
            trainer.pipeline = config.pipeline.setup(
                device="cpu", test_mode="val", world_size=1, local_rank=0, grad_scaler=trainer.grad_scaler
            )
        trainer.optimizers = trainer.setup_optimizers()
        attributes = TrainingCallbackAttributes(trainer.optimizers, trainer.grad_scaler, trainer.pipeline, trainer)
        trainer.callbacks = trainer.pipeline.get_training_callbacks(attributes)
        self.trainer = trainer
        self.model = trainer.pipeline.model
        self.steps: List[dict] = []  # per step: view, output keys, loss terms

    def train(self, num_steps: int) -> None:
        record: dict = {}

        def on_model(_module, inputs, outputs):
            record.update(view=int(inputs[0].metadata["cam_idx"]), keys=set(outputs))

        handle = self.model.register_forward_hook(on_model)
        try:
            for _ in range(num_steps):
                step = len(self.steps)
                for callback in self.trainer.callbacks:
                    callback.run_callback_at_location(step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
                loss, loss_dict, _ = self.trainer.train_iteration(step)
                for callback in self.trainer.callbacks:
                    callback.run_callback_at_location(step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
                assert math.isfinite(loss.item()), loss_dict
                self.steps.append({"step": step, **record, "losses": set(loss_dict)})
        finally:
            handle.remove()


def count_calls(module: torch.nn.Module, calls: List[tuple]):
    """Forward hook appending ``(view ids, input height, last argument)`` for every call of ``module``: the HPKO
    scale for the blur field (``render, depth, view_ids, scale``), the view ids for the resolution model (``render,
    factors, view_ids``: factors are then read from ``inputs[1]``)."""

    def hook(_module, inputs, _outputs):
        render, views = inputs[0], inputs[2]
        last = inputs[3] if len(inputs) > 3 else inputs[1]
        calls.append((tuple(int(v) for v in views.tolist()), render.shape[-2], last))

    return module.register_forward_hook(hook)


def test_blur_field_is_never_evaluated_on_sharp_training_images(scenes, tmp_path):
    run = InProcessTrainer(scenes["partly_sharp"], tmp_path, warmup=2)
    model = run.model
    names = [record["name"] for record in run.trainer.pipeline.datamanager.train_dataset.metadata["degradations"]]
    sharp = {i for i, name in enumerate(names) if name in SHARP_TRAIN_VIEWS}
    assert len(sharp) == 3 and {i for i, p in enumerate(model.degradation.profiles) if p.is_sharp} == sharp
    assert isinstance(model.degradation.blur_field, BlurField) and model.degradation.blur_field.uses_depth
    assert model.degradation.resolution_model is None
    assert torch.isfinite(model.degradation.train_camera_centres).all()  # filled from the datamanager at training start

    calls: List[tuple] = []
    handle = count_calls(model.degradation.blur_field, calls)
    try:
        run.train(18)  # 8 training views: steps 8-15 are one full epoch after the warm-up
    finally:
        handle.remove()

    field_views = defaultdict(int)
    for views, height, scale in calls:
        field_views[views[0]] += 1
        assert (height, scale) == (48, 1)  # num_downscales 0: full resolution, finest HPKO scale
    after_warmup = [s for s in run.steps if s["step"] >= 2]
    assert {s["view"] for s in after_warmup} == set(range(8))  # every view, sharp ones included, was trained
    assert not sharp & set(field_views), f"blur field ran on sharp views {sorted(sharp & set(field_views))}"
    blurred_steps = [s for s in after_warmup if s["view"] not in sharp]
    assert sum(field_views.values()) == len(blurred_steps) > 0  # once per blurred step, never during warm-up
    for s in run.steps:
        degraded = s["step"] >= 2 and s["view"] not in sharp
        assert ("blur_mask_reg" in s["losses"]) == degraded, s
        assert ("blur_deconvolved" in s["losses"]) == degraded, s  # a sharp image pays for no blur term
        assert ({"rgb_sharp", "blur_mask"} <= s["keys"]) == degraded, s
        if not degraded:
            assert "rgb_sharp" not in s["keys"] and s["keys"] == {"rgb", "depth", "accumulation", "background"}
    # the field's parameters are optimised with their own group
    assert "blur_field" in run.trainer.optimizers.optimizers


def test_sharp_scene_builds_no_degradation_model(scenes, tmp_path):
    run = InProcessTrainer(scenes["sharp"], tmp_path)
    model = run.model
    assert all(p.is_sharp for p in model.degradation.profiles)
    assert (
        model.degradation.blur_field is None
        and model.degradation.resolution_model is None
        and model.degradation.hpko is None
    )
    assert not any(k.startswith("degradation.") for k in model.state_dict())
    assert set(run.trainer.optimizers.parameters) & {"blur_field", "resolution_model"} == set()
    run.train(4)
    assert all(s["keys"] == {"rgb", "depth", "accumulation", "background"} for s in run.steps)
    model.eval()
    camera, _ = run.trainer.pipeline.datamanager.next_eval_image(0)
    assert "degraded" not in model.get_outputs_for_camera(camera)


def test_mixres_scene_uses_the_resolution_model_not_the_blur_field(scenes, tmp_path):
    run = InProcessTrainer(scenes["mixres"], tmp_path)
    model = run.model
    factors = [p.mixres_factor for p in model.degradation.profiles]
    assert sorted(set(factors)) == [1, 2, 3, 4]
    assert model.degradation.blur_field is None and isinstance(model.degradation.resolution_model, ResolutionLossModel)
    assert "resolution_model" in run.trainer.optimizers.optimizers
    residual_before = model.degradation.resolution_model.residual.detach().clone()
    calls: List[tuple] = []
    handle = count_calls(model.degradation.resolution_model, calls)
    try:
        run.train(8)  # one epoch: every view once
    finally:
        handle.remove()
    ran_on = sorted(views[0] for views, _, _ in calls)
    assert ran_on == sorted(i for i, f in enumerate(factors) if f > 1)
    assert all(f == [float(factors[v[0]])] for v, _, f in calls)  # num_downscales 0: the full factor
    assert not torch.equal(
        model.degradation.resolution_model.residual.detach(), residual_before
    )  # the residual is trained


# -- model level: profiles -> modules, HPKO scale, viewer outputs --------------------------------------------------


def records(kind: str, n: int = 4) -> List[dict]:
    effects = {"motion": {"motion": {}}, "defocus": {"defocus": {}}, "sharp": {}}
    if kind == "mixres":
        return [{"split": "train", "degraded": f > 1, "effects": {"mixres": {"factor": f}}, "mixres_factor": f}
                for f in (1, 2, 3, 4)[:n]]  # fmt: skip
    return [{"split": "train", "degraded": kind != "sharp", "effects": effects[kind]} for _ in range(n)]


def build(metadata, n: int = 4, **config):
    config = GSMSDRModelConfig(**{"num_random": 100, **config})
    scene_box = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GSMSDRWarning)
        return config.setup(scene_box=scene_box, num_train_data=n, metadata=metadata, seed_points=seed_cloud())


@pytest.mark.parametrize(
    "degradation, degradations, field, depth, resolution, lens",
    [
        ("auto", records("motion"), True, True, False, False),
        ("auto", records("defocus"), True, True, False, True),
        ("auto", records("sharp"), False, False, False, False),
        ("auto", records("mixres"), False, False, True, False),
        ("auto", None, True, True, False, False),  # nothing known: the blur field models any blur, no lens
        ("sharp", records("motion"), False, False, False, False),
        ("motion", records("sharp"), False, False, False, False),  # images the records call undegraded stay sharp
        ("motion", None, True, True, False, False),
        ("defocus", None, True, True, False, True),
        ("mixres", None, True, False, False, False),  # resolution loss of unknown factor: the field learns it
    ],
)
def test_modules_follow_the_profiles(degradation, degradations, field, depth, resolution, lens):
    metadata = None if degradations is None else {"degradations": degradations}
    model = build(metadata, degradation=degradation)
    assert (model.degradation.blur_field is not None) == field
    assert (model.degradation.blur_field is not None and model.degradation.blur_field.uses_depth) == depth
    assert (model.degradation.resolution_model is not None) == resolution
    assert (model.degradation.thin_lens is not None) == lens
    groups = model.get_param_groups()
    assert ("blur_field" in groups) == field and ("resolution_model" in groups) == resolution
    assert ("blur_defocus" in groups) == lens


def test_a_blur_of_unknown_kind_gets_the_field_and_the_lens_only_when_asked():
    """Estimated records that found the images blurred but could not tell motion from defocus name both blurs: the
    field alone models them unless thin_lens_for_unknown_kind; a record naming defocus always gets the lens."""
    estimated = {"model": "estimated"}
    both = {"motion": dict(estimated), "defocus": dict(estimated)}
    unknown_kind = [{"split": "train", "degraded": True, "effects": both, "source": "estimated"} for _ in range(4)]
    for degradations, ask, lens in (
        (unknown_kind, False, False),
        (unknown_kind, True, True),
        (records("defocus"), False, True),  # a true record names defocus
        ([{**r, "effects": {"defocus": dict(estimated)}} for r in unknown_kind], False, True),  # estimated: defocus
        ([{**r, "effects": {"motion": {}, "defocus": {}}} for r in unknown_kind], False, True),  # both, recorded
    ):
        model = build(
            {"degradations": degradations}, degradation_model=DegradationConfig(thin_lens_for_unknown_kind=ask)
        )
        assert model.degradation.blur_field is not None and model.degradation.blur_field.uses_depth
        assert (model.degradation.thin_lens is not None) == lens, (degradations[0]["effects"], ask)
        plan = model.degradation.plan(0, 1, step=10**6)  # past the field's warm-up
        assert plan.thin_lens == lens and plan.blur_scale is not None


@pytest.mark.parametrize("mode", ["full", "view"])
def test_thin_lens_blurs_defocused_images_only_and_learns(mode):
    """Views 0-1 defocused, 2-3 motion-blurred: the lens runs (and gets gradients) for views 0-1 only, before the
    field, and its depth-driven blur is part of the simulated image."""
    metadata = {"degradations": records("defocus", 2) + records("motion", 2)}
    options = DegradationConfig(warmup=0, thin_lens_initial_aperture=20.0, thin_lens_start="warmup")
    model = build(metadata, blur_field=BlurFieldConfig(mode=mode), degradation_model=options)
    model.train()
    model.optimizers = None
    lens = model.degradation.thin_lens
    lens_calls: List[tuple] = []
    handle = lens.register_forward_hook(lambda _m, inputs, _o: lens_calls.append(tuple(inputs[1].tolist())))
    for view in (0, 2):
        camera = make_camera(look_from([2.0, 0.5, 1.0]), width=64, height=48)
        camera.metadata = {"cam_idx": view}
        model.step = 5
        outputs = model.get_outputs(camera)
        assert outputs["depth"] is not None or (mode == "view" and view == 2)  # the lens needs depth, view mode not
        lens.zero_grad()
        (outputs["rgb_degraded"] - 0.5).abs().mean().backward()  # the lens learns on fallback steps too
        if view == 0:
            assert lens.log_aperture.grad is not None and float(lens.log_aperture.grad.abs()) > 0
            assert float(lens.inverse_focus.grad[0].abs()) > 0 and float(lens.inverse_focus.grad[1]) == 0
        else:
            assert lens.log_aperture.grad is None or float(lens.log_aperture.grad.abs()) == 0
    handle.remove()
    assert lens_calls == [(0,)]
    assert lens.focus_initialised.tolist() == [True, False, False, False]


@pytest.mark.parametrize("defocus_field", [False, True])
def test_defocus_only_images_skip_the_field_unless_asked(defocus_field):
    """View 0 defocused only, view 1 motion-blurred and defocused, view 2 unknown (no record): the thin lens alone
    models view 0 (the field is not evaluated, no mask), the field runs after the lens for view 1 and alone for view
    2 (its kind of blur is unknown); with ``defocus_field`` the field runs for view 0 too."""
    both = {"split": "train", "degraded": True, "effects": {"motion": {}, "defocus": {}}}
    unknown = {"split": "train"}
    metadata = {"degradations": records("defocus", 1) + [both, unknown] + records("sharp", 1)}
    config = DegradationConfig(
        warmup=0, thin_lens_initial_aperture=20.0, defocus_field=defocus_field, thin_lens_start="warmup"
    )
    model = build(metadata, degradation_model=config)
    model.train()
    model.optimizers = None
    field_calls: List[tuple] = []
    lens_calls: List[int] = []
    handles = [
        count_calls(model.degradation.blur_field, field_calls),
        model.degradation.thin_lens.register_forward_hook(lambda _m, i, _o: lens_calls.append(int(i[1]))),
    ]
    for view in range(4):
        camera = make_camera(look_from([2.0, 0.5, 1.0]), width=64, height=48)
        camera.metadata = {"cam_idx": view}
        model.step = 5
        outputs = model.get_outputs(camera)
        assert ("blur_mask" in outputs) == (view in (1, 2) or (view == 0 and defocus_field))
        if view == 0:  # the lens's blur is the simulated image
            assert float((outputs["rgb_degraded"] - outputs["rgb_sharp"]).abs().max()) > 1e-3
    for handle in handles:
        handle.remove()
    assert [views for views, _, _ in field_calls] == ([(0,)] if defocus_field else []) + [(1,), (2,)]
    assert lens_calls == [0, 1]


def test_records_must_match_the_training_images():
    with pytest.raises(ValueError, match="describes the degradation of 3 training images, but there are 4"):
        build({"degradations": records("motion", 3)})


def test_hpko_scale_follows_the_current_render_downscale():
    """num_downscales 2, resolution_schedule 4: 1/4 -> 1/2 -> full resolution; K = 5 -> 9 -> 17 in step. The scale
    is a function of the step being rendered (no training callback or running state carries it)."""
    motion = {"degradations": records("motion")}
    model = build(motion, num_downscales=2, resolution_schedule=4, degradation_model=DegradationConfig(warmup=0))
    model.train()
    model.optimizers = None
    callbacks = model.get_training_callbacks(TrainingCallbackAttributes(None, None, None, None))
    assert not any(getattr(c.func, "__self__", None) is model.degradation for c in callbacks)
    calls: List[tuple] = []
    handle = count_calls(model.degradation.blur_field, calls)
    camera = make_camera(look_from([2.0, 0.5, 1.0]), width=64, height=48)
    camera.metadata = {"cam_idx": 1}
    sizes = []
    for step in [*range(10), 3, 0]:  # going back gives the earlier scale again
        model.step = step
        outputs = model.get_outputs(camera)
        assert outputs["rgb"].shape == outputs["rgb_sharp"].shape == outputs["blur_mask"].shape[:2] + (3,)
        sizes.append(model.get_metrics_dict(outputs, {"image": torch.zeros(48, 64, 3)})["blur_kernel_size"])
    handle.remove()
    assert [(h, s) for _, h, s in calls] == [(12, 3)] * 4 + [(24, 2)] * 4 + [(48, 1)] * 2 + [(12, 3)] * 2
    assert sizes == [5] * 4 + [9] * 4 + [17] * 2 + [5] * 2


def _shift_left_two_pixels(model) -> None:
    """Every view's kernel (mode view, one 5 x 5 scale) becomes a delta two columns right of centre: the blurred
    image at column x is the render's column x + 2."""
    with torch.no_grad():
        logits = model.degradation.blur_field.heads.view_logits["1"]
        logits.fill_(-40.0)
        logits[:, 2 * 5 + 4] = 40.0


@pytest.mark.parametrize("margin", [True, False])
def test_blurred_views_render_a_margin_the_blur_reads_then_crop_it(margin):
    """With ``render_margin`` a blurred training view is rendered K // 2 pixels beyond every border and cropped after
    blurring: a kernel that shifts the image fills the last columns with what lies just outside the frame (the
    render of a camera 2 * 2 pixels wider and taller), not with the replicated border."""
    field = BlurFieldConfig(mode="view", kernel_sizes=(5,), progressive=False)
    options = DegradationConfig(warmup=0, linear_light=False, render_margin=margin, fallback=False)
    model = build({"degradations": records("motion")}, num_downscales=0, background_color="white", blur_field=field,
                  degradation_model=options)  # fmt: skip
    _shift_left_two_pixels(model)
    c2w = look_from([0.8, 0.3, 0.35])  # close: the Gaussians fill the frame and run past its borders
    camera = make_camera(c2w, width=64, height=48)
    camera.metadata = {"cam_idx": 0}
    model.train()
    model.optimizers = None  # the densification strategy's pre-backward step reads it
    model.step = 10
    outputs = model.get_outputs(camera)
    assert outputs["rgb"].shape == outputs["rgb_sharp"].shape == (48, 64, 3)
    assert outputs["accumulation"].shape == (48, 64, 1) and outputs["blur_mask"].shape == (48, 64, 1)
    model.eval()
    with torch.no_grad():
        wider = model.get_outputs(make_camera(c2w, width=68, height=52))["rgb"]  # principal point moves by 2 too
        sharp = model.get_outputs(make_camera(c2w, width=64, height=48))["rgb"]
    shifted = wider[2:-2, 4:]
    assert (shifted[:, -1] - sharp[:, -1]).abs().max() > 0.02  # the frame's edge is not what lies past it
    assert torch.allclose(outputs["rgb_sharp"], sharp, atol=4e-3)  # other image size, other tiles: rounding
    if margin:
        assert torch.allclose(outputs["rgb"], shifted, atol=4e-3)
    else:  # replicate padding: the last two columns repeat the render's last column
        assert torch.allclose(outputs["rgb"][:, :-2], shifted[:, :-2], atol=4e-3)
        assert torch.allclose(outputs["rgb"][:, -2:], sharp[:, -1:].expand(-1, 2, -1), atol=1e-3)


def test_camera_shake_runs_on_views_that_may_be_shaken_and_learns():
    """Views: motion, defocus, sharp, blur of unknown kind. With ``camera_shake`` the rotation paths are built, run
    on the motion and unknown-kind views only (before the field), and the drawn view's path gets the gradient."""
    estimated = {"model": "estimated"}
    recs = records("motion", 1) + records("defocus", 1) + records("sharp", 1)
    recs.append({"split": "train", "degraded": True, "source": "estimated",
                 "effects": {"motion": dict(estimated), "defocus": dict(estimated)}})  # fmt: skip
    config = DegradationConfig(camera_shake=True, warmup=0, deconvolved_loss_on_shake=True)
    model = build({"degradations": recs}, num_downscales=0, degradation_model=config)
    shake = model.degradation.camera_shake
    assert shake is not None and model.get_param_groups()["blur_shake"] == [shake.coefficients]
    assert [model.degradation.plan(i, 1, step=10).shake for i in range(4)] == [True, False, False, True]
    model.train()
    model.optimizers = None
    camera = make_camera(look_from([2.0, 0.5, 1.0]), width=32, height=24)
    camera.metadata = {"cam_idx": 3}
    outputs = model.get_outputs(camera)
    assert outputs["rgb"].shape == (24, 32, 3)
    outputs["rgb_degraded"].sum().backward()
    grad = shake.coefficients.grad
    assert grad is not None and float(grad[3].abs().sum()) > 0 and torch.equal(grad[:3], torch.zeros_like(grad[:3]))
    aux, field_size = outputs["degradation"], model.degradation.plan(3, 1, step=10).blur_scale.kernel_size
    assert aux.kernel_mean.shape == (1, 3 * field_size, 3 * field_size)  # the path's window (2 K + 1) composed in
    assert float(aux.kernel_mean.sum()) == pytest.approx(1.0, abs=1e-4)
    config = DegradationConfig(camera_shake=True, warmup=0)  # the path left out of the loss's kernel
    alone = build({"degradations": recs}, num_downscales=0, degradation_model=config)
    alone.train()
    alone.optimizers = None
    assert alone.get_outputs(camera)["degradation"].kernel_mean.shape == (1, field_size, field_size)
    assert build({"degradations": recs}).degradation.camera_shake is None  # off unless asked
    no_motion = build({"degradations": records("defocus")}, degradation_model=DegradationConfig(camera_shake=True))
    assert no_motion.degradation.camera_shake is None and "blur_shake" not in no_motion.get_param_groups()


def test_a_translating_shake_path_renders_depth_and_learns():
    """With ``shake_translation`` a shaken view's plan asks for depth (mode view reads none otherwise), the render
    produces it and both the rotation and the translation coefficients of the drawn view get the gradient."""
    config = DegradationConfig(camera_shake=True, shake_translation=True, warmup=0)
    model = build({"degradations": records("motion", 2) + records("sharp", 1)}, n=3, num_downscales=0,
                  degradation_model=config, blur_field=BlurFieldConfig(mode="view"))  # fmt: skip
    shake = model.degradation.camera_shake
    assert shake is not None and shake.translation_coefficients is not None
    assert model.get_param_groups()["blur_shake"] == [shake.coefficients, shake.translation_coefficients]
    plans = [model.degradation.plan(i, 1, step=10) for i in range(3)]
    assert [(p.shake_depth, p.needs_depth) for p in plans] == [(True, True), (True, True), (False, False)]
    model.train()
    model.optimizers = None
    camera = make_camera(look_from([2.0, 0.5, 1.0]), width=32, height=24)
    camera.metadata = {"cam_idx": 1}
    outputs = model.get_outputs(camera)
    assert outputs["rgb_degraded"].shape == (24, 32, 3) and torch.isfinite(outputs["rgb_degraded"]).all()
    outputs["rgb_degraded"].sum().backward()
    for grad in (shake.coefficients.grad, shake.translation_coefficients.grad):
        assert grad is not None and float(grad[1].abs().sum()) > 0 and torch.equal(grad[0], torch.zeros_like(grad[0]))


def test_shake_translations_start_when_densification_ends_if_asked():
    """``shake_translation_start="densify_end"``: the paths rotate only (no depth, no translation gradient) until
    the model's ``stop_split_at``, then translate; ``shake_parallax`` reaches the module."""
    config = DegradationConfig(
        camera_shake=True, shake_translation=True, shake_translation_start="densify_end", shake_parallax=True, warmup=0
    )
    model = build({"degradations": records("motion", 2)}, n=2, num_downscales=0, stop_split_at=40,
                  degradation_model=config, blur_field=BlurFieldConfig(mode="view"))  # fmt: skip
    degradation = model.degradation
    assert degradation.shake_translation_start == 40 and degradation.camera_shake.parallax
    assert [degradation.plan(0, 1, step).shake_depth for step in (0, 39, 40, 100)] == [False, False, True, True]
    assert not degradation.plan(0, 1, 39).needs_depth
    model.train()
    model.optimizers = None
    camera = make_camera(look_from([2.0, 0.5, 1.0]), width=32, height=24)
    camera.metadata = {"cam_idx": 1}
    shake = degradation.camera_shake
    for step, translates in ((39, False), (40, True)):
        model.step = step
        shake.zero_grad(set_to_none=True)
        model.get_outputs(camera)["rgb_degraded"].sum().backward()
        assert float(shake.coefficients.grad[1].abs().sum()) > 0
        grad = shake.translation_coefficients.grad
        assert (grad is not None and float(grad[1].abs().sum()) > 0) == translates
    with pytest.raises(ValueError, match="shake_translation_start"):
        DegradationConfig(shake_translation_start="never")


def test_warm_up_follows_the_step_being_rendered():
    """The blur field is skipped until the model's step reaches the warm-up."""
    model = build({"degradations": records("motion")}, degradation_model=DegradationConfig(warmup=3))
    model.train()
    model.optimizers = None
    camera = make_camera(look_from([2.0, 0.5, 1.0]), width=64, height=48)
    camera.metadata = {"cam_idx": 0}
    ran = []
    for step in range(5):
        model.step = step
        ran.append("blur_mask" in model.get_outputs(camera))
    assert ran == [False, False, False, True, True]


def test_a_checkpoint_from_before_the_degradation_model_loads():
    """Old layout: ``blur_field.*``, ``resolution_model.*`` and ``train_camera_centres`` on the model itself."""
    metadata = {"degradations": records("motion", 2) + records("mixres", 2)[1:]}
    model = build(metadata, n=3)
    model.degradation.set_train_camera_centres(torch.stack([look_from([float(i), 0.5, 1.0]) for i in range(3)]))
    with torch.no_grad():
        model.degradation.resolution_model.residual.normal_()
        next(model.degradation.blur_field.parameters()).add_(1.0)
    state = model.state_dict()
    old = {k.removeprefix("degradation."): v.clone() for k, v in state.items()}
    assert any(k.startswith("blur_field.heads.") for k in old)
    assert "train_camera_centres" in old and "resolution_model.residual" in old
    fresh = build(metadata, n=3)
    fresh.load_state_dict(old)  # strict
    for key, value in state.items():
        torch.testing.assert_close(fresh.state_dict()[key], value)


@pytest.mark.parametrize("mode, kind", [("full", "motion"), ("view", "motion"), ("view", "defocus")])
def test_eval_rgb_is_the_sharp_render_and_viewer_outputs_are_added(mode, kind):
    model = build({"degradations": records(kind)}, blur_field=BlurFieldConfig(mode=mode))
    model.degradation.set_train_camera_centres(
        torch.stack([look_from([2.0, 0.5, 1.0]), look_from([-2.0, 0.5, 1.0])] * 2)
    )
    camera = make_camera(look_from([-1.9, 0.5, 1.1]), width=64, height=48)
    model.eval()
    outputs = model.get_outputs_for_camera(camera)
    assert set(outputs) >= {"rgb", "degraded", "kernel_size", "blur_mask"}
    assert outputs["degraded"].shape == (48, 64, 3) and outputs["kernel_size"].shape == (48, 64, 1)
    assert float(outputs["kernel_size"].min()) >= 0.0 and torch.isfinite(outputs["degraded"]).all()
    model.config.viewer_blur_outputs = False
    plain = model.get_outputs_for_camera(camera)
    assert set(plain) == {"rgb", "depth", "accumulation", "background"}
    torch.testing.assert_close(plain["rgb"], outputs["rgb"])  # rgb is the sharp render either way


def test_kernel_spread_and_coarsening():
    K = 9
    box = torch.full((1, K * K, 2, 3), 1.0 / (K * K), dtype=torch.float64)
    expected = torch.full((1, 1, 2, 3), math.sqrt((K * K - 1) / 6), dtype=torch.float64)
    torch.testing.assert_close(kernel_spread(box), expected)  # uniform box: variance (K^2 - 1) / 12 per axis
    shifted = torch.zeros(1, K * K, 1, 1, dtype=torch.float64)
    shifted[0, 3] = 1.0  # a pure shift does not blur
    assert float(kernel_spread(shifted)) == 0.0
    coarse = coarsen_kernels(box, 4)
    assert coarse.shape == (1, 9, 2, 3)  # 9 -> 3 x 3 taps on a 4x coarser grid
    torch.testing.assert_close(coarse.sum(dim=1), box.sum(dim=1))
    assert coarsen_kernels(box, 1) is box
    assert preview_downscale(384, 512, 128) == 4 and preview_downscale(48, 64, 128, at_least=2) == 2
    centres = torch.tensor([[0.0, 0.0, 0.0], [float("nan")] * 3, [5.0, 0.0, 0.0]])
    assert nearest_view(centres, torch.tensor([4.0, 0.0, 0.0])) == 2
    assert nearest_view(torch.full((2, 3), float("nan")), torch.zeros(3)) == 0


# -- the real CLI ------------------------------------------------------------------------------------------------


def scalar_tags(run_dir: Path) -> Dict[str, List[float]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run_dir))
    events.Reload()
    return {tag: [e.value for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


@pytest.fixture(scope="module")
def motion_run(scenes, tmp_path_factory):
    work = tmp_path_factory.mktemp("motion_run")
    args = ["gsmsdr", "--data", scenes["motion"], "--output-dir", work / "outputs", "--timestamp", "run",
            "--max-num-iterations", CLI_STEPS, "--steps-per-save", CLI_STEPS, *TRAIN_FLAGS, *BLUR_FLAGS]  # fmt: skip
    proc = run_cli("ns-train", args, cwd=work)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-5000:]
    return work / "outputs" / "motion" / "gsmsdr" / "run"


def test_ns_train_gsmsdr_on_a_motion_scene_trains_the_blur_field(motion_run):
    tags = scalar_tags(motion_run)
    assert all(math.isfinite(v) for v in tags["Train Loss"])
    mask_reg = tags["Train Loss Dict/blur_mask_reg"]
    assert mask_reg and all(0 < v < 0.001 + 1e-9 for v in mask_reg)
    assert tags["Train Metrics Dict/blur_kernel_size"][-1] == 17
    ckpt = torch.load(motion_run / "nerfstudio_models" / f"step-{CLI_STEPS - 1:09d}.ckpt", map_location="cpu")
    state = ckpt["pipeline"]
    assert torch.isfinite(state["_model.degradation.train_camera_centres"]).all()
    assert any(k.startswith("_model.degradation.blur_field.heads.") for k in state)
    assert ckpt["optimizers"]["blur_field"]["state"]  # Adam stepped the field


def test_ns_eval_reports_psnr_on_the_sharp_test_views(motion_run, tmp_path):
    output = tmp_path / "eval.json"
    proc = run_cli("ns-eval", ["--load-config", motion_run / "config.yml", "--output-path", output], cwd=tmp_path)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    results = json.loads(output.read_text())["results"]
    assert 10.0 < results["psnr"] < 60.0 and 0.0 < results["ssim"] <= 1.0


def test_checkpoint_with_a_blur_field_loads_for_the_viewer(motion_run):
    from nerfstudio.utils.eval_utils import eval_setup

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GSMSDRWarning)
        _, pipeline, _, step = eval_setup(motion_run / "config.yml", test_mode="test")
    model = pipeline.model
    assert step == CLI_STEPS - 1 and model.step == step
    state = torch.load(motion_run / "nerfstudio_models" / f"step-{step:09d}.ckpt", map_location="cpu")["pipeline"]
    torch.testing.assert_close(model.degradation.train_camera_centres, state["_model.degradation.train_camera_centres"])
    camera, batch = pipeline.datamanager.fixed_indices_eval_dataloader[0]
    outputs = model.get_outputs_for_camera(camera)
    assert {"degraded", "kernel_size", "blur_mask"} <= set(outputs)
    metrics, _ = model.get_image_metrics_and_images(outputs, batch)
    assert math.isfinite(metrics["psnr"])


def test_ns_train_gsmsdr_lite_with_ablation_switches(scenes, tmp_path):
    args = ["gsmsdr-lite", "--data", scenes["motion"], "--output-dir", tmp_path / "outputs", "--timestamp", "lite",
            "--max-num-iterations", 10, "--steps-per-save", 10, *TRAIN_FLAGS, *BLUR_FLAGS,
            "--pipeline.model.blur-field.mode", "msd_only", "--pipeline.model.blur-field.gaka", "False"]  # fmt: skip
    proc = run_cli("ns-train", args, cwd=tmp_path)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-5000:]
    run_dir = tmp_path / "outputs" / "motion" / "gsmsdr-lite" / "lite"
    config = yaml.load((run_dir / "config.yml").read_text(), Loader=yaml.Loader)
    blur = config.pipeline.model.blur_field
    assert (blur.mode, blur.gaka, blur.size, config.pipeline.model.sh_degree) == ("msd_only", False, "lite", 1)
    state = torch.load(run_dir / "nerfstudio_models" / f"step-{9:09d}.ckpt", map_location="cpu")["pipeline"]
    field_keys = [k for k in state if k.startswith("_model.degradation.blur_field.")]
    assert field_keys and not any(".mca." in k or "gaka" in k for k in field_keys)  # msd_only: BAGS' plain CNN
    tags = scalar_tags(run_dir)
    assert tags["Train Loss Dict/blur_mask_reg"] and all(math.isfinite(v) for v in tags["Train Loss"])


def test_ns_train_gsmsdr_with_the_view_mode_field(scenes, tmp_path):
    """Blur field mode view through ns-train: only per-view tables in the checkpoint, trained in their own optimizer
    group, and the usual losses stay finite."""
    args = ["gsmsdr-lite", "--data", scenes["motion"], "--output-dir", tmp_path / "outputs", "--timestamp", "view",
            "--max-num-iterations", 10, "--steps-per-save", 10, *TRAIN_FLAGS, *BLUR_FLAGS,
            "--pipeline.model.blur-field.mode", "view"]  # fmt: skip
    proc = run_cli("ns-train", args, cwd=tmp_path)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-5000:]
    run_dir = tmp_path / "outputs" / "motion" / "gsmsdr-lite" / "view"
    checkpoint = torch.load(run_dir / "nerfstudio_models" / f"step-{9:09d}.ckpt", map_location="cpu")
    field_keys = [k for k in checkpoint["pipeline"] if k.startswith("_model.degradation.blur_field.")]
    assert field_keys and all(".view_logits." in k for k in field_keys), field_keys  # no mask: m = 1
    assert set(checkpoint["optimizers"]) >= {"blur_view_kernels"} and "blur_field" not in checkpoint["optimizers"]
    tags = scalar_tags(run_dir)
    # no mask, so no mask regulariser (logged for the other modes: see the ablation-switch test above)
    assert "Train Loss Dict/blur_mask_reg" not in tags
    assert tags["Train Loss"] and all(math.isfinite(v) for v in tags["Train Loss"])


def test_ns_train_on_a_defocus_scene_trains_the_thin_lens(scenes, tmp_path):
    """A defocused scene through ns-train: the thin lens is in the checkpoint with its own optimizer, its
    parameters moved from their start once densification stopped (step 10 here, where it starts by default), and
    every view's focus was initialised from its rendered depth."""
    args = ["gsmsdr-lite", "--data", scenes["defocus"], "--output-dir", tmp_path / "outputs", "--timestamp", "lens",
            "--max-num-iterations", 30, "--steps-per-save", 30, *TRAIN_FLAGS, *BLUR_FLAGS,
            "--pipeline.model.blur-field.mode", "view", "--pipeline.model.stop-split-at", 10]  # fmt: skip
    proc = run_cli("ns-train", args, cwd=tmp_path)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-5000:]
    run_dir = tmp_path / "outputs" / "defocus" / "gsmsdr-lite" / "lens"
    checkpoint = torch.load(run_dir / "nerfstudio_models" / f"step-{29:09d}.ckpt", map_location="cpu")
    state = checkpoint["pipeline"]
    prefix = "_model.degradation.thin_lens."
    assert {k[len(prefix):] for k in state if k.startswith(prefix)} == {
        "log_aperture", "view_log_aperture", "inverse_focus", "focus_initialised"}  # fmt: skip
    assert "blur_defocus" in checkpoint["optimizers"]
    assert float(state[prefix + "log_aperture"]) != 0.0  # trained away from log(initial aperture 1)
    seen = state[prefix + "focus_initialised"]
    assert seen.any() and torch.isfinite(state[prefix + "inverse_focus"]).all()
    assert (state[prefix + "inverse_focus"][seen] > 0).all()  # 1 / depth of something in front of the camera


def test_densification_gradient_of_blurred_views_is_scaled_when_asked():
    """A blurred view's 2D-mean gradients count ``degraded_densify_grad_scale`` times in the densification
    statistics; a sharp view's count once; 1 (the default) changes nothing."""
    metadata = {"degradations": records("motion", 1) + records("sharp", 1)}

    def grad2d(scale: float, view: int) -> torch.Tensor:
        torch.manual_seed(0)
        options = DegradationConfig(warmup=0, fallback=False)  # the Gaussians train through the blur
        model = build(metadata, n=2, degradation_model=options, degraded_densify_grad_scale=scale)
        model.train()
        model.optimizers = None  # no refinement at step 1: the statistics are only accumulated
        camera = make_camera(look_from([2.0, 0.5, 1.0]), width=64, height=48)
        camera.metadata = {"cam_idx": view}
        model.step = 1
        outputs = model.get_outputs(camera)
        outputs["rgb"].square().mean().backward()
        model.step_post_backward(1)
        return model.strategy_state["grad2d"].clone()

    blurred, blurred_x3 = grad2d(1.0, 0), grad2d(3.0, 0)
    assert float(blurred.sum()) > 0
    torch.testing.assert_close(blurred_x3, 3.0 * blurred)
    torch.testing.assert_close(grad2d(3.0, 1), grad2d(1.0, 1))  # the sharp view


@pytest.mark.parametrize("mode", ["full", "view"])
def test_the_deconvolved_loss_weighs_a_blurred_views_residual_by_its_mean_kernel(mode):
    """A blurred view's loss gets ``blur_deconvolved``: the weight times the mean square of its residual weighted by
    the inverse of its mean kernel (the field's kernels blended with the mask); a sharp view gets none, nor does a
    blurred view with the weight at 0."""
    from gsmsdr_ns.ops.deconvolved_loss import deconvolved_residual

    metadata = {"degradations": records("motion", 1) + records("sharp", 1)}
    camera = make_camera(look_from([2.0, 0.5, 1.0]), width=64, height=48)
    image = torch.rand(48, 64, 3, generator=torch.Generator().manual_seed(0))

    def loss_terms(view: int, weight: float):
        torch.manual_seed(0)
        field = BlurFieldConfig(mode=mode)
        options = DegradationConfig(warmup=0, deconvolved_loss_weight=weight, fallback=False)
        model = build(metadata, n=2, blur_field=field, degradation_model=options, background_color="black",
                      num_downscales=0)  # fmt: skip
        model.train()
        model.optimizers = None  # no densification step here
        model.step = 1
        camera.metadata = {"cam_idx": view}
        outputs = model.get_outputs(camera)
        return model.get_loss_dict(outputs, {"image": image}), outputs

    losses, outputs = loss_terms(0, 10.0)
    kernel = outputs["degradation"].kernel_mean
    assert kernel.shape[0] == 1 and kernel.shape[1] == kernel.shape[2] and not kernel.requires_grad
    torch.testing.assert_close(kernel.sum(), torch.tensor(1.0))
    residual = (outputs["rgb"] - image).permute(2, 0, 1)[None]
    expected = 10.0 * deconvolved_residual(residual, kernel, eps=0.01).square().mean()
    torch.testing.assert_close(losses["blur_deconvolved"], expected)
    assert losses["blur_deconvolved"].requires_grad  # it trains the Gaussians and the field
    assert "blur_deconvolved" not in loss_terms(1, 10.0)[0]  # the sharp view
    off, outputs = loss_terms(0, 0.0)
    assert "blur_deconvolved" not in off and outputs["degradation"].kernel_mean is None
