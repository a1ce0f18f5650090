"""`gsmsdr-bench suite`: suite YAML validation, the method table, the timing recorder (it must not change training),
and a real two-run suite that is interrupted by SIGINT after its first run and resumed (finished runs are not
redone), with its results.csv / results.md / PNG outputs and their published copies checked. Real nerfstudio
training on tiny generated scenes, no mocks."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from gsmsdr_ns.bench.cli import map_quick
from gsmsdr_ns.bench.fingerprint import fingerprint
from gsmsdr_ns.bench.methods import METHODS
from gsmsdr_ns.bench.records import finished_record, record_path
from gsmsdr_ns.bench.runner import run_suite
from gsmsdr_ns.bench.suite_config import RunKey, SuiteConfigError, find_suite_file, load_suite
from gsmsdr_ns.plugin.schedule import TrainingSchedule

BIN = Path(sys.executable).parent
REPO = Path(__file__).resolve().parents[1]

TINY_SUITE = """\
name: tiny
scene_defaults: {width: 64, height: 48, num_views: 10, hold: 5, num_points: 400, seed: 0}
scenes: [motion]
methods: [plain, full]
steps: [20]
eval_every: 10
schedule: {num_downscales: 0}
threads: 1
align_poses: true
"""

RESUME_STEPS = 20


def write_suite(tmp_path: Path, text: str, name: str = "suite.yaml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text), encoding="utf8")
    return path


# -- suite files -------------------------------------------------------------------------------------------------


SHIPPED = ["quick", "full", "ablations", "ablations-quick", "accuracy", "accuracy-3000", "real-size-gpu"]


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_suites_load(name: str) -> None:
    suite = load_suite(find_suite_file(name))
    assert suite.name == name
    assert suite.runs()
    assert all(m in METHODS for m in suite.methods)


def test_a_folder_named_like_a_suite_does_not_shadow_it(tmp_path: Path, monkeypatch) -> None:
    """``gsmsdr-bench suite --config real-size --out real-size`` run again from the same folder: the name still
    means the packaged suite, not the output folder."""
    (tmp_path / "real-size").mkdir()
    monkeypatch.chdir(tmp_path)
    assert find_suite_file("real-size").is_file()
    assert load_suite(find_suite_file("real-size")).name == "real-size"


BAD_SUITES = [
    ("unknown top-level key", TINY_SUITE + "stepz: [3]\n", "stepz"),
    ("unknown method", TINY_SUITE.replace("[plain, full]", "[plain, fulll]"), "methods[1]"),
    ("unknown variant", TINY_SUITE.replace("[motion]", "[blurry]"), "scenes[0].variant"),
    ("missing steps", TINY_SUITE.replace("steps: [20]\n", ""), "steps"),
    ("bad step budget", TINY_SUITE.replace("steps: [20]", "steps: [0]"), "steps[0]"),
    ("bad scene default", TINY_SUITE.replace("num_points: 400", "pointz: 400"), "scene_defaults.pointz"),
    ("bad scene override", TINY_SUITE.replace("[motion]", "[{variant: motion, width: -3}]"), "scenes[0].width"),
    ("duplicate scenes", TINY_SUITE.replace("[motion]", "[motion, motion]"), "scenes"),
    ("missing user scene", TINY_SUITE.replace("[motion]", "[{path: no/such/scene}]"), "scenes[0].path"),
    ("variant and path", TINY_SUITE.replace("[motion]", "[{variant: motion, path: x}]"), "scenes[0]"),
    (
        "unknown schedule key",
        TINY_SUITE.replace("{num_downscales: 0}", "{num_downscale: 0}"),
        "schedule.num_downscale",
    ),  # fmt: skip
    (
        "bad optional schedule value",
        TINY_SUITE.replace("{num_downscales: 0}", "{densify_warmup_fraction: soon}"),
        "schedule.densify_warmup_fraction",
    ),  # fmt: skip
    (
        "schedule value out of range",
        TINY_SUITE.replace("{num_downscales: 0}", "{resolution_fraction: 2.0}"),
        "resolution_fraction",
    ),  # fmt: skip
    ("bad eval interval", TINY_SUITE.replace("eval_every: 10", "eval_every: often"), "eval_every"),
    ("bad init", TINY_SUITE.replace("[motion]", "[{variant: motion, init: zero}]"), "scenes[0].init"),
    ("unknown ray key", TINY_SUITE + "ray: {num_cpu: 1}\n", "ray.num_cpu"),
    ("no CPUs per Ray run", TINY_SUITE + "ray: {num_cpus: 0}\n", "ray.num_cpus"),
    ("negative Ray retries", TINY_SUITE + "ray: {max_retries: -1}\n", "ray.max_retries"),
    ("not a mapping", "- just\n- a list\n", "must be a YAML mapping"),
    ("not YAML", "name: [unclosed\n", "not valid YAML"),
]


@pytest.mark.parametrize("label,text,key", BAD_SUITES, ids=[b[0] for b in BAD_SUITES])
def test_invalid_suite_names_file_and_key(tmp_path: Path, label: str, text: str, key: str) -> None:
    path = write_suite(tmp_path, text)
    with pytest.raises(SuiteConfigError) as info:
        load_suite(path)
    message = str(info.value)
    assert str(path) in message and key in message, message


def test_random_init_is_a_scene_setting_of_its_own(tmp_path: Path) -> None:
    """``init: random`` starts the Gaussians from random points: its runs have records of their own (fingerprint,
    training identity) on the same scene folder, and the others keep their fingerprints."""
    from gsmsdr_ns.bench.fingerprint import training_identity
    from gsmsdr_ns.plugin.method_config import gsmsdr_trainer_config

    text = TINY_SUITE.replace("[motion]", "[motion, {variant: motion, name: motion-random, init: random}]")
    suite = load_suite(write_suite(tmp_path, text))
    sparse, random = suite.scene("motion"), suite.scene("motion-random")
    assert not sparse.random_init and random.random_init and "random points" in random.describe()
    method = METHODS["full"]
    assert sparse.folder_key(method) == random.folder_key(method)  # the same images
    plain_key, random_key = RunKey("motion", "full", 20, 0), RunKey("motion-random", "full", 20, 0)
    assert fingerprint(suite, plain_key) != fingerprint(suite, random_key)
    assert training_identity(suite, plain_key) != training_identity(suite, random_key)
    before = load_suite(write_suite(tmp_path, TINY_SUITE, "before.yaml"))
    assert fingerprint(before, plain_key) == fingerprint(suite, plain_key)
    config = gsmsdr_trainer_config()
    sparse.configure(config)
    assert config.pipeline.model.random_init is False
    random.configure(config)
    assert config.pipeline.model.random_init is True


def test_ray_settings_do_not_change_the_records(tmp_path: Path) -> None:
    """What a run asks a Ray cluster for changes no number: the records and their fingerprints stay the same."""
    plain = load_suite(write_suite(tmp_path, TINY_SUITE, "a.yaml"))
    on_ray = load_suite(write_suite(tmp_path, TINY_SUITE + "ray: {num_cpus: 2, num_gpus: 0.5, max_retries: 4}\n",
                                    "b.yaml"))  # fmt: skip
    assert (on_ray.ray.num_cpus, on_ray.ray.num_gpus, on_ray.ray.max_retries) == (2, 0.5, 4)
    assert plain.ray.num_cpus is None and plain.ray.max_retries == 2
    for key in plain.runs():
        assert fingerprint(plain, key) == fingerprint(on_ray, key)


def test_suite_schedule_reaches_the_training_schedule(tmp_path: Path) -> None:
    text = TINY_SUITE.replace(
        "{num_downscales: 0}",
        "{num_downscales: 0, densify_warmup_fraction: null, refinement_window_fraction: 1.0, lr_schedulers: [means]}",
    )
    schedule = load_suite(write_suite(tmp_path, text)).schedule_for(300)
    assert schedule.steps == 300 and schedule.num_downscales == 0 and schedule.refinement_window_fraction == 1.0
    assert schedule.densify_warmup_fraction is None and schedule.lr_schedulers == ("means",)


def test_missing_suite_file(tmp_path: Path) -> None:
    with pytest.raises(SuiteConfigError, match="not found"):
        load_suite(tmp_path / "nope.yaml")
    with pytest.raises(SuiteConfigError, match="no suite file"):
        find_suite_file("no-such-suite")


def test_user_scene_without_sharp_twin_skips_the_upper_bound(tmp_path: Path) -> None:
    (tmp_path / "myscene").mkdir()
    text = TINY_SUITE.replace("[motion]", "[motion, {path: myscene}]").replace("[plain, full]", "[plain, sharp]")
    suite = load_suite(write_suite(tmp_path, text))
    user = suite.scene("myscene")
    assert user.path == tmp_path / "myscene" and not user.generated
    assert not user.supports(METHODS["sharp"]) and user.supports(METHODS["plain"])
    assert suite.scene("motion").supports(METHODS["sharp"])


def test_method_table_maps_to_config_switches(tmp_path: Path) -> None:
    assert set(METHODS) == {"plain", "plain-poses", "msd-only", "re-only", "full", "full-poses", "full-uncentred",
                            "full-lens-unknown", "full-paper-loss", "full-lens-paper-loss",
                            "full-margin", "full-shake", "full-true",
                            "full-per-pixel", "full-fallback", "full-fallback-coarse", "full-anchor", "full-lens-early",
                            "full-grid4k", "full-cells4", "cpu-poses", "cpu-shake", "cpu-kernels", "cpu-shake-decay",
                            "cpu-decay", "cpu-late-decay", "cpu-late-path-decay", "cpu-late-kernel-decay",
                            "cpu-shake17", "cpu-shake-move", "cpu-shake-move-late", "cpu-shake-parallax",
                            "cpu-shake-occlusion", "cpu-shake-occlusion17", "cpu-shake-true-occlusion17",
                            "cpu-shake-true-paths", "cpu-kernel-centred", "cpu-path-weighted", "cpu-path-weighted-d05",
                            "cpu-path-weighted-eps04", "cpu-paper-loss", "-view", "view",
                            "view-k25", "view-k33", "view-k49", "-gaka", "-safm", "-mca", "-rgbd", "gsmsdr-lite",
                            "gsmsdr-cpu", "sharp-degraded-poses", "sharp"}  # fmt: skip

    def model(name: str):
        return METHODS[name].make_config(tmp_path, tmp_path / "out").pipeline.model

    assert model("plain").degradation == "sharp" and model("sharp").degradation == "sharp"
    assert model("full-fallback").degradation_model.fallback and not model("full").degradation_model.fallback
    assert model("full-lens-early").degradation_model.thin_lens_start == "warmup"
    assert model("full").degradation_model.thin_lens_start == "densify_end"
    assert model("full").degradation_model.deconvolved_loss_on_lens
    assert not model("full-lens-paper-loss").degradation_model.deconvolved_loss_on_lens
    assert METHODS["sharp"].sharp_data and not METHODS["plain"].sharp_data
    bound = METHODS["sharp-degraded-poses"]
    assert bound.sharp_data and bound.degraded_poses and not METHODS["sharp"].degraded_poses
    assert model("sharp-degraded-poses").degradation == "sharp"
    assert model("full").degradation == "auto" and model("full").blur_field.mode == "full"
    assert model("msd-only").blur_field.mode == "msd_only"
    assert model("re-only").blur_field.mode == "re_only"
    for switch in ("gaka", "safm", "mca", "rgbd"):
        field = model(f"-{switch}").blur_field
        assert getattr(field, switch) is False
        assert all(getattr(field, other) for other in ("gaka", "safm", "mca", "rgbd") if other != switch)
    assert model("gsmsdr-lite").blur_field.size == "lite"
    assert model("full").blur_field.feature_grid_cells == 4096 == model("full-grid4k").blur_field.feature_grid_cells
    assert model("full-cells4").blur_field.feature_grid_cells == 0
    assert model("view-k25").blur_field.kernel_sizes == (7, 13, 25)
    assert model("view-k49").blur_field.kernel_sizes == (13, 25, 49) and model("view-k49").blur_field.mode == "view"
    assert model("view-k33").blur_field.kernel_sizes == (9, 17, 33) == model("gsmsdr-cpu").blur_field.kernel_sizes
    assert model("gsmsdr-cpu").blur_field.mode == "view"
    assert model("full").blur_field.view_kernels and model("full").blur_field.pixel_kernels
    assert not model("-view").blur_field.view_kernels and model("view").blur_field.mode == "view"
    assert METHODS["re-only"].modules() == dict(GAKA=True, SAFM=True, MCA=True, RGBD=True, HPKO=False)
    assert METHODS["msd-only"].modules() == dict(GAKA=False, SAFM=False, MCA=False, RGBD=True, HPKO=True)
    # pose refinement: off as in splatfacto, on the degraded views for full-poses, on every view for plain-poses
    assert model("full").camera_optimizer.mode == "off" and model("plain").camera_optimizer.mode == "off"
    assert (model("full-poses").camera_optimizer.mode, model("full-poses").camera_optimizer_views) == (
        "SO3xR3",
        "degraded",
    )
    assert (model("plain-poses").camera_optimizer.mode, model("plain-poses").camera_optimizer_views) == (
        "SO3xR3",
        "all",
    )
    assert model("plain-poses").degradation == "sharp"
    assert (model("cpu-poses").camera_optimizer.mode, model("cpu-poses").camera_optimizer_views) == ("SO3xR3", "all")
    assert model("cpu-poses").blur_field == model("gsmsdr-cpu").blur_field
    options = {name: model(name).degradation_model for name in METHODS if METHODS[name].has_blur_field}
    assert options["full-uncentred"].kernel_centre_weight == 0 < options["full"].kernel_centre_weight
    assert options["full-lens-unknown"].thin_lens_for_unknown_kind
    assert options["full-margin"].render_margin and not options["full"].render_margin
    assert options["full-shake"].camera_shake and not options["full"].camera_shake
    assert options["gsmsdr-cpu"].camera_shake and options["gsmsdr-cpu"].render_margin
    assert repr(model("cpu-shake-parallax")) == repr(model("gsmsdr-cpu"))
    assert options["gsmsdr-cpu"].shake_translation and options["gsmsdr-cpu"].shake_parallax
    assert options["cpu-shake"].camera_shake and not options["cpu-shake"].shake_translation
    assert options["cpu-shake17"].shake_samples == 17 > options["gsmsdr-cpu"].shake_samples
    occluding17 = options["cpu-shake-occlusion17"]
    assert occluding17.shake_occlusion and occluding17.shake_parallax and occluding17.shake_samples == 17
    assert options["cpu-shake-move"].shake_translation and not options["cpu-shake-move"].shake_parallax
    true_paths = options["cpu-shake-true-paths"]
    assert true_paths.shake_paths == "records" and options["gsmsdr-cpu"].shake_paths == "learnt"
    assert true_paths.shake_translation and not true_paths.shake_parallax
    true_occluding17 = options["cpu-shake-true-occlusion17"]
    assert true_occluding17.shake_paths == "records" and true_occluding17.shake_occlusion
    assert true_occluding17.shake_samples == 17 and not true_occluding17.shake_parallax
    assert (
        options["cpu-kernel-centred"].kernel_centre_after_shake and not options["gsmsdr-cpu"].kernel_centre_after_shake
    )
    late, parallax = options["cpu-shake-move-late"], options["cpu-shake-parallax"]
    assert late.shake_translation and late.shake_translation_start == "densify_end" and not late.shake_parallax
    assert parallax.shake_translation and parallax.shake_parallax and parallax.shake_translation_start == "warmup"
    assert options["cpu-path-weighted"].deconvolved_loss_on_shake
    assert not options["gsmsdr-cpu"].deconvolved_loss_on_shake
    assert options["cpu-path-weighted-eps04"].deconvolved_loss_eps == 0.04 > options["gsmsdr-cpu"].deconvolved_loss_eps
    assert options["cpu-path-weighted-d05"] == options["cpu-path-weighted"]
    assert options["cpu-paper-loss"].deconvolved_loss_weight == 0 < options["gsmsdr-cpu"].deconvolved_loss_weight
    # options of the Gaussian model itself: only the method that names one changes it
    assert model("cpu-path-weighted-d05").degraded_densify_grad_scale == 0.5
    assert model("cpu-path-weighted").degraded_densify_grad_scale == model("gsmsdr-cpu").degraded_densify_grad_scale
    assert not options["cpu-kernels"].camera_shake and not options["cpu-kernels"].render_margin
    assert model("cpu-kernels").blur_field == model("gsmsdr-cpu").blur_field
    # learning-rate decays: the suite's schedule scales them to its steps
    preset = METHODS["gsmsdr-cpu"].make_config(tmp_path, tmp_path / "out")
    TrainingSchedule.bench(1200).apply(preset)
    for name, decayed, hold in (("gsmsdr-cpu", set(), 0.0), ("cpu-shake-decay", {"blur_shake"}, 0.0),
                                ("cpu-decay", {"blur_shake", "blur_view_kernels"}, 0.0),
                                ("cpu-late-decay", {"blur_shake", "blur_view_kernels"}, 0.6),
                                ("cpu-late-path-decay", {"blur_shake"}, 0.6),
                                ("cpu-late-kernel-decay", {"blur_view_kernels"}, 0.6)):  # fmt: skip
        config = METHODS[name].make_config(tmp_path, tmp_path / "out")
        TrainingSchedule.bench(1200).apply(config)
        assert repr(config.pipeline.model) == repr(preset.pipeline.model)
        for group in ("blur_shake", "blur_view_kernels"):
            scheduler = config.optimizers[group]["scheduler"]
            assert (scheduler is not None) == (group in decayed)
            if scheduler is not None:
                assert (scheduler.max_steps, scheduler.warmup_steps) == (1200, 0)
                assert scheduler.lr_final == config.optimizers[group]["optimizer"].lr / 100
                assert getattr(scheduler, "hold_fraction", 0.0) == hold
    assert not options["full"].thin_lens_for_unknown_kind
    paper_loss, full = options["full-paper-loss"], options["full"]
    assert paper_loss.deconvolved_loss_weight == 0 < full.deconvolved_loss_weight


def test_fingerprint_follows_the_resolved_preset(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A record made before a preset default changed is not reused: the fingerprint covers the resolved settings."""
    import gsmsdr_ns.plugin.method_config as method_config

    suite = load_suite(write_suite(tmp_path, TINY_SUITE))
    key = RunKey("motion", "full", 20, 0)
    before = fingerprint(suite, key)
    assert fingerprint(suite, key) == before
    original = method_config.gsmsdr_optimizers

    def changed(*args, **kwargs):
        optimizers = original(*args, **kwargs)
        optimizers["blur_field"]["optimizer"].lr *= 2
        return optimizers

    plain = RunKey("motion", "plain", 20, 0)
    plain_before = fingerprint(suite, plain)
    monkeypatch.setattr(method_config, "gsmsdr_optimizers", changed)
    assert fingerprint(suite, key) != before
    # plain Gaussians never build the blur field: its settings do not invalidate their records
    assert fingerprint(suite, plain) == plain_before

    def means_changed(*args, **kwargs):
        optimizers = original(*args, **kwargs)
        optimizers["means"]["optimizer"].lr *= 2
        return optimizers

    monkeypatch.setattr(method_config, "gsmsdr_optimizers", means_changed)
    assert fingerprint(suite, plain) != plain_before


