"""Sample counts that meet a time budget: the linear time model per render configuration and
scene (:class:`gdpt.cost_model.TimeModel`) fitted by timing a study method (:func:`calibrate`),
and one timed cell (:func:`run_at_budget`).

Methods that render the same thing share one calibration: :func:`configuration_key` names what
a method's ``spp`` buys (:attr:`EvalMethod.configuration`), and :func:`calibration_runner` is
the registered method that renders exactly that and is timed for all of them, so they get the
same sample count at every budget (``auto`` on its plain route and ``pt+oidn-tuned`` under
``render-time``). A method that fills a budget in seconds itself (:func:`fills_seconds`:
``auto`` under ``total``) is given the seconds instead, as a user gives them.

What the budget pays for is the *protocol* (:data:`PROTOCOLS`, :func:`charged_seconds`):
``"total"``, sampling and reconstruction (what a user waits for); ``"render-time"``, sampling
only, reconstruction reported beside it (the paper's equal-time protocol: Kettunen et al. 2019,
sec. 4, give every method the same input rendering time).
"""

from __future__ import annotations

import json
from typing import Any

from gdpt.cost_model import TimeModel, fit_by_probing
from gdpt.study.config import PROTOCOLS
from gdpt.study.methods import EVAL_METHODS, EvalMethod, MethodResult
from gdpt.study.scenes import EvalScene


def charged_seconds(result: MethodResult, protocol: str) -> float:
    """The seconds of ``result`` that count against the budget under ``protocol``.

    Raises:
        ValueError: ``protocol`` is not one of :data:`PROTOCOLS`.
    """
    if protocol == "total":
        return result.seconds
    if protocol == "render-time":
        return result.render_seconds
    raise ValueError(f"unknown protocol {protocol!r}; valid: {', '.join(PROTOCOLS)}")


def configuration_key(method: EvalMethod, protocol: str) -> str:
    """The name of what ``method``'s ``spp`` buys under ``protocol``: its render configuration
    as sorted JSON, without the reconstruction under ``render-time`` (not charged there);
    ``"method NAME"`` for a method without a configuration."""
    if method.configuration is None:
        return f"method {method.name}"
    config = method.configuration()
    if protocol == "render-time":
        config = {k: v for k, v in config.items() if k != "reconstruction"}
    return json.dumps(config, sort_keys=True)


def fills_seconds(method: EvalMethod, protocol: str) -> bool:
    """Whether the study gives ``method`` its budget in seconds (:attr:`EvalMethod.run_for`:
    its count its own, as a user's ``render_and_denoise(seconds=...)``) rather than a
    calibrated count: a method that can, under ``"total"`` (what it fills)."""
    return method.run_for is not None and protocol == "total"


def calibration_runner(method: EvalMethod, protocol: str) -> EvalMethod:
    """The method timed for ``method``'s calibration: the first registered method
    (:data:`~gdpt.study.methods.EVAL_METHODS` order) of the same :func:`configuration_key`
    that can run here, else ``method`` itself."""
    key = configuration_key(method, protocol)
    for candidate in EVAL_METHODS.values():
        if (
            candidate.configuration is not None
            and configuration_key(candidate, protocol) == key
            and candidate.check() is None
        ):
            return candidate
    return method


