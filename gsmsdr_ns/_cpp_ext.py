"""JIT-built C++/OpenMP CPU extensions, shared by the rasterizer (`render.pixels_cpp`) and the blur kernels
(`ops.pixel_kernels_cpp`).

Each extension is one .cpp file registering its ops with TORCH_LIBRARY. It is built through
torch.utils.cpp_extension.load, like gsplat's CUDA code, into
~/.cache/gsmsdr_ns/torch_extensions/<torch version>/<name>_<isa> (or $TORCH_EXTENSIONS_DIR/<name>_<isa>), at most once
per process; torch's file lock serialises concurrent builds. <isa> is the vector instruction set the build targets,
the one torch's own CPU kernels use on this machine (`cpu_isa`): machines sharing a home folder keep a build each. A
failed build is not retried in the same process, and `available()` / `error()` never raise, so callers can fall back
to their PyTorch twin with a clear reason (`choose_backend` does that, warning once; `backend_for` also sends
tensors the C++ kernel does not take to the twin).

Imports only torch and the standard library: `gsmsdr_ns.render` and `gsmsdr_ns.blur` both use it without nerfstudio.
"""

from __future__ import annotations

import hashlib
import logging
import os
import platform
import shlex
import shutil
import sys
import threading
import warnings
from pathlib import Path
from typing import Literal, Optional

import torch


def extensions_root() -> Path:
    """$TORCH_EXTENSIONS_DIR or ~/.cache/gsmsdr_ns/torch_extensions/<torch version>."""
    root = os.environ.get("TORCH_EXTENSIONS_DIR")
    if root:
        return Path(root)
    return Path.home() / ".cache" / "gsmsdr_ns" / "torch_extensions" / torch.__version__.replace("+", "_")


def find_compiler() -> Optional[str]:
    """Path of the C++ compiler torch will use ($CXX or c++), None when it does not exist."""
    cxx = os.environ.get("CXX", "c++")
    parts = shlex.split(cxx) if cxx.strip() else []
    # the first word is the program ("ccache g++", "g++ -fsomething")
    return cxx if parts and shutil.which(parts[0]) else None


def ninja_dir() -> Optional[str]:
    """Directory holding the ninja binary (PATH, the interpreter's bin dir, or the `ninja` pip package)."""
    found = shutil.which("ninja")
    if found:
        return os.path.dirname(found)
    # a venv used without activation: ninja sits next to the interpreter
    beside = Path(sys.executable).parent / "ninja"
    if beside.exists():
        return str(beside.parent)
    try:
        import ninja  # type: ignore[import-not-found]

        return getattr(ninja, "BIN_DIR", None)
    except ImportError:
        return None


# Compiler flags per instruction-set level (x86-64 only): the kernels' inner loops are 64-byte vector blocks, one
# AVX-512 register, two AVX2 ones, four SSE2 ones (the x86-64 baseline, "generic").
ISA_FLAGS = {
    "avx512": ["-mavx2", "-mfma", "-mavx512f", "-mavx512bw", "-mavx512dq", "-mavx512vl"],
    "avx2": ["-mavx2", "-mfma"],
    "generic": [],
}


def cpu_isa() -> str:
    """The instruction-set level the extensions are built for: "avx512", "avx2" or "generic".

    It follows ``torch.backends.cpu.get_cpu_capability()``, the level torch's own CPU kernels run at on this machine
    (``ATEN_CPU_CAPABILITY=avx2`` or ``default`` lowers both); anything but x86-64 is "generic".
    """
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return "generic"
    try:
        capability = torch.backends.cpu.get_cpu_capability().lower()
    except Exception:  # an old or unusual torch build: the baseline is always safe
        return "generic"
    return capability if capability in ISA_FLAGS else "generic"


def headers_digest(folder: Path) -> str:
    """A digest of the headers (*.h) beside a source: torch rebuilds an extension when its sources or flags change, not
    its headers, so the digest goes into the flags."""
    digest = hashlib.sha256()
    for header in sorted(folder.glob("*.h")):
        digest.update(header.name.encode() + b"\0" + header.read_bytes())
    return digest.hexdigest()[:16]


def _tail(text: object, lines: int = 15) -> str:
    return "\n".join(str(text).strip().splitlines()[-lines:])


def _import_cpp_extension_load():
    """torch.utils.cpp_extension.load, imported without its "No CUDA runtime is found" log (irrelevant for .cpp)."""
    cpp_logger = logging.getLogger("torch.utils.cpp_extension")
    level = cpp_logger.level
    cpp_logger.setLevel(logging.ERROR)
    try:
        from torch.utils.cpp_extension import load
    finally:
        cpp_logger.setLevel(level)
    return load