def test_fields_added_at_their_neutral_value_keep_the_fingerprint() -> None:
    """feature_grid_cells=0 (added later, trains as the records made before it) is not in the preset fingerprint;
    another value, the default 4096 included, is: full's records made with 4 px cells are rerun, full-cells4's are
    the ones made before."""
    from gsmsdr_ns.bench.fingerprint import preset_fingerprint
    from gsmsdr_ns.bench.methods import METHODS

    cells4, full = preset_fingerprint(METHODS["full-cells4"]), preset_fingerprint(METHODS["full"])
    assert "feature_grid_cells" not in cells4 and "feature_grid_cells=4096" in full
    assert full.replace("feature_grid_cells=4096, ", "") == cells4
    assert preset_fingerprint(METHODS["full-grid4k"]) == full
    # a field without a feature network (mode view) trains the same at any cap: no rerun of its records
    assert "feature_grid_cells" not in preset_fingerprint(METHODS["gsmsdr-cpu"])
    # the path in the deconvolved loss: named only where it is on, and only models with shake paths read it
    assert "deconvolved_loss_on_shake" not in preset_fingerprint(METHODS["gsmsdr-cpu"])
    assert "deconvolved_loss_on_shake=True" in preset_fingerprint(METHODS["cpu-path-weighted"])
    # a model option a method replaces is in its fingerprint
    assert "degraded_densify_grad_scale=0.5" in preset_fingerprint(METHODS["cpu-path-weighted-d05"])
    assert "degraded_densify_grad_scale=1.0" in preset_fingerprint(METHODS["cpu-path-weighted"])
    assert "deconvolved_loss_on_shake" not in full


