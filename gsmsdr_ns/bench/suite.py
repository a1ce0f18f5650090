"""`gsmsdr-bench suite`: benchmark suites from ``configs/bench/*.yaml`` (scenes x methods x step budgets x seeds).

Every run trains through nerfstudio's own machinery in this process (``Trainer``, ``pipeline.setup``, the
optimizers, ``Trainer.train_iteration`` and the training callbacks: :class:`gsmsdr_ns.bench.accuracy.InProcessRun`)
with the suite's step budget applied to every method's schedules identically (:func:`shorten_schedules`). Every
``eval_every`` steps (and at step 0 and the last step) it renders the held-out sharp test views and records PSNR,
SSIM (scikit-image) and LPIPS (when torchvision's AlexNet weights are cached; nothing is downloaded), the training
wall time so far and its split into rasterization / blur field / kernel application / densification / data / other
(:class:`gsmsdr_ns.bench.timing.TimingRecorder`). Evaluation time is not training time.

Outputs, in the output folder:

* ``runs/<scene>__<method>__<steps>__s<seed>.json``: one record per finished run, written atomically (temporary
  file + rename) when the run ends; ``runs/<same>.log``: what the run printed. A rerun of the suite skips every run
  whose record exists and matches the run's settings (``fingerprint``), so an interrupted suite resumes where it
  stopped (the run that was interrupted starts over);
* ``results.csv`` (one row per run), ``results.md`` (tables shaped like the paper's Tables 3-7 plus time and memory
  columns), ``psnr_vs_time_<scene>.png`` and ``time_breakdown.png``: regenerated from all records after every run;
* ``scenes/``: the generated scenes (made once, reused).
"""

from __future__ import annotations

import contextlib
import csv
import copy
import dataclasses
import datetime
import hashlib
import io
import json
import math
import os
import platform
import re
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

from gsmsdr_ns.bench.timing import CATEGORIES

RECORD_VERSION = 1
"""Bumped when a record's meaning changes: older records are then rerun instead of reused."""

# -- methods -----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MethodSpec:
    """How one suite method differs from the presets (``gsmsdr_ns.plugin.method_config``)."""

    name: str
    label: str
    """Row label in the tables."""
    base: str
    """``method_config`` name: plain / sharp (gsmsdr preset with degradation sharp), gsmsdr, gsmsdr-lite."""
    blur_field: Tuple[Tuple[str, Any], ...] = ()
    """``BlurFieldConfig`` fields replaced on the preset's blur field."""
    sharp_data: bool = False
    """Train on the sharp twin of the scene (the upper bound) instead of its degraded images."""
    description: str = ""

    def make_config(self, data: Path, output_dir: Path):
        """The TrainerConfig of this method on ``data`` (schedules not yet shortened)."""
        from gsmsdr_ns.bench.accuracy import method_config

        config = method_config(self.base, data, output_dir)
        if self.blur_field:
            model = config.pipeline.model
            model.blur_field = dataclasses.replace(model.blur_field, **dict(self.blur_field))
        return config

    @property
    def has_blur_field(self) -> bool:
        return self.base in ("gsmsdr", "gsmsdr-lite")

    def modules(self) -> Optional[Dict[str, bool]]:
        """Table 6's check marks (GAKA, SAFM, MCA, RGBD, HPKO) of the gsmsdr-preset blur field, None otherwise."""
        if self.base in ("plain",):
            return dict(GAKA=False, SAFM=False, MCA=False, RGBD=False, HPKO=False)
        if self.base != "gsmsdr":
            return None
        from gsmsdr_ns.blur.field import BlurFieldConfig

        mods = BlurFieldConfig(**dict(self.blur_field)).modules
        return dict(GAKA=mods.gaka, SAFM=mods.safm, MCA=mods.mca, RGBD=mods.rgbd, HPKO=mods.hpko)


def _method(name: str, label: str, base: str, description: str, sharp_data: bool = False, **blur) -> MethodSpec:
    return MethodSpec(name, label, base, tuple(sorted(blur.items())), sharp_data, description)


METHODS: Dict[str, MethodSpec] = {
    m.name: m
    for m in (
        _method("plain", "plain (3DGS)", "plain", "plain Gaussians (degradation sharp) on the degraded images"),
        _method("msd-only", "MSD-only", "gsmsdr", "HPKO heads on BAGS' plain CNN (no GAKA/SAFM/MCA)", mode="msd_only"),
        _method("re-only", "RE-only", "gsmsdr", "MAAN features, one full-resolution kernel scale (no HPKO)",
                mode="re_only"),  # fmt: skip
        _method("full", "GS-MSDR (full)", "gsmsdr", "the gsmsdr preset: MAAN + HPKO, with per-view kernels"),
        _method("-view", "-view kernels", "gsmsdr", "full without per-view kernels (the paper's blur field)",
                view_kernels=False),  # fmt: skip
        _method("view", "per-view kernels (mode view)", "gsmsdr",
                "one kernel per training view (mask 1), no feature network (fast)", mode="view"),  # fmt: skip
        _method("-gaka", "-GAKA", "gsmsdr", "full without Global-Aware Kernel Attention", gaka=False),
        _method("-safm", "-SAFM", "gsmsdr", "full without the Spatial Adaptive Fusion Module", safm=False),
        _method("-mca", "-MCA", "gsmsdr", "full without the Multi-modal Context Adapter", mca=False),
        _method("-rgbd", "-RGBD", "gsmsdr", "full with an RGB-only feature network (no depth input)", rgbd=False),
        _method("gsmsdr-lite", "gsmsdr-lite", "gsmsdr-lite", "the gsmsdr-lite preset (half-width blur field)"),
        _method("sharp", "sharp (upper bound)", "sharp", "plain Gaussians on the sharp images of the same scene",
                sharp_data=True),  # fmt: skip
    )
}
"""Suite method names -> what they train. Order = row order of the tables."""

TABLE7_METHODS = (("plain", "Baseline (plain)"), ("msd-only", "MSD-only"), ("re-only", "RE-only"),
                  ("full", "GS-MSDR (full)"))  # fmt: skip
