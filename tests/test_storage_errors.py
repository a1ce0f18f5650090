"""A full disk, a read-only folder and what killed writers left behind: one line naming the file or folder, exit
status 1, nothing half-written, and temporaries of dead processes removed by the next writer.

Real file systems where the machine allows: small tmpfs mounts (read-write, and read-only), which need root. Where
mounting is refused, those tests skip, and the injected-error tests beside them still check the same code paths.
"""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import BIN, TrainedRun, scaled
from PIL import Image

from gsmsdr_ns._cli import run_entrypoint
from gsmsdr_ns.io import atomic
from gsmsdr_ns.io.atomic import atomic_dir, remove_stale_temporaries, temp_sibling_dir, write_text_atomic
from gsmsdr_ns.io.errors import DiskFullError, require_free_space, storage_error_line
from gsmsdr_ns.plugin import checkpoint_io as ckpt
from gsmsdr_ns.plugin.checkpoint_io import checkpoint_file, save_checkpoint_atomic

ENV = dict(os.environ, PYTHONUNBUFFERED="1", COLUMNS="200", OMP_NUM_THREADS="1")
ENV.pop("GSMSDR_DEBUG", None)


@pytest.fixture
def tmpfs(tmp_path):
    """``mount(size_kib, read_only=False)`` -> a fresh tmpfs folder under tmp_path, unmounted afterwards."""
    mounted = []

    def mount(size_kib: int, read_only: bool = False) -> Path:
        where = tmp_path / f"tmpfs{len(mounted)}"
        where.mkdir()
        options = f"size={size_kib}k" + (",ro" if read_only else "")
        proc = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)], capture_output=True)
        if proc.returncode != 0:
            pytest.skip(f"mounting a tmpfs is not allowed here: {proc.stderr.decode().strip()}")
        mounted.append(where)
        return where

    yield mount
    for where in mounted:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)


def run_tool(tool: str, *args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(BIN / tool), *map(str, args)], cwd=cwd, env=ENV, capture_output=True, text=True,
                          timeout=scaled(600))  # fmt: skip


def photos(folder: Path, count: int = 3) -> Path:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(count):
        Image.fromarray(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)).save(folder / f"{i:03d}.png")
    return folder


# -- one line for a failed write --------------------------------------------------------------------------------


def test_a_full_disk_behind_another_error_is_one_line_naming_the_file_and_the_free_space(tmp_path):
    try:
        try:
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "out" / "x.png"))
        except OSError:
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 704 vs 598")
    except RuntimeError as wrapped:
        line = storage_error_line(wrapped)
    assert line.startswith(f"gsmsdr: no space left on the disk writing '{tmp_path / 'out' / 'x.png'}' (")
    assert f"free in '{tmp_path}')" in line and line.endswith("Free some space, or write to a disk with room.")
    read_only = storage_error_line(OSError(errno.EROFS, "Read-only file system", "/ro/scene"))
    assert read_only == "gsmsdr: cannot write '/ro/scene': the file system is read-only. Write to another folder."
    assert "permission denied for '/a/b'" in storage_error_line(PermissionError(errno.EACCES, "denied", "/a/b"))
    assert storage_error_line(ValueError("x")) is None and storage_error_line(OSError(errno.ENOENT, "no")) is None


def test_console_scripts_print_a_failed_write_as_one_line_and_exit_1(capsys, monkeypatch):
    from rich.console import Console

    class Writes:
        def main(self):
            try:
                raise OSError(errno.ENOSPC, "No space left on device", "/data/out/scene.ply")
            except OSError as e:
                raise RuntimeError("the writer failed") from e

    with pytest.raises(SystemExit) as exited:
        run_entrypoint(lambda: Writes(), Console(stderr=True, width=300))
    assert exited.value.code == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "error: gsmsdr: no space left on the disk writing '/data/out/scene.ply'" in err
    monkeypatch.setenv("GSMSDR_DEBUG", "1")
    with pytest.raises(RuntimeError, match="the writer failed"):
        run_entrypoint(lambda: Writes(), Console(stderr=True))


