"""Rendering gradient-domain buffers in-process: scene -> :class:`GradientBuffers`.

:func:`render` samples a scene (loaded by :func:`gdpt.scenes.loading.load_scene`) with ``gdpt``
or ``gdpt_rr`` (:func:`gdpt.pipeline.render_and_denoise` also reconstructs).

The integrator's output tensor is handed to torch through DLPack without a copy (on a CUDA
variant it stays on the GPU); the buffers are channel slices (views) of that one tensor.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from typing import Any

from gdpt.aovs import buffers_from_aovs
from gdpt.buffers import GradientBuffers, pool_primal
from gdpt.integrators import PLUGINS
from gdpt.scenes.loading import load_scene


def make_integrator(name: str = "gdpt", **props: Any):
    """Instantiate ``gdpt`` / ``gdpt_rr`` with properties (``max_depth``, ``gradients``, ...)."""
    import mitsuba as mi

    if name not in PLUGINS:
        raise ValueError(f"unknown integrator {name!r}; valid: {', '.join(PLUGINS)}")
    return mi.load_dict({"type": name, **props})


def shared_integrator(scene: Any, name: str = "gdpt", **props: Any):
    """The integrator :func:`render` uses for ``scene`` (an ``mi.Scene``), ``name`` and
    ``props``: one instance per variant, scene object, plugin and properties (the 8 most
    recently used are kept, with their scenes), so a repeated render replays its frozen passes
    (``dr.freeze``; ``docs/performance.md``). The scene object is part of the key: a recording
    replayed on another ``mi.Scene`` of the same layout is not guaranteed to give the same
    images (``docs/architecture.md``). Properties must be hashable (numbers, booleans,
    strings).
    """
    import mitsuba as mi

    key = (mi.variant(), id(scene), name, tuple(sorted(props.items())))
    if key in _SHARED:
        _SHARED.move_to_end(key)
    else:
        _SHARED[key] = (scene, make_integrator(name, **props))  # the scene keeps its id unique
        while len(_SHARED) > _SHARED_SIZE:
            _SHARED.popitem(last=False)
    return _SHARED[key][1]


#: ``(variant, id(scene), plugin, properties) -> (scene, integrator)``, least recently used first.
_SHARED: OrderedDict[tuple, tuple[Any, Any]] = OrderedDict()
_SHARED_SIZE = 8


#: Mixed into the seed of the primal-only render that ``render(..., primal_spp=N)`` pools in, so
#: that its samples are independent of the gradient render's (the integrators derive every pass
#: seed from ``seed``).
PRIMAL_SEED_SALT = 0x7F4A7C15


def render(
    scene: Any,
    *,
    spp: int,
    seed: int = 0,
    integrator: str | Any | None = None,
    progress: bool = False,
    primal_spp: int = 0,
    **props: Any,
) -> GradientBuffers:
    """Render primal, gradients and features of ``scene``.

    Args:
        scene: ``mi.Scene``, path to a Mitsuba XML file, or a scene dict. Its film must use a
            box pixel filter.
        spp (int): samples per pixel (rendered in passes of bounded size).
        seed (int): random seed; different seeds give independent renders.
        integrator: ``None`` (use the scene's integrator if it is ``gdpt``/``gdpt_rr``, else
            ``gdpt``), a plugin name, or an integrator instance; a named one is shared between
            calls with the same ``mi.Scene`` and properties (:func:`shared_integrator`).
        progress (bool): show a progress bar over the passes.
        primal_spp (int): if > 0, also render this many plain path samples per pixel (the same
            integrator with ``gradients=False``, about the cost of a ``path`` sample, seed
            ``seed ^ PRIMAL_SEED_SALT``) and pool them into the primal
            (:func:`gdpt.buffers.pool_primal`); ``dx``/``dy`` keep ``spp`` samples. The
            features then come from the plain samples alone: the gradient pass runs with
            ``features=False`` (features cost 5-20% of a gradient sample). Needs an
            integrator with gradients.
        **props: integrator properties when one is created (``max_depth``, ``gradients``,
            ``features``, ``variance``, ...).

    Returns:
        GradientBuffers: float32 HWC views of one tensor on the variant's device (with
        ``primal_spp``: a pooled copy, see :func:`~gdpt.buffers.pool_primal`), with ``spp``
        and ``metadata`` (integrator, seed, render seconds, and ``guard_counts``: how often
        each numerical guard of the integrator fired) filled in.

    Raises:
        ValueError: ``spp < 1``, ``primal_spp < 0``, or ``primal_spp`` with an integrator
            whose gradients are off.
    """
    from gdpt.integrators.common import GradientIntegratorBase

    scene = load_scene(scene)
    if integrator is None:
        integrator = scene.integrator()
        if not isinstance(integrator, GradientIntegratorBase) or props:
            integrator = shared_integrator(scene, "gdpt", **props)
    elif isinstance(integrator, str):
        integrator = shared_integrator(scene, integrator, **props)
    elif not isinstance(integrator, GradientIntegratorBase):
        raise TypeError(f"integrator must be gdpt or gdpt_rr, got {type(integrator).__name__}")
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    if primal_spp < 0:
        raise ValueError(f"primal_spp must be >= 0, got {primal_spp}")
    if primal_spp and not integrator.gradients:
        raise ValueError(
            f"primal_spp={primal_spp} pools plain path samples into a gradient render, but "
            f"this {integrator.plugin_name} integrator has gradients=false"
        )

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=spp + primal_spp, unit="spp", desc="render", leave=False)
    try:
        if primal_spp:
            buffers = pool_primal(
                _render_one(_twin(integrator, scene, features=False), scene, spp, seed, bar),
                _render_one(
                    _twin(integrator, scene, gradients=False),
                    scene,
                    primal_spp,
                    (int(seed) ^ PRIMAL_SEED_SALT) & 0xFFFFFFFF,
                    bar,
                    start=spp,
                ),
            )
        else:
            buffers = _render_one(integrator, scene, spp, seed, bar)
    finally:
        if bar is not None:
            bar.close()
    return buffers


def _twin(integrator: Any, scene: Any, **changes: Any) -> Any:
    """``integrator`` itself if ``changes`` are its settings already, else the shared integrator
    with its properties and ``changes``."""
    props = integrator.properties()
    if all(props[k] == v for k, v in changes.items()):
        return integrator
    props = {**props, **changes}
    return shared_integrator(scene, props.pop("type"), **props)


def _render_one(integrator, scene, spp: int, seed: int, bar, start: int = 0) -> GradientBuffers:
    """One ``integrator.render`` as zero-copy :class:`GradientBuffers` (``bar``: an optional
    tqdm bar advanced from ``start``)."""
    import drjit as dr

    if bar is not None:
        integrator.pass_callback = lambda done, total: bar.update(start + done - bar.n)
    try:
        begin = time.perf_counter()
        out = integrator.render(scene, seed=seed, spp=spp)
        dr.eval(out)
        dr.sync_thread()
        seconds = time.perf_counter() - begin
    finally:
        integrator.pass_callback = None

    buffers = buffers_from_aovs(out, integrator, seed=seed, spp=spp)
    buffers.metadata["render_seconds"] = seconds
    return buffers