def test_model_options_of_a_method_are_checked(tmp_path: Path) -> None:
    """A method replacing a Gaussian-model option that does not exist fails naming it, before any training."""
    from gsmsdr_ns.bench.methods import MethodSpec

    spec = MethodSpec("bad", "bad", "gsmsdr-cpu", model_overrides=(("densify_scale", 0.5),))
    with pytest.raises(ValueError, match="densify_scale"):
        spec.make_config(tmp_path, tmp_path / "out")


SHARED_TRAINING_SUITE = """\
name: shared
scene_defaults: {width: 48, height: 36, num_views: 8, hold: 4, num_points: 300, seed: 0}
scenes: [motion, defocus]
methods: [plain, sharp]
steps: [6]
schedule: {num_downscales: 0}
threads: 1
lpips: false
"""


def test_runs_with_the_same_training_train_once(tmp_path: Path) -> None:
    """The sharp upper bound of two scenes made from the same sharp scene trains once; the other run gets a copy of
    its record (its own id and fingerprint), and a rerun reuses both. Real training, tiny scenes."""
    from gsmsdr_ns.bench.fingerprint import training_identity
    from gsmsdr_ns.bench.ledger import plan_runs

    suite = load_suite(write_suite(tmp_path, SHARED_TRAINING_SUITE))
    out = tmp_path / "out"
    motion_sharp, defocus_sharp = RunKey("motion", "sharp", 6, 0), RunKey("defocus", "sharp", 6, 0)
    assert training_identity(suite, motion_sharp) == training_identity(suite, defocus_sharp)
    assert training_identity(suite, RunKey("motion", "plain", 6, 0)) != training_identity(suite, motion_sharp)
    assert training_identity(suite, RunKey("motion", "sharp", 6, 1)) != training_identity(suite, motion_sharp)
    plan = plan_runs(suite, out)
    assert [k.id for k in plan.todo] == ["motion__plain__6__s0", "motion__sharp__6__s0", "defocus__plain__6__s0"]
    assert {k.id: v.id for k, v in plan.same_as.items()} == {defocus_sharp.id: motion_sharp.id}

    outcome = run_suite(suite, out, progress=False, plots=False)
    assert sorted(outcome.trained) == sorted(k.id for k in plan.todo) and outcome.copied == [defocus_sharp.id]
    assert not outcome.failed
    source, copy = (finished_record(suite, out, k) for k in (motion_sharp, defocus_sharp))
    assert source is not None and copy is not None
    assert copy["id"] == defocus_sharp.id and copy["scene"] == "defocus" and copy["same_training_as"] == source["id"]
    assert copy["fingerprint"] == fingerprint(suite, defocus_sharp) != source["fingerprint"]
    assert copy["psnr"] == source["psnr"] and copy["curve"] == source["curve"] and copy["data"] == source["data"]
    assert len(outcome.records) == 4
    assert "- 1 of them trained the same images" in (out / "results.md").read_text(encoding="utf8")

    again = run_suite(suite, out, progress=False, plots=False)
    assert again.trained == [] and again.copied == [] and len(again.reused) == 4