def test_the_exception_hook_prints_a_failed_write_as_one_line(capsys):
    import sys

    from gsmsdr_ns._cli import _print_user_errors

    seen = []
    hook = _print_user_errors(lambda *a: seen.append(a))
    error = OSError(errno.EROFS, "Read-only file system", "/ro/out/config.yml")
    hook(OSError, error, None)
    assert capsys.readouterr().err == ("gsmsdr: cannot write '/ro/out/config.yml': the file system is read-only. "
                                       "Write to another folder.\n")  # fmt: skip
    hook(RuntimeError, RuntimeError("bug"), None)
    assert len(seen) == 1  # everything else keeps its traceback
    assert sys.excepthook is not None


# -- checkpoints ------------------------------------------------------------------------------------------------


def test_a_checkpoint_on_a_full_tmpfs_names_the_file_and_leaves_nothing(tmpfs):
    """torch's writer turns the ENOSPC into a RuntimeError (ENOSPC as its context): still a DiskFullError."""
    disk = tmpfs(1024)
    path = checkpoint_file(disk / "run" / "nerfstudio_models", 3)
    path.parent.mkdir(parents=True)
    with pytest.raises(DiskFullError, match=rf"no space left on the disk to save checkpoint '{path}'") as caught:
        save_checkpoint_atomic({"step": 3, "w": torch.zeros(2_000_000)}, path)
    assert "(it needs about 7.6 MiB, " in str(caught.value)  # 2M float32
    assert caught.value.errno == errno.ENOSPC
    assert sorted(p.name for p in (disk / "run").iterdir()) == ["nerfstudio_models"]
    assert not list(path.parent.iterdir())


def test_a_checkpoint_writer_error_caused_by_a_full_disk_is_a_disk_full_error(tmp_path, monkeypatch):
    def torch_save_on_a_full_disk(payload, f):
        f.write(b"PK")
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError:
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 704 vs 598")

    monkeypatch.setattr(ckpt.torch, "save", torch_save_on_a_full_disk)
    path = checkpoint_file(tmp_path / "run" / "nerfstudio_models", 1)
    path.parent.mkdir(parents=True)
    with pytest.raises(DiskFullError, match="no space left on the disk to save checkpoint"):
        save_checkpoint_atomic({"step": 1}, path)
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["nerfstudio_models"]


# -- gsmsdr-process ---------------------------------------------------------------------------------------------


def test_gsmsdr_process_refuses_a_disk_without_room_before_pycolmap_starts(tmp_path, tmpfs):
    """pycolmap aborts the process (exit 134, a native stack dump) when its database meets a full disk."""
    disk = tmpfs(1024)
    proc = run_tool("gsmsdr-process", "--images", photos(tmp_path / "photos"), "--out", disk / "scene", cwd=tmp_path)
    assert proc.returncode == 1, (proc.stdout + proc.stderr)[-3000:]
    assert "Traceback" not in proc.stdout + proc.stderr
    output = proc.stdout + proc.stderr
    lines = [line for line in output.splitlines() if "error:" in line]
    assert len(lines) == 1 and "no space left on the disk for gsmsdr-process: it needs about" in lines[0], output
    assert f"in '{disk}'" in lines[0], output
    assert lines[0].endswith("are free; nothing was written. Free some space, or choose --out on a disk with room.")
    assert list(disk.iterdir()) == []


def test_the_free_space_check_names_what_is_needed(tmp_path, monkeypatch):
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage", lambda _p: usage._replace(free=3 * 2**20))
    with pytest.raises(DiskFullError) as caught:
        require_free_space(tmp_path / "not" / "yet", 10 * 2**20, "gsmsdr-process", "Choose another --out.")
    assert str(caught.value) == (
        f"gsmsdr: no space left on the disk for gsmsdr-process: it needs about 10.0 MiB in '{tmp_path}', 3.0 MiB "
        "are free; nothing was written. Choose another --out."
    )
    require_free_space(tmp_path, 2 * 2**20, "x", "y")  # enough: no error