class CppExtension:
    """One lazily built C++ CPU extension and the op namespace it registers.

    Args:
        name: extension name, e.g. "gsmsdr_rasterize_cpu"; built as <name>_<isa> (see `cpu_isa`).
        source: the .cpp file.
        namespace: the TORCH_LIBRARY namespace its ops live in, returned as `torch.ops.<namespace>`.
        what: what it is, for messages ("C++ rasterizer").
    """

    def __init__(self, name: str, source: Path, namespace: str, what: str) -> None:
        self.name = name
        self.source = Path(source)
        self.namespace = namespace
        self.what = what
        self._lock = threading.Lock()
        self._ops = None
        self._error: Optional[str] = None
        self._attempted = False
        self._fallback_warned = False

    def build_name(self) -> str:
        """<name>_<isa>: the extension built for this machine's instruction set."""
        return f"{self.name}_{cpu_isa()}"

    def build_directory(self) -> Path:
        """$TORCH_EXTENSIONS_DIR/<name>_<isa> or ~/.cache/gsmsdr_ns/torch_extensions/<torch version>/<name>_<isa>."""
        return extensions_root() / self.build_name()

    def _build(self):
        """Compile and load the extension; returns torch.ops.<namespace> or raises RuntimeError with the reason."""
        if not self.source.is_file():
            raise RuntimeError(f"C++ source not found: {self.source} (broken installation?)")
        cxx = find_compiler()
        if cxx is None:
            wanted = os.environ.get("CXX", "c++")
            raise RuntimeError(
                f"no C++ compiler found (set CXX or install g++): {wanted!r} is not an executable on PATH"
            )
        ninja = ninja_dir()
        if ninja is None:
            raise RuntimeError("ninja not found (pip install ninja); torch needs it to build C++ extensions")
        load = _import_cpp_extension_load()

        build_dir = self.build_directory()
        build_dir.mkdir(parents=True, exist_ok=True)
        old_path = os.environ.get("PATH")
        if ninja not in (old_path or "").split(os.pathsep):
            # torch runs `ninja` through PATH; a venv used without activation lacks it
            os.environ["PATH"] = ninja + (os.pathsep + old_path if old_path else "")
        try:
            load(
                name=self.build_name(),
                sources=[str(self.source)],
                extra_cflags=[
                    "-O3",
                    "-fopenmp",
                    *ISA_FLAGS[cpu_isa()],
                    f"-DGSMSDR_HEADERS_DIGEST={headers_digest(self.source.parent)}",
                ],
                extra_ldflags=["-fopenmp"],
                build_directory=str(build_dir),
                is_python_module=False,  # ops are registered with TORCH_LIBRARY
                verbose=False,
            )
        except Exception as exc:  # compiler errors, missing headers, linker failures
            raise RuntimeError(
                f"building the {self.what} in {build_dir} with {cxx!r} failed: {type(exc).__name__}: {_tail(exc)}"
            ) from exc
        finally:
            if old_path is None:
                os.environ.pop("PATH", None)
            else:
                os.environ["PATH"] = old_path
        return getattr(torch.ops, self.namespace)

    def load(self):
        """Build (once per process) and return the op namespace `torch.ops.<namespace>`.

        Raises:
            RuntimeError: the extension cannot be built; the message says what is missing.
        """
        with self._lock:
            if not self._attempted:
                self._attempted = True
                try:
                    self._ops = self._build()
                except Exception as exc:  # never retry a failed build in this process
                    self._error = str(exc)
            if self._ops is None:
                raise RuntimeError(self._error)
            return self._ops

    def available(self) -> bool:
        """True when the extension builds and loads. Never raises."""
        try:
            self.load()
            return True
        except Exception:
            return False

    def error(self) -> Optional[str]:
        """Why the extension is unavailable (None when it works). Never raises."""
        if self.available():
            return None
        return self._error or f"unknown error while loading the {self.what}"

    def backend_for(
        self, tensor: torch.Tensor, requested: str, unavailable: str, fallback: str, stacklevel: int = 2
    ) -> str:
        """The backend of an op with this extension as its CPU float32 / float64 kernel and a PyTorch twin elsewhere.

        "torch" when asked for, or for tensors the kernel does not take (another device or dtype); else
        :meth:`choose_backend` (its ``stacklevel`` as seen from the caller of this method).

        Raises:
            ValueError: ``requested`` is not "auto", "cpp" or "torch", or "cpp" with tensors the kernel does not take.
            RuntimeError: ``requested == "cpp"`` and the extension cannot be built.
        """
        if requested == "torch":
            return "torch"
        if requested not in ("auto", "cpp"):
            raise ValueError(f"backend: expected 'auto', 'cpp' or 'torch', got {requested!r}")
        if tensor.device.type != "cpu" or tensor.dtype not in (torch.float32, torch.float64):
            if requested == "cpp":
                raise ValueError(
                    f"backend='cpp' needs CPU float32/float64 tensors, got {tensor.dtype} on {tensor.device}"
                )
            return "torch"
        return self.choose_backend(requested, unavailable, fallback, stacklevel + 1)

    def choose_backend(
        self, requested: str, unavailable: str, fallback: str, stacklevel: int = 2
    ) -> Literal["cpp", "torch"]:
        """ "cpp" when the extension loads; else "torch", warning once per process why.

        `requested` is "auto" or "cpp" (callers handle "torch" and invalid values, whose messages differ); an
        explicit "cpp" raises instead of falling back.

        Args:
            unavailable: the subject of the messages, "C++ CPU rasterizer" in "the C++ CPU rasterizer is unavailable".
            fallback: what is used instead, "the slower PyTorch rasterizer" in "...; using <fallback>."
            stacklevel: the warning's stacklevel as seen from the caller of this method.

        Raises:
            RuntimeError: `requested == "cpp"` and the extension cannot be built.
        """
        if self.available():
            return "cpp"
        reason = self.error()
        if requested == "cpp":
            raise RuntimeError(f"the {unavailable} is unavailable: {reason}")
        if not self._fallback_warned:
            warnings.warn(
                f"gsmsdr: {unavailable} unavailable ({reason}); using {fallback}.",
                RuntimeWarning,
                stacklevel=stacklevel + 1,
            )
            self._fallback_warned = True
        return "torch"
