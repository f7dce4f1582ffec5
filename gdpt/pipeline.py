"""Render and reconstruct in one process: :func:`render_and_denoise` (``gdpt.render_and_denoise``).

Sampling (Dr.Jit, :func:`gdpt.rendering.render`) and reconstruction (torch,
:func:`gdpt.methods.reconstruct_image`) run in the same process; on a CUDA variant the buffers
stay on the GPU. ``method="auto"`` lets a pilot render choose the route
(:mod:`gdpt.auto_route`).
"""

from __future__ import annotations

import gc
import hashlib
import json
import math
import time
from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import Any

import torch

from gdpt import auto_route
from gdpt.buffers import GradientBuffers
from gdpt.cost_model import (
    MODELS,
    TimeModel,
    drain_compile_seconds,
    fit_by_probing,
    kernel_history,
)
from gdpt.methods import METHODS, reconstruct_image
from gdpt.rendering import forget_integrators, render
from gdpt.scenes.loading import load_scene
from gdpt.seconds_bar import SecondsBar


@dataclass
class RenderResult:
    """What :func:`render_and_denoise` returns.

    Attributes:
        image: ``(H, W, 3)`` float32 reconstruction on the buffers' device.
        buffers: the render.
        spp: the samples per pixel rendered (``auto``: plain samples' worth, the pilot's
            included: with ``seconds``, the cost model's count plus the samples its route's
            fill rendered beyond the count, :func:`gdpt.auto_route.render_route`; a method
            with gradients: gradient samples); with ``seconds``, the count the cost model
            chose.
        budget: the ``seconds`` asked for, ``None`` with ``spp``.
        timings: wall-clock seconds, each without the kernel compilation seen during it:
            ``pilot`` (``method="auto"`` only), ``render`` (sampling; on a configuration's first
            render in a process, also the recording of its frozen passes), ``reconstruct``,
            ``total`` (their sum: what ``seconds`` budgets); apart from it, ``compile`` (Dr.Jit
            kernel compilation during those stages) and, with ``seconds``, ``setup`` (the
            untimed compilation, pass recording and cost-model probes before the render).
        route: for ``method="auto"``, the :class:`gdpt.auto_route.RouteChoice` (also in
            ``buffers.metadata["route"]``); else ``None``.
    """

    image: torch.Tensor
    buffers: GradientBuffers
    spp: int
    budget: float | None = None
    timings: dict[str, float] = field(default_factory=dict)
    route: auto_route.RouteChoice | None = None


def release_scene(scene: Any) -> None:
    """Forget what gdpt keeps for ``scene`` (an ``mi.Scene``): its integrators and their frozen
    passes (:func:`gdpt.rendering.shared_integrator`), ``auto``'s learned cost ratios and the cost
    models of ``seconds=`` (:data:`gdpt.cost_model.MODELS`), then
    collect garbage; the scene is freed once the caller drops its own references.

    Render one scene after another in a process? Release each when done: while another scene's
    objects are alive, Dr.Jit may refuse to record a frozen pass (its virtual calls reach
    instances it cannot find in the pass's inputs) and the integrator traces every pass of those
    settings, much slower (``docs/architecture.md``).
    """
    forget_integrators(scene)
    auto_route.forget_cost_ratios(scene)
    MODELS.forget(scene)
    gc.collect()


#: Mixed into the seed of the pilot render of ``method="auto"`` (independent of the main render).
PILOT_SEED_SALT = 0x2C1B3C6D


