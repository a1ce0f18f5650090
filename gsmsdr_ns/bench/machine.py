"""What a benchmark ran on: CPU, cores, torch version and threads, device, git commit."""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path
from typing import Any, Dict, Mapping, Optional


def git_revision() -> Optional[str]:
    """Short commit of the repository this package is in, ``+dirty`` with uncommitted changes to tracked files; None
    outside a git checkout."""
    try:
        root = Path(__file__).resolve().parents[2]
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True, timeout=10).stdout.strip()  # fmt: skip
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10).stdout.strip()  # fmt: skip
        return (commit + ("+dirty" if dirty else "")) if commit else None
    except (OSError, subprocess.SubprocessError):
        return None


GIT_AT_IMPORT = git_revision()
"""The commit checked out when this module was imported: the code this process runs. A suite imports its code
once, so its records name that commit even when the checkout moves on while it trains."""


def machine_info() -> Dict[str, Any]:
    """CPU model and cores, torch version and threads, device, and the code's commit (:data:`GIT_AT_IMPORT`), for the
    results header and every record."""
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
        "gomp_spincount": os.environ.get("GOMP_SPINCOUNT"),
    }
    info["git"] = GIT_AT_IMPORT
    return info


def describe_machine(info: Mapping[str, Any]) -> str:
    gpu = f" ({info['gpu']})" if info.get("gpu") else ""
    return (f"{info['cpu']}, {info['cores']} cores; torch {info['torch']} ({info['torch_threads']} thread(s)), "
            f"device {info['device']}{gpu}")  # fmt: skip


__all__ = ["GIT_AT_IMPORT", "describe_machine", "git_revision", "machine_info"]