"""Table 7 rows: baseline, multi-scale deblurring only, resolution enhancement only, both."""
TABLE6_METHODS = ("plain", "msd-only", "-gaka", "-safm", "-mca", "-rgbd", "re-only", "full")
"""Table 6 rows (module check marks); ``re-only`` is the paper's -HPKO row."""


# -- suite definition --------------------------------------------------------------------------------------------


class SuiteConfigError(ValueError):
    """A suite YAML file is invalid; the message names the file and the key."""


@dataclass(frozen=True)
class SceneEntry:
    """One scene of a suite: generated (``spec``) or the user's own (``path``, optional ``sharp_path``)."""

    name: str
    spec: Optional[Any] = None  # gsmsdr_ns.bench.accuracy.SceneSpec
    path: Optional[Path] = None
    sharp_path: Optional[Path] = None

    @property
    def generated(self) -> bool:
        return self.spec is not None

    def supports(self, method: MethodSpec) -> bool:
        """False for the sharp upper bound on a user scene without ``sharp_path``."""
        return not method.sharp_data or self.generated or self.sharp_path is not None

    def data(self, method: MethodSpec, scene_root: Path, log: Optional[Callable[[str], None]] = None) -> Path:
        """The scene folder ``method`` trains on (generated on first use, under ``scene_root/scenes``)."""
        if self.spec is not None:
            from gsmsdr_ns.bench.accuracy import ensure_scene

            spec = self.spec.with_variant("sharp") if method.sharp_data else self.spec
            return ensure_scene(scene_root, spec, log)
        path = self.sharp_path if method.sharp_data else self.path
        assert path is not None
        return path

    def describe(self) -> str:
        if self.spec is not None:
            s = self.spec
            return (f"generated `{s.variant}`, {s.width}x{s.height}, {s.num_views} views (every {s.hold}th a sharp "
                    f"test view), {s.num_points} points, scene seed {s.seed}")  # fmt: skip
        sharp = f", sharp twin `{self.sharp_path}`" if self.sharp_path is not None else ""
        return f"user scene `{self.path}`{sharp}"

    def fingerprint(self) -> Dict[str, Any]:
        if self.spec is not None:
            return {"generated": dataclasses.asdict(self.spec)}
        return {"path": str(self.path), "sharp_path": None if self.sharp_path is None else str(self.sharp_path)}


@dataclass
class Suite:
    """A benchmark suite (see ``configs/bench/quick.yaml`` for the keys)."""

    name: str
    scenes: List[SceneEntry]
    methods: List[str]
    steps: List[int]
    seeds: List[int] = field(default_factory=lambda: [0])
    eval_every: int = 0
    """Evaluate the test views every this many steps (and at step 0 and the end); 0: at the end only."""
    schedule: Dict[str, Any] = field(default_factory=dict)
    """``gsmsdr_ns.bench.accuracy.Schedule`` fields other than ``steps``."""
    threads: int = 1
    """torch intra-op threads (0: torch's default)."""
    lpips: bool = True
    """Compute LPIPS when torchvision's AlexNet weights are in the torch hub cache."""
    description: str = ""
    scene_root: Optional[Path] = None
    """Generated scenes go to ``<scene_root>/scenes/<name>`` (None: the output folder)."""
    source: Optional[Path] = None

    def runs(self) -> List["RunKey"]:
        return [RunKey(scene.name, method, steps, seed)
                for steps in self.steps for scene in self.scenes for method in self.methods
                for seed in self.seeds]  # fmt: skip

    def scene(self, name: str) -> SceneEntry:
        return next(s for s in self.scenes if s.name == name)

    def schedule_for(self, steps: int):
        from gsmsdr_ns.bench.accuracy import Schedule

        return Schedule(steps, **self.schedule)

    def eval_steps(self, steps: int) -> List[int]:
        points = {0, steps}
        if self.eval_every > 0:
            points.update(range(self.eval_every, steps, self.eval_every))
        return sorted(points)


@dataclass(frozen=True)
class RunKey:
    scene: str
    method: str
    steps: int
    seed: int

    @property
    def id(self) -> str:
        return f"{self.scene}__{self.method}__{self.steps}__s{self.seed}"


_SUITE_KEYS = {"name", "description", "scenes", "scene_defaults", "methods", "steps", "seeds", "eval_every",
               "schedule", "threads", "lpips", "scene_root"}  # fmt: skip
_SCENE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")


def _fail(source: Path, key: str, message: str) -> SuiteConfigError:
    return SuiteConfigError(f"{source}: {key}: {message}")


def _int_list(values: Any, source: Path, key: str, minimum: int) -> List[int]:
    items = values if isinstance(values, list) else [values]
    if not items:
        raise _fail(source, key, "must not be empty")
    out = []
    for i, v in enumerate(items):
        if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
            raise _fail(source, f"{key}[{i}]" if isinstance(values, list) else key,
                        f"must be an integer >= {minimum}, got {v!r}")  # fmt: skip
        out.append(v)
    if len(set(out)) != len(out):
        raise _fail(source, key, f"has duplicates: {out}")
    return out


def _scene_fields() -> Dict[str, type]:
    from gsmsdr_ns.bench.accuracy import SceneSpec

    return {f.name: int for f in dataclasses.fields(SceneSpec) if f.name != "variant"}


def _check_scene_values(values: Mapping[str, Any], source: Path, key: str) -> Dict[str, int]:
    fields_ = _scene_fields()
    out = {}
    for name, value in values.items():
        if name not in fields_:
            raise _fail(source, f"{key}.{name}", f"unknown key; valid: {', '.join(sorted(fields_))}")
        minimum = 0 if name == "seed" else 1
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise _fail(source, f"{key}.{name}", f"must be an integer >= {minimum}, got {value!r}")
        out[name] = value
    return out


