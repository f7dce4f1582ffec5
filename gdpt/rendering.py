"""Rendering gradient-domain buffers in-process: scene -> :class:`GradientBuffers` -> image.

:func:`render` samples a scene (loaded by :func:`gdpt.scene_io.load_scene`) with ``gdpt`` or
``gdpt_rr``; :func:`render_and_denoise` also reconstructs (:func:`gdpt.denoise.reconstruct`).

Sampling (Dr.Jit) and reconstruction (torch) run in the same process. The integrator's output
tensor is handed to torch through DLPack without a copy (on a CUDA variant it stays on the GPU);
the buffers are channel slices (views) of that one tensor.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import torch

from gdpt.buffers import GradientBuffers
from gdpt.scene_io import load_scene

#: Integrators that produce gradient buffers.
INTEGRATORS = ("gdpt", "gdpt_rr")


@dataclass
class RenderResult:
    """What :func:`render_and_denoise` returns.

    Attributes:
        image: ``(H, W, 3)`` float32 reconstruction on the buffers' device.
        buffers: the render.
        timings: wall-clock seconds: ``render`` (sampling, kernel compilation included),
            ``reconstruct``, ``total``.
    """

    image: torch.Tensor
    buffers: GradientBuffers
    timings: dict[str, float] = field(default_factory=dict)


def make_integrator(name: str = "gdpt", **props: Any):
    """Instantiate ``gdpt`` / ``gdpt_rr`` with properties (``max_depth``, ``gradients``, ...)."""
    import mitsuba as mi

    if name not in INTEGRATORS:
        raise ValueError(f"unknown integrator {name!r}; valid: {', '.join(INTEGRATORS)}")
    return mi.load_dict({"type": name, **props})


def render(
    scene: Any,
    *,
    spp: int,
    seed: int = 0,
    integrator: str | Any | None = None,
    progress: bool = False,
    **props: Any,
) -> GradientBuffers:
    """Render primal, gradients and features of ``scene``.

    Args:
        scene: ``mi.Scene``, path to a Mitsuba XML file, or a scene dict. Its film must use a
            box pixel filter.
        spp (int): samples per pixel (rendered in passes of bounded size).
        seed (int): random seed; different seeds give independent renders.
        integrator: ``None`` (use the scene's integrator if it is ``gdpt``/``gdpt_rr``, else a
            new ``gdpt``), a plugin name, or an integrator instance.
        progress (bool): show a progress bar over the passes.
        **props: integrator properties when one is created (``max_depth``, ``gradients``,
            ``features``, ``variance``, ...).

    Returns:
        GradientBuffers: float32 HWC views of one tensor on the variant's device, with
        ``spp`` and ``metadata`` (integrator, seed, render seconds, and ``guard_counts``: how
        often each numerical guard of the integrator fired) filled in.
    """
    import drjit as dr
    import mitsuba as mi

    from gdpt.integrators.common import GradientIntegratorBase

    scene = load_scene(scene)
    if integrator is None:
        integrator = scene.integrator()
        if not isinstance(integrator, GradientIntegratorBase) or props:
            integrator = make_integrator("gdpt", **props)
    elif isinstance(integrator, str):
        integrator = make_integrator(integrator, **props)
    elif not isinstance(integrator, GradientIntegratorBase):
        raise TypeError(f"integrator must be gdpt or gdpt_rr, got {type(integrator).__name__}")
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=spp, unit="spp", desc="render", leave=False)
        integrator.pass_callback = lambda done, total: bar.update(done - bar.n)
    try:
        start = time.perf_counter()
        out = integrator.render(scene, seed=seed, spp=spp)
        dr.eval(out)
        dr.sync_thread()
        seconds = time.perf_counter() - start
    finally:
        integrator.pass_callback = None
        if bar is not None:
            bar.close()

    tensor = out.torch()  # zero-copy (DLPack) view of the Dr.Jit tensor
    views, offset = {}, 0
    for name, channels in integrator.channels():
        views[name] = tensor[..., offset : offset + channels]
        offset += channels
    metadata = {
        "integrator": integrator.plugin_name,
        "seed": int(seed),
        "max_depth": int(min(integrator.max_depth, 2**31 - 1)),
        "variant": mi.variant(),
        "render_seconds": seconds,
        "guard_counts": dict(integrator.guard_counts),
    }
    return GradientBuffers(**views, spp=int(spp), metadata=metadata)


def render_and_denoise(
    scene: Any,
    *,
    spp: int,
    method: str = "l1",
    seed: int = 0,
    alpha: float = 0.2,
    progress: bool = False,
    **props: Any,
) -> RenderResult:
    """Render with ``gdpt`` and reconstruct, in one process (no host round trip on a GPU).

    Args:
        scene: as in :func:`render`.
        spp (int): samples per pixel.
        method (str): reconstruction, a key of :data:`gdpt.denoise.METHODS`.
        seed (int): random seed.
        alpha (float): screened-Poisson data weight.
        progress (bool): progress bar while rendering.
        **props: integrator properties, as in :func:`render`. ``gradients`` and ``features``
            default to what ``method`` reads (:attr:`gdpt.denoise.Method.needs`): the Poisson
            methods skip the features, ``ngpt-nograd`` the offset paths.

    Returns:
        RenderResult: the image ``(H, W, 3)``, the buffers and the timings.

    Raises:
        ValueError: unknown ``method``, or ``props`` turn off a buffer the method needs.
    """
    from gdpt.denoise import METHODS, reconstruct

    METHODS.check([method])
    props = {**METHODS[method].needs, **props}
    start = time.perf_counter()
    buffers = render(scene, spp=spp, seed=seed, progress=progress, **props)
    t_render = time.perf_counter() - start
    t0 = time.perf_counter()
    image = reconstruct(buffers, method=method, alpha=alpha)
    if image.is_cuda:
        torch.cuda.synchronize(image.device)
    t_rec = time.perf_counter() - t0
    timings = {"render": t_render, "reconstruct": t_rec, "total": t_render + t_rec}
    return RenderResult(image=image, buffers=buffers, timings=timings)
