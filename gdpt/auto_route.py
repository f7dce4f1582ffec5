"""The route of ``method="auto"``: a pilot small in pixels, at the main render's sample count,
decides gradients or not for the whole image; every sample it traced goes into the image.

Two routes fill the same render time; ``spp`` (``N``) counts the plain route's samples:

* ``gradient``: ``G = (1 - s) N / (c + f)`` gradient samples per pixel (``c``: a gradient sample's
  cost in plain ones, measured by the scene's last gradient route, :func:`learned_cost_ratio`,
  else :data:`DEFAULT_COST_RATIO`; ``f``: :data:`~gdpt.adapters.FUSE_PRIMAL_SPP_FACTOR` plain
  samples pooled per gradient sample; ``s``: :data:`FILL_SHARE` of ``N`` left to the last
  pooled plain samples, whose count is set by measured time), reconstructed by ``fuse``;
* ``plain``: plain path samples (features on), reconstructed by the primal-only denoiser ``D``
  (:func:`gdpt.adapters.plain_denoiser`).

The pilot (:func:`run_pilot`) renders a stratified random share :data:`SHARE` of the film's
:data:`TILE` px tiles (:func:`pilot_tiles`; at least :data:`MIN_TILES`) first, at the main
count: ``G`` gradient samples with offsets only in the tiles (``gdpt.render(...,
gradient_mask=tiles)``) and ``(f - 1) G - 1`` pooled plain samples. In its tiles it holds what
the gradient route's render holds there (``G`` gradient samples, ``f G`` of the ``(1 + f) G``
primal samples), so it sees the gain ``fuse`` has at the count where the gain exists;
elsewhere it holds ``f G - 1`` plain samples, which both routes keep. ``fuse``'s held-out check
(:func:`gdpt.reconstruct.fuse.held_out_fusion_terms`: each half's fusion and denoise against the
other half's primal) runs on windows of the tiles with :data:`MARGIN` px of context (the whole
image where those windows would cover more pixels than it has) and is summed over the tiles,
its standard error from :data:`~gdpt.reconstruct.held_out.BLOCK` px blocks: the gradient route
where the sum is below ``-SIGNIFICANCE`` standard errors (a one-sided 5% test that ``fuse`` beats
``D``), else the plain route.

The rest of the image (:func:`render_route`): on the gradient route ``G`` gradient samples with
offsets outside the tiles and the pooled plain samples left (at least one, for the features),
merged gradient by gradient (:func:`gdpt.buffers.merge_renders`): every traced gradient has
``G`` samples; a gradient between a tile and the rest (one pixel in each) is traced by neither
render and has no weight in ``fuse``. On the plain route, plain samples for what is left of
``N``. Either way the pilot's cost beyond what the route keeps (its gradient samples' extra cost
on the plain route, the statistics' time on both) is charged in plain samples at the plain
pass's measured seconds per sample. With a deadline (a budget in seconds,
``render_and_denoise(seconds=...)``) either route's last plain samples instead fill the time
left before it less the route's reconstruction (:func:`render_route`). The gradient route's
render (offsets on most pixels) measures the scene's cost ratio, which sizes ``G`` of the
scene's later renders (kept per scene object and integrator properties, replaced only where
it moves by more than :data:`RELEARN`:
``G`` stays put between renders, so they replay each other's frozen passes; the first gradient
route of a scene is sized at :data:`DEFAULT_COST_RATIO`). Stratified rather than simply random
tiles: one tile in each of ``n`` equal runs of the tiles in row-major order, so every band of
the image is seen (a window, a light, a dark corner) and the sum stays an unbiased sample of
the image's.
Measurements: ``docs/gradients.md``.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch

from gdpt import methods, rendering
from gdpt.adapters import FUSE_PRIMAL_SPP_FACTOR, held_out_fusion_terms_of, plain_denoiser
from gdpt.buffers import GradientBuffers, merge_renders, pool_primal
from gdpt.cost_model import TimeModel
from gdpt.reconstruct.held_out import BLOCK, choose
from gdpt.scenes.loading import load_scene

#: Side of the pilot's tiles (pixels; a multiple of :data:`~gdpt.reconstruct.held_out.BLOCK`).
TILE = 16

#: Share of the film's whole tiles the pilot renders (13 of the 64 tiles of a 128 px film; at
#: 15%, 10 tiles, the statistic missed cornell-box's gain in 2 of 9 runs: docs/gradients.md).
SHARE = 0.2

#: Fewest tiles of a pilot (32 blocks of 8 px for the standard error at 16 px tiles).
MIN_TILES = 8

#: Largest share of the tiles a pilot may take to reach :data:`MIN_TILES`; a film with fewer
#: tiles gets no pilot (the plain route, and the reason).
MAX_SHARE = 0.25

#: Context around each tile for the denoiser and the solve of its statistics (pixels).
MARGIN = 16

#: Standard errors below zero the tiles' held-out sum must reach for the gradient route.
SIGNIFICANCE = 1.645

#: Fewest gradient samples per pixel of the pilot (its halves need two).
PILOT_SPP = 2

#: Clamp of the measured gradient/plain sample cost ratio.
COST_RATIO_RANGE = (1.0, 4.0)

#: Gradient/plain sample cost ratio that sizes ``G`` on a scene's first gradient route: the median
#: of the ratios the pilots of the quick study measured (1.5-2.4 per render, 1.7-1.8 per directly
#: lit scene; docs/gradients.md).
DEFAULT_COST_RATIO = 1.8

#: Share of the plain route's count ``N`` that ``G`` leaves to the gradient route's last plain
#: samples (:func:`pilot_gradient_spp`). With a deadline they fill the time left before it, so a
#: pilot or gradient pass that runs up to this share of the budget long is taken back from them
#: (this VM's run-to-run noise at a fixed count is 5-10%; with no share left the fill was one
#: sample and ``auto`` ended up to 14% past a 4 s budget: docs/lab/2026-12-06-measurements.md).
FILL_SHARE = 0.15

#: Relative change of a scene's measured cost ratio that replaces the remembered one
#: (:func:`learned_cost_ratio`): below it ``G`` stays put between renders of the scene, so a
#: render replays the frozen passes of an earlier one of the same ``N``.
RELEARN = 0.2

#: ``(id(scene), properties) -> (scene, {"cost_ratio": ..., "reconstruct_seconds METHOD": ...,
#: "plain_samples ROUTE": TimeModel, "merge_seconds ROUTE": ...})``, what the scene's routes
#: measured, least recently used first (the scene is kept so that its id stays unique).
_LEARNED: OrderedDict[tuple, tuple[Any, dict[str, Any]]] = OrderedDict()
_LEARNED_SIZE = 8

#: Timings of a route's last plain samples that its model of them is fitted to
#: (:func:`learned_plain_samples`), the most recent kept.
PLAIN_TIMINGS = 8


@dataclass
class RouteChoice:
    """The route ``method="auto"`` took and why.

    Attributes:
        route: ``"gradient"`` or ``"plain"``.
        method: the reconstruction method of that route (``"fuse"`` or the denoiser).
        reason: one line for the CLI and the metadata.
        cost_ratio: cost of a gradient sample over a plain one that sized ``G``
            (:func:`learned_cost_ratio`, else :data:`DEFAULT_COST_RATIO`); the pilot's own
            measurement is ``pilot["measured_cost_ratio"]``.
        pilot_seconds: wall time of the pilot (render and statistics).
        pilot: without a pilot, empty; else ``gradient_spp`` (``G``), ``primal_spp`` (its
            pooled plain samples), ``tile``, ``tiles`` (how many), ``share`` (of the film's
            pixels), ``window_pixels`` (the statistics' windows), ``statistic`` (the tiles'
            held-out sum in standard errors, < 0: ``fuse`` looks better), ``difference`` (its
            relMSE difference per tile pixel), ``nonfinite`` (terms left out),
            ``statistics_seconds``, ``seconds_per_spp`` (a plain sample's),
            ``primal_replayed`` (its pooled plain pass replayed its frozen passes),
            ``cost_spp`` (the pilot's cost in plain samples, statistics included),
            ``measured_cost_ratio`` (from its two passes, clamped to :data:`COST_RATIO_RANGE`).
    """

    route: str
    method: str
    reason: str
    cost_ratio: float = DEFAULT_COST_RATIO
    pilot_seconds: float = 0.0
    pilot: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class Pilot:
    """The pilot's render and tiles, for :func:`render_route`.

    Attributes:
        render: ``fuse``'s input at ``G`` gradient spp, offsets in the tiles only.
        tiles: ``(H, W)`` bool, the pilot's tiles (on the render's device).
    """

    render: GradientBuffers
    tiles: torch.Tensor


def gradient_spp_for(cost: float, cost_ratio: float) -> int:
    """Gradient samples per pixel (with their pooled plain ones) that cost ``cost`` plain
    samples, at least 1."""
    return max(1, round(cost / (cost_ratio + FUSE_PRIMAL_SPP_FACTOR)))


def pilot_gradient_spp(spp: int, cost_ratio: float) -> int:
    """``G`` of a pilot (and its route) at ``spp`` plain samples per pixel: the gradient
    samples that cost ``1 -`` :data:`FILL_SHARE` of them (:func:`gradient_spp_for`)."""
    return gradient_spp_for((1.0 - FILL_SHARE) * spp, cost_ratio)


def pooled_spp(gradient_spp: int) -> int:
    """Pooled plain samples of the pilot at ``gradient_spp``: ``(f - 1) G - 1`` rounded, at
    least 1 (the rest of the image adds ``G`` plain samples and one pooled one)."""
    return max(1, math.floor((FUSE_PRIMAL_SPP_FACTOR - 1.0) * gradient_spp + 0.5) - 1)


def pilot_threshold() -> int:
    """Fewest plain samples per pixel for which the pilot's ``G`` reaches :data:`PILOT_SPP` at
    the default cost ratio: 8."""
    spp = 1
    while pilot_gradient_spp(spp, DEFAULT_COST_RATIO) < PILOT_SPP:
        spp += 1
    return spp


def tile_grid(height: int, width: int, tile: int = TILE) -> tuple[int, int]:
    """``(rows, columns)`` of whole ``tile`` px tiles of an ``height x width`` film.

    Raises:
        ValueError: ``tile`` is not a positive multiple of the held-out blocks or is larger
            than the film (named).
    """
    if not isinstance(tile, int) or isinstance(tile, bool) or tile < 1 or tile % BLOCK:
        raise ValueError(f"pilot tile must be a positive multiple of {BLOCK} px, got {tile!r}")
    if tile > min(height, width):
        raise ValueError(f"pilot tile {tile} px does not fit the {width}x{height} film")
    return height // tile, width // tile


def tile_count(height: int, width: int, tile: int = TILE, share: float = SHARE) -> int:
    """Tiles of the pilot on an ``height x width`` film: ``share`` of its whole tiles, at least
    :data:`MIN_TILES`; 0 where that is more than :data:`MAX_SHARE` of them (no pilot)."""
    rows, cols = tile_grid(height, width, tile)
    n = max(MIN_TILES, math.ceil(share * rows * cols))
    return n if n <= MAX_SHARE * rows * cols else 0


def pilot_tiles(
    height: int, width: int, count: int, seed: int, tile: int = TILE
) -> list[tuple[int, int]]:
    """``count`` tiles' top-left pixels ``(y, x)``, stratified: the film's whole tiles in
    row-major order cut into ``count`` equal runs, one tile drawn uniformly from each
    (``numpy`` generator seeded by ``seed``)."""
    rows, cols = tile_grid(height, width, tile)
    bounds = np.linspace(0, rows * cols, count + 1).round().astype(int)
    rng = np.random.default_rng(seed)
    picks = [int(rng.integers(lo, hi)) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)]
    return [(tile * (k // cols), tile * (k % cols)) for k in picks]


def statistics_windows(
    height: int, width: int, tiles: list[tuple[int, int]], tile: int = TILE, margin: int = MARGIN
) -> list[tuple[tuple[int, int, int, int], list[tuple[int, int]]]]:
    """The windows the statistics run on, each ``((top, left, height, width), its tiles)``:
    every tile with ``margin`` px around it (clipped to the film), or the whole film with all
    tiles where those windows would cover more pixels than it has."""
    windows = []
    for y, x in tiles:
        top, left = max(0, y - margin), max(0, x - margin)
        bottom, right = min(height, y + tile + margin), min(width, x + tile + margin)
        windows.append(((top, left, bottom - top, right - left), [(y, x)]))
    if sum(h * w for (_, _, h, w), _ in windows) >= height * width:
        return [((0, 0, height, width), list(tiles))]
    return windows


def _no_pilot(reason: str, **pilot: Any) -> RouteChoice:
    return RouteChoice("plain", plain_denoiser(), reason, pilot=pilot)


def run_pilot(
    scene: Any, *, spp: int, seed: int = 0, tile: int = TILE, share: float = SHARE, **props: Any
) -> tuple[RouteChoice, Pilot | None]:
    """Render the pilot of ``scene`` and choose the route (see the module docstring).

    Args:
        scene: an ``mi.Scene`` (or anything :func:`gdpt.render` accepts).
        spp: plain samples per pixel of the main render; below :func:`pilot_threshold`, or on a
            film with too few tiles (:func:`tile_count`), no pilot is rendered and the route is
            plain (the reason says which).
        seed: the pilot's seed (its tiles' too).
        tile, share: see :func:`tile_count`.
        **props: integrator properties (``max_depth``, ...).

    Returns:
        The :class:`RouteChoice` and the :class:`Pilot` (``None`` without one). A pilot that
        renders black or whose statistic is not finite takes the plain route and says so.

    Raises:
        ValueError: ``tile`` does not fit the film, ``share`` not in ``(0, 1]``, ``spp < 1``.
    """
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    if not 0.0 < share <= 1.0:
        raise ValueError(f"pilot share must be in (0, 1], got {share}")
    scene = load_scene(scene)
    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    count = tile_count(height, width, tile, share)
    if spp < (threshold := pilot_threshold()):
        return _no_pilot(
            f"{spp} spp: no room for a pilot (it needs >= {threshold} spp); plain route"
        ), None
    if count == 0:
        rows, cols = tile_grid(height, width, tile)
        return _no_pilot(
            f"the {width}x{height} film has {rows * cols} whole {tile} px tiles: too few for a "
            f"pilot of {MIN_TILES} tiles in at most {MAX_SHARE:.0%} of them; plain route"
        ), None
    props = integrator_props(props)
    start = time.perf_counter()
    denoiser, denoise = methods.primal_only()
    corners = pilot_tiles(height, width, count, seed, tile)
    windows = statistics_windows(height, width, corners, tile)
    window_pixels = sum(h * w for (_, _, h, w), _ in windows)
    sizing = learned_cost_ratio(scene, props) or DEFAULT_COST_RATIO
    g = pilot_gradient_spp(spp, sizing)
    mask = np.zeros((height, width), dtype=bool)
    for y, x in corners:
        mask[y : y + tile, x : x + tile] = True
    p1 = pooled_spp(g)
    sampling = {**props, **methods.METHODS["fuse"].sampling(g), "primal_spp": p1}
    render = rendering.render(scene, spp=g, seed=seed, gradient_mask=mask, **sampling)
    pilot = Pilot(render, torch.from_numpy(mask).to(render.device))
    share_px = float(mask.mean())
    t_plain = render.metadata["primal_only"]["render_seconds"]
    seconds_per_spp = max(t_plain / p1, 1e-9)
    cost_ratio = measured_cost_ratio(
        render.metadata["render_seconds"] - t_plain, g, share_px, seconds_per_spp
    )
    counts = {
        "gradient_spp": g,
        "primal_spp": p1,
        "tile": tile,
        "tiles": count,
        "share": share_px,
        "window_pixels": window_pixels,
        "seconds_per_spp": seconds_per_spp,
        "primal_replayed": not render.metadata["primal_only"]["recorded_passes"],
        "cost_spp": render.metadata["render_seconds"] / seconds_per_spp,
        "measured_cost_ratio": cost_ratio,
    }
    if float(render.primal.abs().max()) == 0.0:
        reason = "the pilot rendered black (no light reaches the film): nothing to fuse"
        seconds = time.perf_counter() - start
        return RouteChoice("plain", denoiser, reason, sizing, seconds, counts), pilot
    measure_start = time.perf_counter()
    terms, nonfinite = _tile_terms(render, denoise, windows, tile)
    choice = choose(terms, tile=0, margin=SIGNIFICANCE, nonfinite=nonfinite)
    statistics_seconds = time.perf_counter() - measure_start
    counts.update(
        statistic=choice.statistic,
        difference=choice.difference,
        nonfinite=nonfinite,
        statistics_seconds=statistics_seconds,
        cost_spp=counts["cost_spp"] + statistics_seconds / seconds_per_spp,
    )
    seen = (
        f"fuse - {denoiser} on {count} pilot tiles at {g} gradient spp: "
        f"{choice.statistic:+.1f} standard errors"
    )
    if not math.isfinite(choice.statistic):
        route, reason = "plain", f"{seen}: the pilot cannot decide (no spread); plain route"
    elif choice.statistic < -SIGNIFICANCE:
        route, reason = "gradient", f"{seen} < -{SIGNIFICANCE}: gradient route"
    else:
        route, reason = "plain", f"{seen} >= -{SIGNIFICANCE}: no significant gain; plain route"
    if nonfinite:
        reason += f" ({nonfinite} pixels with non-finite statistics left out)"
    method = "fuse" if route == "gradient" else denoiser
    seconds = time.perf_counter() - start
    return RouteChoice(route, method, reason, sizing, seconds, counts), pilot


def measured_cost_ratio(
    seconds: float, gradient_spp: int, share: float, seconds_per_spp: float
) -> float:
    """The cost of a gradient sample in plain ones, from a gradient pass of ``seconds`` at
    ``gradient_spp`` whose offsets covered ``share`` of the pixels (the others plain samples)
    and a plain sample's ``seconds_per_spp``, clamped to :data:`COST_RATIO_RANGE` (the
    route's charges use measured seconds; the ratio sizes ``G``)."""
    per_sample = seconds / gradient_spp / seconds_per_spp
    measured = 1.0 + (per_sample - 1.0) / max(share, 1e-9)
    return min(max(measured, COST_RATIO_RANGE[0]), COST_RATIO_RANGE[1])


