"""The route of ``method="auto"``: a pilot render chooses gradients or not, and its samples go
into the final image.

Two routes fill the same render time; ``spp`` counts the plain route's samples:

* ``gradient``: gradient-domain samples with :data:`~gdpt.adapters.FUSE_PRIMAL_SPP_FACTOR`
  plain path samples pooled into the primal per gradient sample, reconstructed by ``fuse``;
* ``plain``: plain path samples (features on), reconstructed by the primal-only denoiser ``D``
  (:func:`gdpt.adapters.plain_denoiser`).

The pilot (:func:`run_pilot`) is two independent renders: ``B`` first (below), whose seconds per
sample predict the render's time, so that a pilot whose statistics would cost more than
:data:`STATISTICS_SHARE` of it (as measured by this process's last pilot) stops there, and
``A``, the gradient route's input at
``g`` gradient spp (:func:`pilot_size`: at least ``pilot_spp``; its gradient samples, the only
part the plain route cannot use, cost at most :data:`PILOT_SHARE` of the render), and ``B``,
plain samples, :data:`HELD_OUT_SHARE` of the render. ``B`` is held out: for any image ``X``
made from ``A``, ``w (X - P_B)^2 - w var(P_B)`` is an unbiased estimate of ``X``'s relative
squared error (``w = 1 / (eps + L_D^2)``, the weight of the relMSE metric). On the centre
:data:`PILOT_WINDOW` square it measures

* ``E``: the relMSE of ``D`` on ``A`` and of ``D`` on ``A``'s halves, hence the denoiser's error
  decay ``E(n) ~ n^-beta`` (``beta = log2(E_half / E)``, clamped to ``[0, 1]``: no decay to
  pure variance);
* ``delta``: relMSE(``fuse``) - relMSE(``D``) on ``A`` (the held-out noise cancels) and its
  standard error from :data:`PILOT_TILE` px tiles;
* the cost ratio ``c`` of a gradient sample to a plain one, from ``A``'s two passes.

Prediction at the main render's sample counts (:func:`predict`): ``fuse``'s relMSE over ``D``'s
is ``r = 1 + delta / E`` at the pilot, carried to the main counts by the per-pixel model of
:func:`gdpt.reconstruct.fuse.predicted_gain` (``D``'s error scaled by ``(n / N)^beta``, the
gradient variances by ``g / G``: the model's ratio between the two counts, so its optimism
cancels). At equal time the gradient route's primal has ``sample_ratio = (1 + f) / (c + f)`` of
the plain route's samples, so it is taken when ``r_main < sample_ratio^beta``
(:func:`decide`), and only where the pilot saw ``fuse`` beat ``D`` by :data:`SIGNIFICANCE`
standard errors (Kettunen et al. 2019, Fig. 5: noisy gradients hurt). Both pilot renders go
into the final image (:func:`render_route`, :func:`gdpt.buffers.merge_renders`), and what the
pilot cost beyond the samples either route keeps (the gradient samples' extra cost on the plain
route, the statistics' time on both) is charged to the main render in plain samples; below
:func:`pilot_threshold` plain spp no pilot fits and the route is plain. Measurements:
``docs/gradients.md``.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import torch

from gdpt import methods, rendering
from gdpt.adapters import FUSE_PRIMAL_SPP_FACTOR, fusion_statistics_of, plain_denoiser
from gdpt.buffers import GradientBuffers, merge_renders, primal_count
from gdpt.reconstruct.fuse import fuse_statistics, predicted_gain

#: Clamp of the measured gradient/plain sample cost ratio (2-3 on warm renders, up to ~13 on a
#: first render that records its frozen passes).
COST_RATIO_RANGE = (1.0, 4.0)

#: Fewest gradient spp of the pilot's gradient render (its halves need two).
PILOT_SPP = 2

#: Side of the centre crop the pilot's statistics are computed on (pixels).
PILOT_WINDOW = 256

#: Largest share of the main render's cost that the pilot's gradient samples may take (the
#: plain route cannot use them; everything else of the pilot goes into the image).
PILOT_SHARE = 0.02

#: Share of the main render's plain samples rendered first as the pilot's held-out render (both
#: routes use them: the plain route as its samples, the gradient route pooled into its primal).
HELD_OUT_SHARE = 0.25

#: Gradient/plain sample cost ratio assumed before a pilot measured it (2-3 on warm renders,
#: ``benchmarks/method_cost.py``).
DEFAULT_COST_RATIO = 2.0

#: Standard errors by which the pilot must see ``fuse`` beat ``D`` before the gradient route is
#: considered (a one-sided 5% test: the gain must be visible).
SIGNIFICANCE = 1.645

#: Side of the tiles whose means give the standard error of the pilot's measured difference
#: (pixels; neighbouring pixels of a denoise are correlated, tiles much less).
PILOT_TILE = 16

#: Largest share of the main render's time that the pilot's statistics may take: a pilot whose
#: statistics took longer (per window pixel, :data:`_STATISTICS_SECONDS_PER_PIXEL`) than this
#: share of the render's predicted time (its held-out render's seconds per sample times
#: ``spp``) does not look again; the plain route, its held-out samples kept.
STATISTICS_SHARE = 0.02

#: The statistics' seconds per window pixel of this process's last pilot, per denoiser: a
#: measured machine constant (three denoises and a ``fuse`` of the window), not a setting.
_STATISTICS_SECONDS_PER_PIXEL: dict[str, float] = {}

#: relMSE's ``eps`` (:func:`gdpt.metrics.relmse`).
RELMSE_EPS = 1e-3

#: Mixed into the seed of the pilot's held-out plain render.
HELD_OUT_SEED_SALT = 0x5BD1E995


@dataclass
class PilotEvidence:
    """What the pilot measured (:func:`run_pilot`), the input of :func:`predict`.

    Attributes:
        error: held-out relMSE of ``D`` on the pilot's gradient render ``A``.
        error_half: the same for ``D`` on ``A``'s halves (mean of both).
        delta: held-out relMSE of ``fuse`` minus that of ``D`` on ``A`` (< 0: ``fuse`` wins).
        delta_se: standard error of ``delta`` (from tile means).
        model_pilot: :func:`~gdpt.reconstruct.fuse.predicted_gain` at the pilot's counts.
        model_main: the same with the statistics scaled to the main render's counts.
        nonfinite: pixels left out because a term was not finite.
    """

    error: float
    error_half: float
    delta: float
    delta_se: float
    model_pilot: float
    model_main: float
    nonfinite: int = 0


@dataclass
class RouteChoice:
    """The route ``method="auto"`` took and why.

    Attributes:
        route: ``"gradient"`` or ``"plain"``.
        method: the reconstruction method of that route (``"fuse"`` or the denoiser).
        gain: predicted relative MSE of the fusion over the plain denoise of the same input at
            the main render's counts (1 where the pilot did not see ``fuse`` win).
        sample_ratio: primal samples of the gradient route over the plain route's at equal time.
        cost_ratio: measured cost of a gradient sample over a plain one (clamped to
            :data:`COST_RATIO_RANGE`).
        pilot_seconds: wall time of the pilot (renders and statistics).
        reason: one line for the CLI and the metadata.
        decay: measured exponent ``beta`` of the denoiser's error decay (1 without a pilot).
        pilot: the pilot's sample counts (``gradient_spp``, ``primal_spp``, ``held_out_spp``,
            ``cost_spp``: its cost in plain samples: ``gradient_spp * cost_ratio`` plus its
            plain samples plus the statistics' seconds over the held-out render's seconds per
            sample) and its :class:`PilotEvidence`; empty
            without a pilot.
    """

    route: str
    method: str
    gain: float
    sample_ratio: float
    cost_ratio: float
    pilot_seconds: float
    reason: str
    decay: float = 1.0
    pilot: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def decide(
    gain: float,
    cost_ratio: float,
    factor: float,
    decay: float = 1.0,
    sample_ratio: float | None = None,
) -> tuple[str, float]:
    """``(route, sample_ratio)`` for a predicted ``gain`` (fuse's relMSE over ``D``'s), a
    gradient/plain ``cost_ratio``, the pooling ``factor`` and the denoiser's error ``decay``
    exponent: the gradient route when ``gain < sample_ratio ** decay``; ``sample_ratio``
    (primal samples of the gradient route over the plain route's at equal time) defaults to
    ``(1 + factor) / (cost_ratio + factor)``."""
    if sample_ratio is None:
        sample_ratio = (1.0 + factor) / (cost_ratio + factor)
    return ("gradient" if gain < sample_ratio**decay else "plain"), sample_ratio


def pilot_size(spp: int, pilot_spp: int = PILOT_SPP) -> tuple[int, int, int]:
    """``(gradient_spp, pooled_spp, held_out_spp)`` of the pilot of a render of ``spp`` plain
    samples: at least ``pilot_spp`` gradient samples, more while their cost beyond plain ones
    stays within :data:`PILOT_SHARE` of ``spp`` (at :data:`DEFAULT_COST_RATIO`); the held-out
    render has :data:`HELD_OUT_SHARE` of ``spp``, at least as many samples as the gradient
    render's primal."""
    g = max(pilot_spp, math.floor(PILOT_SHARE * spp / (DEFAULT_COST_RATIO - 1.0)))
    pooled = round(FUSE_PRIMAL_SPP_FACTOR * g)
    return g, pooled, max(g + pooled, math.floor(HELD_OUT_SHARE * spp))


def pilot_threshold(pilot_spp: int = PILOT_SPP) -> int:
    """Fewest plain samples per pixel of the main render for which a pilot of ``pilot_spp``
    gradient samples fits (its primal and held-out samples, which go into the image, leave at
    least one plain sample to render): 15 for the default pilot."""
    g, pooled, held_out = pilot_size(0, pilot_spp)
    return g + pooled + held_out + 1


def _relative_terms(image: torch.Tensor, held_out: torch.Tensor, weight: torch.Tensor):
    """Per pixel ``w mean_c (image - held_out)^2`` ``(H, W)``."""
    return weight * (image - held_out).square().mean(-1)


def _tile_se(values: torch.Tensor, finite: torch.Tensor, tile: int) -> float:
    """Standard error of the mean of ``values`` ``(H, W)`` over ``finite`` pixels, from the
    means of ``tile`` px tiles (per pixel where fewer than two tiles hold finite pixels)."""
    h, w = values.shape
    th, tw = max(1, h // tile), max(1, w // tile)
    v = (
        torch.where(finite, values, 0.0)[: th * tile, : tw * tile]
        if h >= tile and w >= tile
        else None
    )
    if v is not None and th * tw >= 2:
        n = finite[: th * tile, : tw * tile].reshape(th, tile, tw, tile).sum((1, 3)).double()
        s = v.reshape(th, tile, tw, tile).sum((1, 3)).double()
        keep = n > 0
        if int(keep.sum()) >= 2:
            means = s[keep] / n[keep]
            return float(means.std() / math.sqrt(int(keep.sum())))
    x = values[finite].double()
    return float(x.std() / math.sqrt(x.numel())) if x.numel() >= 2 else math.inf


def measure(
    pilot: GradientBuffers,
    held_out: GradientBuffers,
    denoise: Any,
    *,
    main_primal: float,
    main_gradient: float,
) -> PilotEvidence:
    """:class:`PilotEvidence` of a pilot gradient render and its held-out plain render (both
    with variances and halves, cropped alike), ``denoise(buffers) -> image`` the primal-only
    denoiser; ``main_primal`` and ``main_gradient`` are the gradient route's primal and
    gradient samples per pixel at the main render, where the model is evaluated."""
    images: list[torch.Tensor] = []

    def recording(buffers: GradientBuffers) -> torch.Tensor:
        images.append(denoise(buffers))
        return images[-1]

    statistics = fusion_statistics_of(pilot, recording)  # denoises the full render, a, b
    denoised, half_a, half_b = images
    fused, info = fuse_statistics(statistics, pilot.dx, pilot.dy)
    device = denoised.device
    reference = held_out.primal.to(device)
    weight = 1.0 / (RELMSE_EPS + denoised.mean(-1).square())
    noise = weight * _variance_of_mean(held_out).to(device)
    d_terms = _relative_terms(denoised, reference, weight)
    half_terms = (
        _relative_terms(half_a, reference, weight) + _relative_terms(half_b, reference, weight)
    ) / 2
    if info.trusted == 0.0:
        delta_terms = torch.zeros_like(d_terms)
    else:
        delta_terms = _relative_terms(fused, reference, weight) - d_terms
    terms = (d_terms - noise, half_terms - noise, delta_terms)
    finite = torch.stack([torch.isfinite(t) for t in terms]).all(0)
    count = max(int(finite.sum()), 1)
    error, error_half, delta = (float(torch.where(finite, t, 0.0).sum()) / count for t in terms)
    s_error = primal_count(pilot) / max(main_primal, 1.0)
    s_variance = pilot.spp / max(main_gradient, 1.0)
    e = statistics.floored_error()
    decay = _decay(error, error_half)
    model_pilot = predicted_gain(denoised, e, statistics.var_dx, statistics.var_dy)
    model_main = predicted_gain(
        denoised,
        e * s_error**decay,
        statistics.var_dx * s_variance,
        statistics.var_dy * s_variance,
    )
    return PilotEvidence(
        error=error,
        error_half=error_half,
        delta=delta,
        delta_se=_tile_se(delta_terms, finite, PILOT_TILE),
        model_pilot=model_pilot,
        model_main=model_main,
        nonfinite=int((~finite).sum()),
    )


def _variance_of_mean(render: GradientBuffers) -> torch.Tensor:
    """``(H, W)`` variance of the render's primal mean: ``var_primal``, else from its halves
    (``mean_c (p_a - p_b)^2 / 4``, equal halves), else 0."""
    if render.var_primal is not None:
        return render.var_primal[..., 0]
    if render.has_halves:
        return (render.primal_a - render.primal_b).square().mean(-1) / 4
    return torch.zeros_like(render.primal[..., 0])


def _decay(error: float, error_half: float) -> float:
    """``beta`` of ``E(n) ~ n^-beta`` from the errors at ``n`` and ``n / 2``, in ``[0, 1]`` (1
    when either is not positive)."""
    if not (error > 0 and error_half > 0):
        return 1.0
    return min(max(math.log2(error_half / error), 0.0), 1.0)


def predict(
    evidence: PilotEvidence,
    cost_ratio: float,
    factor: float = FUSE_PRIMAL_SPP_FACTOR,
    sample_ratio: float | None = None,
) -> tuple[str, float, float, str]:
    """``(route, gain, decay, reason)`` from what the pilot measured (see the module docstring).

    A pilot whose held-out error of ``D`` is not positive (nothing measurable: a black or
    noiseless image, every statistic floored) takes the plain route and says so.
    """
    if not (math.isfinite(evidence.error) and evidence.error > 0):
        reason = (
            f"the pilot cannot decide (held-out error of the denoiser {evidence.error:.3g} is "
            "not above zero: nothing measurable); plain route"
        )
        return "plain", 1.0, 1.0, reason
    decay = _decay(evidence.error, evidence.error_half)
    measured = 1.0 + evidence.delta / evidence.error
    significant = evidence.delta + SIGNIFICANCE * evidence.delta_se < 0
    scale = evidence.model_main / evidence.model_pilot if evidence.model_pilot > 0 else 1.0
    gain = min(1.0, measured * scale) if significant else 1.0
    route, ratio = decide(gain, cost_ratio, factor, decay, sample_ratio)
    seen = (
        f"fuse/D {measured:.2f} on the pilot ({evidence.delta / evidence.error:+.2f} "
        f"+- {evidence.delta_se / evidence.error:.2f})"
    )
    verdict = "<" if route == "gradient" else ">="
    reason = (
        f"{seen}, predicted {gain:.2f} at the main render {verdict} primal sample ratio "
        f"{ratio:.2f}^{decay:.2f} at equal time (a gradient sample costs {cost_ratio:.1f} plain "
        "ones)"
    )
    if not significant:  # even where gradient samples cost no more than plain ones
        route, reason = "plain", f"{seen}: no significant gain; plain route"
    return route, gain, decay, reason


def run_pilot(
    scene: Any, *, spp: int, seed: int = 0, pilot_spp: int = PILOT_SPP, **props: Any
) -> tuple[RouteChoice, list[GradientBuffers]]:
    """Render the pilot of ``scene`` and choose the route (see the module docstring).

    Args:
        scene: an ``mi.Scene`` (or anything :func:`gdpt.render` accepts).
        spp: plain samples per pixel of the main render; below :func:`pilot_threshold` no
            pilot is rendered and the route is plain.
        seed: the pilot's seed.
        pilot_spp: fewest gradient samples per pixel of the pilot (>= 2: it needs halves).
        **props: integrator properties (``max_depth``, ...).

    Returns:
        The :class:`RouteChoice` and the pilot's renders (gradient, held-out; none without a
        pilot), for :func:`render_route`. A pilot that renders black (no light reaches the
        film) or cannot measure anything takes the plain route and says so.

    Raises:
        ValueError: ``pilot_spp < 2``.
    """
    if pilot_spp < 2:
        raise ValueError(f"pilot_spp must be >= 2 (the pilot needs halves), got {pilot_spp}")
    factor = FUSE_PRIMAL_SPP_FACTOR
    if spp < (threshold := pilot_threshold(pilot_spp)):
        _, ratio = decide(1.0, DEFAULT_COST_RATIO, factor)
        reason = f"{spp} spp: no room for a pilot (it needs >= {threshold} spp); plain route"
        choice = RouteChoice("plain", plain_denoiser(), 1.0, ratio, DEFAULT_COST_RATIO, 0.0, reason)
        return choice, []
    start = time.perf_counter()
    g, pooled, held_out_spp = pilot_size(spp, pilot_spp)
    props = {
        k: v
        for k, v in props.items()
        if k not in ("variance", "halves", "gradients", "features", "primal_spp")
    }
    denoiser, denoise = methods.primal_only()
    held_out = rendering.render(
        scene,
        spp=held_out_spp,
        seed=(seed ^ HELD_OUT_SEED_SALT) & 0xFFFFFFFF,
        **{**props, **methods.METHODS[denoiser].sampling(held_out_spp)},
        variance=True,
        halves=True,
    )
    seconds_per_spp = max(held_out.metadata["render_seconds"] / held_out_spp, 1e-9)
    window = min(held_out.height, PILOT_WINDOW) * min(held_out.width, PILOT_WINDOW)
    looking = _STATISTICS_SECONDS_PER_PIXEL.get(denoiser, 0.0) * window
    if looking > STATISTICS_SHARE * spp * seconds_per_spp:
        _, ratio = decide(1.0, DEFAULT_COST_RATIO, factor)
        reason = (
            f"looking would cost ~{looking:.2f} s of statistics, more than {STATISTICS_SHARE:.0%} "
            f"of the render's ~{spp * seconds_per_spp:.2f} s; plain route"
        )
        counts = {"gradient_spp": 0, "primal_spp": 0, "held_out_spp": held_out_spp}
        counts["cost_spp"] = held_out_spp
        seconds = time.perf_counter() - start
        choice = RouteChoice(
            "plain", denoiser, 1.0, ratio, DEFAULT_COST_RATIO, seconds, reason, pilot=counts
        )
        return choice, [held_out]
    pilot = rendering.render(
        scene, spp=g, seed=seed, **{**props, **methods.METHODS["fuse"].sampling(g)}
    )
    t_gradient = pilot.metadata["render_seconds"] - pilot.metadata["primal_only"]["render_seconds"]
    t_plain = pilot.metadata["primal_only"]["render_seconds"]
    cost_ratio = (t_gradient / g) / max(t_plain / pooled, 1e-9)
    cost_ratio = min(max(cost_ratio, COST_RATIO_RANGE[0]), COST_RATIO_RANGE[1])
    renders = [pilot, held_out]
    counts = {"gradient_spp": g, "primal_spp": pooled, "held_out_spp": held_out_spp}
    counts["cost_spp"] = g * cost_ratio + pooled + held_out_spp
    if float(pilot.primal.abs().max()) == 0.0:
        seconds = time.perf_counter() - start
        _, ratio = decide(1.0, cost_ratio, factor)
        reason = "the pilot rendered black (no light reaches the film): nothing to fuse"
        choice = RouteChoice(
            "plain", denoiser, 1.0, ratio, cost_ratio, seconds, reason, pilot=counts
        )
        return choice, renders
    main_gradient = g + gradient_spp_for(spp - counts["cost_spp"], cost_ratio)
    main_primal = primal_count(pilot) + held_out_spp + main_gradient - g
    main_primal += round(factor * (main_gradient - g))
    measure_start = time.perf_counter()
    evidence = measure(
        pilot.centre_crop(PILOT_WINDOW),
        held_out.centre_crop(PILOT_WINDOW),
        denoise,
        main_primal=main_primal,
        main_gradient=main_gradient,
    )
    statistics_seconds = time.perf_counter() - measure_start
    _STATISTICS_SECONDS_PER_PIXEL[denoiser] = statistics_seconds / window
    counts["cost_spp"] += statistics_seconds / seconds_per_spp
    route, gain, decay, reason = predict(evidence, cost_ratio, factor, main_primal / spp)
    if evidence.nonfinite:
        reason += f" ({evidence.nonfinite} pixels with non-finite statistics left out)"
    _, ratio = decide(gain, cost_ratio, factor, decay, main_primal / spp)
    seconds = time.perf_counter() - start
    method = "fuse" if route == "gradient" else denoiser
    pilot_info = {**counts, "evidence": asdict(evidence)}
    choice = RouteChoice(route, method, gain, ratio, cost_ratio, seconds, reason, decay, pilot_info)
    return choice, renders


def choose_route(
    scene: Any, *, spp: int, seed: int = 0, pilot_spp: int = PILOT_SPP, **props: Any
) -> RouteChoice:
    """The :class:`RouteChoice` of :func:`run_pilot` (its renders discarded)."""
    return run_pilot(scene, spp=spp, seed=seed, pilot_spp=pilot_spp, **props)[0]


def gradient_spp_for(cost: float, cost_ratio: float) -> int:
    """Gradient samples per pixel (with their pooled plain ones) that cost ``cost`` plain
    samples, at least 1."""
    return max(1, round(cost / (cost_ratio + FUSE_PRIMAL_SPP_FACTOR)))


def route_sampling(choice: RouteChoice, spp: int) -> dict[str, Any]:
    """Keyword arguments of :func:`gdpt.render` for the main render of ``choice`` at the cost
    of ``spp`` plain samples per pixel: the plain route's ``spp`` samples, or the gradient
    route's pooled input of the same cost (``spp / (cost_ratio + f)`` gradient samples, at
    least 1)."""
    if choice.route == "plain":
        return {"spp": spp, **methods.METHODS[choice.method].sampling(spp)}
    gradient_spp = gradient_spp_for(spp, choice.cost_ratio)
    return {"spp": gradient_spp, **methods.METHODS["fuse"].sampling(gradient_spp)}


def render_route(
    scene: Any,
    choice: RouteChoice,
    pilot: list[GradientBuffers],
    *,
    spp: int,
    seed: int,
    **props: Any,
) -> GradientBuffers:
    """The main render of ``choice`` at the cost of ``spp`` plain samples per pixel, merged
    with the ``pilot``'s renders (:func:`gdpt.buffers.merge_renders`).

    Either route renders what is left of the cost of ``spp`` plain samples after the pilot's
    ``cost_spp`` (at least 1 sample, :func:`route_sampling`): the plain route keeps the pilot's
    primal and held-out samples (its gradients left out), so its image holds ``spp`` minus what
    looking cost beyond them; the gradient route keeps the pilot's gradients too. ``props`` as
    for :func:`gdpt.render` (they override the route's sampling).
    """
    if not pilot:
        sampling = route_sampling(choice, spp)
        return rendering.render(scene, seed=seed, **{**sampling, **props})
    if choice.route == "plain":
        sampling = route_sampling(choice, max(1, round(spp - choice.pilot["cost_spp"])))
        main = rendering.render(scene, seed=seed, **{**sampling, **props})
        plain = [r.replace(dx=None, dy=None, var_dx=None, var_dy=None) for r in pilot]
        keep = set(main.present())
        return merge_renders(
            [r.replace(**{n: None for n in r.present() if n not in keep}) for r in [*plain, main]]
        )
    sampling = route_sampling(choice, max(1, round(spp - choice.pilot["cost_spp"])))
    main = rendering.render(scene, seed=seed, **{**sampling, **props})
    return merge_renders([*pilot, main])
