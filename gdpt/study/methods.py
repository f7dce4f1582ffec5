"""Rendering methods compared by the equal-time evaluation, registered by name.

A method turns a scene and a sample count into a final image and reports the wall-clock time
it took (sampling + reconstruction)::

    result = EVAL_METHODS["gdpt+l1"].run(scene, spp=8, seed=3)
    result.image, result.seconds

Registered methods:

* ``pt``: path tracing, primal only (``gdpt`` with ``gradients=False, features=False``).
* ``pt+oidn``: path tracing + Intel Open Image Denoise (:data:`gdpt.methods.METHODS`
  ``oidn``: OIDN through ``mitsuba-oidn`` on the render's device; albedo + normal, HDR, quality
  ``high``).
* ``gdpt+l2`` / ``gdpt+l1`` / ``gdpt+l1-fast``: gradient-domain path tracing + screened
  Poisson (L2; L1 with the reference IRLS schedule; L1 with the accelerated preset).
* ``gdpt+oidn-grad``: gradient-domain path tracing (plain path samples pooled into the primal)
  + OIDN's U-Net fine-tuned to read the gradients (shipped).
* ``pt+oidn-tuned``: path tracing (features, no gradients) + the same network fine-tuned without
  gradients (shipped; the ablation).
* ``gdpt+fuse``: pooled gradient-domain samples + variance-weighted fusion of the gradients
  around the primal-only network (:mod:`gdpt.reconstruct.fuse`).
* ``gdpt+fuse-masked-variance``: ``gdpt+fuse`` with offsets only in the 16 px tiles where a
  gradient pilot's per-sample gradient/primal variance ratio is low
  (:func:`gdpt.gradient_mask.render_masked`, the pilot's samples merged in, all of it timed;
  its own cost calibration). Measured at equal time and not kept as a route
  (``docs/gradients.md``); :func:`masked_fuse` makes the method of another design.
* ``auto``: ``render_and_denoise``'s default (:mod:`gdpt.auto_route`: a pilot render's choice
  between plain path tracing + the primal-only denoiser and ``gdpt+fuse``); all of it timed.
  Under the ``total`` protocol it is given the budget in seconds, as a user gives it
  (``render_and_denoise(seconds=...)``: its own cost model, either route's last samples filling
  what its pilot left before the route's reconstruction); under ``render-time``, the count of
  its plain route's calibration (``pt+`` that denoiser).

A method that cannot run here (package not installed, no shipped model) says so through its
``check`` function and is skipped with that note. A reconstruction registered in
:data:`gdpt.methods.METHODS` appears here on its own (as ``gdpt+NAME``, or ``pt+NAME`` when it
reads no gradients; the deprecated study names, such as ``gdpt+ngpt`` for ``gdpt+oidn-grad``,
are :data:`gdpt.deprecated.EVAL_METHOD_ALIASES`); another method (a different sampler) is
``EVAL_METHODS.register(name, EvalMethod(name, description, f))`` with
``f(scene, *, spp, seed, **properties) -> MethodResult``; the harness needs no change.

Integrator properties: a name ``METHOD@NAME=VALUE,NAME=VALUE`` (e.g. ``gdpt+fuse@max_depth=4``)
is the registered ``METHOD`` rendering with those ``gdpt`` integrator properties
(:data:`gdpt.integrators.properties.PROPERTIES`: any property there, checked there, except
those the method sets itself, such as ``gradients``); its configuration holds them, so it has
its own cost calibration, and the name is kept as written in results and reports.

Timing: :attr:`MethodResult.seconds` is the wall time from the start of sampling to the final
image on the host, minus the time Dr.Jit spent compiling kernels during the call (read from
Dr.Jit's kernel history when :data:`drjit.JitFlag.KernelHistory` is enabled, else 0). Callers
warm a method up once per scene so that little compilation remains to subtract.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING, Any

import torch

from gdpt.cost_model import drain_compile_seconds
from gdpt.deprecated import EVAL_METHOD_ALIASES
from gdpt.methods import METHODS as DENOISERS
from gdpt.methods import Method, reconstruct_image
from gdpt.reconstruct.registry import Registry

if TYPE_CHECKING:
    from gdpt.buffers import GradientBuffers
    from gdpt.study.scenes import EvalScene

__all__ = [
    "EVAL_METHODS",
    "MethodRegistry",
    "EvalMethod",
    "MethodResult",
    "MethodUnavailable",
]


class MethodUnavailable(RuntimeError):
    """Raised by a method that cannot run here (missing package or model)."""


@dataclass
class MethodResult:
    """One timed run of a method.

    Attributes:
        image: ``(H, W, 3)`` float32 linear radiance on the CPU.
        seconds: wall time of sampling + reconstruction, kernel compilation excluded.
        render_seconds: part of ``seconds`` spent sampling (compilation excluded).
        reconstruct_seconds: part of ``seconds`` spent reconstructing (denoising).
        compile_seconds: Dr.Jit kernel compilation observed during the call (not in
            ``seconds``).
        route: for ``auto``, the route it chose (:class:`gdpt.auto_route.RouteChoice` as a dict).
        spp: the sample count a run in seconds (:attr:`EvalMethod.run_for`) chose; ``None``
            for a run at a given count.
        recorded: the run recorded frozen passes (``metadata["recorded_passes"]`` of its
            render: the Python tracing of a pass new to the integrator is in its seconds).
    """

    image: torch.Tensor
    seconds: float
    render_seconds: float = 0.0
    reconstruct_seconds: float = 0.0
    compile_seconds: float = 0.0
    route: dict[str, Any] | None = None
    spp: int | None = None
    recorded: bool = False


#: ``f(scene, *, spp, seed) -> MethodResult``.
RunFunction = Callable[..., MethodResult]


@dataclass(frozen=True)
class EvalMethod:
    """A registered method.

    Attributes:
        name: registry key, e.g. ``"gdpt+l1"``.
        description: one line for the report.
        run: ``f(scene: EvalScene, *, spp: int, seed: int, **properties) -> MethodResult``
            (``properties``: integrator properties every render of the method uses).
        check: returns ``None`` when the method can run here, else the reason it cannot.
        render: like ``run`` without the reconstruction (the image is the primal), to
            calibrate render times cheaply; ``None``: the method cannot be split.
        configuration: returns the render configuration the method's ``spp`` buys (integrator
            properties, pooling factor, ``reconstruction``: the method it runs); methods with
            equal configurations share one cost calibration in the study
            (:func:`gdpt.study.calibration.configuration_key`); ``None``: the method's cost is
            its own.
        run_for: ``f(scene, *, seconds: float, seed: int) -> MethodResult``: the method
            filling a budget of ``seconds`` (sampling + reconstruction) itself, the count its
            own choice (:attr:`MethodResult.spp`); the study gives it its budget instead of a
            calibrated count (:func:`gdpt.study.calibration.fills_seconds`). ``None``: it
            renders the counts it is given.
    """

    name: str
    description: str
    run: RunFunction
    check: Callable[[], str | None] = field(default=lambda: None)
    render: RunFunction | None = None
    configuration: Callable[[], dict[str, Any]] | None = None
    run_for: RunFunction | None = None


class MethodRegistry(Registry[EvalMethod]):
    """The study methods: a :class:`~gdpt.reconstruct.registry.Registry` that also answers to
    ``METHOD@PROPERTIES`` (:func:`with_properties`; not listed, made on demand)."""

    def __contains__(self, name: object) -> bool:
        if super().__contains__(name):
            return True
        try:
            self[name]  # type: ignore[index]
        except (KeyError, ValueError):
            return False
        return True

    def __missing__(self, name: str) -> EvalMethod:
        base, sep, text = name.partition("@") if isinstance(name, str) else (name, "", "")
        if not sep:
            return super().__missing__(name)
        return with_properties(self[base], name, parse_properties(text, name))

    def resolve(self, name: str, *, stacklevel: int = 1) -> str:
        """As :meth:`Registry.resolve`, the properties of ``METHOD@PROPERTIES`` checked and
        kept as written (``ValueError`` naming a bad one)."""
        base, sep, text = name.partition("@")
        if not sep:
            return super().resolve(name, stacklevel=stacklevel + 1)
        current = f"{super().resolve(base, stacklevel=stacklevel + 1)}@{text}"
        self[current]  # noqa: B018 (checks the base and the properties)
        return current

    def check(self, names: object) -> None:
        for name in names:  # type: ignore[attr-defined]
            if "@" in name:
                self[name]  # noqa: B018 (a ValueError naming the bad property)
        super().check(names)


#: Registered methods, name -> :class:`EvalMethod`, in registration order.
EVAL_METHODS: MethodRegistry = MethodRegistry("method")


def parse_properties(text: str, name: str) -> dict[str, Any]:
    """The integrator properties ``NAME=VALUE,NAME=VALUE`` of the method name ``name``,
    typed and checked (:func:`gdpt.integrators.properties.parse_property`).

    Raises:
        ValueError: one line naming ``name`` and what is wrong (a property twice, an unknown
            one, an invalid value).
    """
    from gdpt.integrators.properties import parse_property

    properties: dict[str, Any] = {}
    for item in text.split(","):
        try:
            key, value = parse_property(item)
        except ValueError as err:
            raise ValueError(f"method {name!r}: {err}") from None
        if key in properties:
            raise ValueError(f"method {name!r}: property {key!r} is given twice")
        properties[key] = value
    return properties


def with_properties(base: EvalMethod, name: str, properties: dict[str, Any]) -> EvalMethod:
    """``base`` rendering with the integrator ``properties`` (from :func:`parse_properties`),
    named ``name``; its configuration is ``base``'s with the properties.

    Raises:
        ValueError: ``base`` sets one of the properties itself (e.g. ``gradients``).
    """
    config = {} if base.configuration is None else base.configuration()
    if fixed := sorted(set(properties) & set(config)):
        raise ValueError(
            f"method {name!r}: {base.name} sets {', '.join(map(repr, fixed))} itself "
            f"({', '.join(f'{k}={config[k]}' for k in fixed)})"
        )
    return EvalMethod(
        name,
        f"{base.description}; integrator properties "
        + ", ".join(f"{k}={v}" for k, v in properties.items()),
        partial(base.run, **properties),
        base.check,
        None if base.render is None else partial(base.render, **properties),
        None if base.configuration is None else lambda: {**base.configuration(), **properties},  # type: ignore[misc]
        None if base.run_for is None else partial(base.run_for, **properties),
    )


# ------------------------------------------------------------------------------------ timing
def _timed_run(
    scene: EvalScene,
    spp: int,
    seed: int,
    reconstruct: Callable[[GradientBuffers], torch.Tensor] | None,
    render: Callable[..., GradientBuffers] | None = None,
    **props: Any,
) -> MethodResult:
    """Render with ``render`` (default :func:`gdpt.render`; called as ``render(scene, spp=,
    seed=, max_depth=, **props)``), reconstruct, and time both parts; ``route`` holds the
    buffers' ``metadata["pilot_mask"]`` where the render set one."""
    if render is None:
        from gdpt.rendering import render

    props = {"max_depth": scene.max_depth, **props}  # (a method's properties may set it)
    drain_compile_seconds()
    start = time.perf_counter()
    buffers = render(scene.scene, spp=spp, seed=seed, **props)
    middle = time.perf_counter()
    compile_seconds = drain_compile_seconds()
    image = buffers.primal if reconstruct is None else reconstruct(buffers)
    image = image.detach().to("cpu", torch.float32).contiguous()  # waits for the device
    end = time.perf_counter()
    render_seconds = max(0.0, middle - start - compile_seconds)
    return MethodResult(
        image=image,
        seconds=render_seconds + (end - middle),
        render_seconds=render_seconds,
        reconstruct_seconds=end - middle,
        compile_seconds=compile_seconds,
        recorded=bool(buffers.metadata.get("recorded_passes", 0)),
        **(
            {"route": {"pilot_mask": buffers.metadata["pilot_mask"]}}
            if "pilot_mask" in buffers.metadata
            else {}
        ),
    )