def integrator_props(props: dict[str, Any]) -> dict[str, Any]:
    """``props`` without the sampling a route sets itself and without ``progress``: what the
    scene's learned cost ratio and reconstruction seconds are kept under."""
    routed = ("variance", "halves", "gradients", "features", "primal_spp", "progress")
    return {k: v for k, v in props.items() if k not in routed}


def _learned_key(scene: Any, props: dict[str, Any]) -> tuple:
    return (id(scene), tuple(sorted(props.items())))


def _learned(scene: Any, props: dict[str, Any]) -> dict[str, Any]:
    key = _learned_key(scene, props)
    if key not in _LEARNED:
        return {}
    _LEARNED.move_to_end(key)
    return _LEARNED[key][1]


def _learn(scene: Any, props: dict[str, Any], name: str, value: Any) -> None:
    key = _learned_key(scene, props)
    _LEARNED.setdefault(key, (scene, {}))[1][name] = value
    _LEARNED.move_to_end(key)
    while len(_LEARNED) > _LEARNED_SIZE:
        _LEARNED.popitem(last=False)


def learned_cost_ratio(scene: Any, props: dict[str, Any]) -> float | None:
    """The cost ratio the last gradient route measured on ``scene`` (an ``mi.Scene``) rendered
    with integrator ``props`` (the 8 most recently used scenes are kept), ``None`` before."""
    return _learned(scene, props).get("cost_ratio")


