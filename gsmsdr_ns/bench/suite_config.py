"""Suite files (``configs/bench/*.yaml``) -> :class:`Suite`: validation with errors naming the file and the key."""

from __future__ import annotations

import dataclasses
import os
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional

from gsmsdr_ns.bench.methods import METHODS
from gsmsdr_ns.bench.real_scenes import parse_real_spec
from gsmsdr_ns.bench.scenes import SceneSpec
from gsmsdr_ns.bench.suite_scene import SceneEntry
from gsmsdr_ns.io.config import read_yaml_mapping
from gsmsdr_ns.io.errors import InputError
from gsmsdr_ns.plugin.schedule import TrainingSchedule


class SuiteConfigError(InputError):
    """A suite YAML file is invalid; the message names the file and the key."""


@dataclass(frozen=True)
class RunKey:
    """One run of a suite: a scene, a method, a step budget and a training seed."""

    scene: str
    method: str
    steps: int
    seed: int

    @property
    def id(self) -> str:
        return f"{self.scene}__{self.method}__{self.steps}__s{self.seed}"


@dataclass(frozen=True)
class RaySettings:
    """What each run of a suite asks a Ray cluster for (``gsmsdr-bench suite --ray``); no effect on the numbers."""

    num_cpus: Optional[float] = None
    """CPUs per run (None: the suite's ``threads``, or 1 when that is 0)."""
    num_gpus: Optional[float] = None
    """GPUs per run (None: 1 when the cluster has GPUs, else 0; a run given no GPU trains on the CPU)."""
    max_retries: int = 2
    """Times a run whose worker process or node died is started again (a run that raises is not retried)."""


@dataclass
class Suite:
    """A benchmark suite (see ``configs/bench/quick.yaml`` for the keys)."""

    name: str
    """Suite name (results header, default output folder)."""
    scenes: List[SceneEntry]
    """Scenes, in table order."""
    methods: List[str]
    """Method names of :data:`gsmsdr_ns.bench.methods.METHODS`, in the registry's (table) order."""
    steps: List[int]
    """Step budgets; every method trains every budget."""
    seeds: List[int] = field(default_factory=lambda: [0])
    """Training seeds (tables show seed means)."""
    eval_every: int = 0
    """Evaluate the test views every this many steps (and at step 0 and the end); 0: at the end only."""
    schedule: Dict[str, Any] = field(default_factory=dict)
    """:class:`TrainingSchedule` fields other than ``steps`` (the bench preset's defaults otherwise)."""
    threads: int = 1
    """torch intra-op threads (0: torch's default)."""
    lpips: bool = True
    """Compute LPIPS when torchvision's AlexNet weights are in the torch hub cache."""
    align_poses: bool = False
    """At the final evaluation, also report the metrics after test-pose alignment (real captures, whose test poses
    come from the degraded photos' structure-from-motion)."""
    final_renders: bool = False
    """Write each run's final test renders and their ground truth to ``<out>/renders/<run id>/`` (PNG)."""
    train_fit: bool = False
    """At the end of each run, also record how well it fits its own training images (``train_psnr``: the training
    render, degraded as the model simulates, against the degraded photo): a low fit is a degradation model that
    cannot explain the photos, a high fit with a low test PSNR one that explains them the wrong way."""
    description: str = ""
    """Free text for the results header."""
    ray: RaySettings = field(default_factory=RaySettings)
    """Resources and retries of each run under ``gsmsdr-bench suite --ray``."""
    scene_root: Optional[Path] = None
    """Generated scenes go to ``<scene_root>/scenes/<name>`` (None: the output folder)."""
    source: Optional[Path] = None
    """The suite file."""

    def runs(self) -> List[RunKey]:
        return [RunKey(scene.name, method, steps, seed)
                for steps in self.steps for scene in self.scenes for method in self.methods
                for seed in self.seeds]  # fmt: skip

    def scene(self, name: str) -> SceneEntry:
        return next(s for s in self.scenes if s.name == name)

    def schedule_for(self, steps: int) -> TrainingSchedule:
        """The training schedule every method of this suite gets at ``steps``."""
        return TrainingSchedule.bench(steps, **self.schedule)

    def eval_steps(self, steps: int) -> List[int]:
        points = {0, steps}
        if self.eval_every > 0:
            points.update(range(self.eval_every, steps, self.eval_every))
        return sorted(points)