# ---------------------------------------------------------------------------------- methods
def path_tracing(scene: EvalScene, *, spp: int, seed: int, **properties: Any) -> MethodResult:
    """Plain path tracing: the primal of ``gdpt`` with ``gradients=False``.

    Args:
        scene: the scene (its ``max_depth`` is used).
        spp: samples per pixel.
        seed: random seed.
        **properties: further integrator properties.

    Returns:
        The image and its timing.
    """
    return _timed_run(scene, spp, seed, None, gradients=False, features=False, **properties)


def render_configuration(
    name: str | None, sampling: dict[str, Any], factor: float = 0.0
) -> Callable[[], dict[str, Any]]:
    """``configuration()`` of an :class:`EvalMethod` that renders with ``gdpt`` and
    ``sampling`` (:meth:`gdpt.methods.Method.needs`), pools ``factor`` plain samples per
    gradient sample and reconstructs with ``name`` (``None``: the primal as it is)."""
    config = {"integrator": "gdpt", **dict(sorted(sampling.items()))}
    return lambda: {**config, "primal_spp_factor": factor, "reconstruction": name}


EVAL_METHODS.register(
    "pt",
    EvalMethod(
        "pt",
        "path tracing, primal only (gdpt integrator, gradients=False)",
        path_tracing,
        configuration=render_configuration(None, {"gradients": False, "features": False}),
    ),
)