DIAGNOSTICS_SUITE = """\
name: diagnostics
scene_defaults: {width: 64, height: 48, num_views: 10, hold: 5, num_points: 400, seed: 0}
scenes: [motion]
methods: [full]
steps: [6]
schedule: {num_downscales: 0}
threads: 1
lpips: false
final_renders: true
train_fit: true
"""


def test_final_renders_and_train_fit_are_written_without_changing_the_run(tmp_path: Path) -> None:
    """``final_renders`` writes each test view's render and ground truth (their PSNR is the view's recorded PSNR up
    to 8-bit rounding); ``train_fit`` records the training-view fit and shows it in results.md; neither changes the
    run's fingerprint. Real training, tiny scene."""
    import numpy as np

    from gsmsdr_ns.io.images import read_image

    suite = load_suite(write_suite(tmp_path, DIAGNOSTICS_SUITE))
    plain = load_suite(write_suite(tmp_path, DIAGNOSTICS_SUITE.replace("final_renders: true\ntrain_fit: true\n", ""),
                                   "plain.yaml"))  # fmt: skip
    key = RunKey("motion", "full", 6, 0)
    assert suite.final_renders and suite.train_fit and not plain.final_renders and not plain.train_fit
    assert fingerprint(suite, key) == fingerprint(plain, key)

    out = tmp_path / "out"
    outcome = run_suite(suite, out, progress=False, plots=False)
    assert not outcome.failed
    record = finished_record(suite, out, key)
    assert record is not None and np.isfinite(record["train_psnr"]) and record["train_psnr"] > 5.0
    views = record["psnr_views"]
    assert len(views) == record["num_test_views"] == 2
    assert abs(sum(views) / len(views) - record["psnr"]) < 1e-3
    folder = out / "renders" / key.id
    assert sorted(p.name for p in folder.iterdir()) == ["000_gt.png", "000_render.png", "001_gt.png", "001_render.png"]
    for index, expected in enumerate(views):
        render, gt = (
            read_image(folder / f"{index:03d}_{kind}.png").astype(np.float64) / 255.0 for kind in ("render", "gt")
        )
        assert render.shape == gt.shape == (48, 64, 3)
        assert abs(-10.0 * np.log10(np.mean((render - gt) ** 2)) - expected) < 0.2
    text = (out / "results.md").read_text(encoding="utf8")
    assert "train-view fit PSNR" in text and f"{record['train_psnr']:.2f}" in text