def forget_cost_ratios(scene: Any) -> None:
    """Drop the cost ratios, reconstruction seconds and plain samples' timings learned on
    ``scene`` (and the reference to it)."""
    for key in [k for k, (kept, _) in _LEARNED.items() if kept is scene]:
        del _LEARNED[key]


def learn_cost_ratio(scene: Any, props: dict[str, Any], ratio: float) -> None:
    """Remember ``ratio`` for ``scene`` and ``props`` where none is remembered or it differs from
    the remembered one by more than :data:`RELEARN` of it."""
    known = learned_cost_ratio(scene, props)
    if known is None or abs(ratio - known) > RELEARN * known:
        _learn(scene, props, "cost_ratio", ratio)


def learned_reconstruct_seconds(scene: Any, props: dict[str, Any], method: str) -> float | None:
    """The seconds of reconstruction ``method`` (``"fuse"`` or the plain route's denoiser)
    after the last route that used it on ``scene`` with integrator ``props``
    (:func:`learn_reconstruct_seconds`), ``None`` before."""
    return _learned(scene, props).get(f"reconstruct_seconds {method}")


def learn_reconstruct_seconds(
    scene: Any, props: dict[str, Any], method: str, seconds: float
) -> None:
    """Remember the seconds a route's reconstruction ``method`` took on ``scene`` with ``props``
    (the latest replaces the one before): what :func:`render_route` leaves for it before a
    deadline."""
    _learn(scene, props, f"reconstruct_seconds {method}", float(seconds))


