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
    """Instantiate ``gdpt`` / ``gdpt_rr`` with properties (``max_depth``, ``gradients``, ...).

    Raises:
        ValueError: an unknown plugin, an unknown property or an invalid value (one line,
            checked against :data:`gdpt.integrators.properties.PROPERTIES` before Mitsuba
            loads the plugin).
    """
    import mitsuba as mi

    from gdpt.integrators.properties import PROPERTIES, checked

    if name not in PLUGINS:
        raise ValueError(f"unknown integrator {name!r}; valid: {', '.join(PLUGINS)}")
    if unknown := [k for k in props if k not in PROPERTIES]:
        raise ValueError(
            f"unknown {name} integrator property {', '.join(map(repr, unknown))}; valid: "
            + ", ".join(PROPERTIES)
        )
    return mi.load_dict({"type": name, **{k: checked(name, k, v) for k, v in props.items()}})


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


def forget_integrators(scene: Any) -> None:
    """Drop the integrators :func:`shared_integrator` keeps for ``scene`` (and its reference to
    the scene)."""
    for key in [k for k, (kept, _) in _SHARED.items() if kept is scene]:
        del _SHARED[key]


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
    gradient_mask: Any = None,
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
        gradient_mask: ``None`` (offsets everywhere) or an ``(H, W)`` bool torch tensor or
            numpy array over the film's (crop) pixels, no tiles: the samples of a masked pixel
            trace the four offset paths, the others plain paths, each group on its own
            compacted wavefront (work shrinks with the mask). The primal, features, variances
            and halves cover every pixel. A gradient is traced iff both of its pixels are
            masked (``gdpt.integrators.common.traced_gradients``); the others are marked in
            ``buffers.gradient_mask`` (0, infinite variance). An all-True mask renders exactly
            the render without one; an all-False one renders with ``gradients=False`` (no
            ``dx``/``dy``; ``metadata["gradient_mask"]["reason"]`` says so).
            ``metadata["gradient_mask"]["share"]`` is the share of masked pixels.
        **props: integrator properties when one is created (``max_depth``, ``gradients``,
            ``features``, ``variance``, ``primal``: ``"base"`` or ``"mis"``, ...).

    Returns:
        GradientBuffers: float32 HWC views of one tensor on the variant's device (with
        ``primal_spp``: a pooled copy, see :func:`~gdpt.buffers.pool_primal`), with ``spp``
        and ``metadata`` (integrator, seed, render seconds, and ``guard_counts``: how often
        each numerical guard of the integrator fired) filled in.

    Raises:
        ValueError: ``spp < 1``, ``primal_spp < 0``, ``primal_spp`` or ``gradient_mask``
            with an integrator whose gradients are off, or a ``gradient_mask`` that is not a
            bool ``(H, W)`` tensor or array of the film's size (named), or an unknown ``primal``.
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
    mask = None if gradient_mask is None else _pixel_mask(gradient_mask, scene, integrator)
    if mask is not None and not mask.any():
        return _render_without_gradients(integrator, scene, spp, seed, progress, primal_spp)

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=spp + primal_spp, unit="spp", desc="render", leave=False)
    try:
        if primal_spp:
            gradient = _twin(integrator, scene, features=False)
            buffers = pool_primal(
                _render_one(gradient, scene, spp, seed, bar, mask=mask),
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
            buffers = _render_one(integrator, scene, spp, seed, bar, mask=mask)
    finally:
        if bar is not None:
            bar.close()
    if mask is not None:
        buffers.metadata["gradient_mask"] = {"share": float(mask.mean())}
    return buffers


def _pixel_mask(mask: Any, scene: Any, integrator: Any):
    """``gradient_mask`` of :func:`render` as a bool numpy ``(H, W)`` array, checked against the
    film of ``scene``'s first sensor and the integrator before anything is rendered."""
    import numpy as np
    import torch

    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    expected = f"a bool torch tensor or numpy array of shape (H, W) = ({height}, {width})"
    if not integrator.gradients:
        raise ValueError(
            f"gradient_mask ({expected}) selects where offsets are traced, but this "
            f"{integrator.plugin_name} integrator has gradients=false"
        )
    if isinstance(mask, torch.Tensor):
        if mask.dtype != torch.bool:
            raise ValueError(f"gradient_mask must be {expected}, got a {mask.dtype} tensor")
        mask = mask.detach().cpu().numpy()
    elif not isinstance(mask, np.ndarray) or mask.dtype != np.bool_:
        dtype = getattr(mask, "dtype", None)
        raise ValueError(
            f"gradient_mask must be {expected}, got {type(mask).__name__}"
            + (f" of {dtype}" if dtype is not None else "")
        )
    if mask.shape != (height, width):
        raise ValueError(f"gradient_mask must be {expected}, got shape {tuple(mask.shape)}")
    return mask


def _render_without_gradients(integrator, scene, spp: int, seed: int, progress, primal_spp: int):
    """The render of an all-False gradient mask: ``spp`` (+ ``primal_spp``) plain samples
    (``gradients=False``, seed ``seed``), the reason in ``metadata["gradient_mask"]``."""
    plain = _twin(integrator, scene, gradients=False)
    buffers = render(scene, spp=spp + primal_spp, seed=seed, integrator=plain, progress=progress)
    buffers.metadata["gradient_mask"] = {
        "share": 0.0,
        "reason": "the gradient mask is empty: rendered without gradients (gradients=False)",
    }
    return buffers


def _twin(integrator: Any, scene: Any, **changes: Any) -> Any:
    """``integrator`` itself if ``changes`` are its settings already, else the shared integrator
    with its properties and ``changes``."""
    props = integrator.properties()
    if all(props[k] == v for k, v in changes.items()):
        return integrator
    props = {**props, **changes}
    return shared_integrator(scene, props.pop("type"), **props)


def _render_one(
    integrator, scene, spp: int, seed: int, bar, start: int = 0, mask=None
) -> GradientBuffers:
    """One ``integrator.render`` as zero-copy :class:`GradientBuffers` (``bar``: an optional
    tqdm bar advanced from ``start``; ``mask``: the integrator's ``gradient_mask`` for it)."""
    import drjit as dr

    if bar is not None:
        integrator.pass_callback = lambda done, total: bar.update(start + done - bar.n)
    integrator.gradient_mask = mask
    try:
        recordings = integrator.recordings
        begin = time.perf_counter()
        out = integrator.render(scene, seed=seed, spp=spp)
        dr.eval(out)
        dr.sync_thread()
        seconds = time.perf_counter() - begin
        buffers = buffers_from_aovs(out, integrator, seed=seed, spp=spp)
    finally:
        integrator.pass_callback = None
        integrator.gradient_mask = None

    buffers.metadata["render_seconds"] = seconds
    buffers.metadata["recorded_passes"] = integrator.recordings - recordings
    return buffers