# ------------------------------------------------------------------------------- calibration
def timed_run(
    method: EvalMethod,
    scene: EvalScene,
    spp: int | None,
    seed: int,
    *,
    render_only: bool = False,
    seconds: float | None = None,
) -> MethodResult:
    """A timed render, after an untimed one at the same ``spp`` and seed unless it is warm;
    with ``render_only``, without the reconstruction where the method can be split
    (:attr:`EvalMethod.render`); with ``seconds`` (``spp`` ``None``), the method's
    :attr:`~EvalMethod.run_for` at that budget, warmed up the same way at the same seed.

    The warm-up records what a configuration needs once (kernel compilation, and the Python
    tracing of a frozen pass, which the integrators record per spp per pass and replay
    afterwards: about 0.35 s for ``gdpt`` on a 49-BSDF scene at 128 px); the timed render
    replays it, as any repeated render of that configuration does. A method that can be
    split renders a configuration set by ``spp`` alone, and records a frozen pass per pass
    size (:func:`gdpt.integrators.common.plan_passes`: a new count mostly replays passes
    recorded for others): at a count new on this scene object (:attr:`EvalScene.warm`) its
    first run is the timing unless it recorded passes (:attr:`MethodResult.recorded`; then
    it is the warm-up and runs again), and its next runs there replay, with no warm-up. The
    others (``auto``: its pilot's tiles and the route they choose depend on the seed) warm up
    every time, at the same seed, so that the warm-up records what the timed
    render replays (a warm-up on the other route left the timed render to record the route's
    passes, charged as samples it then did not render).
    """
    if seconds is not None:
        assert method.run_for is not None
        method.run_for(scene, seconds=seconds, seed=seed)
        return method.run_for(scene, seconds=seconds, seed=seed)
    render = method.render or method.run
    timed = render if render_only else method.run
    key, split = (method.name, spp, render_only), method.render is not None
    if not split:
        render(scene, spp=spp, seed=seed)
    elif key not in scene.warm:  # a count new here: warmed up only where it recorded passes
        scene.warm.add(key)
        result = timed(scene, spp=spp, seed=seed)
        if not result.recorded:
            return result
    return timed(scene, spp=spp, seed=seed)


def calibrate(
    method: EvalMethod,
    scene: EvalScene,
    *,
    budget: float,
    seed: int,
    repeats: int = 3,
    probe_fraction: float = 0.5,
    max_probe_spp: int = 1 << 16,
    protocol: str = "total",
) -> TimeModel:
    """Fit a :class:`TimeModel` by timing ``method`` on ``scene``.

    Warms up at 1 and 2 spp (untimed: the kernels compile) where the method cannot be split
    (a split method's run at a new count is its own warm-up where it records passes:
    :func:`timed_run`), takes the median of ``repeats`` 1-spp runs (a first call's loading
    is one of them at most), then raises the sample count geometrically (x2 to x8, aiming at
    the target: :func:`gdpt.cost_model.fit_by_probing`)
    until a run takes at least ``probe_fraction * budget`` (and at least two probes ran); the
    least-squares line through these timings is the model. Under ``render-time`` the
    reconstruction is not charged, so the probes skip it where the method can be split
    (:attr:`EvalMethod.render`).

    Args:
        method: the method.
        scene: the scene.
        budget: the smallest budget the model will be used for (seconds).
        seed: seed of the calibration renders (their images are discarded).
        repeats: number of 1-spp timings whose median is used.
        probe_fraction: the probing stops at this fraction of ``budget``.
        max_probe_spp: the probing stops at this sample count.
        protocol: which seconds are modelled (:func:`charged_seconds`).

    Returns:
        The fitted model.

    Raises:
        MethodUnavailable: the method cannot run here.
    """
    split = protocol == "render-time"  # the reconstruction is not charged: not run
    if method.render is None:  # (a split method's first run at a count warms up where needed)
        timed_run(method, scene, 1, seed, render_only=split)
        timed_run(method, scene, 2, seed, render_only=split)
    return fit_by_probing(
        lambda spp, offset: charged_seconds(
            timed_run(method, scene, spp, seed + offset, render_only=split), protocol
        ),
        budget=budget,
        repeats=repeats,
        probe_fraction=probe_fraction,
        max_probe_spp=max_probe_spp,
    )


#: The cost model of each ``(scene name, resolution, configuration key)`` in this process
#: (:func:`configuration_model`): fitted by the configuration's first calibration
#: (:func:`calibrate`), refined by every timed run after it (the study's cells, ``advise``).
_MODELS: dict[tuple[str, str, str], TimeModel] = {}


