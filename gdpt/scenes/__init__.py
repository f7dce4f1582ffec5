"""Scenes: the one loader of every scene source (:mod:`.loading`: XML files, dicts,
``builtin:NAME``, ``random:SEED[:VIEW]``), and scenes built in code: built-in test scenes
(:mod:`.builtin`) and the procedural training-scene generator (:mod:`.procedural`, with its
knobs in :mod:`.procedural_config`, rooms and objects in :mod:`.procedural_layout` and materials
in :mod:`.procedural_materials`),
from the blocks in :mod:`.elements`.

Importing :mod:`gdpt.scenes` or :mod:`gdpt.scenes.loading` imports no Mitsuba (the loader sets
the variant first, :func:`gdpt.backend.ensure_variant`); the builders below are loaded on first
use. Every builder returns a Mitsuba 3 scene *dictionary* built in code (no files, no external
assets) for :func:`mitsuba.load_dict`. The contract shared by all scenes:

* an ``hdrfilm`` with a ``box`` reconstruction filter (gradient-domain rendering needs it; the
  film's default is gaussian), ``pixel_format='rgb'`` and the requested resolution;
* an ``independent`` sampler (its ``sample_count`` is a placeholder: pass ``spp`` to
  :func:`mitsuba.render`);
* **no integrator.** Mitsuba refuses to render a scene without one, so add it before loading,
  e.g. ``mi.load_dict({**scene, 'integrator': {'type': 'gdpt'}})``, or pass
  ``integrator=`` to :func:`mitsuba.render`;
* only the plugins listed in the project brief (diffuse with optional ``checkerboard``,
  (rough)conductor, (rough)plastic, dielectric, thindielectric, twosided; rectangle, cube, sphere,
  cylinder, disk; area, point, constant, envmap emitters; perspective and thinlens sensors),
  plus ``principled`` in the one scene that tests it;
* deterministic: the same arguments give an identical dictionary.

Conventions: +y is up, lengths are metres, transforms are ``mi.ScalarTransform4f``. A Mitsuba
variant must be set before calling any builder (transforms and bitmaps are variant types); the
code itself is variant-agnostic.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

#: Public name -> module that defines it (imported on first attribute access).
_LAZY: dict[str, str] = {
    "TEST_RESOLUTION": "gdpt.scenes.elements",
    "SceneDict": "gdpt.scenes.elements",
    "RandomSceneConfig": "gdpt.scenes.procedural_config",
    "builtin_names": "gdpt.scenes.builtin",
    "builtin_scene": "gdpt.scenes.builtin",
    "random_scene": "gdpt.scenes.procedural",
    "random_views": "gdpt.scenes.procedural",
}

__all__ = [
    "TEST_RESOLUTION",
    "RandomSceneConfig",
    "SceneDict",
    "builtin_names",
    "builtin_scene",
    "random_scene",
    "random_views",
]

if TYPE_CHECKING:
    from gdpt.scenes.builtin import builtin_names, builtin_scene
    from gdpt.scenes.elements import TEST_RESOLUTION, SceneDict
    from gdpt.scenes.procedural import random_scene, random_views
    from gdpt.scenes.procedural_config import RandomSceneConfig


def __getattr__(name: str) -> Any:
    """Import the builders lazily (PEP 562); submodules import as usual."""
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})