def register_denoiser(name: str, method: Method) -> str:
    """Register ``gdpt+NAME`` (or ``pt+NAME`` for a method without gradients): the buffers
    ``method`` reads, reconstructed by :func:`gdpt.reconstruct_image` with ``NAME`` (which
    must be in :data:`gdpt.methods.METHODS`); returns the study method's name."""
    sampler = "gdpt" if method.gradients else "pt"

    def run(scene: EvalScene, *, spp: int, seed: int, **properties: Any) -> MethodResult:
        if reason := method.check():
            raise MethodUnavailable(reason)
        props = {**method.sampling(spp), **properties}
        return _timed_run(scene, spp, seed, partial(reconstruct_image, method=name), **props)

    def render(scene: EvalScene, *, spp: int, seed: int, **properties: Any) -> MethodResult:
        return _timed_run(scene, spp, seed, None, **method.sampling(spp), **properties)

    label = "gradient-domain path tracing" if method.gradients else "path tracing"
    factor = method.primal_spp_factor() if method.gradients else 0.0
    if factor:
        label += f" (+ {factor:g} plain path samples per sample, pooled into the primal)"
    run.__name__ = run.__qualname__ = f"{sampler}_{name}".replace("-", "_")
    run.__doc__ = f"{label} buffers reconstructed with :data:`gdpt.methods.METHODS` ``{name}``."
    EVAL_METHODS.register(
        f"{sampler}+{name}",
        EvalMethod(
            f"{sampler}+{name}",
            f"{label} + {method.description}",
            run,
            method.check,
            render,
            render_configuration(name, method.needs, factor),
        ),
    )
    return f"{sampler}+{name}"


