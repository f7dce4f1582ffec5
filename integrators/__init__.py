"""Mitsuba 3 integrator plugins ``gdpt`` and ``gdpt_rr`` (Dr.Jit only; no torch).

Importing this package registers nothing. :func:`register` (called by ``gdpt.set_variant``)
imports the plugin modules for the active JIT variant, which registers them with Mitsuba; it
re-imports them after a variant change so the classes bind the new variant's types.
"""

from __future__ import annotations

import importlib
import sys

_MODULES = ("common", "shifts", "gdpt", "gdpt_rr")
_registered_variant: str | None = None

#: Names of the plugins this package provides (the integrators that produce gradient buffers).
PLUGINS = ("gdpt", "gdpt_rr")


def register() -> None:
    """Register ``gdpt`` and ``gdpt_rr`` for the current Mitsuba variant (idempotent).

    Raises:
        RuntimeError: no variant is set, or it is not a JIT (``llvm_*``/``cuda_*``) variant.
    """
    global _registered_variant  # noqa: PLW0603 (one registration per variant)
    import mitsuba as mi

    variant = mi.variant()
    if variant is None:
        raise RuntimeError("set a Mitsuba variant first (gdpt.set_variant())")
    if not (variant.startswith("llvm_") or variant.startswith("cuda_")):
        raise RuntimeError(f"gdpt integrators need a JIT variant (llvm_*/cuda_*), not '{variant}'")
    if _registered_variant == variant:
        return
    for name in _MODULES:
        full = f"{__name__}.{name}"
        if full in sys.modules:
            importlib.reload(sys.modules[full])
        else:
            importlib.import_module(full)
    _registered_variant = variant
