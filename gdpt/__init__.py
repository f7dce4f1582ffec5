"""gdpt: gradient-domain path tracing for Mitsuba 3, with Poisson and neural reconstruction.

Importing :mod:`gdpt` is light and has no side effects: it imports neither Mitsuba, Dr.Jit nor
torch, sets no variant and registers no plugin. The public functions below are loaded on first
use; submodules keep their own names (no function shadows a module)::

    import gdpt

    gdpt.set_variant()                      # cuda_ad_rgb if available, else llvm_ad_rgb
    buffers = gdpt.render("scene.xml", spp=64)   # or gdpt.load_buffers("render.exr")
    image = gdpt.render_and_denoise("scene.xml", spp=64, method="l1").image
    image = gdpt.reconstruct_image(buffers, method="oidn")   # reconstruct existing buffers
    image = gdpt.render_differentiable(scene, params, spp=4)  # mi.TensorXf in the AD graph
    buffers = gdpt.buffers_from_aovs(mi.render(scene), scene.integrator())  # gdpt plugin in XML

:func:`reconstruct_image` is the one reconstruction call (methods: :data:`gdpt.methods.METHODS`);
``gdpt.reconstruct`` is the subpackage of reconstruction algorithms (Poisson solvers, networks,
losses).

The pipeline, one module per stage: :mod:`gdpt.scenes.loading` (load a scene) ->
:mod:`gdpt.rendering` (integrator -> :class:`~gdpt.buffers.GradientBuffers`) ->
:mod:`gdpt.methods` (reconstruction methods) -> :mod:`gdpt.study` (equal-time evaluation);
:mod:`gdpt.pipeline` renders and reconstructs in one call (``method="auto"``:
:mod:`gdpt.auto_route`);
:mod:`gdpt.differentiable` renders and reconstructs inside Mitsuba's AD graph;
:mod:`gdpt.training` trains the networks, :mod:`gdpt.io` reads and writes files.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from gdpt.version import __version__

#: Public name -> module that defines it (imported on first attribute access).
_LAZY: dict[str, str] = {
    "GradientBuffers": "gdpt.buffers",
    "advise": "gdpt.advice",
    "buffers_from_aovs": "gdpt.aovs",
    "load_buffers": "gdpt.io.exr",
    "save_buffers": "gdpt.io.exr",
    "load_scene": "gdpt.scenes.loading",
    "set_variant": "gdpt.backend",
    "render": "gdpt.rendering",
    "render_and_denoise": "gdpt.pipeline",
    "render_differentiable": "gdpt.differentiable",
    "reconstruct_image": "gdpt.methods",
    "release_scene": "gdpt.pipeline",
}

__all__ = [
    "GradientBuffers",
    "__version__",
    "advise",
    "buffers_from_aovs",
    "load_buffers",
    "load_scene",
    "reconstruct_image",
    "release_scene",
    "render",
    "render_and_denoise",
    "render_differentiable",
    "save_buffers",
    "set_variant",
]

if TYPE_CHECKING:
    from gdpt.advice import advise
    from gdpt.aovs import buffers_from_aovs
    from gdpt.backend import set_variant
    from gdpt.buffers import GradientBuffers
    from gdpt.differentiable import render_differentiable
    from gdpt.io.exr import load_buffers, save_buffers
    from gdpt.methods import reconstruct_image
    from gdpt.pipeline import release_scene, render_and_denoise
    from gdpt.rendering import render
    from gdpt.scenes.loading import load_scene


def __getattr__(name: str) -> Any:
    """Import the public functions lazily (PEP 562); submodules import as usual."""
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})