for _name, _method in {"oidn": DENOISERS["oidn"], **DENOISERS}.items():  # pt+oidn next to pt
    register_denoiser(_name, _method)
for _old, _new in EVAL_METHOD_ALIASES.items():
    EVAL_METHODS.alias(_old, _new)


def auto_route(scene: EvalScene, *, spp: int, seed: int, **properties: Any) -> MethodResult:
    """``render_and_denoise(method="auto")``: the pilot, the route's render and its
    reconstruction, all timed (kernel compilation excluded as for every method); ``spp`` are
    plain samples (the pilot's included), the gradient route renders gradient samples of the
    same cost."""
    return _auto(scene, seed, properties, spp=spp)


def auto_route_for(
    scene: EvalScene, *, seconds: float, seed: int, **properties: Any
) -> MethodResult:
    """``render_and_denoise(method="auto", seconds=seconds)``: the count from its own cost
    model of the scene (the first call per scene object probes, untimed), the route's last
    plain samples filling what is left of ``seconds`` after its pilot and before its
    reconstruction (``fuse`` or the denoiser: :func:`gdpt.auto_route.render_route`); the
    seconds are its ``timings["total"]`` (pilot, render, reconstruction, each without kernel
    compilation) and the copy of the image to the host; its setup is not timed."""
    return _auto(scene, seed, properties, seconds=seconds)


