"""The CUDA path's set-up check: a clear error naming what is missing when gsplat's CUDA backend cannot load.

No GPU exists here, so gsplat's backend module is replaced by stand-ins (the only mock in this file: importing the
real module would start a CUDA build)."""

from __future__ import annotations

import sys
import types

import pytest

from gsmsdr_ns.render import gsplat_backend
from gsmsdr_ns.render.gsplat_backend import GsplatUnavailableError, require_gsplat_cuda


@pytest.fixture
def fake_backend(monkeypatch):
    """Install a stand-in ``gsplat.cuda._backend`` (with the given ``_C``) and clear the cached check."""

    def install(compiled=None, import_error: Exception | None = None):
        gsplat_backend.gsplat_cuda_problem.cache_clear()
        if import_error is not None:

            def failing_import(name, *args, **kwargs):
                if name == "gsplat.cuda._backend":
                    raise import_error
                return original(name, *args, **kwargs)

            original = gsplat_backend.importlib.import_module
            monkeypatch.setattr(gsplat_backend.importlib, "import_module", failing_import)
        else:
            module = types.ModuleType("gsplat.cuda._backend")
            module._C = compiled
            monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", module)

    yield install
    gsplat_backend.gsplat_cuda_problem.cache_clear()


def test_missing_nvcc_is_named_with_the_fix(fake_backend, monkeypatch):
    fake_backend(compiled=None)
    monkeypatch.setattr(gsplat_backend.shutil, "which", lambda name: None)
    with pytest.raises(GsplatUnavailableError, match="`nvcc` was not found on PATH") as info:
        require_gsplat_cuda()
    assert "--machine.device-type cpu" in str(info.value) and "CUDA toolkit" in str(info.value)


def test_failed_build_is_reported_with_its_cause(fake_backend):
    fake_backend(import_error=RuntimeError("Error building extension 'gsplat_cuda'"))
    with pytest.raises(GsplatUnavailableError, match="Error building extension 'gsplat_cuda'"):
        require_gsplat_cuda()


def test_loaded_backend_passes_and_the_check_is_cached(fake_backend, monkeypatch):
    fake_backend(compiled=object())
    require_gsplat_cuda()
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", types.ModuleType("gsplat.cuda._backend"))
    require_gsplat_cuda()  # cached: the replaced module (no _C) is not looked at again
