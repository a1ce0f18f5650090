"""Bad runs, checkpoints and commands give one clear line, and nothing partial is left behind.

* our errors (``InputError``, ``DiskFullError``) print as one line without a traceback in ``ns-train`` / ``ns-eval``
  (a traceback with ``GSMSDR_DEBUG=1``); other exceptions keep theirs;
* checkpoints are written atomically; a full disk (a real ENOSPC from ``/dev/full``, and a failing fsync) says so
  and leaves no partial ``.ckpt``;
* empty, truncated and damaged checkpoints, folders without checkpoints and run folders given as ``--load-dir``
  name the file or folder and what to do, in ``ns-train`` (the trainer) and ``ns-eval``;
* a ``gsmsdr`` checkpoint loaded with ``gsmsdr-lite`` names the widths of both and the method to use;
* Ctrl-C in our CLIs prints one line and exits 130 without leaving output; in ``ns-train`` it names the last complete
  checkpoint (or says set-up was interrupted) and exits 130, and closing the viewer after training exits 0;
* step counts below 1 and kernel sizes above the limit name the allowed range; a run whose scene moved tells the
  commands that load it to fix config.yml.
"""

from __future__ import annotations

import dataclasses
import errno
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import BIN, TRAIN_FLAGS, TrainedRun, scaled
from nerfstudio.data.scene_box import SceneBox
from PIL import Image

import gsmsdr_ns.plugin  # noqa: F401  (checkpoint globals, exception hook)
from gsmsdr_ns._cli import install_excepthook, run_entrypoint
from gsmsdr_ns.blur.degradation_config import DegradationConfig
from gsmsdr_ns.io.errors import DiskFullError, InputError
from gsmsdr_ns.plugin import checkpoint_io as ckpt
from gsmsdr_ns.plugin.checkpoint_compat import CheckpointMismatchError
from gsmsdr_ns.plugin.checkpoint_io import (
    check_checkpoint_file,
    checkpoint_file,
    find_checkpoint,
    load_checkpoint_file,
    save_checkpoint_atomic,
)
from gsmsdr_ns.plugin.method_config import gsmsdr_lite_trainer_config, gsmsdr_trainer_config
from gsmsdr_ns.plugin.model import GSMSDRWarning
from gsmsdr_ns.plugin.trainer import GSMSDRTrainer, GSMSDRTrainerConfig