def _auto(scene: EvalScene, seed: int, properties: dict[str, Any], **budget: Any) -> MethodResult:
    from gdpt.pipeline import render_and_denoise

    if reason := DENOISERS["oidn"].check() and DENOISERS["oidn-tuned"].check():
        raise MethodUnavailable(reason)
    drain_compile_seconds()
    start = time.perf_counter()
    props = {"max_depth": scene.max_depth, **properties}
    result = render_and_denoise(scene.scene, seed=seed, **budget, **props)
    copy = time.perf_counter()
    image = result.image.detach().to("cpu", torch.float32).contiguous()
    end = time.perf_counter()
    compile_seconds = result.timings["compile"] + drain_compile_seconds()  # it drains its own
    reconstruct_seconds = result.timings["reconstruct"]
    if "seconds" in budget:  # its setup (probes, warm-ups) untimed
        seconds = result.timings["total"] + (end - copy)
    else:
        seconds = max(0.0, end - start - compile_seconds)
    return MethodResult(
        image=image,
        seconds=seconds,
        render_seconds=max(0.0, seconds - reconstruct_seconds),
        reconstruct_seconds=reconstruct_seconds,
        compile_seconds=compile_seconds,
        route=result.route.to_json(),
        spp=result.spp if "seconds" in budget else None,
    )


def plain_route_configuration() -> dict[str, Any]:
    """The render configuration of ``auto``'s plain route: that of ``pt+`` the primal-only
    denoiser, whose cost calibration ``auto`` shares (its ``spp`` are plain samples)."""
    from gdpt.adapters import plain_denoiser

    name = plain_denoiser()
    return render_configuration(name, DENOISERS[name].needs)()


EVAL_METHODS.register(
    "auto",
    EvalMethod(
        "auto",
        "a pilot render's choice between path tracing + the primal-only network and "
        "gradient-domain path tracing + fuse, the pilot's samples in the image (gdpt.auto_route)",
        auto_route,
        lambda: DENOISERS["oidn"].check() and DENOISERS["oidn-tuned"].check(),
        configuration=plain_route_configuration,
        run_for=auto_route_for,
    ),
)


def masked_fuse(design: str) -> RunFunction:
    """``run`` of ``gdpt+fuse-masked-DESIGN`` (``design`` of :func:`gdpt.gradient_mask.pilot_mask`):
    :func:`gdpt.gradient_mask.render_masked` (the pilot, its mask and the masked render of
    ``spp`` gradient samples in the mask) reconstructed by ``fuse``, all of it timed as the
    render except the final reconstruction (kernel compilation excluded)."""

    def run(scene: EvalScene, *, spp: int, seed: int, **properties: Any) -> MethodResult:
        from gdpt.gradient_mask import render_masked

        if reason := DENOISERS["fuse"].check():
            raise MethodUnavailable(reason)
        return _timed_run(
            scene,
            spp,
            seed,
            partial(reconstruct_image, method="fuse"),
            render=partial(render_masked, design=design),
            **properties,
        )

    run.__name__ = run.__qualname__ = f"masked_fuse_{design}"
    return run


EVAL_METHODS.register(
    "gdpt+fuse-masked-variance",
    EvalMethod(
        "gdpt+fuse-masked-variance",
        "a gradient pilot's gradient/primal variance ratio per 16 px tile masks the offsets of "
        "the rest of the samples, + fuse (gdpt.gradient_mask; measured, not a default); the "
        "pilot timed",
        masked_fuse("variance"),
        DENOISERS["fuse"].check,
    ),
)