def learned_plain_samples(scene: Any, props: dict[str, Any], route: str) -> TimeModel | None:
    """The seconds of ``route``'s last plain samples (``"plain"``: its render; ``"gradient"``:
    the plain samples pooled into its primal) on ``scene`` with integrator ``props``: a line
    through the timings of the last :data:`PLAIN_TIMINGS` such renders that replayed their
    passes (:func:`render_route`; a render's own overhead is its intercept, which a ratio of
    one small render's seconds to its count would charge to every sample: 0.020 s per sample
    from a cost model's probe on sponza against 0.012-0.015 at 30-40 spp), ``None`` before."""
    return _learned(scene, props).get(f"plain_samples {route}")


def learned_merge_seconds(scene: Any, props: dict[str, Any], route: str) -> float:
    """Seconds ``route`` took on ``scene`` with ``props`` after its last samples to put its
    renders together (pooling and merging, :func:`render_route`), 0 before."""
    return _learned(scene, props).get(f"merge_seconds {route}", 0.0)


def samples_before(deadline: float, finish: float, samples: TimeModel) -> int:
    """Samples per pixel whose seconds under ``samples`` (their time model) fill the time from
    now to ``deadline`` (a :func:`time.perf_counter` instant) less ``finish`` seconds (the
    reconstruction after them), at least 1."""
    return samples.spp_for(deadline - time.perf_counter() - finish)


