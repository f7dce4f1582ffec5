"""Choose and activate the Mitsuba variant gdpt runs on, and the matching torch device.

gdpt runs on ``cuda_ad_rgb`` when Dr.Jit sees a CUDA device and the installed torch is a CUDA
build (the buffers go from Dr.Jit to torch through DLPack, without a copy, so both must hold
them on the GPU), and on ``llvm_ad_rgb`` otherwise; with a CUDA device but a CPU-only torch the
automatic choice takes ``llvm_ad_rgb`` and says so in a warning. The environment variable
``GDPT_VARIANT`` overrides the automatic choice.

Dr.Jit's LLVM backend loads a system ``libLLVM`` when ``drjit`` is first imported, and it needs
LLVM >= 16 (some distributions also ship older versions that it would otherwise pick up).
:func:`set_variant` therefore locates a suitable library *before* importing ``drjit`` and exports
it as ``DRJIT_LIBLLVM_PATH``; a path that is already set and exists is respected. The search
mirrors ``tools/ensure_llvm.sh``.

After activating a variant, :func:`set_variant` registers the gdpt integrators
(``gdpt.integrators.register()``) and installs a Mitsuba variant callback once, so that a later
``mi.set_variant(...)`` to another JIT variant registers them again for that variant's types.
"""

from __future__ import annotations

import importlib
import os
import sys
import warnings
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

from gdpt.interrupt import interrupts_deferred

if TYPE_CHECKING:
    import torch

#: Environment variable that overrides the automatic variant choice.
ENV_VARIANT = "GDPT_VARIANT"
#: Environment variable Dr.Jit reads to locate libLLVM.
ENV_LIBLLVM = "DRJIT_LIBLLVM_PATH"
#: Variants gdpt supports, in order of preference.
SUPPORTED_VARIANTS: tuple[str, ...] = ("cuda_ad_rgb", "llvm_ad_rgb")

_LLVM_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib",
    "/usr/local/lib",
    "/usr/lib64",
)
_LLVM_VERSIONS = (21, 20, 19, 18, 17, 16)
_LLVM_NAMES = ("libLLVM-{v}.so", "libLLVM.so.{v}.1", "libLLVM-{v}.so.1", "llvm-{v}/lib/libLLVM.so")
_INSTALL_HINT = (
    "install LLVM >= 16 (Debian/Ubuntu: 'apt-get install libllvm19', or run "
    "tools/ensure_llvm.sh) or point DRJIT_LIBLLVM_PATH at a libLLVM >= 16 shared library; "
    "for the CUDA backend install an NVIDIA driver"
)

_TORCH_CPU = (
    "the installed torch has no CUDA (a CPU-only build, or no driver it can use); install a "
    "CUDA build (e.g. make TORCH_INDEX=https://download.pytorch.org/whl/cu126, docs/mitsuba.md)"
)

_callback_installed = False


def find_libllvm() -> str | None:
    """Search the usual system directories for a libLLVM >= 16 shared library.

    Returns:
        The path of the newest library found, or ``None``.
    """
    for directory in _LLVM_DIRS:
        for version in _LLVM_VERSIONS:
            for pattern in _LLVM_NAMES:
                candidate = Path(directory) / pattern.format(v=version)
                if candidate.exists():
                    return str(candidate)
    return None


def ensure_libllvm() -> str | None:
    """Export ``DRJIT_LIBLLVM_PATH`` before Dr.Jit is first imported, if it needs setting.

    An existing ``DRJIT_LIBLLVM_PATH`` that names an existing file is kept. Once ``drjit`` has
    been imported the variable no longer has any effect, so it is left alone.

    Returns:
        The libLLVM path Dr.Jit will use, or ``None`` if none is known (Dr.Jit then falls back
        to its own search).
    """
    current = os.environ.get(ENV_LIBLLVM)
    if (current and Path(current).exists()) or "drjit" in sys.modules:
        return current
    found = find_libllvm()
    if found is not None:
        os.environ[ENV_LIBLLVM] = found
    return found


def set_variant(name: str | None = None) -> str:
    """Activate a Mitsuba variant and register the gdpt integrators for it.

    Precedence: the ``name`` argument, then ``$GDPT_VARIANT``, then ``cuda_ad_rgb`` if Dr.Jit
    has a CUDA device and torch is a CUDA build, else ``llvm_ad_rgb`` (with a ``UserWarning``
    when only torch lacks CUDA). Calling it again is cheap and idempotent.

    Args:
        name (str | None): a variant from :data:`SUPPORTED_VARIANTS`, or ``None`` to choose
            automatically.

    Returns:
        The active variant name.

    Raises:
        ValueError: ``name`` (or ``$GDPT_VARIANT``) is not a supported variant.
        RuntimeError: the requested backend, or no backend at all, is available, or
            ``cuda_ad_rgb`` is requested and torch has no CUDA.
    """
    with interrupts_deferred():  # a Ctrl-C inside Mitsuba's module set-up would abort
        return _set_variant(name)