def test_a_run_with_the_recorded_shake_paths_keeps_them_as_its_learnt_paths(tmp_path: Path, capsys) -> None:
    """``cpu-shake-true-paths`` through the real trainer: its run record's ``shake_paths`` (written with
    ``train_fit``) are the scene's recorded paths, so ``tools/shake/path_error.py`` finds them at no distance from the
    truth. Real training, tiny scene."""
    from tools.shake.path_error import PathError

    suite = load_suite(write_suite(tmp_path, DIAGNOSTICS_SUITE.replace("[full]", "[cpu-shake-true-paths]")))
    out = tmp_path / "out"
    assert not run_suite(suite, out, progress=False, plots=False).failed
    key = RunKey("motion", "cpu-shake-true-paths", 6, 0)
    record = finished_record(suite, out, key)
    assert record is not None and record["shake_paths"]["pose_scale"] > 0
    views = record["shake_paths"]["views"]
    assert len(views) == 8 and all(v["motion"] and not v["centred"] and len(v["rotvecs"]) == 9 for v in views)
    PathError(run=out / "runs" / f"{key.id}.json", data=Path(record["data"]), stride=2).main()
    extent, error = (float(x) for x in capsys.readouterr().out.splitlines()[-1].strip("| ").split("|")[1:3])
    assert extent > 0.3 and error < 0.05 * extent, (extent, error)


