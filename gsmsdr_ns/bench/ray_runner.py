"""`gsmsdr-bench suite --ray ADDRESS`: a suite's runs as Ray tasks, on a local Ray instance or a cluster.

* The driver (this process) plans the runs exactly as the serial runner does (:class:`SuiteLedger`: same run keys,
  fingerprints, resume and ``same_training_as`` sharing) and alone writes the records, atomically, from what the
  tasks return, rewriting the tables and plots after each run.
* Scenes are built by one task per set of folders that share work (a generated scene's folder; every folder made
  from one real photo set and seed, whose twins share its structure-from-motion), ahead of the runs that read them:
  a run's task depends on its scene's build task.
* Each run is a task asking for the suite's ``ray.num_cpus`` CPUs and ``ray.num_gpus`` GPUs. A task whose worker
  process or node dies is started again (``ray.max_retries`` times; its partial output is never a record); a run
  that raises fails, as in the serial runner. Tasks write their log to ``runs/<id>.log`` and report their steps and
  evaluations to a progress actor (:class:`RunBoard`) the driver shows.
* Ctrl-C on the driver cancels the runs not finished; finished records are kept and the next invocation resumes.

Workers read the scenes and write the logs under ``--out`` (and the suite's ``scene_root``): on a cluster of several
machines these must be on storage every node mounts at the same path.
"""

from __future__ import annotations

import contextlib
import heapq
import json
import logging
import os
import platform
import signal
import sys
import time
import traceback
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple

from gsmsdr_ns.bench.ledger import SuiteLedger, SuiteOutcome, training_records_digest
from gsmsdr_ns.bench.methods import METHODS
from gsmsdr_ns.bench.runner import LPIPS_MISSING, progress_columns, train_and_record
from gsmsdr_ns.bench.suite_config import RunKey, Suite

RAY_MISSING = "--ray needs Ray, an optional extra: pip install 'gsmsdr-ns[ray]'"

PASSED_ENV = (
    "OMP_WAIT_POLICY",
    "GOMP_SPINCOUNT",
    "GSMSDR_DATA_DIR",
    "TORCH_EXTENSIONS_DIR",
    "GSMSDR_TEST_TIMEOUT_SCALE",
)
"""Environment variables of the driver that the workers get too (data and compiled-kernel locations, OpenMP)."""

LOCAL_OBJECT_STORE_BYTES = 512 * 2**20
"""Object store of a local instance: tasks pass run settings and records (kilobytes), not images."""

LOCAL_SYSTEM_CONFIG = {"worker_niceness": 0}
"""A local instance's workers train at the driver's priority: at Ray's default (nice +15) any other busy process on
the machine starves them (two 1-thread trainings beside a 2-CPU instance held its 12-step runs past 900 s)."""

PROGRESS_SECONDS = 0.5
"""A task reports its step count at most this often."""


class RaySetupError(RuntimeError):
    """Ray cannot run the suite as asked (not installed, no cluster at the address, a bad ``--ray`` value, no node
    large enough for a run); the message says what to do."""


def import_ray():
    """The ``ray`` module, or :class:`RaySetupError` saying how to install it."""
    try:
        import ray
    except ImportError:
        raise RaySetupError(RAY_MISSING) from None
    return ray


def parse_address(text: str) -> Tuple[Optional[str], Optional[int]]:
    """``--ray``'s value -> (the address ``ray.init`` connects to, or None to start a local instance; the local
    instance's CPUs, None: all). ``local``, ``local:N``, ``auto`` (the cluster started on this machine with
    ``ray start --head``) or a cluster address (``HOST:PORT``, ``ray://HOST:PORT``)."""
    text = text.strip()
    if text == "local":
        return None, None
    if text.startswith("local:"):
        count = text.split(":", 1)[1]
        if not count.isdigit() or int(count) < 1:
            raise RaySetupError(f"--ray {text}: local:N needs a whole number of CPUs N >= 1, e.g. local:2")
        return None, int(count)
    if not text:
        raise RaySetupError("--ray needs a value: auto, local, local:N or a cluster address HOST:PORT")
    return text, None