def _tile_terms(
    render: GradientBuffers,
    denoise: Any,
    windows: list[tuple[tuple[int, int, int, int], list[tuple[int, int]]]],
    tile: int,
) -> tuple[torch.Tensor, int]:
    """The held-out terms of ``fuse`` against ``D`` (:func:`gdpt.adapters.held_out_fusion_terms_of`
    on each window of :func:`statistics_windows`) on the pilot's tiles, stacked:
    ``(tiles * tile, tile, 1)`` (every :data:`~gdpt.reconstruct.held_out.BLOCK` px block lies in
    one tile), and the count of non-finite terms."""
    parts, nonfinite = [], 0
    for (top, left, h, w), corners in windows:
        crop = render.crop(top, left, h, w)
        terms, bad = held_out_fusion_terms_of(crop, denoise, whole_denoise=False)
        nonfinite += bad
        parts += [terms[y - top : y - top + tile, x - left : x - left + tile] for y, x in corners]
    return torch.cat(parts), nonfinite


def route_sampling(choice: RouteChoice, spp: int) -> dict[str, Any]:
    """Keyword arguments of :func:`gdpt.render` for a render of ``choice``'s route without a
    pilot, at the cost of ``spp`` plain samples per pixel: ``spp`` plain samples, or the
    gradient route's pooled input of the same cost (at least 1 gradient sample)."""
    if choice.route == "plain":
        return {"spp": spp, **methods.METHODS[choice.method].sampling(spp)}
    gradient_spp = gradient_spp_for(spp, choice.cost_ratio)
    return {"spp": gradient_spp, **methods.METHODS["fuse"].sampling(gradient_spp)}