def test_a_preset_that_degrades_nothing_shares_its_sharp_photos_scene() -> None:
    """On the real-photo suite, the sharp fern's "sharp photos with the degraded photos' poses" bound, its plain
    Gaussians and every scene's sharp upper bound read the same folder (named without building it), so they train
    once per seed; the degraded scenes' own rows do not."""
    from gsmsdr_ns.bench.fingerprint import training_identity

    suite = load_suite(find_suite_file("real"))
    sharp = suite.scene("fern-sharp")
    assert sharp.data_key(METHODS["sharp-degraded-poses"]) == sharp.data_key(METHODS["sharp"])
    assert sharp.data_key(METHODS["plain"]) == sharp.data_key(METHODS["sharp"])
    motion = suite.scene("fern-motion")
    assert motion.data_key(METHODS["sharp-degraded-poses"]) != motion.data_key(METHODS["sharp"])
    assert motion.data_key(METHODS["sharp"]) == sharp.data_key(METHODS["sharp"])
    identities = {run.id: training_identity(suite, run) for run in suite.runs() if run.seed == 0}
    same = identities["fern-motion__sharp__3000__s0"]
    assert sorted(k for k, v in identities.items() if v == same) == [
        "fern-defocus-disk__sharp__3000__s0", "fern-defocus__sharp__3000__s0", "fern-motion__sharp__3000__s0",
        "fern-sharp__plain__3000__s0", "fern-sharp__sharp-degraded-poses__3000__s0", "fern-sharp__sharp__3000__s0",
    ]  # fmt: skip
    assert len(set(identities.values())) == len(identities) - 5


def test_quick_flag_maps_to_the_quick_suite() -> None:
    assert map_quick(["--quick"]) == ["suite", "--config", "quick"]
    assert map_quick(["--quick", "--out", "x"]) == ["suite", "--config", "quick", "--out", "x"]
    assert map_quick(["suite", "--quick"]) == ["suite", "--config", "quick"]
    assert map_quick(["raster", "--repeats", "1"]) == ["raster", "--repeats", "1"]
    with pytest.raises(SystemExit):
        map_quick(["raster", "--quick"])


# -- timing recorder ---------------------------------------------------------------------------------------------