def _parse_scene(item: Any, index: int, defaults: Dict[str, int], source: Path) -> SceneEntry:
    from gsmsdr_ns.bench.accuracy import SceneSpec
    from gsmsdr_ns.degrade.variants import VARIANTS

    key = f"scenes[{index}]"
    if isinstance(item, str):
        item = {"variant": item}
    if not isinstance(item, dict):
        raise _fail(source, key, f"must be a variant name or a mapping, got {type(item).__name__}")
    if ("variant" in item) == ("path" in item):
        raise _fail(source, key, "needs exactly one of 'variant' (a generated scene) or 'path' (a scene folder)")
    name = item.get("name")
    if "variant" in item:
        variant = item["variant"]
        if variant not in VARIANTS:
            raise _fail(source, f"{key}.variant", f"unknown variant {variant!r}; valid: {', '.join(VARIANTS)}")
        extra = {k: v for k, v in item.items() if k not in ("variant", "name")}
        values = {**defaults, **_check_scene_values(extra, source, key)}
        spec = SceneSpec(variant=variant, **values)
        if spec.hold < 2 or spec.hold > spec.num_views:
            raise _fail(source, f"{key}.hold", f"must be in [2, num_views={spec.num_views}], got {spec.hold}")
        entry = SceneEntry(name=name or variant, spec=spec)
    else:
        unknown = sorted(set(item) - {"path", "name", "sharp_path"})
        if unknown:
            raise _fail(source, f"{key}.{unknown[0]}", "unknown key for a user scene; valid: path, name, sharp_path")
        base = source.parent

        def resolve(k: str) -> Optional[Path]:
            if item.get(k) is None:
                return None
            p = Path(os.path.expanduser(str(item[k])))
            p = p if p.is_absolute() or p.exists() else (base / p)
            if not p.is_dir():
                raise _fail(source, f"{key}.{k}", f"scene folder {p} does not exist")
            return p

        path, sharp = resolve("path"), resolve("sharp_path")
        assert path is not None
        entry = SceneEntry(name=name or path.name, path=path, sharp_path=sharp)
    if not isinstance(entry.name, str) or not _SCENE_NAME.match(entry.name) or "__" in entry.name:
        raise _fail(source, f"{key}.name", f"{entry.name!r} is not a usable scene name (letters, digits, . _ + -)")
    return entry


def load_suite(path: str | Path) -> Suite:
    """Read and validate a suite YAML file; errors are :class:`SuiteConfigError` naming the file and the key."""
    import yaml

    source = Path(path)
    if not source.is_file():
        raise SuiteConfigError(f"{source}: suite file not found")
    try:
        values = yaml.safe_load(source.read_text(encoding="utf8"))
    except yaml.YAMLError as e:
        raise SuiteConfigError(f"{source}: not valid YAML: {e}") from e
    if not isinstance(values, dict):
        raise SuiteConfigError(f"{source}: must be a YAML mapping, got {type(values).__name__}")
    unknown = sorted(set(values) - _SUITE_KEYS)
    if unknown:
        raise _fail(source, unknown[0], f"unknown key; valid keys: {', '.join(sorted(_SUITE_KEYS))}")
    for required in ("scenes", "methods", "steps"):
        if required not in values:
            raise _fail(source, required, "missing (required)")

    name = values.get("name", source.stem)
    if not isinstance(name, str) or not _SCENE_NAME.match(name):
        raise _fail(source, "name", f"must be a simple name (letters, digits, . _ + -), got {name!r}")
    defaults_in = values.get("scene_defaults") or {}
    if not isinstance(defaults_in, dict):
        raise _fail(source, "scene_defaults", "must be a mapping")
    defaults = _check_scene_values(defaults_in, source, "scene_defaults")

    scenes_in = values["scenes"]
    if not isinstance(scenes_in, list) or not scenes_in:
        raise _fail(source, "scenes", "must be a non-empty list")
    scenes = [_parse_scene(item, i, defaults, source) for i, item in enumerate(scenes_in)]
    names = [s.name for s in scenes]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise _fail(source, "scenes", f"duplicate scene names {duplicates}; give them distinct 'name's")

    methods_in = values["methods"]
    if not isinstance(methods_in, list) or not methods_in:
        raise _fail(source, "methods", "must be a non-empty list")
    for i, m in enumerate(methods_in):
        if m not in METHODS:
            raise _fail(source, f"methods[{i}]", f"unknown method {m!r}; valid: {', '.join(METHODS)}")
    if len(set(methods_in)) != len(methods_in):
        raise _fail(source, "methods", "has duplicates")
    methods = [m for m in METHODS if m in methods_in]  # table order

    steps = _int_list(values["steps"], source, "steps", 1)
    seeds = _int_list(values.get("seeds", [0]), source, "seeds", 0)
    eval_every = values.get("eval_every", 0)
    if isinstance(eval_every, bool) or not isinstance(eval_every, int) or eval_every < 0:
        raise _fail(source, "eval_every", f"must be an integer >= 0, got {eval_every!r}")
    threads = values.get("threads", 1)
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 0:
        raise _fail(source, "threads", f"must be an integer >= 0, got {threads!r}")
    lpips = values.get("lpips", True)
    if not isinstance(lpips, bool):
        raise _fail(source, "lpips", f"must be true or false, got {lpips!r}")

    from gsmsdr_ns.bench.accuracy import Schedule

    schedule = values.get("schedule") or {}
    if not isinstance(schedule, dict):
        raise _fail(source, "schedule", "must be a mapping")
    schedule_fields = {f.name: f for f in dataclasses.fields(Schedule) if f.name != "steps"}
    for k, v in schedule.items():
        if k not in schedule_fields:
            raise _fail(source, f"schedule.{k}", f"unknown key; valid: {', '.join(schedule_fields)}")
        expected = type(getattr(Schedule(1), k))
        if isinstance(v, bool) or not isinstance(v, (int, float)) or (expected is int and not isinstance(v, int)):
            raise _fail(source, f"schedule.{k}", f"must be a number ({expected.__name__}), got {v!r}")
    try:
        Schedule(1, **schedule)
    except (TypeError, ValueError) as e:
        raise _fail(source, "schedule", str(e)) from e

    scene_root = values.get("scene_root")
    if scene_root is not None and not isinstance(scene_root, str):
        raise _fail(source, "scene_root", f"must be a folder path, got {scene_root!r}")
    return Suite(
        name=name,
        scenes=scenes,
        methods=methods,
        steps=steps,
        seeds=seeds,
        eval_every=eval_every,
        schedule=dict(schedule),
        threads=threads,
        lpips=lpips,
        description=str(values.get("description", "")).strip(),
        scene_root=None if scene_root is None else Path(os.path.expanduser(scene_root)),
        source=source,
    )