def connect(address: str) -> bool:
    """Connect this process to Ray at ``address`` (:func:`parse_address`) unless it already is; True when this
    call connected (the caller then disconnects, which stops a local instance it started)."""
    ray = import_ray()
    if ray.is_initialized():
        return False
    target, cpus = parse_address(address)
    env = {name: os.environ[name] for name in PASSED_ENV if name in os.environ}
    options: Dict[str, Any] = dict(log_to_driver=False, logging_level=logging.WARNING,
                                   runtime_env={"env_vars": env} if env else None)  # fmt: skip
    try:
        if target is None:
            ray.init(num_cpus=cpus, include_dashboard=False, object_store_memory=LOCAL_OBJECT_STORE_BYTES,
                     _system_config=LOCAL_SYSTEM_CONFIG, **options)  # fmt: skip
        else:
            ray.init(address=target, **options)
    except ConnectionError as e:
        start = " (start one on this machine with `ray start --head`, or use --ray local)" if target == "auto" else ""
        raise RaySetupError(f"gsmsdr-bench suite --ray {address}: no Ray cluster reachable{start}: {e}") from None
    return True


class RunBoard:
    """The progress of a suite's runs as their tasks report it (a Ray actor; the driver reads :meth:`snapshot`)."""

    def __init__(self) -> None:
        self.runs: Dict[str, Dict[str, Any]] = {}

    def started(self, run_id: str, node: str) -> int:
        """Run ``run_id`` started (again) on ``node`` -> which attempt this is (1 for the first)."""
        entry = self.runs.setdefault(run_id, {"attempts": 0})
        entry.update(attempts=entry["attempts"] + 1, step=0, info=f"on {node}")
        return entry["attempts"]

    def advanced(self, run_id: str, step: int) -> None:
        self.runs[run_id]["step"] = step

    def evaluated(self, run_id: str, step: int, psnr: float) -> None:
        self.runs[run_id]["info"] = f"PSNR {psnr:.2f} @ {step}"

    def snapshot(self) -> Dict[str, Dict[str, Any]]:
        return self.runs


@contextlib.contextmanager
def _working_directory(folder: Optional[str]) -> Iterator[None]:
    """Run the block in ``folder`` when this machine has it (relative suite paths resolve as on the driver)."""
    previous = os.getcwd()
    if folder is not None and os.path.isdir(folder):
        os.chdir(folder)
    try:
        yield
    finally:
        os.chdir(previous)


def build_unit(suite: Suite, key: RunKey) -> Optional[Tuple[str, str]]:
    """(unit, folder) of the scene folder run ``key`` reads, None when nothing is built (a user's scene). Folders of
    one unit are built one after another: a generated scene's folder is a unit alone; every folder made from one
    real photo set and seed is one unit (they share its structure-from-motion and degradations)."""
    scene, method = suite.scene(key.scene), METHODS[key.method]
    if not scene.generated:
        return None
    folder = json.dumps(scene.folder_key(method), sort_keys=True, default=str)
    return (f"real {scene.real.photos_name} s{scene.real.seed}" if scene.real is not None else folder), folder


def build_units(suite: Suite, keys: List[RunKey]) -> Dict[str, List[RunKey]]:
    """{unit: runs} with one run of ``keys`` per scene folder to build, grouped by :func:`build_unit`."""
    units: Dict[str, List[RunKey]] = {}
    seen = set()
    for key in keys:
        unit = build_unit(suite, key)
        if unit is not None and unit[1] not in seen:
            seen.add(unit[1])
            units.setdefault(unit[0], []).append(key)
    return units


def build_scenes(suite: Suite, keys: List[RunKey], scene_root: Path, work_dir: Path, log_path: Path,
                 cwd: Optional[str]) -> List[str]:  # fmt: skip
    """(a Ray task) Build the scene folders runs ``keys`` read, and the degradation estimate of those that train on
    estimated records, logging to ``log_path``. -> the folders."""
    folders = []
    with _working_directory(cwd), open(log_path, "w", encoding="utf8") as log_file:

        def log(message: str) -> None:
            print(message, file=log_file, flush=True)

        try:
            for key in keys:
                scene, method = suite.scene(key.scene), METHODS[key.method]
                folders.append(str(scene.data(method, scene_root, log)))
                if scene.trains_on_estimated_records(method):  # estimated once here, not by each run at once
                    training_records_digest(suite, key, scene_root, work_dir, log)
        except Exception:
            log_file.write(traceback.format_exc())
            raise
    return folders


