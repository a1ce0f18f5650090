"""Shared session fixtures: a tiny generated scene and one short real ``ns-train gsmsdr`` run on it, and the
suite's hang guards.

Kept small on purpose. ``trained_run`` is trained once per session and reused by the plugin tests (ns-eval,
resume) and the viewer tests; treat its directory as read-only.

Hang guards, not speed checks: pytest-timeout's per-test limit (``[tool.pytest.ini_options]``, ``slow`` tests get
``SLOW_TIMEOUT_S``), subprocess timeouts and server waits are all far above a normal run and all multiplied by the
``GSMSDR_TEST_TIMEOUT_SCALE`` environment variable (default 1) for a slow or heavily shared machine.
"""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, List, Sequence, Tuple

import pytest

if TYPE_CHECKING:
    import numpy as np

TIMEOUT_SCALE = float(os.environ.get("GSMSDR_TEST_TIMEOUT_SCALE", "1"))
"""Multiplies every hang guard of the suite (pytest-timeout limits, subprocess timeouts, server waits)."""

SLOW_TIMEOUT_S = 3600.0
"""pytest-timeout's limit (before scaling) for ``slow`` tests without their own ``timeout`` mark; the fixture
setup counts towards it, and the slow fixtures train for minutes."""


def scaled(seconds: float) -> float:
    """A hang guard of ``seconds`` multiplied by ``GSMSDR_TEST_TIMEOUT_SCALE``."""
    return seconds * TIMEOUT_SCALE


def pytest_collection_modifyitems(config: pytest.Config, items: list) -> None:
    """Give ``slow`` tests ``SLOW_TIMEOUT_S`` and scale every test's pytest-timeout limit by the timeout scale."""
    if not config.pluginmanager.hasplugin("timeout"):  # -p no:timeout
        return
    from pytest_timeout import get_env_settings

    default = get_env_settings(config).timeout or 0.0  # --timeout, PYTEST_TIMEOUT or the ini file; 0: none
    for item in items:
        marker = item.get_closest_marker("timeout")
        args, kwargs = (marker.args, dict(marker.kwargs)) if marker is not None else ((), {})
        base = kwargs.pop("timeout", args[0] if args else None)
        if base is None:
            base = SLOW_TIMEOUT_S if item.get_closest_marker("slow") is not None else default
        if base:  # the closest mark wins: prepend the scaled one
            item.add_marker(pytest.mark.timeout(scaled(float(base)), *args[1:], **kwargs), append=False)


BIN = Path(sys.executable).parent  # the venv running the tests also holds ns-train / ns-eval / ns-viewer

TINY_SCENE = dict(num_views=10, width=64, height=48, num_points=500, seed=0)
"""10 views -> nerfstudio's default eval split (every 8th view) holds views 0 and 8; 8 train views."""

TRAIN_STEPS = 60
TRAIN_FLAGS = (
    "--machine.device-type", "cpu",
    "--vis", "tensorboard",  # no viewer server; writes the scalars the tests read
    "--logging.steps-per-log", "5",
    "--steps-per-eval-image", "0",
    "--steps-per-eval-all-images", "0",
    "--pipeline.model.num-downscales", "0",
    "--pipeline.model.warmup-length", "10",
    "--pipeline.model.refine-every", "10",
)  # fmt: skip


@dataclass(frozen=True)
class TrainedRun:
    scene: Path  # the scene directory passed as --data
    run_dir: Path  # <output-dir>/<experiment>/gsmsdr/<timestamp>
    config: Path  # run_dir / "config.yml" (for ns-eval / ns-viewer --load-config)
    checkpoint_dir: Path  # run_dir / "nerfstudio_models"
    log: str  # ns-train's stdout + stderr
    steps: int