def find_suite_file(name_or_path: str | Path) -> Path:
    """A suite file path, or a suite name looked up in ``configs/bench/`` (the checkout's, then the cwd's)."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml") or path.exists():
        return path
    for root in (Path(__file__).resolve().parents[2], Path.cwd()):
        candidate = root / "configs" / "bench" / f"{name_or_path}.yaml"
        if candidate.is_file():
            return candidate
    raise SuiteConfigError(f"no suite file {name_or_path!r} (looked for configs/bench/{name_or_path}.yaml)")


# -- machine -----------------------------------------------------------------------------------------------------


def machine_info() -> Dict[str, Any]:
    """CPU model and cores, torch version and threads, device, for the results header and every record."""
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf8") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    device = "cuda" if torch.cuda.is_available() else "cpu"
    info = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "device": device,
        "gpu": torch.cuda.get_device_name(0) if device == "cuda" else None,
        "python": platform.python_version(),
        "platform": platform.platform(terse=True),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
    }
    try:
        root = Path(__file__).resolve().parents[2]
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True, timeout=10).stdout.strip()  # fmt: skip
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10).stdout.strip()  # fmt: skip
        info["git"] = (commit + ("+dirty" if dirty else "")) if commit else None
    except (OSError, subprocess.SubprocessError):
        info["git"] = None
    return info


def describe_machine(info: Mapping[str, Any]) -> str:
    gpu = f" ({info['gpu']})" if info.get("gpu") else ""
    return (f"{info['cpu']}, {info['cores']} cores; torch {info['torch']} ({info['torch_threads']} thread(s)), "
            f"device {info['device']}{gpu}")  # fmt: skip


# -- evaluation --------------------------------------------------------------------------------------------------


def make_lpips(device) -> Optional[Any]:
    """torchmetrics' LPIPS (AlexNet) when its backbone weights are in the torch hub cache, else None."""
    from gsmsdr_ns.plugin.model import lpips_backbone_cache_path

    if not lpips_backbone_cache_path().is_file():
        return None
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    return LearnedPerceptualImagePatchSimilarity(normalize=True).to(device)


def evaluate_test_views(run, lpips=None) -> Dict[str, float]:
    """Mean PSNR / SSIM / LPIPS of the sharp renders of the held-out test views against their sharp ground truth.

    The views and ground truth are the pipeline's eval split (``fixed_indices_eval_dataloader``, what ns-eval
    uses). PSNR = -10 log10(MSE) on [0, 1] images; SSIM is scikit-image's ``structural_similarity`` with the
    Gaussian window of the SSIM paper (sigma 1.5, ``use_sample_covariance=False``), averaged over RGB; LPIPS is
    torchmetrics' AlexNet LPIPS (NaN when ``lpips`` is None). Renders without gradients and with the random state
    restored, in eval mode, then back to train mode: training continues exactly as without the evaluation.
    """
    import numpy as np
    import torch
    from skimage.metrics import structural_similarity

    pipeline, model = run.pipeline, run.model
    devices = [torch.cuda.current_device()] if torch.cuda.is_available() else []
    psnrs, ssims, lpipss = [], [], []
    pipeline.eval()
    try:
        with torch.random.fork_rng(devices=devices), torch.no_grad():
            for camera, batch in pipeline.datamanager.fixed_indices_eval_dataloader:
                outputs = model.get_outputs_for_camera(camera)
                gt = model.composite_with_background(model.get_gt_img(batch["image"]), outputs["background"])
                gt = gt[..., :3].clamp(0.0, 1.0)
                pred = outputs["rgb"][..., :3].clamp(0.0, 1.0)
                mse = torch.mean((pred.double() - gt.double()) ** 2).clamp_min(1e-12)
                psnrs.append(float(-10.0 * torch.log10(mse)))
                g, p = gt.double().cpu().numpy(), pred.double().cpu().numpy()
                ssims.append(float(structural_similarity(
                    g, p, data_range=1.0, channel_axis=2, gaussian_weights=True, sigma=1.5,
                    use_sample_covariance=False)))  # fmt: skip
                if lpips is not None:
                    to_nchw = lambda x: x.permute(2, 0, 1)[None].float().to(model.device)  # noqa: E731
                    lpipss.append(float(lpips(to_nchw(pred), to_nchw(gt))))
    finally:
        pipeline.train()
    if not psnrs:
        raise RuntimeError("the scene has no test views to evaluate")
    return {
        "psnr": float(np.mean(psnrs)),
        "ssim": float(np.mean(ssims)),
        "lpips": float(np.mean(lpipss)) if lpipss else float("nan"),
        "num_views": len(psnrs),
    }


# -- one run -----------------------------------------------------------------------------------------------------


def preset_fingerprint(method: MethodSpec) -> str:
    """The resolved model and optimizer settings of ``method`` (its preset with its changes applied), so a record
    made before a preset default changed is rerun. Paths are left out, and so are the blur field's settings for
    methods that never build it (plain, sharp)."""
    config = method.make_config(Path("data"), Path("outputs"))
    model, optimizers = config.pipeline.model, dict(config.optimizers)
    if not method.has_blur_field:
        model = copy.copy(model)
        model.blur_field = None
        optimizers = {k: v for k, v in optimizers.items() if not k.startswith("blur_")}
    return repr(model) + repr(sorted(optimizers.items()))