def render_route(
    scene: Any,
    choice: RouteChoice,
    pilot: Pilot | None,
    *,
    spp: int,
    seed: int,
    deadline: float | None = None,
    **props: Any,
) -> GradientBuffers:
    """The main render of ``choice`` at the cost of ``spp`` plain samples per pixel, merged
    with the ``pilot``'s render (:func:`gdpt.buffers.merge_renders`; see the module docstring).

    With a pilot, the plain route renders what is left of ``spp`` after the pilot's
    ``cost_spp`` (at least 1 sample); the gradient route renders ``G`` gradient samples outside
    the pilot's tiles (features off), then plain samples for what is left after the pilot and
    that render's measured time (at least 1, which brings the features), pooled into it
    (:func:`gdpt.buffers.pool_primal`); the cost ratio that render measured (offsets on most
    pixels; not where it recorded frozen passes, whose tracing and compilation it timed too)
    sizes ``G`` of the scene's next renders (:func:`learn_cost_ratio`).

    With a ``deadline`` (a :func:`time.perf_counter` instant: the end of a budget in seconds),
    either route's last plain samples fill the time left before it (:func:`samples_before`),
    less what followed the route's last samples the last time it ran on the scene: putting its
    renders together (:func:`learned_merge_seconds`) and its reconstruction
    (:func:`learned_reconstruct_seconds`; where none was measured yet, none: a route's first
    render on a scene ends past the deadline by its reconstruction): the pilot, its
    statistics, the samples and the reconstruction all within the budget. The plain
    samples are timed by the route's own last ones that replayed their passes on the scene
    (:func:`learned_plain_samples`: the same sampling), else at the pilot's measured seconds
    per plain sample. ``props`` as for :func:`gdpt.render` (they override the route's
    sampling). With a pilot, the result's ``metadata["plain_fill"]`` holds the count of the last
    plain samples (``spp``) and the count left of ``spp`` without a deadline (``count_spp``):
    the render's plain samples' worth is ``spp`` plus their difference.
    """
    if pilot is None:
        return rendering.render(scene, seed=seed, **{**route_sampling(choice, spp), **props})
    info = choice.pilot
    left = spp - info["cost_spp"]
    fuse = methods.METHODS["fuse"]
    routed = integrator_props(props)
    finish = 0.0  # with a deadline, all that follows the last samples
    if deadline is not None:
        finish = learned_reconstruct_seconds(scene, routed, choice.method) or 0.0
        finish += learned_merge_seconds(scene, routed, choice.route)
    if choice.route == "plain":
        rest = by_count = max(1, round(left))
        if deadline is not None:
            samples = learned_plain_samples(scene, routed, "plain") or _per_spp(info)
            rest = samples_before(deadline, finish, samples)
        sampling = {"spp": rest, **methods.METHODS[choice.method].sampling(rest), **props}
        main = rendering.render(scene, seed=seed, **sampling)
        _learn_plain_samples(scene, routed, "plain", main, rest)
        start = time.perf_counter()
        first = pilot.render.replace(dx=None, dy=None, var_dx=None, var_dy=None)
        keep = set(main.present())
        first = first.replace(**{n: None for n in first.present() if n not in keep})
        merged = merge_renders([first.replace(gradient_mask=None), main])
        _learn(scene, routed, "merge_seconds plain", time.perf_counter() - start)
        merged.metadata["plain_fill"] = {"spp": rest, "count_spp": by_count}
        return merged
    g = info["gradient_spp"]
    sampling = {**fuse.sampling(g), "primal_spp": 0, "features": False, **props}
    gradient = rendering.render(scene, spp=g, seed=seed, gradient_mask=~pilot.tiles, **sampling)
    seconds = gradient.metadata["render_seconds"]
    if not gradient.metadata["recorded_passes"]:  # a recording's time is not the samples'
        ratio = measured_cost_ratio(seconds, g, 1.0 - info["share"], info["seconds_per_spp"])
        learn_cost_ratio(scene, routed, ratio)
    rest = by_count = max(1, round(left - seconds / info["seconds_per_spp"]))
    if deadline is not None:
        rest = samples_before(deadline, finish, _gradient_route_fill(scene, routed, info))
    plain_sampling = {**fuse.sampling(rest), "gradients": False, "primal_spp": 0, **props}
    plain_seed = (int(seed) ^ rendering.PRIMAL_SEED_SALT) & 0xFFFFFFFF
    plain = rendering.render(scene, spp=rest, seed=plain_seed, **plain_sampling)
    _learn_plain_samples(scene, routed, "gradient", plain, rest)
    start = time.perf_counter()
    merged = merge_renders([pilot.render, pool_primal(gradient, plain)])
    _learn(scene, routed, "merge_seconds gradient", time.perf_counter() - start)
    merged.metadata["plain_fill"] = {"spp": rest, "count_spp": by_count}
    return merged


