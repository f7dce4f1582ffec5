"""The route of ``method="auto"``: a short pilot render chooses gradients or not.

Two routes fill the same render time; ``spp`` counts the plain route's samples:

* ``gradient``: gradient-domain samples with :data:`~gdpt.adapters.FUSE_PRIMAL_SPP_FACTOR`
  plain path samples pooled into the primal per gradient sample, reconstructed by ``fuse``;
* ``plain``: plain path samples (features on), reconstructed by the primal-only denoiser
  (:func:`gdpt.adapters.plain_denoiser`).

The pilot renders the gradient route's input at ``pilot_spp`` (with variances and halves),
measures the cost ratio ``c`` of a gradient sample to a plain one from its two passes, and
predicts the fusion's relative error ``gain`` on its centre :data:`PILOT_WINDOW` square
(:func:`gdpt.reconstruct.fuse.fusion_statistics`, :func:`gdpt.reconstruct.fuse.predicted_gain`
times :data:`PREDICTION_BIAS`). At equal time the gradient route's primal has ``sample_ratio =
(1 + f) / (c + f)`` of the plain route's samples (``f`` the pooling factor); the gradient route
is taken when ``gain < sample_ratio`` (Kettunen et al. 2019, Fig. 5: noisy gradients hurt).
Below :func:`pilot_threshold` plain samples per pixel there is no pilot and the route is plain.
Calibration: ``docs/gradients.md``.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import Any

from gdpt import methods, rendering
from gdpt.adapters import FUSE_PRIMAL_SPP_FACTOR, fusion_statistics_of, plain_denoiser
from gdpt.reconstruct.fuse import predicted_gain

#: Measured fusion gain over the per-pixel prediction, 10.6-26.3 (``random:5``, ``cbox-demo``,
#: 128 px, 8 and 32 gradient spp; ``benchmarks/fuse_calibration.py``).
PREDICTION_BIAS = 20.0

#: Clamp of the measured gradient/plain sample cost ratio (2-3 on warm renders, up to ~13 on a
#: first render that records its frozen passes).
COST_RATIO_RANGE = (1.0, 4.0)

#: Gradient spp of the pilot render (plus its pooled plain samples).
PILOT_SPP = 4

#: Side of the centre crop the pilot's statistics are computed on (pixels).
PILOT_WINDOW = 256

#: Largest share of the main render's samples a pilot may take (:func:`pilot_threshold`).
PILOT_SHARE = 0.05

#: Gradient/plain sample cost ratio assumed before a pilot measured it (2-3 on warm renders,
#: ``benchmarks/method_cost.py``).
DEFAULT_COST_RATIO = 2.0


@dataclass
class RouteChoice:
    """The route ``method="auto"`` took and why.

    Attributes:
        route: ``"gradient"`` or ``"plain"``.
        method: the reconstruction method of that route (``"fuse"`` or the denoiser).
        gain: predicted relative MSE of the fusion over the plain denoise of the same input
            (bias-corrected, capped at 1).
        sample_ratio: primal samples of the gradient route over the plain route's at equal time.
        cost_ratio: measured cost of a gradient sample over a plain one (clamped to
            :data:`COST_RATIO_RANGE`).
        pilot_seconds: wall time of the pilot (render and statistics).
        reason: one line for the CLI and the metadata.
    """

    route: str
    method: str
    gain: float
    sample_ratio: float
    cost_ratio: float
    pilot_seconds: float
    reason: str

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def decide(gain: float, cost_ratio: float, factor: float) -> tuple[str, float]:
    """``(route, sample_ratio)`` for a predicted (bias-corrected) ``gain``, a gradient/plain
    ``cost_ratio`` and the pooling ``factor`` (see the module docstring)."""
    sample_ratio = (1.0 + factor) / (cost_ratio + factor)
    return ("gradient" if gain < sample_ratio else "plain"), sample_ratio


def pilot_threshold(pilot_spp: int = PILOT_SPP) -> int:
    """Fewest plain samples per pixel of the main render for which a pilot of ``pilot_spp``
    gradient samples (and its pooled plain ones) is at most :data:`PILOT_SHARE` of the samples:
    360 for the default pilot."""
    return math.ceil(pilot_spp * (DEFAULT_COST_RATIO + FUSE_PRIMAL_SPP_FACTOR) / PILOT_SHARE)


def choose_route(
    scene: Any, *, spp: int, seed: int = 0, pilot_spp: int = PILOT_SPP, **props: Any
) -> RouteChoice:
    """Render the pilot of ``scene`` and choose the route (see the module docstring).

    Args:
        scene: an ``mi.Scene`` (or anything :func:`gdpt.render` accepts).
        spp: plain samples per pixel of the main render (the gradient route renders
            samples of the same cost); below :func:`pilot_threshold` no pilot is rendered and
            the route is plain.
        seed: the pilot's seed.
        pilot_spp: gradient samples per pixel of the pilot (>= 2: it needs halves).
        **props: integrator properties (``max_depth``, ...).

    Returns:
        The :class:`RouteChoice`. A pilot that renders black (no light reaches the film)
        takes the plain route and says so.

    Raises:
        ValueError: ``pilot_spp < 2``.
    """
    if pilot_spp < 2:
        raise ValueError(f"pilot_spp must be >= 2 (the pilot needs halves), got {pilot_spp}")
    factor = FUSE_PRIMAL_SPP_FACTOR
    if spp < (threshold := pilot_threshold(pilot_spp)):
        _, ratio = decide(1.0, DEFAULT_COST_RATIO, factor)
        reason = (
            f"{spp} spp: a pilot would take more than {PILOT_SHARE:.0%} of the samples "
            f"(it needs >= {threshold} spp); plain route"
        )
        return RouteChoice("plain", plain_denoiser(), 1.0, ratio, DEFAULT_COST_RATIO, 0.0, reason)
    start = time.perf_counter()
    plain_spp = max(1, round(factor * pilot_spp))
    pilot = rendering.render(
        scene,
        spp=pilot_spp,
        seed=seed,
        primal_spp=plain_spp,
        variance=True,
        halves=True,
        **{k: v for k, v in props.items() if k not in ("variance", "halves")},
    )
    t_gradient = pilot.metadata["render_seconds"] - pilot.metadata["primal_only"]["render_seconds"]
    t_plain = pilot.metadata["primal_only"]["render_seconds"]
    cost_ratio = (t_gradient / pilot_spp) / max(t_plain / plain_spp, 1e-9)
    cost_ratio = min(max(cost_ratio, COST_RATIO_RANGE[0]), COST_RATIO_RANGE[1])
    if float(pilot.primal.abs().max()) == 0.0:
        seconds = time.perf_counter() - start
        _, ratio = decide(1.0, cost_ratio, factor)
        reason = "the pilot rendered black (no light reaches the film): nothing to fuse"
        return RouteChoice("plain", plain_denoiser(), 1.0, ratio, cost_ratio, seconds, reason)
    denoiser, denoise = methods.primal_only()
    statistics = fusion_statistics_of(pilot.centre_crop(PILOT_WINDOW), denoise)
    gain = predicted_gain(
        statistics.denoised, statistics.floored_error(), statistics.var_dx, statistics.var_dy
    )
    gain = min(1.0, PREDICTION_BIAS * gain)
    route, ratio = decide(gain, cost_ratio, factor)
    seconds = time.perf_counter() - start
    verdict = "<" if route == "gradient" else ">="
    reason = (
        f"predicted fusion gain {gain:.2f} {verdict} primal sample ratio {ratio:.2f} at equal "
        f"time (a gradient sample costs {cost_ratio:.1f} plain ones)"
    )
    method = "fuse" if route == "gradient" else denoiser
    return RouteChoice(route, method, gain, ratio, cost_ratio, seconds, reason)


def route_sampling(choice: RouteChoice, spp: int) -> dict[str, Any]:
    """Keyword arguments of :func:`gdpt.render` for the main render of ``choice`` at the cost
    of ``spp`` plain samples per pixel: the plain route's ``spp`` samples, or the gradient
    route's pooled input of the same cost (``spp / (cost_ratio + f)`` gradient samples, at
    least 1)."""
    if choice.route == "plain":
        return {"spp": spp, **methods.METHODS[choice.method].sampling(spp)}
    gradient_spp = max(1, round(spp / (choice.cost_ratio + FUSE_PRIMAL_SPP_FACTOR)))
    return {"spp": gradient_spp, **methods.METHODS["fuse"].sampling(gradient_spp)}