def fingerprint(suite: Suite, key: RunKey) -> str:
    """What a record's numbers depend on; a record whose fingerprint differs is rerun."""
    method = METHODS[key.method]
    payload = {
        "version": RECORD_VERSION,
        "scene": suite.scene(key.scene).fingerprint(),
        "method": {"base": method.base, "blur_field": method.blur_field, "sharp_data": method.sharp_data},
        "preset": preset_fingerprint(method),
        "steps": key.steps,
        "seed": key.seed,
        "schedule": dataclasses.asdict(suite.schedule_for(key.steps)),
        "eval_steps": suite.eval_steps(key.steps),
        "lpips": suite.lpips,
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _finite_or_none(value: Any) -> Any:
    """NaN / infinity -> None (null): records are standard JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_none(v) for v in value]
    return value


def write_json_atomic(path: Path, payload: Any) -> None:
    """Write ``payload`` as JSON to a temporary file in the same folder, then rename it into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w", encoding="utf8") as f:
        json.dump(_finite_or_none(payload), f, indent=1, default=_json_default, allow_nan=False)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def write_text_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text, encoding="utf8")
    os.replace(tmp, path)


def _json_default(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "item"):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def train_and_record(
    suite: Suite,
    key: RunKey,
    scene_root: Path,
    work_dir: Path,
    lpips=None,
    on_step: Optional[Callable[[int], None]] = None,
    on_eval: Optional[Callable[[Dict[str, Any]], None]] = None,
    log: Optional[Callable[[str], None]] = None,
) -> Dict[str, Any]:
    """Train one run of ``suite`` and return its record (not written). ``on_step(n)`` after every n steps."""
    import torch

    from gsmsdr_ns.bench.accuracy import InProcessRun, shorten_schedules
    from gsmsdr_ns.bench.timing import PeakMemory, TimingRecorder

    method = METHODS[key.method]
    scene = suite.scene(key.scene)
    data = scene.data(method, scene_root, log)
    config = method.make_config(data, work_dir)
    config.experiment_name = key.id
    shorten_schedules(config, suite.schedule_for(key.steps))

    memory = PeakMemory()
    memory.reset()
    started = time.perf_counter()
    run = InProcessRun(config, seed=key.seed)
    setup_seconds = time.perf_counter() - started
    device = str(run.trainer.device)
    recorder = TimingRecorder(sync_cuda=device.startswith("cuda")).attach(run.pipeline)
    curve: List[Dict[str, Any]] = []
    eval_seconds = 0.0
    try:
        eval_steps = suite.eval_steps(key.steps)
        for target in eval_steps:
            while run.step < target:
                with recorder.measure():
                    run.train(1)
                if on_step is not None:
                    on_step(1)
            t0 = time.perf_counter()
            metrics = evaluate_test_views(run, lpips)
            eval_seconds += time.perf_counter() - t0
            point = {"step": run.step, "seconds": recorder.wall, **metrics,
                     "num_gaussians": int(run.model.num_points), "breakdown": recorder.totals()}  # fmt: skip
            curve.append(point)
            if on_eval is not None:
                on_eval(point)
        final = curve[-1]
        record = {
            "version": RECORD_VERSION,
            "id": key.id,
            "suite": suite.name,
            "scene": key.scene,
            "method": key.method,
            "steps": key.steps,
            "seed": key.seed,
            "fingerprint": fingerprint(suite, key),
            "data": str(data),
            "psnr": final["psnr"],
            "ssim": final["ssim"],
            "lpips": final["lpips"],
            "train_seconds": recorder.wall,
            "step_ms": 1000.0 * recorder.wall / max(key.steps, 1),
            "setup_seconds": setup_seconds,
            "eval_seconds": eval_seconds,
            "num_gaussians": final["num_gaussians"],
            "num_test_views": final["num_views"],
            "peak_rss_mb": memory.peak_rss_mb(),
            "peak_rss_span": memory.span_reset,
            "peak_cuda_mb": memory.peak_cuda_mb(),
            "breakdown": recorder.totals(),
            "breakdown_split": recorder.split(),
            "blur_field_modules": _active_modules(run.model),
            "curve": curve,
            "machine": machine_info(),
            "finished": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        }
    finally:
        recorder.detach()
        run.close()
        if torch.cuda.is_available():
            torch.cuda.empty_cache()
    return record


def _active_modules(model) -> str:
    """What the model built (e.g. "blur field (full, RGB-D, kernels (5, 9, 17))"), from its own description."""
    describe = getattr(model, "_describe_modules", None)
    try:
        return str(describe()) if describe is not None else ""
    except Exception:  # noqa: BLE001 - informative only
        return ""


# -- the suite ---------------------------------------------------------------------------------------------------


def record_path(out: Path, key: RunKey) -> Path:
    return Path(out) / "runs" / f"{key.id}.json"


def load_record(path: Path) -> Optional[Dict[str, Any]]:
    try:
        with open(path, encoding="utf8") as f:
            record = json.load(f)
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and "id" in record else None


def finished_record(suite: Suite, out: Path, key: RunKey) -> Optional[Dict[str, Any]]:
    """The run's record if it exists and matches the run's current settings."""
    record = load_record(record_path(out, key))
    if record is None or record.get("fingerprint") != fingerprint(suite, key):
        return None
    return record


@dataclass
class SuiteOutcome:
    records: List[Dict[str, Any]]
    trained: List[str]
    reused: List[str]
    failed: Dict[str, str]
    skipped: Dict[str, str]
    outputs: List[Path]


