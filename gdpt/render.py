"""Rendering gradient-domain buffers in-process: Mitsuba scene -> :class:`GradientBuffers`.

Sampling (Dr.Jit) and reconstruction (torch) run in the same process. The integrator's output
tensor is handed to torch through DLPack without a copy (on a CUDA variant it stays on the GPU);
the buffers are channel slices (views) of that one tensor.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from gdpt._modules import make_callable
from gdpt.buffers import GradientBuffers

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


def load_scene(scene: Any, *, box_filter: bool = False, long_side: int | None = None):
    """A ``mi.Scene`` from a scene, an XML path or a scene dict (variant set if needed).

    Args:
        scene: ``mi.Scene``, scene dict, or path to a Mitsuba XML file.
        box_filter (bool): XML only: replace the film's pixel filter by a box filter (gradient-
            domain rendering needs one). The change is explicit: callers should report it.
        long_side (int | None): XML only: rescale the film to this many pixels on its long side
            (aspect ratio kept).

    Raises:
        FileNotFoundError: the XML file does not exist.
        ValueError: Mitsuba cannot load the scene (the message names the file).
    """
    from gdpt.backend import set_variant

    import mitsuba as mi

    if mi.variant() is None:
        set_variant()
    else:
        from gdpt.integrators import register

        register()
    if isinstance(scene, mi.Scene):
        return scene
    if isinstance(scene, dict):
        return mi.load_dict(scene)
    path = Path(os.fspath(scene))
    if not path.is_file():
        raise FileNotFoundError(f"scene file not found: {path}")
    try:
        text = _edit_scene_xml(path, box_filter=box_filter, long_side=long_side)
        resolver = mi.file_resolver()
        saved = [resolver[i] for i in range(len(resolver))]
        resolver.prepend(str(path.parent.resolve()))  # relative meshes and textures
        try:
            return mi.load_string(text)
        finally:
            resolver.clear()
            for entry in saved:
                resolver.append(entry)
    except Exception as exc:  # Mitsuba raises RuntimeError with its parser message
        raise ValueError(f"cannot load scene {path}: {exc}") from exc


def _edit_scene_xml(path: Path, *, box_filter: bool, long_side: int | None) -> str:
    """The scene XML with the film's filter and size changed as requested."""
    import xml.etree.ElementTree as ET

    tree = ET.parse(path)
    root = tree.getroot()
    film = root.find("./sensor/film")
    if film is None or not (box_filter or long_side):
        return ET.tostring(root, encoding="unicode")
    if box_filter:
        for old in film.findall("rfilter"):
            film.remove(old)
        ET.SubElement(film, "rfilter", {"type": "box"})
    if long_side:
        defaults = {d.get("name"): d.get("value") for d in root.findall("default")}

        def size(name: str, fallback: int) -> tuple[ET.Element | None, int]:
            node = next((n for n in film.findall("integer") if n.get("name") == name), None)
            if node is None:
                return None, fallback
            value = node.get("value", "")
            return node, int(defaults.get(value[1:], fallback) if value.startswith("$") else value)

        (w_node, w), (h_node, h) = size("width", 768), size("height", 576)
        scale = long_side / max(w, h)
        for name, node, value in (("width", w_node, w), ("height", h_node, h)):
            if node is None:
                node = ET.SubElement(film, "integer", {"name": name})
            node.set("value", str(max(1, round(value * scale))))
    return ET.tostring(root, encoding="unicode")


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
        ``spp`` and ``metadata`` (integrator, seed, render seconds) filled in.
    """
    from gdpt.integrators.common import GradientIntegratorBase

    import drjit as dr
    import mitsuba as mi

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
        method (str): reconstruction, a key of :data:`gdpt.reconstruction.METHODS`.
        seed (int): random seed.
        alpha (float): screened-Poisson data weight.
        progress (bool): progress bar while rendering.
        **props: integrator properties, as in :func:`render`. ``gradients`` and ``features``
            default to what ``method`` reads (:data:`gdpt.reconstruction.NEEDS`): the Poisson
            methods skip the features, ``ngpt-nograd`` the offset paths.

    Returns:
        RenderResult: the image ``(H, W, 3)``, the buffers and the timings.

    Raises:
        ValueError: unknown ``method``, or ``props`` turn off a buffer the method needs.
    """
    from gdpt.reconstruction import METHODS, NEEDS, reconstruct

    if method not in METHODS:
        raise ValueError(
            f"unknown reconstruction method {method!r}; valid methods: {', '.join(METHODS)}"
        )
    props = {**NEEDS.get(method, {}), **props}
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


make_callable(__name__, render)