def _train_losses(data: Path, steps: int, record: bool, evaluate_at=()) -> tuple:
    from gsmsdr_ns.bench.evaluation import evaluate_test_views
    from gsmsdr_ns.bench.timing import TimingRecorder
    from gsmsdr_ns.bench.training import InProcessRun, method_run_config
    from gsmsdr_ns.plugin.schedule import TrainingSchedule

    schedule = TrainingSchedule.bench(steps, num_downscales=0, refinements=4)
    config = method_run_config("gsmsdr-lite", data, data.parent / "ns", schedule)
    run = InProcessRun(config, seed=3)
    losses = []
    train_iteration = run.trainer.train_iteration

    def capture(step):
        out = train_iteration(step)
        losses.append(float(out[0].detach()))
        return out

    run.trainer.train_iteration = capture
    recorder = TimingRecorder().attach(run.pipeline) if record else None
    try:
        for step in range(steps):
            if recorder is not None:
                with recorder.measure():
                    run.train(1)
            else:
                run.train(1)
            if step + 1 in evaluate_at:
                evaluate_test_views(run)
        final = evaluate_test_views(run)
    finally:
        if recorder is not None:
            recorder.detach()
        run.close()
    return losses, final, recorder


def test_timing_recorder_and_evaluations_do_not_change_training(tmp_path: Path) -> None:
    from gsmsdr_ns.bench.scenes import SceneSpec, ensure_scene
    from gsmsdr_ns.blur.field import BlurField

    data = ensure_scene(tmp_path, SceneSpec("motion", 48, 36, 8, 0, 4, num_points=300))
    blur = BlurField.__dict__["blur"]
    plain_losses, plain_final, _ = _train_losses(data, 12, record=False)
    losses, final, recorder = _train_losses(data, 12, record=True, evaluate_at=(4, 8))
    assert losses == plain_losses  # bit-identical training
    assert final["psnr"] == plain_final["psnr"] and final["ssim"] == plain_final["ssim"]
    assert BlurField.__dict__["blur"] is blur  # detach() restored the class

    totals, split = recorder.totals(), recorder.split()
    for category in ("rasterization", "blur_field", "kernels", "data"):
        assert totals[category] > 0, (category, totals)
        assert recorder.calls[category] >= 11, (category, dict(recorder.calls))
    for category in ("rasterization", "blur_field", "kernels"):
        assert split["backward"][category] > 0, (category, split)
    assert recorder.calls["densification"] == 24  # pre- and post-backward hook every step
    assert sum(totals.values()) == pytest.approx(recorder.wall)
    assert totals["other"] >= 0


# -- a real suite: interrupted, resumed, outputs -----------------------------------------------------------------