def test_read_only_outputs_are_one_line(tmp_path, tmpfs, trained_run: TrainedRun):
    disk = tmpfs(64 * 1024, read_only=True)  # room enough: the write itself is refused
    process = run_tool("gsmsdr-process", "--images", photos(tmp_path / "photos"), "--out", disk / "scene",
                       cwd=tmp_path)  # fmt: skip
    export = run_tool("gsmsdr-export", "--load-config", trained_run.config, "--output", disk / "scene.ply",
                      cwd=tmp_path)  # fmt: skip
    for proc, target in ((process, disk / "scene"), (export, disk / "scene.ply")):
        output = proc.stdout + proc.stderr
        assert proc.returncode == 1 and "Traceback" not in output, output[-3000:]
        (line,) = [line for line in output.splitlines() if "error:" in line]
        assert "the file system is read-only. Write to another folder." in line and f"'{disk}" in line, line
    assert list(disk.iterdir()) == []


# -- temporaries of killed writers --------------------------------------------------------------------------------


def _dead_pid() -> int:
    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid  # reaped: no process has it (until the kernel reuses it)


def _age(path: Path, seconds: float) -> None:
    then = time.time() - seconds
    os.utime(path, (then, then), follow_symlinks=False)


def test_the_next_writer_removes_what_a_killed_writer_left(tmp_path):
    dead = _dead_pid()
    stale = tmp_path / f".scene.partial-{dead}-0123abcd"
    (stale / "images").mkdir(parents=True)
    _age(stale, 3600)
    fresh = tmp_path / f".scene.partial-{dead}-89abcdef"  # touched a moment ago: maybe another machine's
    fresh.mkdir()
    alive = tmp_path / f".scene.partial-{os.getpid()}-fedcba98"  # a running process's
    alive.mkdir()
    _age(alive, 3600)
    other = tmp_path / f".other.partial-{dead}-0123abcd"  # another target's: not this writer's business
    other.mkdir()
    _age(other, 3600)
    with atomic_dir(tmp_path / "scene") as tmp:
        (tmp / "done").write_text("ok")
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == sorted(["scene", fresh.name, alive.name, other.name])
    assert remove_stale_temporaries(tmp_path, ".scene.") == []


def test_stale_temporary_files_of_files_and_checkpoints_are_removed(tmp_path):
    dead = _dead_pid()
    stale_file = tmp_path / f".results.md.tmp-{dead}-0123abcd.md"
    stale_file.write_text("half")
    _age(stale_file, 3600)
    write_text_atomic(tmp_path / "results.md", "all")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.md"]
    models = tmp_path / "run" / "nerfstudio_models"
    models.mkdir(parents=True)
    stale_ckpt = tmp_path / "run" / f".nerfstudio_models.step-000000005.ckpt.partial-{dead}-0123abcd"
    stale_ckpt.write_bytes(b"PK")
    _age(stale_ckpt, 3600)
    save_checkpoint_atomic({"step": 6}, checkpoint_file(models, 6))
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["nerfstudio_models"]


def test_temporary_names_carry_the_pid_and_keep_the_extension(tmp_path):
    folder = temp_sibling_dir(tmp_path / "scene")
    assert folder.name.startswith(f".scene.partial-{os.getpid()}-")
    seen = []
    atomic.write_file_atomic(tmp_path / "plot.png", lambda tmp: seen.append(tmp) or Path(tmp).write_bytes(b"x"))
    assert seen[0].name.startswith(f".plot.png.tmp-{os.getpid()}-") and seen[0].suffix == ".png"


# -- every writer on a full disk ---------------------------------------------------------------------------------


def _fill(disk: Path) -> None:
    """Fill the file system of ``disk`` up to its last byte."""
    with open(disk / "filler", "wb", buffering=0) as f:  # unbuffered: nothing left to flush at close
        try:
            while True:
                f.write(b"\0" * 4096)
        except OSError as e:
            assert e.errno == errno.ENOSPC