def run_suite(
    suite: Suite,
    out: Path,
    command: str = "",
    progress: bool = True,
    plots: bool = True,
    console=None,
) -> SuiteOutcome:
    """Run every run of ``suite`` that has no matching record in ``out/runs``; rewrite the outputs after each."""
    import torch
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.progress import TimeRemainingColumn

    out = Path(out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    scene_root = suite.scene_root if suite.scene_root is not None else out
    if suite.threads > 0:
        torch.set_num_threads(suite.threads)
    console = console or Console(file=sys.stdout)
    machine = machine_info()

    keys = suite.runs()
    skipped: Dict[str, str] = {}
    todo: List[RunKey] = []
    reused: List[str] = []
    for key in keys:
        scene, method = suite.scene(key.scene), METHODS[key.method]
        if not scene.supports(method):
            skipped[key.id] = f"scene {scene.name} has no sharp_path for the sharp upper bound"
        elif finished_record(suite, out, key) is not None:
            reused.append(key.id)
        else:
            todo.append(key)
    lpips = None
    if suite.lpips and todo:
        lpips = make_lpips("cuda" if torch.cuda.is_available() else "cpu")
    if suite.lpips and lpips is None and todo:
        console.print("[yellow]LPIPS: torchvision's AlexNet weights are not in the torch hub cache; LPIPS is left out "
                      "(nothing is downloaded)[/yellow]")  # fmt: skip

    console.print(f"suite [bold]{suite.name}[/bold]: {len(keys)} runs ({len(reused)} already finished, "
                  f"{len(todo)} to train, {len(skipped)} skipped) -> {out}")  # fmt: skip
    trained: List[str] = []
    failed: Dict[str, str] = {}
    outputs: List[Path] = []

    def refresh() -> None:
        nonlocal outputs
        outputs = write_outputs(suite, out, command, machine, skipped, failed, plots=plots)

    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TextColumn("eta"), TimeRemainingColumn(), TextColumn("{task.fields[info]}"))  # fmt: skip
    current = ""
    try:
        with Progress(*columns, console=console, disable=not progress, redirect_stdout=False,
                      redirect_stderr=False) as bars:  # fmt: skip
            suite_task = bars.add_task(f"{suite.name}", total=len(keys), completed=len(keys) - len(todo), info="")
            for key in todo:
                current = key.id
                run_task = bars.add_task(f"  {key.scene} {key.method} s{key.seed}", total=key.steps, info="")

                def on_eval(point: Dict[str, Any], task=run_task) -> None:
                    bars.update(task, info=f"PSNR {point['psnr']:.2f} @ {point['step']}")

                log_path = out / "runs" / f"{key.id}.log"
                started = time.perf_counter()
                try:
                    with open(log_path, "w", encoding="utf8") as log_file, contextlib.redirect_stdout(log_file), \
                            contextlib.redirect_stderr(log_file):  # fmt: skip
                        record = train_and_record(
                            suite, key, scene_root, out / "runs" / "nerfstudio", lpips,
                            on_step=lambda n, task=run_task: bars.advance(task, n), on_eval=on_eval,
                            log=lambda message: print(message, flush=True),
                        )  # fmt: skip
                    write_json_atomic(record_path(out, key), record)
                    trained.append(key.id)
                    console.print(f"{key.id}: PSNR {record['psnr']:.2f}  SSIM {record['ssim']:.4f}  train "
                                  f"{record['train_seconds']:.0f} s ({record['step_ms']:.0f} ms/step)")  # fmt: skip
                except Exception as e:  # noqa: BLE001 - one failed run does not stop the suite
                    with open(log_path, "a", encoding="utf8") as log_file:
                        log_file.write(traceback.format_exc())
                    failed[key.id] = f"{type(e).__name__}: {e}"
                    console.print(f"[red]{key.id} failed after {time.perf_counter() - started:.0f} s: "
                                  f"{type(e).__name__}: {e} (log: {log_path})[/red]")  # fmt: skip
                finally:
                    bars.remove_task(run_task)
                current = f"writing the outputs after {key.id}"
                bars.advance(suite_task, 1)
                refresh()
    except KeyboardInterrupt:
        console.print(f"[red]interrupted ({current or 'before the first run'}); {len(trained) + len(reused)} "
                      "finished runs are kept in runs/: run the same command again to resume[/red]")  # fmt: skip
        raise
    refresh()
    records = collect_records(suite, out)
    return SuiteOutcome(records, trained, reused, failed, skipped, outputs)


# -- results -----------------------------------------------------------------------------------------------------


def collect_records(suite: Suite, out: Path) -> List[Dict[str, Any]]:
    """The suite's finished records in ``out/runs`` (current settings only), in the suite's run order."""
    records = []
    for key in suite.runs():
        record = finished_record(suite, out, key)
        if record is not None:
            records.append(record)
    return records


CSV_FIELDS = ("suite", "scene", "method", "steps", "seed", "psnr", "ssim", "lpips", "train_seconds", "step_ms",
              *(f"t_{c}" for c in CATEGORIES), "peak_rss_mb", "peak_cuda_mb", "num_gaussians", "eval_seconds",
              "setup_seconds", "device", "torch_threads")  # fmt: skip


def _num(value: Any, digits: int) -> str:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return ""
    return "" if not math.isfinite(v) else f"{v:.{digits}f}"


def write_csv(records: Sequence[Mapping[str, Any]], path: Path) -> None:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(CSV_FIELDS)
    for r in records:
        b = r.get("breakdown", {})
        m = r.get("machine", {})
        writer.writerow([r["suite"], r["scene"], r["method"], r["steps"], r["seed"], _num(r["psnr"], 4),
                         _num(r["ssim"], 5), _num(r["lpips"], 5), _num(r["train_seconds"], 2), _num(r["step_ms"], 2),
                         *(_num(b.get(c, float("nan")), 3) for c in CATEGORIES), _num(r["peak_rss_mb"], 1),
                         _num(r["peak_cuda_mb"], 1), r["num_gaussians"], _num(r["eval_seconds"], 2),
                         _num(r["setup_seconds"], 2), m.get("device", ""), m.get("torch_threads", "")])  # fmt: skip
    write_text_atomic(path, buffer.getvalue())


def _mean(values: Sequence[float]) -> float:
    finite = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return sum(finite) / len(finite) if finite else float("nan")


def aggregate(records: Sequence[Mapping[str, Any]]) -> Dict[Tuple[int, str, str], Dict[str, Any]]:
    """Seed means per (steps, scene, method): the metrics, times, memory, Gaussians and the breakdown."""
    groups: Dict[Tuple[int, str, str], List[Mapping[str, Any]]] = {}
    for r in records:
        groups.setdefault((r["steps"], r["scene"], r["method"]), []).append(r)
    out = {}
    for k, rs in groups.items():
        row: Dict[str, Any] = {"seeds": len(rs)}
        for name in ("psnr", "ssim", "lpips", "train_seconds", "step_ms", "peak_rss_mb", "peak_cuda_mb",
                     "num_gaussians", "eval_seconds"):  # fmt: skip
            row[name] = _mean([r.get(name, float("nan")) for r in rs])
        row["breakdown"] = {c: _mean([r.get("breakdown", {}).get(c, float("nan")) for r in rs]) for c in CATEGORIES}
        split = [r.get("breakdown_split") for r in rs if r.get("breakdown_split")]
        row["backward"] = {c: _mean([s["backward"].get(c, float("nan")) for s in split]) for c in CATEGORIES[:-1]}
        out[k] = row
    return out


