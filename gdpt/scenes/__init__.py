"""Scenes built in code: built-in test scenes (:mod:`.builtin`) and the procedural
training-scene generator (:mod:`.procedural`), from the blocks in :mod:`.elements`.

Every function here returns a Mitsuba 3 scene *dictionary* built in code (no files, no external
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
variant must be set before calling any function (transforms and bitmaps are variant types); the
code itself is variant-agnostic.
"""

from gdpt.scenes.builtin import builtin_names, builtin_scene
from gdpt.scenes.elements import TEST_RESOLUTION, SceneDict
from gdpt.scenes.procedural import RandomSceneConfig, random_scene, random_views

__all__ = [
    "TEST_RESOLUTION",
    "RandomSceneConfig",
    "SceneDict",
    "builtin_names",
    "builtin_scene",
    "random_scene",
    "random_views",
]