def test_every_writer_on_a_full_disk_says_so_in_one_line_and_leaves_nothing(tiny_scene, trained_run, tmp_path,
                                                                            tmpfs):  # fmt: skip
    """Each command's output on a full tmpfs: exit 1, one error line about the full disk (no traceback), and nothing
    on that disk but what was there. The commands run at once (each is mostly interpreter start-up)."""
    out = tmpfs(512)
    in_place = tmpfs(4096)  # gsmsdr-estimate writes into the scene itself
    scene = in_place / "scene"
    shutil.copytree(tiny_scene, scene, ignore=shutil.ignore_patterns("degradation*.json"))
    _fill(out)
    _fill(in_place)
    before = {disk: sorted(p.relative_to(disk) for p in disk.rglob("*")) for disk in (out, in_place)}
    commands = {
        "gsmsdr-synth": ["--out", out / "synth", "--num-views", "4", "--width", "32", "--height", "24"],
        "gsmsdr-degrade": ["--input", tiny_scene, "--out", out / "degraded", "--effect", "motion"],
        "gsmsdr-estimate": ["--scene", scene],
        "gsmsdr-eval": ["--load-config", trained_run.config, "--output-path", out / "eval.json", "--no-align-poses"],
        "gsmsdr-export": ["--load-config", trained_run.config, "--output", out / "scene.ply"],
        "gsmsdr-bench": [
            "step",
            "--data",
            tiny_scene,
            "--methods",
            "plain",
            "--warmup",
            "1",
            "--steps",
            "1",
            "--out",
            out / "step",
            "--work-dir",
            tmp_path / "bench-work",
        ],
    }
    procs = {
        tool: subprocess.Popen(
            [str(BIN / tool), *map(str, args)],
            cwd=tmp_path,
            env=ENV,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for tool, args in commands.items()
    }
    for tool, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=scaled(600))
        output = stdout + stderr
        assert proc.returncode == 1, f"{tool}: exit {proc.returncode}\n{output[-3000:]}"
        assert "Traceback" not in output, f"{tool}:\n{output[-3000:]}"
        errors = [line for line in output.splitlines() if line.startswith("error:")]
        assert len(errors) == 1 and "no space left on the disk" in errors[0], f"{tool}:\n{output[-3000:]}"
    for disk, entries in before.items():
        assert sorted(p.relative_to(disk) for p in disk.rglob("*")) == entries, disk


def test_a_checkpoints_size_counts_each_tensor_storage_once():
    from gsmsdr_ns.plugin.checkpoint_io import tensor_bytes

    weights = torch.zeros(1000)
    payload = {"step": 3, "model": {"w": weights, "w_view": weights[:10]}, "optim": [torch.ones(5, dtype=torch.int64)]}
    assert tensor_bytes(payload) == 1000 * 4 + 5 * 8


def test_an_atomic_file_on_a_full_tmpfs_names_the_room_it_needs_and_leaves_nothing(tmpfs):
    from gsmsdr_ns.io.atomic import write_bytes_atomic, write_file_atomic

    disk = tmpfs(64)
    _fill(disk)
    before = sorted(disk.rglob("*"))
    data = bytes(3 * 2**20)
    with pytest.raises(DiskFullError) as caught:
        write_bytes_atomic(disk / "out" / "records.json", data)
    message = str(caught.value)
    assert message.startswith(f"gsmsdr: no space left on the disk writing '{disk / 'out' / 'records.json'}' (")
    assert "(it needs 3.0 MiB, " in message and f"free in '{disk}'" in message
    assert caught.value.errno == errno.ENOSPC and storage_error_line(caught.value) is None  # printed as it is
    with pytest.raises(DiskFullError, match=r"\(it needs more than [0-9.]+ \w+, "):
        write_file_atomic(disk / "image.png", lambda tmp: Path(tmp).write_bytes(data))  # size unknown in advance
    assert sorted(disk.rglob("*")) == before  # no temporary, no folder made for the file