def _gradient_route_fill(scene: Any, props: dict[str, Any], pilot: dict[str, Any]) -> TimeModel:
    """The seconds of the gradient route's last plain samples: the line through its last
    replayed fills on ``scene`` (:func:`learned_plain_samples`) and the ``pilot``'s pooled
    plain pass where it replayed (the same sampling at ``1.5 G`` samples, timed in this render:
    it holds the line's slope where the fills so far were small, such as those of a cost
    model's probes), else at the pilot's seconds per plain sample."""
    known = learned_plain_samples(scene, props, "gradient")
    timings = list(known.measurements) if known else []
    if pilot.get("primal_replayed"):
        timings.append((pilot["primal_spp"], pilot["seconds_per_spp"] * pilot["primal_spp"]))
    return TimeModel.fit(timings[-PLAIN_TIMINGS:]) if timings else _per_spp(pilot)


def _per_spp(pilot: dict[str, Any]) -> TimeModel:
    """Plain samples timed at the ``pilot``'s measured seconds per plain sample."""
    return TimeModel(fixed=0.0, per_spp=pilot["seconds_per_spp"])


def _learn_plain_samples(scene: Any, props: dict[str, Any], route: str, render: Any, spp: int):
    """Add ``render`` of ``spp`` samples to ``route``'s timings of its plain samples and refit
    their line (:func:`learned_plain_samples`), where it replayed its passes (a recording's
    time is not the samples')."""
    if render.metadata["recorded_passes"]:
        return
    known = learned_plain_samples(scene, props, route)
    timings = [*(known.measurements if known else []), (spp, render.metadata["render_seconds"])]
    _learn(scene, props, f"plain_samples {route}", TimeModel.fit(timings[-PLAIN_TIMINGS:]))