def _f(value: Any, digits: int = 2) -> str:
    s = _num(value, digits)
    return s if s else "-"


def format_markdown(
    suite: Suite,
    records: Sequence[Mapping[str, Any]],
    command: str = "",
    machine: Optional[Mapping[str, Any]] = None,
    skipped: Optional[Mapping[str, str]] = None,
    failed: Optional[Mapping[str, str]] = None,
) -> str:
    """results.md: header, per-scene tables (Tables 3-5), Table 7, Table 6, time breakdown, gaps."""
    machine = machine or machine_info()
    agg = aggregate(records)
    expected = len(suite.runs()) - len(skipped or {})
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [f"# Benchmark suite `{suite.name}`", ""]
    lines.append(f"- date: {now}")
    lines.append(f"- machine: {describe_machine(machine)}; {machine.get('platform', '')}, Python "
                 f"{machine.get('python', '')}, git {machine.get('git') or '-'}")  # fmt: skip
    others = sorted({describe_machine(r["machine"]) for r in records if r.get("machine")} - {describe_machine(machine)})
    if others:
        lines.append(f"- some records were measured on: {'; '.join(others)}")
    if command:
        lines.append(f"- command: `{command}`")
    lines.append(f"- suite: `{_display_path(suite.source)}`" + (f": {suite.description}" if suite.description else ""))
    lines.append(f"- runs: {len(records)} of {expected} finished"
                 + (f", {len(failed)} failed" if failed else "")
                 + (f", {len(skipped)} skipped" if skipped else ""))  # fmt: skip
    for scene in suite.scenes:
        lines.append(f"- scene `{scene.name}`: {scene.describe()}")
    sched = ", ".join(f"{k} {v}" for k, v in dataclasses.asdict(suite.schedule_for(1)).items() if k != "steps")
    lines.append(f"- budgets: {', '.join(map(str, suite.steps))} steps; seeds {', '.join(map(str, suite.seeds))}"
                 f" (tables show seed means); every method gets the same shortened schedule ({sched})")  # fmt: skip
    lines.append("- metrics on the held-out sharp test views (sharp renders vs sharp ground truth): PSNR; SSIM from "
                 "scikit-image (Gaussian window, sigma 1.5); LPIPS (AlexNet) only when its weights are cached, "
                 "else `-`")  # fmt: skip
    lines.append("- train s: training wall time without evaluation and set-up; ms/step = train s / steps; peak mem: "
                 "peak resident memory of the process during the run (includes the Python/torch baseline)"
                 + ("; peak CUDA: torch.cuda.max_memory_allocated" if machine.get("device") == "cuda" else "")
                 )  # fmt: skip
    lines.append("")

    show_cuda = any(math.isfinite(row["peak_cuda_mb"]) for row in agg.values())
    multi_seed = len(suite.seeds) > 1
    for steps in suite.steps:
        suffix = f", {steps} steps"
        lines.append(f"## Per scene{suffix} (the paper's Tables 3-5)")
        lines.append("")
        for scene in suite.scenes:
            rows = [(m, agg.get((steps, scene.name, m))) for m in suite.methods]
            rows = [(m, r) for m, r in rows if r is not None]
            if not rows:
                continue
            lines.append(f"### {scene.name}")
            lines.append("")
            head = ["method", "PSNR", "SSIM", "LPIPS", "train s", "ms/step", "peak mem MB"]
            head += ["peak CUDA MB"] if show_cuda else []
            head += ["Gaussians"] + (["seeds"] if multi_seed else [])
            lines.append("| " + " | ".join(head) + " |")
            lines.append("| --- | " + " | ".join("---:" for _ in head[1:]) + " |")
            for m, r in rows:
                cells = [METHODS[m].label, _f(r["psnr"]), _f(r["ssim"], 4), _f(r["lpips"], 4),
                         _f(r["train_seconds"], 0), _f(r["step_ms"], 0), _f(r["peak_rss_mb"], 0)]  # fmt: skip
                cells += [_f(r["peak_cuda_mb"], 0)] if show_cuda else []
                cells += [_f(r["num_gaussians"], 0)] + ([str(r["seeds"])] if multi_seed else [])
                lines.append("| " + " | ".join(cells) + " |")
            lines.append("")

        scene_names = [s.name for s in suite.scenes]

        def scene_cells(method: str) -> List[str]:
            cells = []
            for name in scene_names:
                r = agg.get((steps, name, method))
                cells += [_f(r["psnr"]) if r else "-", _f(r["ssim"], 4) if r else "-"]
            return cells

        header_pairs = " | ".join(f"{n} PSNR | {n} SSIM" for n in scene_names)
        align = " | ".join("---: | ---:" for _ in scene_names)
        t7 = [(m, label) for m, label in TABLE7_METHODS if m in suite.methods]
        if sum(m != "plain" for m, _ in t7) >= 2:
            lines += [f"## Table 7{suffix}: multi-scale deblurring vs resolution enhancement", ""]
            lines.append(f"| configuration | {header_pairs} |")
            lines.append(f"| --- | {align} |")
            for m, label in t7:
                lines.append(f"| {label} | " + " | ".join(scene_cells(m)) + " |")
            lines.append("")
        t6 = [m for m in TABLE6_METHODS if m in suite.methods]
        if sum(m not in ("plain", "full", "msd-only") for m in t6) >= 1:
            lines += [f"## Table 6{suffix}: module ablation (✓ present, ✗ removed; RE-only = -HPKO)", ""]
            lines.append(f"| GAKA | SAFM | MCA | RGBD | HPKO | method | {header_pairs} |")
            lines.append(f"| :-: | :-: | :-: | :-: | :-: | --- | {align} |")
            for m in t6:
                mods = METHODS[m].modules() or {}
                marks = " | ".join("✓" if mods.get(k) else "✗" for k in ("GAKA", "SAFM", "MCA", "RGBD", "HPKO"))
                lines.append(f"| {marks} | {METHODS[m].label} | " + " | ".join(scene_cells(m)) + " |")
            lines.append("")

        lines += [f"## Time breakdown{suffix} (seconds of training, forward + backward)", ""]
        names = {"rasterization": "raster", "blur_field": "blur field", "kernels": "kernels", "densification":
                 "densify", "data": "data", "other": "other"}  # fmt: skip
        lines.append("| scene | method | " + " | ".join(names[c] for c in CATEGORIES)
                     + " | total | of which backward (raster / blur field / kernels) |")  # fmt: skip
        lines.append("| --- | --- | " + " | ".join("---:" for _ in CATEGORIES) + " | ---: | ---: |")
        for scene in suite.scenes:
            for m in suite.methods:
                r = agg.get((steps, scene.name, m))
                if r is None:
                    continue
                b, bw = r["breakdown"], r["backward"]
                back = " / ".join(_f(bw.get(c), 1) for c in ("rasterization", "blur_field", "kernels"))
                lines.append(f"| {scene.name} | {METHODS[m].label} | "
                             + " | ".join(_f(b[c], 1) for c in CATEGORIES)
                             + f" | {_f(r['train_seconds'], 1)} | {back} |")  # fmt: skip
        lines.append("")
        lines.append("raster: `_rasterize` (activation, projection, SH, tiles, pixel kernel); blur field: kernel and "
                     "mask prediction (MAAN, MCA, HPKO heads, thin lens); kernels: kernel application "
                     "(`BlurField.blur`) and the resolution-loss model; densify: the strategy's pre/post-backward "
                     "hooks; data: `next_train`; other: the rest of the step (mask blend, losses and their backward, "
                     "composite, optimizer and scheduler steps, callbacks). Backward time is attributed by gradient-hook event times "
                     "at component boundaries (see `gsmsdr_ns/bench/timing.py`).")  # fmt: skip
        lines.append("")

        gap_rows = []
        for scene in suite.scenes:
            plain, sharp = agg.get((steps, scene.name, "plain")), agg.get((steps, scene.name, "sharp"))
            if plain and sharp:
                gap_rows.append(f"| {scene.name} | {METHODS['plain'].label} | 0.00 | 0.0000 | "
                                f"{_sign(sharp['psnr'] - plain['psnr'])} |")  # fmt: skip
            for m in suite.methods:
                if m in ("plain", "sharp"):
                    continue
                r = agg.get((steps, scene.name, m))
                if r is None or (plain is None and sharp is None):
                    continue
                d_plain = r["psnr"] - plain["psnr"] if plain else float("nan")
                d_sharp = sharp["psnr"] - r["psnr"] if sharp else float("nan")
                s_plain = r["ssim"] - plain["ssim"] if plain else float("nan")
                gap_rows.append(f"| {scene.name} | {METHODS[m].label} | {_sign(d_plain)} | {_sign(s_plain, 4)} "
                                f"| {_sign(d_sharp)} |")  # fmt: skip
        if gap_rows:
            lines += [f"## Gaps{suffix} (test PSNR in dB, SSIM)", ""]
            lines.append("| scene | method | PSNR: method - plain | SSIM: method - plain | PSNR: sharp - method |")
            lines.append("| --- | --- | ---: | ---: | ---: |")
            lines += gap_rows
            lines.append("")

    if failed:
        lines += ["## Failed runs", ""] + [f"- `{k}`: {v} (log: `runs/{k}.log`)" for k, v in failed.items()] + [""]
    if skipped:
        lines += ["## Skipped runs", ""] + [f"- `{k}`: {v}" for k, v in skipped.items()] + [""]
    return "\n".join(lines).rstrip() + "\n"