SCHEDULE_KEYS_V1 = ("steps", "num_downscales", "resolution_fraction", "blur_warmup_fraction",
                    "densify_until_fraction", "refinements", "densify_grad_thresh")  # fmt: skip
"""The schedule settings the first suites recorded; the others are listed only when they differ from the bench
preset, so records of unchanged settings keep their fingerprint."""


def schedule_settings(schedule: TrainingSchedule) -> Dict[str, Any]:
    """The settings of ``schedule`` that define a bench run (fingerprints, results header)."""
    preset = dataclasses.asdict(TrainingSchedule.bench(schedule.steps))
    return {k: v for k, v in dataclasses.asdict(schedule).items() if k in SCHEDULE_KEYS_V1 or v != preset[k]}


_SUITE_KEYS = {"name", "description", "scenes", "scene_defaults", "methods", "steps", "seeds", "eval_every",
               "schedule", "threads", "lpips", "align_poses", "final_renders", "train_fit", "scene_root",
               "ray"}  # fmt: skip
_SCENE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$")


def _fail(source: Path, key: str, message: str) -> SuiteConfigError:
    return SuiteConfigError(f"{source}: {key}: {message}")


def _bool(values: Mapping[str, Any], key: str, default: bool, source: Path) -> bool:
    value = values.get(key, default)
    if not isinstance(value, bool):
        raise _fail(source, key, f"must be true or false, got {value!r}")
    return value


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


def _check_scene_values(values: Mapping[str, Any], source: Path, key: str) -> Dict[str, int]:
    names = {f.name for f in dataclasses.fields(SceneSpec) if f.name != "variant"}
    out = {}
    for name, value in values.items():
        if name not in names:
            raise _fail(source, f"{key}.{name}", f"unknown key; valid: {', '.join(sorted(names))}")
        minimum = 0 if name == "seed" else 1
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise _fail(source, f"{key}.{name}", f"must be an integer >= {minimum}, got {value!r}")
        out[name] = value
    return out


def _parse_scene(item: Any, index: int, defaults: Dict[str, int], source: Path) -> SceneEntry:
    from gsmsdr_ns.degrade.variants import VARIANTS

    key = f"scenes[{index}]"
    if isinstance(item, str):
        item = {"variant": item}
    if not isinstance(item, dict):
        raise _fail(source, key, f"must be a variant name or a mapping, got {type(item).__name__}")
    if sum(k in item for k in ("variant", "path", "real")) != 1:
        raise _fail(source, key, "needs exactly one of 'variant' (a generated scene), 'real' (a scene built from "
                                 "real photos) or 'path' (a scene folder)")  # fmt: skip
    name = item.get("name")
    init = item.get("init", "points")
    if init not in ("points", "random"):
        raise _fail(source, f"{key}.init", f"must be 'points' (the scene's sparse points) or 'random', got {init!r}")
    item = {k: v for k, v in item.items() if k != "init"}
    if "real" in item:
        unknown = sorted(set(item) - {"real", "name"})
        if unknown:
            raise _fail(source, f"{key}.{unknown[0]}", "unknown key for a real-photo scene; valid: real, name, init")
        real = parse_real_spec(item["real"], lambda k, message: _fail(source, f"{key}.real{k}", message))
        entry = SceneEntry(name=name or real.degraded_name, real=real)
    elif "variant" in item:
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
            raise _fail(source, f"{key}.{unknown[0]}", "unknown key for a user scene; valid: path, name, sharp_path, "
                                                       "init")  # fmt: skip
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
    if init == "random":
        entry = dataclasses.replace(entry, random_init=True)
    if not isinstance(entry.name, str) or not _SCENE_NAME.match(entry.name) or "__" in entry.name:
        raise _fail(source, f"{key}.name", f"{entry.name!r} is not a usable scene name (letters, digits, . _ + -)")
    return entry


