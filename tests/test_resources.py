"""The packaged configs: ``gsmsdr_ns.resources`` finds the top-level ``configs/`` files through the package (the
same files), and a wheel built from the checkout carries copies of all of them, which resolve from outside the
checkout."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from gsmsdr_ns.bench.suite_config import SuiteConfigError, find_suite_file
from gsmsdr_ns.resources import CONFIG_KINDS, config_file, config_names

REPO = Path(__file__).resolve().parents[1]


def _repo_configs() -> dict:
    return {p.relative_to(REPO / "configs").as_posix(): p for p in sorted((REPO / "configs").glob("*/*.yaml"))}


def test_packaged_configs_are_the_repository_configs() -> None:
    files = _repo_configs()
    assert files and {name.split("/")[0] for name in files} == set(CONFIG_KINDS)
    for name, path in files.items():
        kind, stem = name.split("/")[0], Path(name).stem
        packaged = config_file(kind, stem)
        assert packaged.resolve() == path.resolve(), (packaged, path)
    for kind in CONFIG_KINDS:
        assert config_names(kind) == sorted(Path(n).stem for n in files if n.startswith(kind + "/"))


def test_unknown_config_names_the_valid_ones() -> None:
    with pytest.raises(FileNotFoundError, match="quick"):
        config_file("bench", "no-such-suite")
    with pytest.raises(ValueError, match="unknown config kind"):
        config_file("suites", "quick")
    with pytest.raises(SuiteConfigError, match="packaged suites: .*quick"):
        find_suite_file("no-such-suite")


def test_suite_names_resolve_outside_the_checkout(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert find_suite_file("quick").resolve() == (REPO / "configs" / "bench" / "quick.yaml").resolve()


def test_wheel_carries_the_configs(tmp_path: Path) -> None:
    """Build a wheel from a copy of the checkout (symlink kept), unpack it, and resolve a suite name with only the
    unpacked wheel on the path, from a folder outside any checkout."""
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    shutil.copytree(REPO / "configs", src / "configs")
    ignore = shutil.ignore_patterns("__pycache__", "*.so", "build")
    shutil.copytree(REPO / "gsmsdr_ns", src / "gsmsdr_ns", symlinks=True, ignore=ignore)
    assert (src / "gsmsdr_ns" / "configs").is_symlink()
    wheels = tmp_path / "wheels"
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                            str(wheels), str(src)], capture_output=True, text=True, timeout=600)  # fmt: skip
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    (wheel,) = wheels.glob("gsmsdr_ns-*.whl")
    unpacked = tmp_path / "site"
    with zipfile.ZipFile(wheel) as archive:
        packaged = sorted(n for n in archive.namelist() if n.startswith("gsmsdr_ns/configs/"))
        sources = {n for n in archive.namelist() if "/csrc/" in n}
        archive.extractall(unpacked)
    # the C++ ops are compiled on first use: every source and header they include must be in the wheel
    repo_sources = {str(p.relative_to(REPO)) for p in (REPO / "gsmsdr_ns").rglob("csrc/*") if p.is_file()}
    assert sources == repo_sources
    assert packaged == sorted(f"gsmsdr_ns/configs/{name}" for name in _repo_configs())
    for name, path in _repo_configs().items():
        assert (unpacked / "gsmsdr_ns" / "configs" / name).read_bytes() == path.read_bytes(), name

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    code = ("from gsmsdr_ns.bench.suite_config import find_suite_file, load_suite; p = find_suite_file('quick'); "
            "print(p); print(load_suite(p).name)")  # fmt: skip
    env = {"PYTHONPATH": str(unpacked), "PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "1", "HOME": str(tmp_path)}
    run = subprocess.run([sys.executable, "-W", "ignore", "-c", code], cwd=elsewhere, env=env, capture_output=True,
                         text=True, timeout=300)  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    path, name = run.stdout.strip().splitlines()[-2:]
    assert Path(path) == unpacked / "gsmsdr_ns" / "configs" / "bench" / "quick.yaml" and name == "quick"
