"""Render and reconstruct in one process: :func:`render_and_denoise` (``gdpt.render_and_denoise``).

Sampling (Dr.Jit, :func:`gdpt.rendering.render`) and reconstruction (torch,
:func:`gdpt.methods.reconstruct_image`) run in the same process; on a CUDA variant the buffers
stay on the GPU. ``method="auto"`` lets a pilot render choose the route
(:mod:`gdpt.auto_route`).
"""

from __future__ import annotations

import gc
import time
from dataclasses import dataclass, field
from typing import Any

import torch

from gdpt import auto_route
from gdpt.buffers import GradientBuffers
from gdpt.methods import METHODS, reconstruct_image
from gdpt.rendering import forget_integrators, render
from gdpt.scenes.loading import load_scene


@dataclass
class RenderResult:
    """What :func:`render_and_denoise` returns.

    Attributes:
        image: ``(H, W, 3)`` float32 reconstruction on the buffers' device.
        buffers: the render.
        timings: wall-clock seconds: ``render`` (sampling, kernel compilation included),
            ``reconstruct``, ``total`` (and ``pilot`` for ``method="auto"``).
        route: for ``method="auto"``, the :class:`gdpt.auto_route.RouteChoice` (also in
            ``buffers.metadata["route"]``); else ``None``.
    """

    image: torch.Tensor
    buffers: GradientBuffers
    timings: dict[str, float] = field(default_factory=dict)
    route: auto_route.RouteChoice | None = None


def release_scene(scene: Any) -> None:
    """Forget what gdpt keeps for ``scene`` (an ``mi.Scene``): its integrators and their frozen
    passes (:func:`gdpt.rendering.shared_integrator`) and ``auto``'s learned cost ratios, then
    collect garbage; the scene is freed once the caller drops its own references.

    Render one scene after another in a process? Release each when done: while another scene's
    objects are alive, Dr.Jit may refuse to record a frozen pass (its virtual calls reach
    instances it cannot find in the pass's inputs) and the integrator traces every pass of those
    settings, much slower (``docs/architecture.md``).
    """
    forget_integrators(scene)
    auto_route.forget_cost_ratios(scene)
    gc.collect()


#: Mixed into the seed of the pilot render of ``method="auto"`` (independent of the main render).
PILOT_SEED_SALT = 0x2C1B3C6D


def render_and_denoise(
    scene: Any,
    *,
    spp: int,
    method: str = "auto",
    seed: int = 0,
    alpha: float = 0.2,
    progress: bool = False,
    **props: Any,
) -> RenderResult:
    """Render with ``gdpt`` and reconstruct, in one process (no host round trip on a GPU).

    Args:
        scene: as in :func:`render`.
        spp (int): samples per pixel (for ``"auto"``: plain path samples, the pilot's
            included; the gradient route renders gradient samples of the same cost,
            :func:`gdpt.auto_route.render_route`).
        method (str): ``"auto"`` (from :func:`gdpt.auto_route.pilot_threshold` spp on, a pilot
            of a share of the film's tiles at the main render's gradient count, whose samples
            go into the image, chooses between the primal-only denoiser on plain samples and
            ``fuse`` on gradient-domain samples, :mod:`gdpt.auto_route`; below, or on a film
            with too few tiles, the former), or a key of
            :data:`gdpt.methods.METHODS` (a deprecated name runs its new one, with a
            ``DeprecationWarning``).
        seed (int): random seed.
        alpha (float): screened-Poisson data weight.
        progress (bool): progress bar while rendering.
        **props: integrator properties, as in :func:`render` (with ``gradient_mask`` for a
            method that reads gradients). ``gradients`` and ``features``
            default to what ``method`` reads (:meth:`gdpt.methods.Method.sampling`): the
            Poisson methods skip the features, ``oidn-tuned`` the offset paths, and a network
            trained on pooled inputs gets its plain path samples (``primal_spp``).

    Returns:
        RenderResult: the image ``(H, W, 3)``, the buffers and the timings.

    Raises:
        ValueError: unknown ``method``, ``props`` turn off a buffer the method needs, or a
            ``gradient_mask`` (:func:`render`) with ``"auto"`` or a method without gradients.
    """
    method = METHODS.resolve(method, stacklevel=2)  # a deprecated name warns once, here
    if method != "auto":
        METHODS.check([method])
    if props.get("gradient_mask") is not None and (
        method == "auto" or not METHODS[method].gradients
    ):
        raise ValueError(
            f"gradient_mask selects where offsets are traced; method {method!r} "
            + ("chooses its own route" if method == "auto" else "reads no gradients")
            + ": give a method that reads gradients (e.g. 'fuse')"
        )
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    choice, timings = None, {}
    start = time.perf_counter()
    if method == "auto":
        scene = load_scene(scene)
        seed_pilot = (int(seed) ^ PILOT_SEED_SALT) & 0xFFFFFFFF
        choice, pilot = auto_route.run_pilot(scene, spp=spp, seed=seed_pilot, **props)
        timings["pilot"] = choice.pilot_seconds
        start = time.perf_counter()
        buffers = auto_route.render_route(
            scene, choice, pilot, spp=spp, seed=seed, progress=progress, **props
        )
        method = choice.method
    else:
        props = {**METHODS[method].sampling(spp), **props}
        buffers = render(scene, spp=spp, seed=seed, progress=progress, **props)
    t_render = time.perf_counter() - start
    if choice is not None:
        buffers.metadata["route"] = choice.to_json()
    t0 = time.perf_counter()
    image = reconstruct_image(buffers, method=method, alpha=alpha)
    if image.is_cuda:
        torch.cuda.synchronize(image.device)
    t_rec = time.perf_counter() - t0
    timings.update(render=t_render, reconstruct=t_rec)
    timings["total"] = sum(timings.values())
    return RenderResult(image=image, buffers=buffers, timings=timings, route=choice)
