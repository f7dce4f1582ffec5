"""gdpt: gradient-domain path tracing for Mitsuba 3, with Poisson and neural reconstruction.

Importing :mod:`gdpt` is light and has no side effects: it imports neither Mitsuba, Dr.Jit nor
torch, sets no variant and registers no plugin. The public names below are loaded on first use::

    import gdpt

    gdpt.set_variant()                      # cuda_ad_rgb if available, else llvm_ad_rgb
    buffers = gdpt.render("scene.xml", spp=64)   # or gdpt.load_buffers("render.exr")
    image = gdpt.reconstruct(buffers, method="l1", alpha=0.2)

``gdpt.reconstruct`` is both the subpackage of reconstruction algorithms (Poisson solvers,
networks) and, called, the dispatcher :func:`gdpt.reconstruction.reconstruct`; likewise
``gdpt.render`` is the module and, called, :func:`gdpt.render.render` (see ``gdpt._modules``).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from gdpt.version import __version__

#: Public name -> module that defines it (imported on first attribute access).
_LAZY: dict[str, str] = {
    "GradientBuffers": "gdpt.buffers",
    "load_buffers": "gdpt.exr",
    "save_buffers": "gdpt.exr",
    "set_variant": "gdpt.backend",
    "render": "gdpt.render",
    "render_and_denoise": "gdpt.render",
}
#: Submodules reachable as attributes right after ``import gdpt``.
_SUBMODULES = ("backend", "buffers", "cli", "exr", "images", "reconstruction")

__all__ = ["__version__", *_LAZY]

if TYPE_CHECKING:
    from gdpt.backend import set_variant
    from gdpt.buffers import GradientBuffers
    from gdpt.exr import load_buffers, save_buffers
    from gdpt.render import render, render_and_denoise


def _dispatch_reconstruct(*args: Any, **kwargs: Any) -> Any:
    from gdpt.reconstruction import reconstruct

    return reconstruct(*args, **kwargs)


def _bind_reconstruct() -> None:
    import gdpt.reconstruct  # light: the subpackage's __init__ imports nothing
    from gdpt._modules import make_callable

    make_callable("gdpt.reconstruct", _dispatch_reconstruct)


_bind_reconstruct()


def __getattr__(name: str) -> Any:
    """Import public names and submodules lazily (PEP 562)."""
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
    elif name in _SUBMODULES:
        value = importlib.import_module(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY, *_SUBMODULES})