ENV = dict(os.environ, PYTHONUNBUFFERED="1", COLUMNS="200", OMP_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE")


def cli_env(**extra: str) -> dict:
    env = {k: v for k, v in ENV.items() if k != "GSMSDR_DEBUG"}
    return {**env, **extra}


def lines_with(text: str, needle: str) -> list:
    return [line for line in text.splitlines() if needle in line]


def last_checkpoint(run: TrainedRun) -> Path:
    return checkpoint_file(run.checkpoint_dir, run.steps - 1)


def make_trainer(config: GSMSDRTrainerConfig, scene: Path, out: Path, **overrides) -> GSMSDRTrainer:
    """A real trainer on ``scene`` in this process (CPU, no viewer); ``overrides`` go through the dataclass
    constructor, as ns-train's flags do."""
    config.pipeline.datamanager.data = scene
    config.machine.device_type = "cpu"
    config = dataclasses.replace(config, output_dir=out, vis="tensorboard", timestamp="run", **overrides)
    return config.setup(local_rank=0, world_size=1)


def run_dir_copy(run: TrainedRun, dest: Path) -> Path:
    """A copy of ``run`` under ``dest`` whose config.yml points at the copy (ns-eval finds checkpoints through it)."""
    copy = dest / "outputs" / run.scene.name / "gsmsdr" / "run"
    shutil.copytree(run.run_dir, copy)
    config = yaml.load((copy / "config.yml").read_text(), Loader=yaml.Loader)
    config.output_dir = dest / "outputs"
    (copy / "config.yml").write_text(yaml.dump(config), encoding="utf8")
    return copy


# -- our errors as one line ---------------------------------------------------------------------------------------


def test_ns_train_prints_our_error_as_one_line_and_the_traceback_only_with_gsmsdr_debug(tmp_path: Path):
    """A folder of photos without poses (the data checks reject it): one line, no traceback; with GSMSDR_DEBUG=1
    the traceback is back. Both runs at once: each is mostly interpreter and nerfstudio start-up."""
    photos = tmp_path / "photos"
    (photos / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(3):
        Image.fromarray(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)).save(photos / "images" / f"{i:03d}.png")
    args = [str(BIN / "ns-train"), "gsmsdr", "--data", str(photos), "--output-dir", str(tmp_path / "out"),
            *map(str, TRAIN_FLAGS)]  # fmt: skip
    runs = {
        debug: subprocess.Popen(
            args,
            cwd=tmp_path,
            env=cli_env(**({"GSMSDR_DEBUG": "1"} if debug else {})),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for debug in (False, True)
    }
    logs = {debug: proc.communicate(timeout=scaled(600)) for debug, proc in runs.items()}
    out, err = logs[False]
    assert runs[False].returncode == 1, (out + err)[-3000:]
    assert "Traceback" not in out + err, err[-3000:]
    expected = (
        f"InputError: gsmsdr: '{photos}' holds photos ({photos / 'images'}) but no camera poses. Compute "
        f"them with `gsmsdr-process --images {photos / 'images'} --out {tmp_path / 'photos-scene'}`"
    )
    assert lines_with(out + err, "InputError") == [err.strip().splitlines()[-1]], err[-3000:]
    assert err.strip().splitlines()[-1].startswith(expected), err[-3000:]
    debug_out, debug_err = logs[True]
    assert runs[True].returncode == 1
    assert "Traceback (most recent call last)" in debug_err, debug_err[-3000:]
    assert "gsmsdr_ns.io.errors.InputError: gsmsdr: '" in debug_err
    assert not list(tmp_path.rglob("*.ckpt"))


def test_the_exception_hook_changes_only_our_errors(monkeypatch, capsys):
    seen = []
    monkeypatch.setattr(sys, "excepthook", lambda *exc: seen.append(exc[0]))
    monkeypatch.delenv("GSMSDR_DEBUG", raising=False)
    install_excepthook()
    install_excepthook()  # idempotent: one wrapper
    for error in (InputError("gsmsdr: bad scene 'x'"), DiskFullError("gsmsdr: no space left"), RuntimeError("bug")):
        sys.excepthook(type(error), error, None)
    assert seen == [RuntimeError]  # the previous hook (the interpreter's traceback) still prints the others
    assert capsys.readouterr().err.splitlines() == ["InputError: gsmsdr: bad scene 'x'",
                                                    "DiskFullError: gsmsdr: no space left"]  # fmt: skip
    monkeypatch.setenv("GSMSDR_DEBUG", "1")
    sys.excepthook(InputError, InputError("x"), None)
    assert seen == [RuntimeError, InputError]


# -- writing checkpoints ------------------------------------------------------------------------------------------


def test_ns_train_leaves_one_complete_checkpoint_and_no_temporary_file(trained_run: TrainedRun):
    assert sorted(p.name for p in trained_run.checkpoint_dir.iterdir()) == [last_checkpoint(trained_run).name]
    assert not [p for p in trained_run.run_dir.iterdir() if ".partial-" in p.name]
    state = load_checkpoint_file(last_checkpoint(trained_run))
    assert sorted(state) == ["optimizers", "pipeline", "scalers", "schedulers", "step"]
    assert state["step"] == trained_run.steps - 1


def test_a_full_disk_says_so_and_leaves_no_partial_checkpoint(tmp_path: Path, monkeypatch):
    """A real ENOSPC: the temporary file is a symlink to /dev/full, where every write fails with ENOSPC."""
    models = tmp_path / "run" / "nerfstudio_models"
    models.mkdir(parents=True)
    previous = save_checkpoint_atomic({"step": 1, "w": torch.ones(3)}, checkpoint_file(models, 1))
    path = checkpoint_file(models, 2)
    monkeypatch.setattr(ckpt.secrets, "token_hex", lambda _n: "full")
    temporary = tmp_path / "run" / f".nerfstudio_models.{path.name}.partial-{os.getpid()}-full"
    temporary.symlink_to("/dev/full")
    with pytest.raises(DiskFullError) as caught:
        save_checkpoint_atomic({"step": 2, "w": torch.zeros(100_000)}, path)
    message = str(caught.value)
    assert message.startswith(f"gsmsdr: no space left on the disk to save checkpoint '{path}' (")
    assert f"free in '{models}')" in message  # how much room the checkpoint folder's disk has
    assert "Free some space, or train with --output-dir on a disk with room" in message
    assert caught.value.errno == errno.ENOSPC and isinstance(caught.value.__cause__, OSError)
    assert not path.exists() and not os.path.lexists(temporary)
    assert Path("/dev/full").is_char_device()  # only the link was removed
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["nerfstudio_models"]
    assert sorted(p.name for p in models.iterdir()) == [previous.name]
    assert load_checkpoint_file(previous)["step"] == 1


@pytest.fixture(scope="module")
def trainer(tiny_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> GSMSDRTrainer:
    """A set-up ``gsmsdr`` trainer on the tiny scene (in this process, not trained)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GSMSDRWarning)
        trainer = make_trainer(gsmsdr_trainer_config(), tiny_scene, tmp_path_factory.mktemp("trainer"))
        trainer.setup()
    return trainer


def test_trainer_checkpoints_are_atomic_and_only_the_latest_is_kept(trainer: GSMSDRTrainer, monkeypatch):
    models = trainer.checkpoint_dir
    trainer.save_checkpoint(3)
    trainer.save_checkpoint(7)
    assert sorted(p.name for p in models.iterdir()) == ["step-000000007.ckpt"]
    state = load_checkpoint_file(models / "step-000000007.ckpt")
    assert sorted(state) == ["optimizers", "pipeline", "scalers", "schedulers", "step"] and state["step"] == 7
    means = trainer.pipeline.model.gauss_params["means"].detach()
    torch.testing.assert_close(state["pipeline"]["_model.gauss_params.means"], means)

    def fsync_on_a_full_disk(_fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(ckpt.os, "fsync", fsync_on_a_full_disk)
    with pytest.raises(DiskFullError, match=rf"no space left on the disk to save checkpoint '{models}/step-000000009"):
        trainer.save_checkpoint(9)
    assert sorted(p.name for p in models.iterdir()) == ["step-000000007.ckpt"]
    assert not [p for p in models.parent.iterdir() if ".partial-" in p.name]


# -- reading checkpoints ------------------------------------------------------------------------------------------


def test_empty_truncated_and_damaged_checkpoints_are_named(trained_run: TrainedRun, tmp_path: Path):
    good = last_checkpoint(trained_run)
    models = tmp_path / "nerfstudio_models"
    models.mkdir()
    shutil.copy(good, checkpoint_file(models, 59))
    empty = checkpoint_file(models, 60)
    empty.touch()
    with pytest.raises(InputError, match=rf"checkpoint '{empty}' is empty \(0 bytes\): it was cut off while being "
                                         r"written .* Delete it to use the previous checkpoint 'step-000000059.ckpt' "
                                         r"\(.*--load-step 59\)"):  # fmt: skip
        find_checkpoint(models)
    empty.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(InputError, match=rf"checkpoint '{empty}' is truncated or not a torch checkpoint"):
        find_checkpoint(models)
    assert find_checkpoint(models, load_step=59) == checkpoint_file(models, 59)
    with pytest.raises(InputError, match=rf"no checkpoint of step 61 in '{models}' \(it has steps \[59, 60\]\)"):
        find_checkpoint(models, load_step=61)
    # Damaged inside (a complete zip without one of its tensors): torch's error, with the file named.
    damaged = tmp_path / "damaged.ckpt"
    with zipfile.ZipFile(good) as source, zipfile.ZipFile(damaged, "w") as copy:
        tensors = [i for i in source.infolist() if "/data/" in i.filename]
        dropped = max(tensors, key=lambda i: i.file_size)
        for info in source.infolist():
            if info is not dropped:
                copy.writestr(info, source.read(info))
    check_checkpoint_file(damaged)
    with pytest.raises(InputError, match=rf"cannot read checkpoint '{damaged}' \(PytorchStreamReader failed locating "
                                         r"file data/\d+: file not found\): the file is damaged"):  # fmt: skip
        load_checkpoint_file(damaged)


def test_load_dirs_without_checkpoints_say_where_they_are_expected(trained_run: TrainedRun, tmp_path: Path):
    models = trained_run.checkpoint_dir
    with pytest.raises(InputError, match=rf"'{trained_run.run_dir}' is a run folder; its checkpoints are expected in "
                                         rf"'{models}'. Pass --load-dir {models}"):  # fmt: skip
        find_checkpoint(trained_run.run_dir)
    empty = tmp_path / "nerfstudio_models"
    empty.mkdir()
    with pytest.raises(InputError, match=rf"no checkpoint \(step-\*.ckpt\) in '{empty}'; checkpoints are written to "
                                         r"<run>/nerfstudio_models"):  # fmt: skip
        find_checkpoint(empty)
    with pytest.raises(InputError, match=rf"checkpoint folder '{tmp_path / 'nope'}' does not exist"):
        find_checkpoint(tmp_path / "nope")
    with pytest.raises(InputError, match=r"is a file; --load-dir takes a folder of checkpoints .* --load-checkpoint"):
        find_checkpoint(last_checkpoint(trained_run))
    shutil.copy(last_checkpoint(trained_run), empty / "step-000000059.ckpt")
    (empty / "notes.txt").write_text("")
    assert find_checkpoint(empty) == empty / "step-000000059.ckpt"  # our trainer ignores other names
    with pytest.raises(InputError, match=rf"'{empty / 'notes.txt'}' is not a checkpoint .* Move it out"):
        find_checkpoint(empty, nerfstudio_names=True)  # nerfstudio's loaders (eval_setup) would fail on it


def test_the_trainer_checks_load_dir_and_load_checkpoint(trainer: GSMSDRTrainer, trained_run: TrainedRun, tmp_path):
    config = trainer.config
    run_folder = dataclasses.replace(config, load_dir=trained_run.run_dir)  # as ns-train --load-dir builds it
    resumed = run_folder.setup(local_rank=0, world_size=1)
    resumed.pipeline, resumed.optimizers = trainer.pipeline, trainer.optimizers
    with pytest.raises(InputError, match=r"is a run folder; its checkpoints are expected in"):
        resumed._load_checkpoint()
    empty = tmp_path / "step-000000003.ckpt"
    empty.touch()
    resumed.config = dataclasses.replace(config, load_checkpoint=empty)
    with pytest.raises(InputError, match=rf"checkpoint '{empty}' is empty \(0 bytes\)"):
        resumed._load_checkpoint()
    # Assigning load_dir after construction (what eval_setup does) checks it right away.
    with pytest.raises(InputError, match=r"is a run folder"):
        resumed.config.load_dir = trained_run.run_dir


def test_ns_eval_names_a_truncated_checkpoint(trained_run: TrainedRun, tmp_path: Path):
    run = run_dir_copy(trained_run, tmp_path)
    broken = run / "nerfstudio_models" / last_checkpoint(trained_run).name
    broken.write_bytes(broken.read_bytes()[:4096])
    output = tmp_path / "eval.json"
    env = cli_env()
    proc = subprocess.run([str(BIN / "ns-eval"), "--load-config", str(run / "config.yml"), "--output-path",
                           str(output)], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=scaled(600))  # fmt: skip
    log = proc.stdout + proc.stderr
    assert proc.returncode == 1 and "Traceback" not in log, log[-3000:]
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith(f"InputError: gsmsdr: checkpoint '{broken}' is truncated or not a torch checkpoint "
                           "(4096 bytes, no zip index at its end)"), log[-3000:]  # fmt: skip
    assert "Delete it and train again" in line
    assert not output.exists()


# -- a checkpoint of the other preset -----------------------------------------------------------------------------


def _model(make_config, **overrides):
    config = make_config().pipeline.model
    config = dataclasses.replace(config, **{"degradation": "motion", "num_random": 50, **overrides})
    scene_box = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GSMSDRWarning)
        return config.setup(scene_box=scene_box, num_train_data=4)


def test_a_gsmsdr_checkpoint_in_gsmsdr_lite_names_the_blur_field_widths():
    full, lite = _model(gsmsdr_trainer_config), _model(gsmsdr_lite_trainer_config)
    with pytest.raises(CheckpointMismatchError) as caught:
        lite.load_state_dict(full.state_dict())
    assert str(caught.value) == (
        "gsmsdr: the checkpoint was trained with other widths (blur field n=32, view 32, mid 64, kernels 5/9/17; "
        "SH degree 3) than this run's config builds (blur field n=16, view 16, mid 32, kernels 5/9/13; SH degree "
        "1); load it with `ns-train gsmsdr`."
    )
    with pytest.raises(CheckpointMismatchError, match=r"load it with `ns-train gsmsdr-lite`\.$"):
        full.load_state_dict(lite.state_dict())
    other_scene = _model(gsmsdr_trainer_config)
    other_scene.degradation.blur_field.mcf.view_embedding = torch.nn.Embedding(7, 32)
    with pytest.raises(CheckpointMismatchError, match=r"view_embedding.weight' has shape \[7, 32\], this model's "
                                                      r"\[4, 32\] .* on the scene it was trained on\.$"):  # fmt: skip
        full.load_state_dict(other_scene.state_dict())


def test_the_widths_named_are_read_where_the_model_keeps_them():
    """Any width option (not only the presets'), found in the tensors it sets, whatever the feature network."""

    def model(**blur_options):
        blur = dataclasses.replace(gsmsdr_trainer_config().pipeline.model.blur_field, **blur_options)
        return _model(gsmsdr_trainer_config, blur_field=blur)

    with pytest.raises(CheckpointMismatchError) as caught:
        model().load_state_dict(model(mid_channels=48, kernel_sizes=(5, 11, 17)).state_dict())
    assert str(caught.value) == (
        "gsmsdr: the checkpoint was trained with other widths (blur field n=32, view 32, mid 48, kernels 5/11/17; "
        "SH degree 3) than this run's config builds (blur field n=32, view 32, mid 64, kernels 5/9/17; SH degree "
        "3); load it with `ns-train gsmsdr`."
    )
    with pytest.raises(CheckpointMismatchError) as caught:  # BAGS' plain CNN as the feature network
        model(mode="msd_only").load_state_dict(model(mode="msd_only", feature_dim=24).state_dict())
    assert str(caught.value) == (
        "gsmsdr: the checkpoint was trained with other widths (blur field n=24, view 32, mid 64, kernels 5/9/17; "
        "SH degree 3) than this run's config builds (blur field n=32, view 32, mid 64, kernels 5/9/17; SH degree "
        "3); load it with the method and flags it was trained with."
    )


def test_a_checkpoint_with_a_lens_for_unknown_blur_names_the_flag_to_load_it():
    """Before the thin lens became optional on images of unknown blur, such scenes' checkpoints carry one."""

    def nothing_known(lens: bool):  # 4 training views without records, with or without the lens on them
        options = DegradationConfig(thin_lens_for_unknown_kind=lens)
        return _model(gsmsdr_trainer_config, degradation="auto", degradation_model=options)

    with_lens, without = nothing_known(lens=True), nothing_known(lens=False)
    with pytest.raises(CheckpointMismatchError,
                       match=r"has a thin lens .*degradation-model.thin-lens-for-unknown-kind True\)"):  # fmt: skip
        without.load_state_dict(with_lens.state_dict())
    with pytest.raises(CheckpointMismatchError, match=r"has no thin lens, but .*degradation-model.thin-lens False"):
        with_lens.load_state_dict(without.state_dict())
    without.load_state_dict(nothing_known(lens=False).state_dict())  # the same config loads


def test_a_checkpoint_with_or_without_camera_shake_paths_names_the_flag_to_load_it():
    def motion_model(shake: bool):  # 4 motion-blurred training views, with or without rotation paths
        options = DegradationConfig(camera_shake=shake)
        return _model(gsmsdr_trainer_config, degradation="motion", degradation_model=options)

    with_paths, without = motion_model(shake=True), motion_model(shake=False)
    with pytest.raises(
        CheckpointMismatchError, match=r"has camera shake paths .*degradation-model.camera-shake True\)"
    ):
        without.load_state_dict(with_paths.state_dict())
    with pytest.raises(
        CheckpointMismatchError, match=r"has no camera shake paths, .*degradation-model.camera-shake False"
    ):
        with_paths.load_state_dict(without.state_dict())
    with_paths.load_state_dict(motion_model(shake=True).state_dict())  # the same config loads
    moving = _model(gsmsdr_trainer_config, degradation="motion",
                    degradation_model=DegradationConfig(camera_shake=True, shake_translation=True))  # fmt: skip
    with pytest.raises(CheckpointMismatchError, match=r"move the camera, .*degradation-model.shake-translation True\)"):
        with_paths.load_state_dict(moving.state_dict())
    with pytest.raises(CheckpointMismatchError, match=r"only turn the camera, .*shake-translation False\)"):
        moving.load_state_dict(with_paths.state_dict())


def test_the_gsmsdr_lite_trainer_names_a_gsmsdr_checkpoint_and_its_method(trained_run: TrainedRun, tmp_path):
    """What ``ns-train gsmsdr-lite --load-dir <gsmsdr run>/nerfstudio_models`` does, in this process: the trained
    scene is sharp (no blur field), so the SH degree is what differs; the method comes from the run's config.yml."""
    lite = make_trainer(gsmsdr_lite_trainer_config(), trained_run.scene, tmp_path, load_dir=trained_run.checkpoint_dir)
    with warnings.catch_warnings(), pytest.raises(CheckpointMismatchError) as caught:
        warnings.simplefilter("ignore", GSMSDRWarning)
        lite.setup()
    assert str(caught.value) == (
        f"gsmsdr: checkpoint '{last_checkpoint(trained_run)}' was trained with other widths (SH degree 3) than this "
        "run's config builds (SH degree 1); load it with `ns-train gsmsdr`."
    )
    assert not list(tmp_path.rglob("*.ckpt"))


# -- Ctrl-C -------------------------------------------------------------------------------------------------------


def test_ctrl_c_in_gsmsdr_synth_prints_one_line_and_exits_130(tmp_path: Path):
    out = tmp_path / "scene"
    args = [str(BIN / "gsmsdr-synth"), "--out", str(out), "--num-views", "1000", "--width", "96", "--height", "72"]
    # As in a terminal: SIGINT raises KeyboardInterrupt (a background shell may have set it to ignored).
    proc = subprocess.Popen(args, cwd=tmp_path, env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
    try:
        deadline = time.monotonic() + scaled(300)
        # Interrupt while views are being written into the temporary folder.
        while not any(p.suffix == ".png" for p in tmp_path.glob(".scene.*/**/*")):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "gsmsdr-synth wrote no view"
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=scaled(120))
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, (stdout + stderr)[-3000:]
    assert "Traceback" not in stdout + stderr and "KeyboardInterrupt" not in stdout + stderr
    assert lines_with(stdout + stderr, "interrupted") == ["interrupted; nothing was written"]
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_run_entrypoint_ctrl_c_and_user_errors(capsys, monkeypatch):
    from rich.console import Console

    class Interrupted:
        def main(self):
            raise KeyboardInterrupt

    class BadInput:
        def main(self):
            raise InputError("gsmsdr: '[x]' is bad; fix it")

    console = Console(width=40)
    with pytest.raises(SystemExit) as caught:
        run_entrypoint(Interrupted, console, interrupted="interrupted; 3 finished runs are kept in runs/")
    assert caught.value.code == 130
    assert capsys.readouterr().out == "interrupted; 3 finished runs are kept in runs/\n"  # one line, not wrapped
    monkeypatch.delenv("GSMSDR_DEBUG", raising=False)
    with pytest.raises(SystemExit) as caught:
        run_entrypoint(BadInput, console)
    assert caught.value.code == 1 and capsys.readouterr().out == "error: gsmsdr: '[x]' is bad; fix it\n"
    monkeypatch.setenv("GSMSDR_DEBUG", "1")
    with pytest.raises(InputError):
        run_entrypoint(BadInput, console)


def _interrupt_when(proc: subprocess.Popen, ready, what: str) -> tuple:
    """Send SIGINT once ``ready()`` holds (hang guard: scaled 600 s), then collect the output."""
    try:
        deadline = time.monotonic() + scaled(600)
        while not ready():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, f"ns-train never got to {what}"
            time.sleep(0.1)
        proc.send_signal(signal.SIGINT)
        return proc.communicate(timeout=scaled(120))
    finally:
        if proc.poll() is None:
            proc.kill()


def test_ctrl_c_in_ns_train_prints_one_line_keeps_the_last_checkpoint_and_exits_130(tiny_scene: Path, tmp_path):
    """nerfstudio's launcher prints KeyboardInterrupt's traceback and exits 0; our trainer exits 130 with one line
    naming the last complete checkpoint, which loads."""
    args = [
        str(BIN / "ns-train"),
        "gsmsdr",
        "--data",
        str(tiny_scene),
        "--output-dir",
        str(tmp_path / "out"),
        "--timestamp",
        "run",
        "--max-num-iterations",
        "100000",
        "--steps-per-save",
        "3",
        *map(str, TRAIN_FLAGS),
    ]
    proc = subprocess.Popen(args, cwd=tmp_path, env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
    models = tmp_path / "out" / tiny_scene.name / "gsmsdr" / "run" / "nerfstudio_models"
    stdout, stderr = _interrupt_when(proc, lambda: len(list(models.glob("*.ckpt"))) > 0, "a checkpoint")
    assert proc.returncode == 130, (stdout + stderr)[-3000:]
    assert "Traceback" not in stdout + stderr and "KeyboardInterrupt" not in stdout + stderr, stderr[-3000:]
    (line,) = lines_with(stdout + stderr, "interrupted")
    assert line.startswith("gsmsdr: interrupted at step ") and "the last complete checkpoint is " in line
    kept = Path(line.split("the last complete checkpoint is ")[1])
    assert kept.parent == models and kept.is_file()
    assert load_checkpoint_file(kept)["step"] == int(kept.stem.split("-")[1])
    assert not [p for p in models.parent.iterdir() if ".partial-" in p.name]


def test_ctrl_c_while_ns_train_sets_up_exits_130_with_one_line(tiny_scene: Path, tmp_path):
    args = [
        str(BIN / "ns-train"),
        "gsmsdr",
        "--data",
        str(tiny_scene),
        "--output-dir",
        str(tmp_path / "out"),
        "--timestamp",
        "run",
        *map(str, TRAIN_FLAGS),
    ]
    proc = subprocess.Popen(args, cwd=tmp_path, env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
    log = []

    def reading_the_scene() -> bool:  # printed inside set-up, before the scene's COLMAP model is read
        log.append(os.read(proc.stdout.fileno(), 1 << 16).decode(errors="replace"))
        return "gsmsdr-data: reading" in "".join(log)

    stdout, stderr = _interrupt_when(proc, reading_the_scene, "reading the scene")
    stdout = "".join(log) + stdout
    assert proc.returncode == 130, (stdout + stderr)[-3000:]
    assert "Traceback" not in stdout + stderr, stderr[-3000:]
    assert len(lines_with(stdout + stderr, "gsmsdr: interrupted")) == 1


def test_out_of_range_step_options_and_kernel_sizes_name_the_allowed_range():
    from gsmsdr_ns.blur.field import BlurFieldConfig
    from gsmsdr_ns.blur.hpko import MAX_KERNEL_SIZE, MAX_VIEW_KERNEL_SIZE, check_kernel_sizes
    from gsmsdr_ns.plugin.trainer import check_step_options

    per_pixel = rf"from 1 to {MAX_KERNEL_SIZE}; per-view kernels \(mode view\) up to {MAX_VIEW_KERNEL_SIZE}"
    for bad in ((5, 9, 999), (5, MAX_KERNEL_SIZE + 2), (4,)):
        with pytest.raises(InputError, match=per_pixel + r" \(--pipeline.model."):
            check_kernel_sizes(bad)
    assert check_kernel_sizes((5, 9, MAX_KERNEL_SIZE)) == (5, 9, MAX_KERNEL_SIZE)
    # one kernel per image (mode view) may be larger than a per-pixel one, up to its own limit
    assert BlurFieldConfig(mode="view", kernel_sizes=(13, 25, 49)).max_kernel_size == MAX_VIEW_KERNEL_SIZE
    with pytest.raises(InputError, match=per_pixel):
        BlurFieldConfig(mode="full", kernel_sizes=(13, 25, 49))
    with pytest.raises(InputError, match=rf"odd integers from 1 to {MAX_VIEW_KERNEL_SIZE} \(--pipeline.model."):
        BlurFieldConfig(mode="view", kernel_sizes=(13, 25, MAX_VIEW_KERNEL_SIZE + 2))
    config = gsmsdr_trainer_config()
    check_step_options(config)
    for name, flag in (("max_num_iterations", "--max-num-iterations"), ("steps_per_save", "--steps-per-save")):
        bad = dataclasses.replace(config, **{name: 0})
        with pytest.raises(InputError, match=rf"^gsmsdr: {flag} must be an integer >= 1, got 0$"):
            check_step_options(bad)
    config.logging.steps_per_log = -5
    with pytest.raises(InputError, match="--logging.steps-per-log must be an integer >= 1, got -5"):
        check_step_options(config)


def test_a_moved_scene_names_the_fix_of_the_command_that_met_it(monkeypatch, tmp_path):
    from gsmsdr_ns._cli import user_error_line
    from gsmsdr_ns.io.errors import SceneFolderMissingError

    error = SceneFolderMissingError(tmp_path / "gone")
    monkeypatch.setattr(sys, "argv", ["/venv/bin/ns-train", "gsmsdr"])
    assert user_error_line(error).endswith("Pass the scene directory with --data <dir> (make a test scene with "
                                           "`gsmsdr-synth`).")  # fmt: skip
    for command in ("ns-eval", "gsmsdr-eval", "gsmsdr-export", "ns-viewer"):
        monkeypatch.setattr(sys, "argv", [f"/venv/bin/{command}"])
        line = user_error_line(error)
        assert line.startswith(f"InputError: gsmsdr: the scene folder '{tmp_path / 'gone'}' that the run's config.yml")
        assert "--data" not in line and f"{command} reads it from config.yml" in line


def test_ns_eval_of_a_run_whose_scene_moved_says_to_fix_config_yml(trained_run: TrainedRun, tmp_path: Path):
    config = yaml.load(trained_run.config.read_text(), Loader=yaml.Loader)  # nerfstudio's own way to read it
    moved = tmp_path / "moved-away"
    config.data = config.pipeline.datamanager.data = config.pipeline.datamanager.dataparser.data = moved
    run = tmp_path / "run"  # the checkpoints stay where config.yml says (the trained run's)
    run.mkdir()
    (run / "config.yml").write_text(yaml.dump(config))
    proc = subprocess.run([str(BIN / "ns-eval"), "--load-config", str(run / "config.yml"), "--output-path",
                           str(tmp_path / "eval.json")], cwd=tmp_path, env=cli_env(), capture_output=True, text=True,
                          timeout=scaled(600))  # fmt: skip
    output = proc.stdout + proc.stderr
    assert proc.returncode == 1 and "Traceback" not in output, output[-3000:]
    (line,) = lines_with(output, "InputError")
    assert f"the scene folder '{moved}' that the run's config.yml names does not exist" in line
    assert "ns-eval reads it from config.yml" in line and "--data" not in line
    assert not (tmp_path / "eval.json").exists()


def test_ctrl_c_closing_the_viewer_after_training_is_not_an_interruption(tiny_scene: Path, tmp_path):
    """With the viewer, ns-train waits after the last step until Ctrl-C: that ends the run normally (exit 0)."""
    from viewer_client import LOOPBACK, free_loopback_port

    flags = [str(f) for f in TRAIN_FLAGS]
    vis = flags.index("--vis")
    del flags[vis : vis + 2]
    stdout_path = tmp_path / "stdout.txt"
    args = [str(BIN / "ns-train"), "gsmsdr", "--data", str(tiny_scene), "--output-dir", str(tmp_path / "out"),
            "--timestamp", "run", "--max-num-iterations", "3", *flags, "--vis", "viewer",
            "--viewer.quit-on-train-completion", "False", "--viewer.websocket-host", LOOPBACK,
            "--viewer.websocket-port", str(free_loopback_port())]  # fmt: skip
    with open(stdout_path, "w") as stdout:
        proc = subprocess.Popen(args, cwd=tmp_path, env=cli_env(), stdout=stdout, stderr=subprocess.PIPE, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # fmt: skip
        _, stderr = _interrupt_when(proc, lambda: "Training Finished" in stdout_path.read_text(errors="replace"),
                                    "the end of training")  # fmt: skip
    output = stdout_path.read_text(errors="replace") + stderr
    assert proc.returncode == 0, output[-3000:]
    assert "Traceback" not in output and "interrupted" not in output
    assert "gsmsdr: viewer closed; training had finished" in output


def test_ctrl_c_that_a_library_turned_into_its_own_error_still_exits_130(trainer: GSMSDRTrainer, monkeypatch,
                                                                         capsys):  # fmt: skip
    """pycolmap's import turns a KeyboardInterrupt into RuntimeError("Cannot import the C++ backend ...")."""
    from nerfstudio.engine.trainer import Trainer

    def interrupted_import(*_args, **_kwargs):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise RuntimeError("Cannot import the C++ backend pycolmap._core.")

    monkeypatch.setattr(Trainer, "setup", interrupted_import)
    with pytest.raises(SystemExit) as exited:
        trainer.setup()
    assert exited.value.code == 130
    assert capsys.readouterr().err == "gsmsdr: interrupted while setting up; nothing was trained\n"
    monkeypatch.setattr(Trainer, "setup", lambda *_a, **_k: (_ for _ in ()).throw(RuntimeError("a bug")))
    with pytest.raises(RuntimeError, match="a bug"):  # other errors stay what they are
        trainer.setup()