@pytest.fixture(scope="module")
def interrupted_suite(tmp_path_factory: pytest.TempPathFactory):
    """Run the tiny suite (2 runs) with the CLI, interrupted by SIGINT after its first run (``--interrupt-after 1``:
    the runner signals itself once that run's record and outputs are written, so where the interrupt lands does not
    depend on timing), then rerun it to the end with ``--publish``."""
    work = tmp_path_factory.mktemp("suite")
    config = write_suite(work, TINY_SUITE, "tiny.yaml")
    out = work / "out"
    published = work / "docs" / "results" / "tiny"
    first = out / "runs" / f"motion__plain__{RESUME_STEPS}__s0.json"
    second = out / "runs" / f"motion__full__{RESUME_STEPS}__s0.json"
    env = dict(os.environ, PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE", COLUMNS="200")
    args = [str(BIN / "gsmsdr-bench"), "suite", "--config", str(config), "--out", str(out)]
    # A shell that starts jobs in the background (nohup, `cmd &` in CI scripts) makes them ignore SIGINT, and Python
    # then installs no KeyboardInterrupt handler: give the suite the default disposition a terminal's Ctrl-C meets.
    proc = subprocess.run(args + ["--interrupt-after", "1"], cwd=work, env=env, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True, timeout=600,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
    log1 = proc.stdout
    assert first.exists(), log1[-4000:]
    assert proc.returncode == 130 and not second.exists(), log1[-4000:]
    first_mtime = first.stat().st_mtime_ns
    # another suite sharing --out leaves a plot of its own scene there: it is not this suite's to publish
    (out / "psnr_vs_time_other-suites-scene.png").write_bytes((out / "time_breakdown.png").read_bytes())

    proc2 = subprocess.run(args + ["--publish", str(published)], cwd=work, env=env, capture_output=True, text=True,
                           timeout=600)  # fmt: skip
    log2 = proc2.stdout + proc2.stderr
    assert proc2.returncode == 0, log2[-4000:]
    outputs = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}  # before later tests rewrite them
    return dict(config=config, out=out, first=first, second=second, first_mtime=first_mtime, log1=log1, log2=log2,
                published=published, outputs=outputs)  # fmt: skip


def test_interrupted_suite_resumes_without_redoing_finished_runs(interrupted_suite) -> None:
    s = interrupted_suite
    assert "interrupted (" in s["log1"] and "1 finished runs are kept" in s["log1"], s["log1"][-3000:]
    assert "1 already finished, 1 to train" in s["log2"], s["log2"][-3000:]
    assert "1 runs trained, 1 reused, 0 failed" in s["log2"], s["log2"][-3000:]
    assert s["first"].stat().st_mtime_ns == s["first_mtime"]  # the finished run was not redone
    assert s["second"].exists()

    # A third pass trains nothing; a changed setting invalidates the records (they would be rerun).
    suite = load_suite(s["config"])
    outcome = run_suite(suite, s["out"], command="gsmsdr-bench suite --config tiny.yaml", progress=False, plots=False)
    assert outcome.trained == [] and len(outcome.reused) == 2 and not outcome.failed
    assert s["first"].stat().st_mtime_ns == s["first_mtime"]
    key = RunKey("motion", "plain", RESUME_STEPS, 0)
    assert finished_record(suite, s["out"], key) is not None
    suite.eval_every = 5
    assert finished_record(suite, s["out"], key) is None
    assert record_path(s["out"], key) == s["first"]


def test_suite_outputs_parse(interrupted_suite) -> None:
    from PIL import Image

    out = interrupted_suite["out"]
    with open(out / "results.csv", newline="", encoding="utf8") as f:
        rows = list(csv.DictReader(f))
    assert [(r["method"], r["steps"]) for r in rows] == [("plain", str(RESUME_STEPS)), ("full", str(RESUME_STEPS))]
    for r in rows:
        for column in ("psnr", "ssim", "train_seconds", "step_ms", "t_rasterization", "t_blur_field", "t_kernels",
                       "t_densification", "t_data", "t_other", "peak_rss_mb", "num_gaussians"):  # fmt: skip
            assert float(r[column]) >= 0, (column, r)
        assert 5 < float(r["psnr"]) < 60 and 0 < float(r["ssim"]) <= 1
        # test-pose alignment keeps the given pose unless it fits the photo better
        assert float(r["psnr_aligned"]) >= float(r["psnr"]) - 0.01 and float(r["pose_correction_deg"]) >= 0
        assert "lpips_aligned" in r  # empty without LPIPS weights, like lpips
        parts = sum(float(r[f"t_{c}"]) for c in ("rasterization", "blur_field", "kernels", "densification", "data",
                                                 "other"))  # fmt: skip
        assert parts == pytest.approx(float(r["train_seconds"]), rel=1e-3, abs=0.01)
    full = next(r for r in rows if r["method"] == "full")
    plain = next(r for r in rows if r["method"] == "plain")
    assert float(full["t_blur_field"]) > 0 and float(full["t_kernels"]) > 0
    assert float(plain["t_blur_field"]) == 0

    md = (out / "results.md").read_text(encoding="utf8")
    assert md.startswith("# Benchmark suite `tiny`")
    for text in ("- machine:", "- command: `gsmsdr-bench suite", "### motion", "| method | PSNR | SSIM | LPIPS",
                 "| PSNR aligned | SSIM aligned | pose corr. ° |", "- aligned: the same metrics", "| GS-MSDR (full) |",
                 "## Time breakdown", "## Gaps", "PSNR: sharp - method", "PSNR aligned: method - plain"):  # fmt: skip
        assert text in md, text
    table = [line for line in md.splitlines() if line.startswith("| plain (3DGS) |")][0]
    assert f"{float(plain['psnr']):.2f}" in table

    for png in ("psnr_vs_time_motion.png", "time_breakdown.png"):
        with Image.open(out / png) as image:
            image.verify()
        with Image.open(out / png) as image:
            assert image.size[0] > 200 and image.size[1] > 100


def test_published_results_are_the_outputs(interrupted_suite) -> None:
    outputs, published = interrupted_suite["outputs"], interrupted_suite["published"]
    names = sorted(p.name for p in published.iterdir())
    assert names == ["psnr_vs_time_motion.png", "results.csv", "results.md", "time_breakdown.png"], names
    for name in names:
        assert (published / name).read_bytes() == outputs[name], name
    assert "published " in interrupted_suite["log2"]


def test_two_processes_generating_the_same_scene_both_get_it(tmp_path: Path) -> None:
    """Suites run in parallel (one per core) may need the same generated scene at the same time."""
    script = (
        "import sys; from pathlib import Path; from gsmsdr_ns.bench.scenes import SceneSpec, ensure_scene; "
        "print(ensure_scene(Path(sys.argv[1]), SceneSpec('motion', width=40, height=30, num_views=6, hold=3, "
        "num_points=200)))"
    )
    procs = [
        subprocess.Popen([sys.executable, "-c", script, str(tmp_path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        for _ in range(2)
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [err.decode()[-2000:] for _, err in outs]
    scenes = sorted(p for p in (tmp_path / "scenes").iterdir() if p.suffix != ".lock")  # the (empty) lock stays
    assert [s.name for s in scenes] == ["motion-40x30-v6-h3-s0-g2"]  # no partial copies left behind
    assert (scenes[0] / "degradation.json").is_file() and len(list((scenes[0] / "images").iterdir())) == 6