def forget_cost_models() -> None:
    """Start without models (each study fits its own)."""
    _MODELS.clear()


def configuration_model(
    runner: EvalMethod, scene: EvalScene, key: str, **calibration: Any
) -> tuple[TimeModel, str]:
    """The cost model of configuration ``key`` (:func:`configuration_key`) on ``scene`` (its
    name and resolution) kept in this process, refined in place by its callers' timed runs;
    where there is none, :func:`calibrate` times ``runner`` with ``calibration`` (its keyword
    arguments) and keeps the model.

    Returns:
        The model and where it came from: ``"model"`` (kept) or ``"calibrated"`` (probed now).
    """
    model_key = (scene.name, str(scene.resolution), key)
    if (model := _MODELS.get(model_key)) is not None:
        return model, "model"
    model = _MODELS[model_key] = calibrate(runner, scene, **calibration)
    return model, "calibrated"


def run_at_budget(
    method: EvalMethod,
    scene: EvalScene,
    model: TimeModel,
    *,
    budget: float,
    seed: int,
    tolerance: float = 0.2,
    max_rounds: int = 3,
    protocol: str = "total",
) -> tuple[MethodResult, dict[str, Any]]:
    """Render ``method`` with the sample count that fills ``budget``, checking the time.

    Renders at ``model.spp_for(budget)``; while the achieved time misses the budget by more
    than ``tolerance`` (relative) and rounds remain, the per-spp cost is re-estimated from the
    achieved time (:meth:`TimeModel.update`) and the cell rendered again. The run closest to
    the budget is returned; the model keeps the last estimate.

    Args:
        method: the method.
        scene: the scene.
        model: its calibrated cost model.
        budget: seconds.
        seed: seed of every attempt (the chosen one is the cell's replicate of that seed).
        tolerance: accepted relative deviation.
        max_rounds: renders at most.
        protocol: which seconds fill the budget (:func:`charged_seconds`); ``model`` must
            have been calibrated under the same protocol.

    Returns:
        The chosen run and a record: ``spp``, ``seconds`` (sampling + reconstruction),
        ``render_seconds``, ``reconstruct_seconds``, ``charged_seconds`` (under
        ``protocol``), ``relative_error`` (of the charged seconds), ``attempts`` (``[{"spp",
        "seconds", "charged_seconds", "seed", "compile_seconds"}]``), ``within_tolerance``,
        ``over_budget_at_1spp``, ``protocol``.
    """
    attempts: list[dict[str, Any]] = []
    best: tuple[float, MethodResult, int] | None = None
    spp = model.spp_for(budget)
    for _ in range(max_rounds):
        result = timed_run(method, scene, spp, seed)
        charged = charged_seconds(result, protocol)
        attempts.append(
            {
                "spp": spp,
                "seconds": result.seconds,
                "charged_seconds": charged,
                "seed": seed,
                "compile_seconds": result.compile_seconds,
            }
        )
        error = abs(charged - budget) / budget
        if best is None or error < best[0]:
            best = (error, result, spp)
        if error <= tolerance:
            break
        model.update(spp, charged)
        new_spp = model.spp_for(budget)
        if new_spp == spp:
            break
        spp = new_spp
    assert best is not None
    error, result, spp = best
    record = {
        "spp": spp,
        "seed": seed,
        "seconds": result.seconds,
        "render_seconds": result.render_seconds,
        "reconstruct_seconds": result.reconstruct_seconds,
        "compile_seconds": result.compile_seconds,
        "charged_seconds": charged_seconds(result, protocol),
        "relative_error": (charged_seconds(result, protocol) - budget) / budget,
        "within_tolerance": error <= tolerance,
        "over_budget_at_1spp": spp == 1
        and charged_seconds(result, protocol) > budget * (1 + tolerance),
        "protocol": protocol,
        "attempts": attempts,
    }
    return result, record