def train_run(suite: Suite, key: RunKey, scene_root: Path, work_dir: Path, log_path: Path, cwd: Optional[str],
              board, kill_at_step: Optional[int] = None, *scenes_built: Any) -> Dict[str, Any]:  # fmt: skip
    """(a Ray task) Train run ``key`` as the serial runner does and return its record (the driver writes it).
    ``kill_at_step``: a fault drill, the worker process kills itself at that step of the run's first attempt."""
    import ray
    import torch

    from gsmsdr_ns.bench.evaluation import make_lpips

    node = platform.node()
    attempt = ray.get(board.started.remote(key.id, node))
    reported = [0.0]
    steps = [0]

    def on_step(n: int) -> None:
        steps[0] += n
        if kill_at_step is not None and steps[0] >= kill_at_step and attempt == 1:
            sys.stdout.flush()
            os.kill(os.getpid(), signal.SIGKILL)
        now = time.monotonic()
        if now - reported[0] >= PROGRESS_SECONDS:
            reported[0] = now
            board.advanced.remote(key.id, steps[0])

    def on_eval(point: Dict[str, Any]) -> None:
        board.evaluated.remote(key.id, point["step"], point["psnr"])

    with _working_directory(cwd), open(log_path, "w", encoding="utf8") as log_file, \
            contextlib.redirect_stdout(log_file), contextlib.redirect_stderr(log_file):  # fmt: skip
        try:
            if suite.threads > 0:
                torch.set_num_threads(suite.threads)
            lpips = make_lpips("cuda" if torch.cuda.is_available() else "cpu") if suite.lpips else None
            record = train_and_record(suite, key, scene_root, work_dir, lpips, on_step=on_step, on_eval=on_eval,
                                      log=lambda message: print(message, flush=True))  # fmt: skip
        except Exception:
            log_file.write(traceback.format_exc())
            raise
    record["executor"] = {"kind": "ray", "attempt": attempt, "node": node}
    return record


def task_resources(suite: Suite, ray) -> Dict[str, float]:
    """What each run's task asks for: the suite's ``ray`` settings, else its threads in CPUs and a GPU when the
    cluster has one. RaySetupError when no node is large enough (Ray would wait for one forever)."""
    settings = suite.ray
    cpus = settings.num_cpus if settings.num_cpus is not None else float(max(suite.threads, 1))
    total = ray.cluster_resources()
    gpus = settings.num_gpus if settings.num_gpus is not None else (1.0 if total.get("GPU", 0) >= 1 else 0.0)
    nodes = [node.get("Resources", {}) for node in ray.nodes() if node.get("Alive")]
    if not any(n.get("CPU", 0) >= cpus and n.get("GPU", 0) >= gpus for n in nodes):
        largest = max(((n.get("CPU", 0), n.get("GPU", 0)) for n in nodes), default=(0, 0))
        raise RaySetupError(f"each run asks for {cpus:g} CPUs and {gpus:g} GPUs, but the largest Ray node has "
                         f"{largest[0]:g} CPUs and {largest[1]:g} GPUs; lower the suite's ray.num_cpus / "
                         "ray.num_gpus (or threads), or add a larger node")  # fmt: skip
    return {"num_cpus": cpus, "num_gpus": gpus}


METHOD_COST = {"plain": 1.0, "sharp": 1.0, "view": 1.5, "gsmsdr-lite": 1.6}
"""A method's step cost relative to plain Gaussians (the quick suite's ms/step: plain 41, view 61, gsmsdr-lite 66,
full 87); a method not listed costs :data:`BLUR_FIELD_COST` with a blur field, else 1."""
BLUR_FIELD_COST = 2.1


