"""Build, on this machine, the wheelhouse the GPU check installs from (<out>/wheels), within the device's carry limit.

The lent GPU machine has PyTorch, numpy, scipy, scikit-image, pytest and nvcc but no network: every other package the
training and test code imports travels as a wheel for its Python (3.12 by default), downloaded here with
``pip download --no-deps``. Versions are this checkout's ``.venv`` ones (what the tests ran with here), except where
``VERSION_OVERRIDES`` says why. Files no code imports (datasets, documentation, duplicate web assets) are dropped from
three wheels (``SLIM``) so the wheels, the repository and the scenes fit the 64 MiB that travels to the device.

    .venv/bin/python scripts/gpu_wheelhouse.py .gpu            # Python 3.12
    .venv/bin/python scripts/gpu_wheelhouse.py .gpu --python 3.11
"""

from __future__ import annotations

import argparse
import fnmatch
import importlib.metadata as metadata
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

PACKAGES = (
    # nerfstudio's trainer, viewer-less (the chain of `nerfstudio.scripts.train`) and what it imports
    "nerfstudio", "gsplat", "nerfacc", "viser", "tyro", "docstring_parser", "typeguard", "websockets", "rawpy",
    "fpsample", "msgspec", "multiprocess", "dill", "pathos", "ppft", "pox", "tensorly", "appdirs", "defusedxml",
    "PySocks", "pyquaternion", "pytorch-msssim", "splines",
    # ours: image ops, COLMAP models
    "kornia", "kornia_rs", "pycolmap",
)  # fmt: skip
"""Packages the device image lacks (its list: the device tool's KINDS.md)."""

VERSION_OVERRIDES = {
    "pycolmap": "4.0.2",  # 4.2's cp312 wheel is 38 MB, 4.0's 27 MB; both read and write our models (rigs, frames)
    "fpsample": "0.2.0",  # the newest with a cp312 manylinux wheel; only imported (its sampler is not the default)
}

SLIM = {
    "tensorly": ("tensorly/datasets/data/*",),  # example datasets (12 MB), loaded only by tensorly.datasets
    "gsplat": ("gsplat/cuda/csrc/third_party/glm/doc/*", "gsplat/cuda/csrc/third_party/glm/test/*"),  # GLM's docs
    "viser": ("viser/client/public/*", "viser/client/src/*"),  # the client's sources; the built client stays
}
"""Per wheel, files dropped (fnmatch patterns on the archive path); the RECORD loses their lines too."""

PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_24_x86_64", "manylinux_2_17_x86_64",
             "manylinux2014_x86_64", "manylinux1_x86_64", "manylinux_2_5_x86_64")  # fmt: skip


def pinned(name: str) -> str:
    """``name==version``: the override, else the version installed in this interpreter's environment."""
    version = VERSION_OVERRIDES.get(name) or metadata.version(name)
    return f"{name}=={version}"


def download(requirement: str, python: str, dest: Path) -> None:
    command = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "--python-version",
               python, "--implementation", "cp", "-d", str(dest), requirement]  # fmt: skip
    for platform in PLATFORMS:
        command[-1:-1] = ["--platform", platform]
    subprocess.run(command, check=True)


def slim(wheel: Path, patterns: tuple) -> int:
    """Rewrite ``wheel`` without the files matching ``patterns`` (and their RECORD lines); returns bytes saved."""
    before = wheel.stat().st_size
    with tempfile.TemporaryDirectory(dir=wheel.parent) as tmp:
        slimmed = Path(tmp) / wheel.name
        with zipfile.ZipFile(wheel) as src, zipfile.ZipFile(slimmed, "w", zipfile.ZIP_DEFLATED) as dst:
            dropped = {i.filename for i in src.infolist() if any(fnmatch.fnmatch(i.filename, p) for p in patterns)}
            for info in src.infolist():
                if info.filename in dropped:
                    continue
                data = src.read(info.filename)
                if info.filename.endswith(".dist-info/RECORD"):
                    lines = data.decode().splitlines(keepends=True)
                    data = "".join(line for line in lines if line.split(",", 1)[0] not in dropped).encode()
                dst.writestr(info, data)
        slimmed.replace(wheel)
    return before - wheel.stat().st_size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, nargs="?", default=Path(".gpu"))
    parser.add_argument("--python", default="3.12", help="the device's Python version (its KINDS.md: 3.12)")
    args = parser.parse_args()
    wheels = args.out / "wheels"
    partial = args.out / "wheels.partial"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    for name in PACKAGES:
        requirement = pinned(name)
        download(requirement, args.python, partial)
        print(f"downloaded {requirement}")
    for name, patterns in SLIM.items():
        (wheel,) = partial.glob(f"{name}-*.whl")
        print(f"{wheel.name}: {slim(wheel, patterns) / 2**20:.1f} MiB of unused files dropped")
    shutil.rmtree(wheels, ignore_errors=True)
    partial.rename(wheels)
    total = sum(p.stat().st_size for p in wheels.glob("*.whl"))
    print(f"{wheels}: {len(list(wheels.glob('*.whl')))} wheels, {total / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
