"""gdpt.backend: variant choice, GDPT_VARIANT override, libLLVM discovery, plugin registration.

Tests that depend on what happens *before* the first Dr.Jit import run in a fresh interpreter.
The in-process tests leave the variant they found (or ``llvm_ad_rgb``) active afterwards.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from gdpt import backend


def run_python(code: str, **env: str | None) -> str:
    """Run ``code`` in a fresh interpreter (with ``env`` changes) and return its stdout."""
    environment = {k: v for k, v in os.environ.items() if k not in env}
    environment.update({k: v for k, v in env.items() if v is not None})
    result = subprocess.run(
        [sys.executable, "-c", code],
        check=False,
        env=environment,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    return result.stdout.strip()


@pytest.fixture(autouse=True)
def register_calls(monkeypatch):
    """Replace ``gdpt.integrators.register`` by a recorder (the integrators are tested apart)."""
    import gdpt.integrators

    calls: list[str | None] = []

    def record() -> None:
        import mitsuba as mi

        calls.append(mi.variant())

    monkeypatch.setattr(gdpt.integrators, "register", record, raising=False)
    return calls


@pytest.fixture
def restore_variant():
    """Re-activate the variant that was active before the test."""
    import mitsuba as mi

    before = mi.variant()
    yield
    if before is not None and mi.variant() != before:
        mi.set_variant(before)


def test_invalid_name_lists_valid_variants():
    with pytest.raises(ValueError, match=r"'foo_rgb'.*cuda_ad_rgb, llvm_ad_rgb"):
        backend.set_variant("foo_rgb")


def test_invalid_env_variant_names_the_variable(monkeypatch):
    monkeypatch.setenv("GDPT_VARIANT", "scalar_rgb")
    with pytest.raises(ValueError, match=r"\$GDPT_VARIANT.*'scalar_rgb'.*llvm_ad_rgb"):
        backend.set_variant()


def test_auto_choice_and_torch_device(monkeypatch, restore_variant):
    import drjit as dr
    import mitsuba as mi

    monkeypatch.delenv("GDPT_VARIANT", raising=False)
    expected = "cuda_ad_rgb" if dr.has_backend(dr.JitBackend.CUDA) else "llvm_ad_rgb"
    assert backend.set_variant() == expected
    assert mi.variant() == expected
    device = backend.torch_device()
    assert device.type == ("cuda" if expected.startswith("cuda") else "cpu")
    assert mi.TensorXf([1.0, 2.0]).torch().device == device


def test_env_override(monkeypatch, restore_variant):
    import mitsuba as mi

    monkeypatch.setenv("GDPT_VARIANT", "llvm_ad_rgb")
    assert backend.set_variant() == "llvm_ad_rgb"
    assert mi.variant() == "llvm_ad_rgb"
    assert str(backend.torch_device()) == "cpu"


def test_unavailable_cuda_is_a_clear_error(restore_variant):
    import drjit as dr

    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("a CUDA device is present")
    with pytest.raises(RuntimeError, match=r"'cuda_ad_rgb'.*no CUDA device"):
        backend.set_variant("cuda_ad_rgb")


def test_no_backend_says_what_to_install(monkeypatch):
    import drjit as dr

    monkeypatch.delenv("GDPT_VARIANT", raising=False)
    monkeypatch.setattr(dr, "has_backend", lambda _backend: False)
    with pytest.raises(RuntimeError, match=r"no Dr\.Jit backend.*libllvm19.*DRJIT_LIBLLVM_PATH"):
        backend.set_variant()


def test_registers_plugins_and_reregisters_on_variant_change(register_calls, restore_variant):
    import mitsuba as mi

    calls = register_calls
    calls.clear()
    assert backend.set_variant("llvm_ad_rgb") == "llvm_ad_rgb"
    assert calls == ["llvm_ad_rgb"]
    backend.set_variant("llvm_ad_rgb")  # idempotent; the callback is installed only once
    mi.set_variant("scalar_rgb")  # not a JIT variant: nothing to register
    mi.set_variant("llvm_ad_mono")
    mi.set_variant("llvm_ad_rgb")
    assert calls == ["llvm_ad_rgb", "llvm_ad_rgb", "llvm_ad_mono", "llvm_ad_rgb"]


def test_torch_device_needs_a_variant():
    code = (
        "from gdpt import backend\n"
        "try:\n    backend.torch_device()\nexcept RuntimeError as e:\n    print(e)\n"
    )
    assert "set_variant" in run_python(code)


def test_libllvm_is_located_before_the_first_drjit_import():
    found = backend.find_libllvm()
    if found is None:
        pytest.skip("no libLLVM >= 16 in the standard locations")
    code = (
        "import os, sys, gdpt\n"
        "assert not {'drjit', 'mitsuba', 'torch'} & set(sys.modules), 'import gdpt is heavy'\n"
        "print(gdpt.set_variant('llvm_ad_rgb'), os.environ['DRJIT_LIBLLVM_PATH'])\n"
    )
    assert run_python(code, DRJIT_LIBLLVM_PATH=None, GDPT_VARIANT=None) == f"llvm_ad_rgb {found}"


def test_existing_libllvm_path_is_respected():
    found = backend.find_libllvm()
    if found is None:
        pytest.skip("no libLLVM >= 16 in the standard locations")
    other = str(Path(found).resolve())  # a different spelling of a valid library
    code = (
        "import os, gdpt\n"
        "gdpt.set_variant('llvm_ad_rgb')\n"
        "print(os.environ['DRJIT_LIBLLVM_PATH'])\n"
    )
    assert run_python(code, DRJIT_LIBLLVM_PATH=other, GDPT_VARIANT=None) == other
    stale = run_python(code, DRJIT_LIBLLVM_PATH="/nonexistent/libLLVM.so", GDPT_VARIANT=None)
    assert stale == found


@pytest.fixture
def cuda_drjit_cpu_torch(monkeypatch):
    """Dr.Jit reports both backends, torch has no CUDA (a CPU wheel on a GPU machine)."""
    import drjit as dr
    import torch

    monkeypatch.delenv("GDPT_VARIANT", raising=False)
    monkeypatch.setattr(dr, "has_backend", lambda _backend: True)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


@pytest.mark.usefixtures("cuda_drjit_cpu_torch", "restore_variant")
def test_auto_choice_takes_llvm_when_torch_has_no_cuda():
    import mitsuba as mi

    with pytest.warns(UserWarning, match=r"llvm_ad_rgb \(CPU\): Dr\.Jit has a CUDA device but"):
        assert backend.set_variant() == "llvm_ad_rgb"
    assert mi.variant() == "llvm_ad_rgb"


@pytest.mark.usefixtures("cuda_drjit_cpu_torch", "restore_variant")
@pytest.mark.parametrize("env", [False, True])
def test_explicit_cuda_with_cpu_torch_is_a_clear_error(monkeypatch, env):
    import mitsuba as mi

    before = mi.variant()
    if env:
        monkeypatch.setenv("GDPT_VARIANT", "cuda_ad_rgb")
    source = r"\$GDPT_VARIANT" if env else r"set_variant\(\)"
    with pytest.raises(RuntimeError, match=source + r": 'cuda_ad_rgb' needs a CUDA build of torch"):
        backend.set_variant(None if env else "cuda_ad_rgb")
    assert mi.variant() == before