def _set_variant(name: str | None) -> str:
    source = "set_variant()"
    if name is None and os.environ.get(ENV_VARIANT):
        name, source = os.environ[ENV_VARIANT], f"${ENV_VARIANT}"
    if name is not None and name not in SUPPORTED_VARIANTS:
        raise ValueError(
            f"{source}: unsupported variant {name!r}; valid variants: "
            + ", ".join(SUPPORTED_VARIANTS)
        )
    ensure_libllvm()
    import drjit as dr

    has_cuda = bool(dr.has_backend(dr.JitBackend.CUDA))
    has_llvm = bool(dr.has_backend(dr.JitBackend.LLVM))
    if name is None:
        if not (has_cuda or has_llvm):
            raise RuntimeError(
                f"gdpt found no Dr.Jit backend (neither CUDA nor LLVM): {_INSTALL_HINT}"
            )
        name = "cuda_ad_rgb" if has_cuda else "llvm_ad_rgb"
        if has_cuda and has_llvm and not _torch_has_cuda():
            warnings.warn(
                f"gdpt uses llvm_ad_rgb (CPU): Dr.Jit has a CUDA device but {_TORCH_CPU}",
                stacklevel=3,
            )
            name = "llvm_ad_rgb"
    elif name.startswith("cuda_") and not has_cuda:
        raise RuntimeError(
            f"{source} requested {name!r} but Dr.Jit found no CUDA device/driver; "
            f"use 'llvm_ad_rgb' or unset ${ENV_VARIANT}"
        )
    elif name.startswith("llvm_") and not has_llvm:
        raise RuntimeError(
            f"{source} requested {name!r} but Dr.Jit cannot load libLLVM: {_INSTALL_HINT}"
        )
    if name.startswith("cuda_") and not _torch_has_cuda():
        raise RuntimeError(
            f"{source}: {name!r} needs a CUDA build of torch, but {_TORCH_CPU}, or use "
            "'llvm_ad_rgb'"
        )

    import mitsuba as mi

    mi.set_variant(name)
    _register_plugins()
    _install_variant_callback(mi)
    return name


def _torch_has_cuda() -> bool:
    """Whether torch can use a CUDA device (imports torch)."""
    import torch

    return bool(torch.cuda.is_available())


def ensure_variant() -> str:
    """Keep the active Mitsuba variant (set the default one if none) with the plugins registered.

    Every function that loads or renders a scene calls this first; an explicit
    :func:`set_variant` before it wins.

    Returns:
        The active variant name.

    Raises:
        ValueError: the active variant is not one of :data:`SUPPORTED_VARIANTS` (e.g. a
            spectral one set with ``mi.set_variant``).
    """
    with interrupts_deferred():  # a Ctrl-C inside Mitsuba's module set-up would abort
        import mitsuba as mi

        if mi.variant() is None:
            return _set_variant(None)
        if mi.variant() not in SUPPORTED_VARIANTS:
            raise ValueError(
                f"the Mitsuba variant {mi.variant()!r} is not supported; gdpt renders RGB "
                f"buffers on {', '.join(SUPPORTED_VARIANTS)} (gdpt.set_variant())"
            )
        _register_plugins()
        return mi.variant()


def torch_device() -> torch.device:
    """The torch device that holds the data of the active Mitsuba variant.

    Returns:
        ``cpu`` for ``llvm_*`` variants, ``cuda:N`` (Dr.Jit's device) for ``cuda_*`` variants.

    Raises:
        RuntimeError: no Mitsuba variant has been set yet.
    """
    import torch

    mi = sys.modules.get("mitsuba")
    variant = mi.variant() if mi is not None else None
    if variant is None:
        raise RuntimeError("no Mitsuba variant is active; call gdpt.set_variant() first")
    if variant.startswith("cuda_"):
        # DLPack reports (device_type, device_id) of the array's storage.
        _, device_id = mi.Float(0).__dlpack_device__()
        return torch.device("cuda", int(device_id))
    return torch.device("cpu")


def _register_plugins() -> None:
    """Call ``gdpt.integrators.register()`` if the integrators package provides it."""
    register = getattr(importlib.import_module("gdpt.integrators"), "register", None)
    if register is not None:
        register()


def _on_variant_change(old: str | None, new: str | None) -> None:
    """Mitsuba variant callback: re-register the integrators for a new JIT variant."""
    if new is not None and new.startswith(("llvm_", "cuda_")):
        _register_plugins()


def _install_variant_callback(mi: ModuleType) -> None:
    """Install :func:`_on_variant_change` as a Mitsuba variant callback (once per process)."""
    global _callback_installed  # noqa: PLW0603 (one flag per process)
    if not _callback_installed:
        mi.detail.add_variant_callback(_on_variant_change)
        _callback_installed = True