def expected_cost(suite: Suite, key: RunKey) -> float:
    """A rough training cost of run ``key`` for ordering the runs: steps x pixels of a generated scene (1 for other
    scenes, whose size is not known before they are built) x the method's relative step cost."""
    spec, method = suite.scene(key.scene).spec, METHODS[key.method]
    pixels = spec.width * spec.height if spec is not None else 1
    default = BLUR_FIELD_COST if method.has_blur_field else 1.0
    return key.steps * pixels * METHOD_COST.get(key.method, default)


def makespan(costs: Sequence[float], slots: int) -> float:
    """When ``slots`` workers that each take the next job of ``costs`` (in order) as they free up are done."""
    free = [0.0] * max(slots, 1)
    for cost in costs:
        heapq.heappush(free, heapq.heappop(free) + cost)
    return max(free)


def run_order(costs: Sequence[float], slots: int, rounds: int = 20) -> List[int]:
    """The order to submit jobs of ``costs`` in so that ``slots`` workers taking them in that order finish soonest:
    longest first, then any swap of two jobs that shortens :func:`makespan`, for at most ``rounds`` passes."""
    order = sorted(range(len(costs)), key=lambda i: -costs[i])
    best = makespan([costs[i] for i in order], slots)
    for _ in range(rounds):
        improved = False
        for a in range(len(order)):
            for b in range(a + 1, len(order)):
                order[a], order[b] = order[b], order[a]
                span = makespan([costs[i] for i in order], slots)
                if span < best - 1e-9:
                    best, improved = span, True
                else:
                    order[a], order[b] = order[b], order[a]
        if not improved:
            break
    return order


def _count(value: float, noun: str) -> str:
    return f"{value:g} {noun}" + ("" if value == 1 else "s")


def _cause(error: Exception) -> str:
    """A failed task's error as the serial runner words a run's exception: "Type: message"."""
    cause = getattr(error, "cause", None)
    if isinstance(cause, BaseException):
        return f"{type(cause).__name__}: {cause}"
    first = str(error).strip().splitlines()
    return f"{type(error).__name__}: {first[0] if first else ''}"