def _display_path(path: Optional[Path]) -> str:
    """``path`` relative to the working directory when it is inside it."""
    if path is None:
        return "-"
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def _sign(value: float, digits: int = 2) -> str:
    return "-" if not math.isfinite(value) else f"{value:+.{digits}f}"


def write_outputs(
    suite: Suite,
    out: Path,
    command: str = "",
    machine: Optional[Mapping[str, Any]] = None,
    skipped: Optional[Mapping[str, str]] = None,
    failed: Optional[Mapping[str, str]] = None,
    plots: bool = True,
) -> List[Path]:
    """Regenerate results.csv, results.md and the PNG plots from the suite's records in ``out/runs``."""
    out = Path(out)
    records = collect_records(suite, out)
    write_csv(records, out / "results.csv")
    write_text_atomic(out / "results.md", format_markdown(suite, records, command, machine, skipped, failed))
    written = [out / "results.csv", out / "results.md"]
    if plots and records:
        from gsmsdr_ns.bench.plots import plot_psnr_vs_time, plot_time_breakdown

        labels = {name: spec.label for name, spec in METHODS.items()}
        for scene in suite.scenes:
            scene_records = [r for r in records if r["scene"] == scene.name]
            if scene_records:
                references = [name for name, spec in METHODS.items() if spec.sharp_data]
                written.append(plot_psnr_vs_time(scene_records, out / f"psnr_vs_time_{scene.name}.png", scene.name,
                                                 labels, references))  # fmt: skip
        written.append(plot_time_breakdown(records, out / "time_breakdown.png", labels))
    return written


def main_tables(markdown: str) -> str:
    """The part of results.md to print at the end: from the first table section to the time breakdown."""
    start = markdown.find("## ")
    return markdown[start:] if start >= 0 else markdown


__all__ = [
    "METHODS",
    "MethodSpec",
    "RunKey",
    "SceneEntry",
    "Suite",
    "SuiteConfigError",
    "SuiteOutcome",
    "evaluate_test_views",
    "find_suite_file",
    "format_markdown",
    "load_suite",
    "run_suite",
    "train_and_record",
    "write_outputs",
]
