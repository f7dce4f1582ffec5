"""Callable modules: ``gdpt.render(...)`` and ``gdpt.reconstruct(...)`` next to their packages.

``gdpt.render`` is both the module :mod:`gdpt.render` and the function
:func:`gdpt.render.render`; ``gdpt.reconstruct`` is both the subpackage of reconstruction
algorithms and the dispatcher :func:`gdpt.reconstruction.reconstruct`. Python binds a submodule
to its parent's attribute on import, which would shadow a function of the same name, so the
module object itself is made callable.
"""

from __future__ import annotations

import sys
import types
from collections.abc import Callable
from typing import Any


def make_callable(module_name: str, func: Callable[..., Any]) -> None:
    """Make ``sys.modules[module_name]`` callable as ``func`` (idempotent)."""
    module = sys.modules[module_name]

    class CallableModule(types.ModuleType):
        __call__ = staticmethod(func)

    CallableModule.__doc__ = module.__doc__
    module.__class__ = CallableModule