def run_cli(tool: str, args: Sequence[str], cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    """Run a console script of this venv (``ns-train``, ``ns-eval``, ...) and capture its output as text.
    ``timeout``: a hang guard in seconds, multiplied by ``GSMSDR_TEST_TIMEOUT_SCALE``."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", COLUMNS="200")
    return subprocess.run(
        [str(BIN / tool), *map(str, args)],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=scaled(timeout),
    )


def make_tiny_scene(out_dir: Path, **overrides) -> Path:
    """Generate a tiny procedural scene (``gsmsdr_ns.synth``) into ``out_dir`` and return it."""
    from gsmsdr_ns.synth.config import SynthSceneConfig
    from gsmsdr_ns.synth.generate import generate_scene

    return generate_scene(out_dir, SynthSceneConfig(**{**TINY_SCENE, **overrides}))


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 10-view 64x48 scene with 500 sparse points (read-only: copy it before corrupting it)."""
    return make_tiny_scene(tmp_path_factory.mktemp("scenes") / "tiny")


@pytest.fixture(scope="session")
def trained_run(tiny_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> TrainedRun:
    """``ns-train gsmsdr`` for 60 CPU steps on ``tiny_scene`` with refinement every 10 steps."""
    work = tmp_path_factory.mktemp("trained")
    args = ["gsmsdr", "--data", tiny_scene, "--output-dir", work / "outputs", "--timestamp", "run",
            "--max-num-iterations", TRAIN_STEPS, "--steps-per-save", TRAIN_STEPS, *TRAIN_FLAGS]  # fmt: skip
    proc = run_cli("ns-train", args, cwd=work)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"ns-train failed (exit {proc.returncode}):\n{log[-6000:]}"
    run_dir = work / "outputs" / tiny_scene.name / "gsmsdr" / "run"
    return TrainedRun(tiny_scene, run_dir, run_dir / "config.yml", run_dir / "nerfstudio_models", log, TRAIN_STEPS)


def write_transforms_json(src: Path, dst: Path) -> Path:
    """A nerfstudio transforms.json scene (OpenGL camera-to-world, per-frame OPENCV intrinsics) from the COLMAP scene
    ``src``, written to ``dst`` (images copied)."""
    import json
    import shutil

    from gsmsdr_ns.data.cameras import cameras_from_colmap
    from gsmsdr_ns.io.colmap import read_colmap

    shutil.copytree(src / "images", dst / "images")
    cameras = cameras_from_colmap(read_colmap(src / "sparse" / "0"))
    frames = []
    for name, c2w, (fx, fy, cx, cy), (w, h) in zip(cameras.names, cameras.c2w, cameras.intrinsics, cameras.sizes):
        gl = c2w.copy()
        gl[:3, 1:3] *= -1
        frames.append({"file_path": f"images/{name}", "transform_matrix": gl.tolist(), "fl_x": fx, "fl_y": fy,
                       "cx": cx, "cy": cy, "w": int(w), "h": int(h)})  # fmt: skip
    (dst / "transforms.json").write_text(json.dumps({"camera_model": "OPENCV", "frames": frames}))
    return dst


def cpu_trainer_config(scene: Path, output_dir: Path, max_steps: int):
    """The ``gsmsdr`` TrainerConfig on ``scene`` as the in-process trainer tests use it: CPU, tensorboard only, no
    periodic saves, evaluations or logs, nothing known about the images, the thin lens put before the field on every
    image (``thin_lens_for_unknown_kind``: the most expensive path, every part exercised), a lite blur field on from
    step 0, full resolution from the start."""
    from gsmsdr_ns.blur.degradation_config import DegradationConfig
    from gsmsdr_ns.blur.field import BlurFieldConfig
    from gsmsdr_ns.plugin.method_config import gsmsdr_trainer_config

    config = gsmsdr_trainer_config()
    config.machine.device_type = "cpu"
    config.vis = "tensorboard"
    config.output_dir = output_dir
    config.timestamp = "run"
    config.max_num_iterations = max_steps
    config.steps_per_save = 10_000
    config.steps_per_eval_image = config.steps_per_eval_batch = config.steps_per_eval_all_images = 0
    config.logging.steps_per_log = 10_000
    config.logging.local_writer.enable = False
    config.pipeline.datamanager.data = scene
    config.pipeline.datamanager.dataparser.estimate_degradations = False  # nothing known about any image
    model = config.pipeline.model
    model.num_downscales, model.warmup_length = 0, 2
    model.blur_field = BlurFieldConfig(size="lite", kernel_sizes=(3, 5, 9))
    model.degradation_model = DegradationConfig(warmup=0, thin_lens_for_unknown_kind=True, thin_lens_start="warmup")
    return config


def shared_fern() -> Path:
    """The real LLFF fern photos (``llff-fern``, with ``images_8``, ``images_16`` and ``poses_bounds.npy``): under
    $GSMSDR_DATA_DIR, else in ``shared/data/`` of the nearest parent folder of the tests that has them (beside the
    repository in CI, further up from a git worktree). Fails the test, naming where it looked, when they are
    missing."""
    from gsmsdr_ns.io.photo_sets import DATA_DIR_ENV, find_photo_set, photo_set_roots

    anchors = [Path(__file__).parent]
    fern = find_photo_set("llff-fern", anchors, subfolder="images_16")
    if fern is None:
        pytest.fail(f"the fern photos (llff-fern) are missing: looked in {photo_set_roots(anchors)[0]} and its "
                    f"parents' shared/data; they sit beside the repository in CI, or set {DATA_DIR_ENV}")  # fmt: skip
    return fern


@dataclass
class FernCapture:
    """The first photos of the fern's ``images_16`` (252x189) with their LLFF poses."""

    folder: Path  # llff-fern/images_16
    names: List[str]  # photo file names, sorted
    c2w_opengl: "np.ndarray"  # [N, 4, 4] camera-to-world, OpenGL axes (nerfstudio's transforms.json)
    focal: float  # px at this size
    size: Tuple[int, int]  # (width, height)


def fern_capture(count: int) -> FernCapture:
    """The first ``count`` fern photos at 252x189 with their poses from ``poses_bounds.npy``."""
    import numpy as np
    from PIL import Image

    fern = shared_fern()
    poses = np.load(fern / "poses_bounds.npy")[:count, :15].reshape(-1, 3, 5)
    names = sorted(p.name for p in (fern / "images_16").iterdir())[:count]
    with Image.open(fern / "images_16" / names[0]) as image:
        w, h = image.size
    focal = float(poses[0, 2, 4]) * w / float(poses[0, 1, 4])
    llff = poses[:, :, :4]  # columns: down, right, back -> OpenGL right, up, back
    c2w = np.concatenate([llff[..., 1:2], -llff[..., 0:1], llff[..., 2:3], llff[..., 3:4]], axis=-1)
    bottom = np.broadcast_to(np.array([[0.0, 0.0, 0.0, 1.0]]), (len(names), 1, 4))
    return FernCapture(fern / "images_16", names, np.concatenate([c2w, bottom], axis=1), focal, (w, h))


def shaken_photo(path: Path, extent_px: float, drift_px: tuple = (-2.0, 3.0), samples: int = 25):
    """The photo at ``path`` [H, W, 3] uint8, blurred by a camera shake along a straight path: ``extent_px`` px wide
    in x (centred), from ``drift_px[0]`` to ``drift_px[1]`` px in y, sampled ``samples`` times."""
    import numpy as np
    import torch

    from gsmsdr_ns.degrade.kernels import convolve_psf, motion_kernel_from_trajectory
    from gsmsdr_ns.io.images import read_image

    image = torch.from_numpy(read_image(path)[..., :3].astype(np.float32) / 255.0).permute(2, 0, 1)[None]
    shake = np.stack([np.linspace(-extent_px / 2, extent_px / 2, samples), np.linspace(*drift_px, samples)], axis=1)
    image = convolve_psf(image, motion_kernel_from_trajectory(shake).float())
    return (image[0].permute(1, 2, 0).clamp(0, 1).numpy() * 255).round().astype(np.uint8)