def _check_schedule(schedule: Any, source: Path) -> Dict[str, Any]:
    """The ``schedule:`` mapping checked against the :class:`TrainingSchedule` field types."""
    if not isinstance(schedule, dict):
        raise _fail(source, "schedule", "must be a mapping")
    hints = typing.get_type_hints(TrainingSchedule)
    valid = [f.name for f in dataclasses.fields(TrainingSchedule) if f.name != "steps"]
    out: Dict[str, Any] = {}
    for k, v in schedule.items():
        if k not in valid:
            raise _fail(source, f"schedule.{k}", f"unknown key; valid: {', '.join(valid)}")
        hint = hints[k]
        args = typing.get_args(hint)
        if hint == typing.Tuple[str, ...]:
            if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
                raise _fail(source, f"schedule.{k}", f"must be a list of optimizer group names, got {v!r}")
            out[k] = tuple(v)
            continue
        optional = type(None) in args
        expected = next(a for a in args if a is not type(None)) if optional else hint
        if v is None and optional:
            out[k] = v
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or (expected is int and not isinstance(v, int)):
            suffix = " or null" if optional else ""
            raise _fail(source, f"schedule.{k}", f"must be a number ({expected.__name__}){suffix}, got {v!r}")
        out[k] = v
    try:
        TrainingSchedule.bench(1, **out)
    except (TypeError, ValueError) as e:
        raise _fail(source, "schedule", str(e)) from e
    return out


def _parse_ray(values: Any, source: Path) -> RaySettings:
    """The ``ray:`` mapping -> :class:`RaySettings`."""
    if values is None:
        return RaySettings()
    if not isinstance(values, dict):
        raise _fail(source, "ray", "must be a mapping of num_cpus, num_gpus, max_retries")
    out: Dict[str, Any] = {}
    for k, v in values.items():
        if k not in ("num_cpus", "num_gpus", "max_retries"):
            raise _fail(source, f"ray.{k}", "unknown key; valid: num_cpus, num_gpus, max_retries")
        if k == "max_retries":
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise _fail(source, f"ray.{k}", f"must be an integer >= 0, got {v!r}")
        elif v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0
                                or (k == "num_cpus" and v == 0)):  # fmt: skip
            low = "> 0" if k == "num_cpus" else ">= 0"
            raise _fail(source, f"ray.{k}", f"must be a number {low} or null, got {v!r}")
        out[k] = v
    return RaySettings(**out)


def load_suite(path: str | Path) -> Suite:
    """Read and validate a suite YAML file; errors are :class:`SuiteConfigError` naming the file and the key."""
    source = Path(path)
    try:
        values = read_yaml_mapping(source)
    except InputError as err:
        raise SuiteConfigError(str(err)) from err
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
    lpips = _bool(values, "lpips", True, source)
    align_poses = _bool(values, "align_poses", False, source)
    final_renders = _bool(values, "final_renders", False, source)
    train_fit = _bool(values, "train_fit", False, source)
    schedule = _check_schedule(values.get("schedule") or {}, source)

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
        schedule=schedule,
        threads=threads,
        lpips=lpips,
        align_poses=align_poses,
        final_renders=final_renders,
        train_fit=train_fit,
        ray=_parse_ray(values.get("ray"), source),
        description=str(values.get("description", "")).strip(),
        scene_root=None if scene_root is None else Path(os.path.expanduser(scene_root)),
        source=source,
    )


def find_suite_file(name_or_path: str | Path) -> Path:
    """A suite file path, or a suite name: the packaged ``configs/bench/<name>.yaml`` (installed with the package),
    else ``configs/bench/<name>.yaml`` under the working directory. A folder of that name (a suite's ``--out``, say)
    is not a suite file."""
    from gsmsdr_ns.resources import config_file, config_names

    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml") or path.is_file():
        return path
    try:
        return config_file("bench", str(name_or_path))
    except FileNotFoundError:
        pass
    candidate = Path.cwd() / "configs" / "bench" / f"{name_or_path}.yaml"
    if candidate.is_file():
        return candidate
    raise SuiteConfigError(f"no suite file {name_or_path!r} (looked for configs/bench/{name_or_path}.yaml in the "
                           f"package and the working directory); packaged suites: "
                           f"{', '.join(config_names('bench'))}")  # fmt: skip


__all__ = [
    "RaySettings",
    "RunKey",
    "SceneEntry",
    "Suite",
    "SuiteConfigError",
    "find_suite_file",
    "load_suite",
    "schedule_settings",
]