def render_and_denoise(
    scene: Any,
    *,
    spp: int | None = None,
    seconds: float | None = None,
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
            :func:`gdpt.auto_route.render_route`; for a method with gradients, gradient
            samples, each the cost of several plain ones: ``docs/cost-table.md``).
        seconds (float): instead of ``spp``, the wall seconds of sampling and reconstruction
            (``auto``'s pilot and statistics included) to fill: the sample count comes from a
            cost model of ``scene`` and this configuration (:class:`gdpt.cost_model.TimeModel`,
            kept per scene object in :data:`gdpt.cost_model.MODELS` and refined by every
            render; ``auto``'s route then fills what its pilot left of the seconds, before
            its reconstruction: :func:`gdpt.auto_route.render_route`). The first such render
            of a scene and configuration in a process first compiles the kernels, records
            the frozen passes and times probe renders (all of it untimed,
            ``timings["setup"]``); later ones reuse the model.
        method (str): ``"auto"`` (from :func:`gdpt.auto_route.pilot_threshold` spp on, a pilot
            of a share of the film's tiles at the main render's gradient count, whose samples
            go into the image, chooses between the primal-only denoiser on plain samples and
            ``fuse`` on gradient-domain samples, :mod:`gdpt.auto_route`; below, or on a film
            with too few tiles, the former), or a key of
            :data:`gdpt.methods.METHODS` (a deprecated name runs its new one, with a
            ``DeprecationWarning``).
        seed (int): random seed.
        alpha (float): screened-Poisson data weight.
        progress (bool): a progress bar in seconds (stderr) over the pilot, the render and the
            reconstruction, against the budget with ``seconds``.
        **props: integrator properties, as in :func:`render` (with ``gradient_mask`` for a
            method that reads gradients). ``gradients`` and ``features``
            default to what ``method`` reads (:meth:`gdpt.methods.Method.sampling`): the
            Poisson methods skip the features, ``oidn-tuned`` the offset paths, and a network
            trained on pooled inputs gets its plain path samples (``primal_spp``).

    Returns:
        RenderResult: the image ``(H, W, 3)``, the buffers, the sample count and the timings.

    Raises:
        ValueError: unknown ``method``, ``props`` turn off a buffer the method needs, a
            ``gradient_mask`` (:func:`render`) with ``"auto"`` or a method without gradients,
            both or neither of ``spp`` and ``seconds``, ``spp < 1``, or ``seconds`` not a
            finite number > 0 (all before rendering).
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
    check_budget(spp, seconds)
    with kernel_history():
        if seconds is None:
            with SecondsBar(None, "render", disable=not progress) as bar:
                return _render_at(scene, spp, method, seed, alpha, bar, props)
        return _render_for(scene, float(seconds), method, seed, alpha, progress, props)


def check_budget(spp: Any, seconds: Any) -> None:
    """Raise a one-line ``ValueError`` unless exactly one of ``spp`` (an int >= 1) and
    ``seconds`` (a finite number > 0) is given."""
    if (spp is None) == (seconds is None):
        given = "both" if spp is not None else "neither"
        raise ValueError(f"give spp (samples per pixel) or seconds (a time budget): {given} given")
    if spp is not None and (isinstance(spp, bool) or not isinstance(spp, int) or spp < 1):
        raise ValueError(f"spp must be an int >= 1, got {spp!r}")
    if seconds is not None and not (
        isinstance(seconds, (int, float))
        and not isinstance(seconds, bool)
        and math.isfinite(seconds)
        and seconds > 0
    ):
        raise ValueError(f"seconds must be a finite number > 0, got {seconds!r}")


def _render_at(
    scene: Any,
    spp: int,
    method: str,
    seed: int,
    alpha: float,
    bar: SecondsBar,
    props: dict,
    budget: float | None = None,
) -> RenderResult:
    """:func:`render_and_denoise` at ``spp``: each stage's wall seconds without the kernel
    compilation seen during it (``timings["compile"]``), ``total`` their sum. With ``budget``
    (seconds), ``auto``'s route fills what is left of it after its pilot and before the
    route's reconstruction (:func:`gdpt.auto_route.render_route`'s ``deadline``), whose
    seconds every ``auto`` render here teaches the next
    (:func:`gdpt.auto_route.learn_reconstruct_seconds`)."""
    choice, timings, compiled = None, {}, 0.0
    drain_compile_seconds()
    start = time.perf_counter()
    if method == "auto":
        scene = load_scene(scene)
        bar.stage("pilot")
        seed_pilot = (int(seed) ^ PILOT_SEED_SALT) & 0xFFFFFFFF
        choice, pilot = auto_route.run_pilot(scene, spp=spp, seed=seed_pilot, **props)
        compiled += (c := drain_compile_seconds())
        deadline = None if budget is None else start + c + budget
        timings["pilot"] = max(0.0, time.perf_counter() - start - c)
        bar.stage(f"render ({choice.route} route)")
        start = time.perf_counter()
        buffers = auto_route.render_route(
            scene, choice, pilot, spp=spp, seed=seed, deadline=deadline, **props
        )
        method = choice.method
    else:
        bar.stage("render")
        props = {**METHODS[method].sampling(spp), **props}
        buffers = render(scene, spp=spp, seed=seed, **props)
    compiled += (c := drain_compile_seconds())
    timings["render"] = max(0.0, time.perf_counter() - start - c)
    if choice is not None:
        buffers.metadata["route"] = choice.to_json()
        if fill := buffers.metadata.get("plain_fill"):  # a deadline's fill: more or fewer
            spp = max(1, spp + fill["spp"] - fill["count_spp"])
    bar.stage(f"reconstruct ({method})")
    start = time.perf_counter()
    image = reconstruct_image(buffers, method=method, alpha=alpha)
    if image.is_cuda:
        torch.cuda.synchronize(image.device)
    compiled += (c := drain_compile_seconds())
    timings["reconstruct"] = max(0.0, time.perf_counter() - start - c)
    if choice is not None:  # what the route's next deadline leaves for its reconstruction
        routed = auto_route.integrator_props(props)
        auto_route.learn_reconstruct_seconds(scene, routed, method, timings["reconstruct"])
    timings["total"] = sum(timings.values())
    timings["compile"] = compiled
    return RenderResult(image=image, buffers=buffers, spp=spp, timings=timings, route=choice)


#: Mixed into the seed of the probe renders that fit the cost model of ``seconds=``.
CALIBRATION_SEED_SALT = 0x5EC0D5

#: A count already rendered within this share of the model's count is rendered instead (it
#: replays its frozen passes: no warm-up).
REUSE = 0.03

#: A warm-up (its frozen-pass recording included) that takes less than ``1 - SHORT`` of the
#: budget shows the model too slow (probes slowed by other work): the model is scaled down to
#: it (:meth:`TimeModel.rescale`; a bound, the recording counted) and the count chosen again.
SHORT = 0.15

#: The key suffix of ``auto``'s model below its pilot threshold.
BELOW_PILOT = " below the pilot threshold"

#: The probes of ``seconds=`` stop at this share of the budget (:func:`fit_by_probing`).
PROBE_FRACTION = 0.3


def configuration_key(method: str, alpha: float, props: dict[str, Any]) -> str:
    """The name of what a sample costs in :func:`render_and_denoise`: ``method``, ``alpha``
    and the integrator properties as sorted JSON (an array or tensor by a digest of its
    bytes)."""

    def describe(value: Any) -> str:
        if isinstance(value, torch.Tensor):
            value = value.detach().cpu().numpy()
        if hasattr(value, "tobytes"):
            return f"{getattr(value, 'shape', '')} {hashlib.sha1(value.tobytes()).hexdigest()}"
        return repr(value)

    config = {"method": method, "alpha": alpha, **props}
    return json.dumps(config, sort_keys=True, default=describe)


def _render_for(
    scene: Any, seconds: float, method: str, seed: int, alpha: float, progress: bool, props: dict
) -> RenderResult:
    """:func:`render_and_denoise` with ``seconds``: the setup (compilation, pass recording,
    the cost model's probes where it has none) untimed, then the render at the model's count,
    whose time refines the model. ``auto`` has two models: from its pilot threshold on (the
    pilot's cost in the line) and below it (no pilot: plain samples and the denoiser), used
    where the first leaves no room for the pilot."""
    scene = load_scene(scene)
    quiet = SecondsBar(None, disable=True)
    threshold = auto_route.pilot_threshold() if method == "auto" else None

    def warm_key(spp: int) -> Hashable:
        """What a render's frozen passes depend on: ``spp``, and for ``auto`` the cost ratio
        that sizes its gradient count (:func:`gdpt.auto_route.learned_cost_ratio`, which a
        timed run may relearn)."""
        return spp if threshold is None else (spp, auto_route.learned_cost_ratio(scene, props))

    def warm_up(key: str, spp: int, seed: int) -> float:
        """Records what a timed run at ``spp`` and ``seed`` replays (auto: its route) and loads
        what the reconstruction loads once; its seconds, recording included (at least the
        cost of ``spp``)."""
        seconds = _render_at(scene, spp, method, seed, alpha, quiet, props).timings["total"]
        MODELS.mark_warm(scene, key, warm_key(spp))
        return seconds

    def model_of(key: str, first: int, most: int) -> TimeModel:
        """The model of ``key``, probed from ``first`` up to ``most`` spp where there is none."""
        if (model := MODELS.get(scene, key)) is not None:
            return model

        def timed(spp: int, offset: int) -> float:
            probe_seed = ((int(seed) ^ CALIBRATION_SEED_SALT) + offset) & 0xFFFFFFFF
            if not MODELS.is_warm(scene, key, warm_key(spp)):
                warm_up(key, spp, probe_seed)
            return _render_at(scene, spp, method, probe_seed, alpha, quiet, props).timings["total"]

        model = fit_by_probing(
            timed,
            budget=seconds,
            first_spp=first,
            repeats=3,
            probe_fraction=PROBE_FRACTION,
            max_probe_spp=most,
        )
        MODELS.set(scene, key, model)
        return model

    with SecondsBar(None, "setup (compilation, pass recording, cost model)", disable=not progress):
        start = time.perf_counter()
        key = configuration_key(method, alpha, props)
        model = model_of(key, threshold or 1, 1 << 16)
        spp = model.spp_for(seconds)
        if threshold is not None and spp < threshold:  # no room for the pilot: auto without one
            key += BELOW_PILOT
            model = model_of(key, 1, threshold - 1)
            spp = min(threshold - 1, model.spp_for(seconds))
        warm = [  # counts near spp that replay (on the same side of auto's pilot threshold)
            n
            for n in range(max(1, math.ceil(spp * (1 - REUSE))), math.floor(spp * (1 + REUSE)) + 1)
            if (threshold is None or (n < threshold) == (spp < threshold))
            and MODELS.is_warm(scene, key, warm_key(n))
        ]
        if warm:
            spp = min(warm, key=lambda n: abs(n - spp))
        for _ in range(3):  # again where auto's warm-up relearned its cost ratio or fell short
            if MODELS.is_warm(scene, key, warm_key(spp)):
                break
            warm = warm_up(key, spp, seed)
            if warm < seconds * (1 - SHORT):  # short even with its recording: slow probes
                model.rescale(spp, warm)
                spp = model.spp_for(seconds)
                if threshold is not None and key.endswith(BELOW_PILOT):
                    spp = min(threshold - 1, spp)
        setup = time.perf_counter() - start
    with SecondsBar(seconds, "render", disable=not progress) as bar:
        result = _render_at(scene, spp, method, seed, alpha, bar, props, seconds)
    model.update(spp, result.timings["total"])
    result.budget = seconds
    result.timings["setup"] = setup
    return result