def run_suite_on_ray(
    suite: Suite,
    out: Path,
    address: str = "local",
    command: str = "",
    progress: bool = True,
    plots: bool = True,
    console=None,
    interrupt_after: Optional[int] = None,
    kill_worker_at: Optional[Tuple[str, int]] = None,
) -> SuiteOutcome:
    """Run every run of ``suite`` without a matching record in ``out/runs`` as a Ray task at ``address``
    (:func:`parse_address`; a process already connected to Ray uses that connection); rewrite the outputs after
    each. ``interrupt_after``: as in :func:`gsmsdr_ns.bench.runner.run_suite`. ``kill_worker_at`` (run id, step):
    the fault drill of :func:`train_run`."""
    from rich.console import Console
    from rich.progress import Progress

    from gsmsdr_ns.plugin.lpips import lpips_backbone_cache_path

    ray = import_ray()
    parse_address(address)  # a bad value fails before anything is done
    console = console or Console(file=sys.stdout)
    ledger = SuiteLedger(suite, Path(out).resolve(), command, console, plots)
    todo = ledger.plan.todo
    if suite.lpips and todo and not lpips_backbone_cache_path().is_file():
        console.print(LPIPS_MISSING)
    ledger.start()
    if not todo:
        return ledger.outcome()
    if kill_worker_at is not None and kill_worker_at[0] not in {key.id for key in todo}:
        raise RaySetupError(f"--kill-worker-at {kill_worker_at[0]}: no such run to train; runs: "
                         f"{', '.join(key.id for key in todo)}")  # fmt: skip

    owned = connect(address)
    pending: Dict[Any, RunKey] = {}
    builds: List[Any] = []
    current = "starting the tasks"
    try:
        resources = task_resources(suite, ray)
        cluster = ray.cluster_resources()
        console.print(f"Ray: {_count(cluster.get('CPU', 0), 'CPU')} and {_count(cluster.get('GPU', 0), 'GPU')}; "
                      f"each run asks for {_count(resources['num_cpus'], 'CPU')} and "
                      f"{_count(resources['num_gpus'], 'GPU')} and is started again up to "
                      f"{_count(suite.ray.max_retries, 'time')} if its worker dies")  # fmt: skip
        cwd, root, work = os.getcwd(), Path(ledger.scene_root).resolve(), ledger.work_dir
        board = ray.remote(num_cpus=0)(RunBoard).remote()
        build = ray.remote(build_scenes).options(num_cpus=1, max_retries=suite.ray.max_retries)
        train = ray.remote(train_run).options(**resources, max_retries=suite.ray.max_retries)
        built: Dict[str, Any] = {}  # unit -> its build task
        for index, (unit, keys) in enumerate(build_units(suite, todo).items()):
            log_path = ledger.out / "runs" / f"build-scenes-{index}.log"
            built[unit] = build.remote(suite, keys, root, work, log_path, cwd)
        builds = list(built.values())

        with Progress(*progress_columns(), console=console, disable=not progress, redirect_stdout=False,
                      redirect_stderr=False) as bars:  # fmt: skip
            suite_task = bars.add_task(suite.name, total=ledger.plan.total, completed=ledger.plan.total - ledger.left,
                                       info="")  # fmt: skip
            # Runs start once every scene is built, in the order that ends them soonest on the cluster's workers.
            current = f"building the scenes (logs: {ledger.out / 'runs'}/build-scenes-*.log)"
            bars.update(suite_task, info=current)
            while ray.wait(builds, num_returns=len(builds), timeout=1.0)[1]:
                pass  # waiting in short slices lets Ctrl-C through
            slots = int(cluster.get("CPU", 1) // resources["num_cpus"])
            if resources["num_gpus"] > 0:
                slots = min(slots, int(cluster.get("GPU", 0) // resources["num_gpus"]))
            for index in run_order([expected_cost(suite, key) for key in todo], slots):
                key = todo[index]
                kill = kill_worker_at[1] if kill_worker_at is not None and kill_worker_at[0] == key.id else None
                unit = build_unit(suite, key)
                deps = [built[unit[0]]] if unit is not None else []
                pending[train.remote(suite, key, root, work, ledger.log_path(key), cwd, board, kill, *deps)] = key
            run_bars: Dict[str, Any] = {}
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
                ids = {key.id: key for key in pending.values()}
                running = {run_id: state for run_id, state in ray.get(board.snapshot.remote()).items()
                           if run_id in ids}  # fmt: skip
                current = "running " + (", ".join(running) or "nothing yet (waiting for workers)")
                for run_id, state in running.items():
                    key = ids[run_id]
                    if run_id not in run_bars:
                        run_bars[run_id] = bars.add_task(f"  {key.scene} {key.method} s{key.seed}", total=key.steps,
                                                         info="")  # fmt: skip
                    info = state["info"] + (f" (attempt {state['attempts']})" if state["attempts"] > 1 else "")
                    bars.update(run_bars[run_id], completed=state["step"], info=info)
                bars.update(suite_task, info=f"{len(running)} running, {len(ledger.failed)} failed")
                for ref in done:
                    key = pending.pop(ref)
                    try:
                        record = ray.get(ref)
                        attempt = record["executor"]["attempt"]
                        note = f"  (attempt {attempt}: its worker died before)" if attempt > 1 else ""
                        ledger.finished(key, record, note)
                    except ray.exceptions.RayError as e:
                        ledger.failed_run(key, _cause(e))
                    if key.id in run_bars:
                        bars.remove_task(run_bars.pop(key.id))
                    bars.advance(suite_task, ledger.weight(key))
                    current = f"writing the outputs after {key.id}"
                    ledger.refresh()
                    if interrupt_after is not None and len(ledger.trained) + len(ledger.failed) >= interrupt_after:
                        signal.raise_signal(signal.SIGINT)
    except KeyboardInterrupt:
        for ref in [*pending, *builds]:
            ray.cancel(ref, force=True)
        ledger.interrupted(current)
        raise
    finally:
        if owned:
            ray.shutdown()
    return ledger.outcome()


__all__ = [
    "RAY_MISSING",
    "RaySetupError",
    "RunBoard",
    "build_unit",
    "build_units",
    "connect",
    "parse_address",
    "run_suite_on_ray",
    "train_run",
]
