"""``method="auto"`` (gdpt.auto_route): the tile pilot at the main render's count, its samples
in the final image, the decision on the tiles' held-out statistic, the charge to the budget,
what it does where it cannot decide; and the replicate statistics of the study that measures
it."""

from __future__ import annotations

import hashlib
import math
import time

import numpy as np
import pytest
import scipy.stats
import torch

import gdpt
from gdpt import auto_route as route
from gdpt import methods
from gdpt.adapters import FUSE_PRIMAL_SPP_FACTOR
from gdpt.buffers import GradientBuffers, merge_renders, pool_primal
from gdpt.rendering import PRIMAL_SEED_SALT
from gdpt.scenes import builtin_scene
from gdpt.statistics import mean_interval
from gdpt.study.results import replicate_seed

pytestmark = pytest.mark.usefixtures("variant", "single_thread")

#: A small film with enough tiles for a pilot at 8 px tiles (64 tiles: 10 of them).
TILE = 8


@pytest.fixture(scope="module")
def scene():
    return gdpt.load_scene(builtin_scene("cbox-demo"), long_side=64)


@pytest.fixture(autouse=True)
def _forget_learned_ratios():
    """Each test starts without a cost ratio learned by an earlier test's gradient route."""
    route._LEARNED.clear()
    yield
    route._LEARNED.clear()


class RenderLog:
    """Wraps ``gdpt.rendering.render``, recording each call's keyword arguments."""

    def __init__(self, monkeypatch):
        self.calls: list[dict] = []
        self.results: list = []
        self._render = gdpt.rendering.render
        monkeypatch.setattr(gdpt.rendering, "render", self)

    def __call__(self, scene, **kwargs):
        self.calls.append(kwargs)
        self.results.append(self._render(scene, **kwargs))
        return self.results[-1]


def _forced_terms(monkeypatch, value: float, seconds: float = 0.0) -> None:
    """The held-out terms replaced by ``value`` + small seeded noise per pixel (``< 0``: fuse
    looks better), after ``seconds`` of sleep: the decision and the charge made observable."""
    gen = torch.Generator().manual_seed(0)

    def terms(buffers, denoise, **_):
        time.sleep(seconds)
        noise = 0.1 * torch.randn(buffers.height, buffers.width, 1, generator=gen)
        return value + noise, 0

    monkeypatch.setattr(route, "held_out_fusion_terms_of", terms)


def _digest(t: torch.Tensor) -> str:
    return hashlib.sha256(t.detach().cpu().contiguous().numpy().tobytes()).hexdigest()


def test_the_pilot_renders_its_tiles_at_the_main_renders_gradient_count(scene, monkeypatch):
    log = RenderLog(monkeypatch)
    _forced_terms(monkeypatch, -1.0)
    spp = 300
    choice, pilot = route.run_pilot(scene, spp=spp, seed=3, tile=TILE)
    g = route.pilot_gradient_spp(spp, route.DEFAULT_COST_RATIO)
    assert choice.route == "gradient" and choice.pilot["gradient_spp"] == g
    # G and its pooled samples leave the fill share of spp to the route's last plain samples
    cost = (route.DEFAULT_COST_RATIO + FUSE_PRIMAL_SPP_FACTOR) * g
    assert (1 - route.FILL_SHARE) * spp - 5 <= cost <= (1 - route.FILL_SHARE) * spp
    first = log.calls[0]
    assert first["spp"] == g and first["primal_spp"] == route.pooled_spp(g)
    assert first["variance"] and first["halves"] and first["gradients"]
    tiles = torch.as_tensor(first["gradient_mask"])
    assert torch.equal(tiles, pilot.tiles.cpu())
    share = math.ceil(route.SHARE * (64 // TILE) ** 2)  # of the 64x64 film's whole tiles
    assert int(tiles.sum()) == choice.pilot["tiles"] * TILE * TILE == share * TILE * TILE
    log.calls.clear()
    buffers = route.render_route(scene, choice, pilot, spp=spp, seed=4)
    gradient, plain = log.calls  # the rest: offsets outside the tiles, then plain samples
    assert gradient["spp"] == g and torch.equal(torch.as_tensor(gradient["gradient_mask"]), ~tiles)
    assert not plain["gradients"] and plain["features"]
    assert buffers.spp == g and buffers.metadata["gradient_half_spp"] == [g - g // 2, g // 2]
    primal = g + route.pooled_spp(g) + g + plain["spp"]
    assert buffers.metadata["primal_spp"] == primal


def test_every_pilot_sample_is_in_the_final_image(scene, monkeypatch):
    """The pilot's render is the render of its seeds (digest of a re-render), its gradients
    in the tiles are the final image's there, and the final primal is the sample-weighted mean
    of the pilot and of the rest re-rendered from the same seeds and counts."""
    _forced_terms(monkeypatch, -1.0)
    choice, pilot = route.run_pilot(scene, spp=300, seed=3, tile=TILE)
    final = route.render_route(scene, choice, pilot, spp=300, seed=4)
    g, p1 = choice.pilot["gradient_spp"], choice.pilot["primal_spp"]
    fuse = methods.METHODS["fuse"].sampling(g)
    tiles = pilot.tiles.cpu().numpy()
    again = gdpt.render(scene, spp=g, seed=3, gradient_mask=tiles, **{**fuse, "primal_spp": p1})
    assert _digest(again.primal) == _digest(pilot.render.primal)
    assert _digest(again.dx) == _digest(pilot.render.dx)
    inside = pilot.render.gradient_mask[..., 0]
    assert inside.any() and torch.equal(final.dx[inside], pilot.render.dx[inside])
    n_pilot, n_rest = final.metadata["merged_spp"]
    rest_gradient = gdpt.render(
        scene, spp=g, seed=4, gradient_mask=~tiles, **{**fuse, "primal_spp": 0, "features": False}
    )
    plain_sampling = {**fuse, "gradients": False, "primal_spp": 0}
    rest_plain = gdpt.render(
        scene, spp=n_rest - g, seed=(4 ^ PRIMAL_SEED_SALT) & 0xFFFFFFFF, **plain_sampling
    )
    expected = merge_renders([pilot.render, pool_primal(rest_gradient, rest_plain)])
    assert n_pilot == g + p1
    assert _digest(final.primal) == _digest(expected.primal)
    assert _digest(final.dx) == _digest(expected.dx)


@pytest.mark.parametrize("value, expected", [(-1.0, "gradient"), (1.0, "plain")])
def test_the_decision_follows_the_tiles_held_out_statistic(scene, monkeypatch, value, expected):
    _forced_terms(monkeypatch, value)
    choice, _ = route.run_pilot(scene, spp=300, seed=3, tile=TILE)
    assert choice.route == expected, choice.reason
    assert (choice.pilot["statistic"] < -route.SIGNIFICANCE) == (expected == "gradient")
    assert choice.method == ("fuse" if expected == "gradient" else methods.primal_only()[0])


def test_a_denoiser_that_leaves_nothing_to_fix_makes_fuse_lose(scene, monkeypatch):
    """With the identity for a denoiser (the noisy primal), the gradients have plenty to fix:
    the gradient route. With a denoiser that returns a converged render (a test double: no
    error left), the fusion can only add the gradients' noise: the plain route."""
    converged = gdpt.render(scene, spp=2048, seed=99, gradients=False, features=False).primal

    def primal_only(denoise):
        return lambda denoiser=None: ("oidn", denoise)

    monkeypatch.setattr(methods, "primal_only", primal_only(lambda b: b.primal))
    noisy, _ = route.run_pilot(scene, spp=300, seed=3, tile=TILE)
    monkeypatch.setattr(methods, "primal_only", primal_only(lambda b: converged.clone()))
    perfect, _ = route.run_pilot(scene, spp=300, seed=3, tile=TILE)
    assert noisy.route == "gradient", noisy.reason
    assert perfect.route == "plain", perfect.reason


def test_the_statistics_time_is_charged_to_the_main_render(scene, monkeypatch):
    """Statistics made to take one second leave the main render that second's worth of plain
    samples fewer (at the pilot's measured seconds per sample): the pilot's cost is its render's
    time and its statistics' time, and the plain route renders what is left of ``spp``. Checked
    within each render (no comparison of wall times between renders: it holds under load)."""
    spp = 3000  # the pilot keeps ~60% of it: a second's charge fits in the rest
    for seconds in (0.0, 1.0):
        _forced_terms(monkeypatch, 1.0, seconds)
        choice, pilot = route.run_pilot(scene, spp=spp, seed=3, tile=TILE)
        buffers = route.render_route(scene, choice, pilot, spp=spp, seed=4)
        assert choice.route == "plain" and not buffers.has_gradients
        info = choice.pilot
        per_spp = info["seconds_per_spp"]
        assert info["statistics_seconds"] >= seconds
        render_cost = pilot.render.metadata["render_seconds"] / per_spp
        assert info["cost_spp"] == pytest.approx(render_cost + info["statistics_seconds"] / per_spp)
        assert buffers.metadata["merged_spp"][1] == max(1, round(spp - info["cost_spp"]))
    assert info["statistics_seconds"] / per_spp > 10  # a second is many samples of this film


def test_no_pilot_below_its_threshold_or_on_a_film_with_too_few_tiles(monkeypatch):
    def no_render(*args, **kwargs):
        raise AssertionError("pilot rendered")

    monkeypatch.setattr(gdpt.rendering, "render", no_render)
    small = gdpt.load_scene(builtin_scene("cbox-demo"), long_side=64)
    limit = route.pilot_threshold()
    choice, pilot = route.run_pilot(small, spp=limit - 1, tile=TILE)
    assert choice.route == "plain" and pilot is None and f">= {limit}" in choice.reason
    choice, pilot = route.run_pilot(small, spp=1000)  # 16 tiles of 16 px: too few
    assert choice.route == "plain" and pilot is None and "16 whole 16 px tiles" in choice.reason
    assert choice.pilot_seconds == 0.0 and choice.cost_ratio == route.DEFAULT_COST_RATIO


@pytest.mark.parametrize(
    "tile, share, message",
    [(12, 0.15, "multiple of 8"), (128, 0.15, "does not fit the 64x64 film"), (8, 0.0, "share")],
)
def test_a_tile_or_share_that_does_not_fit_is_refused_before_rendering(
    scene, monkeypatch, tile, share, message
):
    monkeypatch.setattr(gdpt.rendering, "render", None)
    with pytest.raises(ValueError, match=message):
        route.run_pilot(scene, spp=1000, tile=tile, share=share)


def test_a_black_scene_takes_the_plain_route_and_says_why():
    film = {"type": "hdrfilm", "width": 64, "height": 64, "rfilter": {"type": "box"}}
    scene = {
        "type": "scene",
        "sensor": {"type": "perspective", "film": film},
        "shape": {"type": "sphere", "bsdf": {"type": "diffuse"}},  # no emitter anywhere
    }
    choice, pilot = route.run_pilot(gdpt.load_scene(scene), spp=1000, seed=1, tile=TILE)
    assert choice.route == "plain" and "rendered black" in choice.reason and pilot is not None


def test_a_statistic_without_spread_cannot_decide(scene, monkeypatch):
    monkeypatch.setattr(
        route, "held_out_fusion_terms_of", lambda b, d, **_: (b.primal[..., :1] * 0, 0)
    )
    choice, _ = route.run_pilot(scene, spp=300, seed=3, tile=TILE)
    assert choice.route == "plain" and "cannot decide" in choice.reason


def test_auto_records_its_choice_and_keeps_the_pilot():
    result = gdpt.render_and_denoise(
        gdpt.load_scene(builtin_scene("cbox-demo"), long_side=128), spp=64
    )
    assert result.route is not None and result.route.pilot["tiles"] >= route.MIN_TILES
    assert result.buffers.metadata["route"]["route"] == result.route.route
    assert result.timings["pilot"] > 0 and torch.isfinite(result.image).all()


def test_tiles_are_stratified_and_seeded():
    tiles = route.pilot_tiles(128, 128, 10, seed=7, tile=16)
    again = route.pilot_tiles(128, 128, 10, seed=7, tile=16)
    other = route.pilot_tiles(128, 128, 10, seed=8, tile=16)
    assert tiles == again and tiles != other and len(set(tiles)) == 10
    bounds = np.linspace(0, 64, 11).round()  # ten runs of the 64 tiles in row-major order
    runs = [int(np.searchsorted(bounds, y // 16 * 8 + x // 16, side="right")) - 1 for y, x in tiles]
    assert runs == list(range(10))
    assert route.tile_count(128, 128, share=0.15) == 10 and route.tile_count(72, 128) == 8
    assert route.tile_count(64, 64) == 0  # 16 tiles: 8 of them would be half


def test_statistics_windows_are_crops_until_the_whole_image_is_cheaper():
    few = route.statistics_windows(512, 512, [(0, 0), (256, 256)], tile=16, margin=16)
    assert few == [((0, 0, 32, 32), [(0, 0)]), ((240, 240, 48, 48), [(256, 256)])]
    many = [(16 * i, 16 * j) for i in range(5) for j in range(5)]
    assert route.statistics_windows(128, 128, many) == [((0, 0, 128, 128), many)]


@pytest.mark.parametrize("cost_ratio", [2.0, 3.0])
def test_without_a_pilot_both_routes_spend_the_samples_of_spp_plain_ones(cost_ratio):
    plain = route.RouteChoice("plain", "oidn", "", cost_ratio)
    gradient = route.RouteChoice("gradient", "fuse", "", cost_ratio)
    assert route.route_sampling(plain, 450)["spp"] == 450
    sampling = route.route_sampling(gradient, 450)
    assert sampling["gradients"] and sampling["variance"] and sampling["halves"]
    cost = sampling["spp"] * cost_ratio + sampling["primal_spp"]
    assert abs(cost - 450) <= cost_ratio + 2.5  # rounding to whole gradient samples


def test_mean_interval_matches_student_t():
    values = [1.0, 1.4, 0.7, 1.1]
    mean, low, high = mean_interval(values)
    t = scipy.stats.t.interval(0.95, len(values) - 1, loc=mean, scale=scipy.stats.sem(values))
    assert mean == pytest.approx(1.05) and (low, high) == pytest.approx(t, rel=1e-3)
    assert mean_interval([2.0]) == (2.0, 2.0, 2.0)
    assert not math.isnan(mean_interval([1.0] * 40)[1])


def test_replicate_seeds_are_paired_across_methods_and_distinct_across_replicates():
    seeds = [replicate_seed(0, "cornell-box", "1", r) for r in range(3)]
    assert len(set(seeds)) == 3
    assert seeds == [replicate_seed(0, "cornell-box", "1", r) for r in range(3)]
    assert replicate_seed(0, "cornell-box", "2", 0) != seeds[0]


def test_merged_renders_are_the_sample_weighted_mean():
    ones, threes = torch.ones(2, 3, 3), torch.full((2, 3, 3), 3.0)
    var = torch.ones(2, 3, 1)
    gradient = GradientBuffers(
        primal=ones, dx=ones, dy=ones, var_primal=var, var_dx=var, var_dy=var, spp=1,
        metadata={"primal_spp": 3, "render_seconds": 1.0},
    )  # fmt: skip
    plain = GradientBuffers(primal=threes, var_primal=var, spp=1, metadata={"render_seconds": 2.0})
    merged = merge_renders([gradient, plain])
    assert torch.allclose(merged.primal, torch.full_like(ones, 1.5))  # 3 samples of 1, 1 of 3
    assert torch.allclose(merged.var_primal, var * (0.75**2 + 0.25**2))
    assert torch.equal(merged.dx, ones) and merged.spp == 1
    assert merged.metadata["primal_spp"] == 4 and merged.metadata["render_seconds"] == 3.0
    plain_only = merge_renders(
        [gradient.replace(dx=None, dy=None, var_dx=None, var_dy=None), plain]
    )
    assert plain_only.spp == 4 and not plain_only.has_gradients


def test_merged_gradient_renders_pool_their_gradient_halves_by_count():
    """Renders of one gradient mask pool their gradient halves (what ``fuse``'s held-out check
    reads), each weighted by its gradient half count."""

    def render(value: float, halves: tuple[int, int]) -> GradientBuffers:
        image = torch.full((2, 3, 3), value)
        names = ("primal", "dx", "dy", "primal_a", "primal_b", "dx_a", "dx_b", "dy_a", "dy_b")
        return GradientBuffers(
            **dict.fromkeys(names, image), spp=sum(halves), metadata={"half_spp": list(halves)}
        )

    merged = merge_renders([render(1.0, (1, 1)), render(4.0, (3, 1))])
    assert merged.metadata["gradient_half_spp"] == [4, 2]
    assert torch.allclose(merged.dx_a, torch.full((2, 3, 3), 3.25))  # (1 * 1 + 3 * 4) / 4
    assert torch.allclose(merged.dy_b, torch.full((2, 3, 3), 2.5))  # (1 * 1 + 1 * 4) / 2


def test_renders_of_disjoint_gradient_masks_merge_gradient_by_gradient():
    """Where each render traced the gradients the other did not, at equal ``spp``, every traced
    gradient keeps its one render's value and variance; one traced by neither stays untraced;
    unequal counts per gradient are refused."""
    from gdpt.buffers import fill_untraced

    def render(value: float, columns: slice, spp: int) -> GradientBuffers:
        mask = torch.zeros(2, 4, 2, dtype=torch.bool)
        mask[:, columns, 0] = True
        image = torch.full((2, 4, 3), value)
        variance = torch.full((2, 4, 1), value)
        buffers = GradientBuffers(
            primal=image, dx=image, dy=image, var_dx=variance, var_dy=variance, spp=spp,
            gradient_mask=mask,
        )  # fmt: skip
        return fill_untraced(buffers, 0.0, 0.0).replace(gradient_mask=mask)

    left, right = render(1.0, slice(0, 1), 4), render(2.0, slice(2, 3), 4)
    merged = merge_renders([left, right])
    assert merged.spp == 4
    assert torch.equal(merged.dx[:, 0], torch.ones(2, 3)) and torch.equal(
        merged.dx[:, 2], 2 * torch.ones(2, 3)
    )
    assert torch.equal(merged.var_dx[:, 2], 2 * torch.ones(2, 1))
    assert torch.isinf(merged.var_dx[:, 1]).all() and not merged.gradient_mask[:, 1, 0].any()
    with pytest.raises(ValueError, match="different sample counts"):
        merge_renders([left, render(2.0, slice(2, 3), 8)])


def test_statistics_run_on_crops_around_few_tiles():
    """With few tiles on a large film the statistics see windows around the tiles only (their
    pixels counted in ``window_pixels``) and still give a finite statistic."""
    film = gdpt.load_scene(builtin_scene("cbox-demo"), long_side=256)
    choice, _ = route.run_pilot(film, spp=20, seed=5, tile=TILE, share=0.01)
    tiles = choice.pilot["tiles"]
    assert tiles == 11 and choice.pilot["window_pixels"] < 256 * 256
    assert choice.pilot["window_pixels"] <= tiles * (TILE + 2 * route.MARGIN) ** 2
    assert math.isfinite(choice.pilot["statistic"]), choice.reason


def test_a_gradient_route_sizes_the_scenes_next_pilot(scene, monkeypatch):
    """The gradient route's render measures the cost ratio, not where it recorded its passes
    (their tracing is in its time); the next pilot of the same scene and properties is sized by
    it (``G`` and ``route.cost_ratio``), another ``max_depth`` is not."""
    _forced_terms(monkeypatch, -1.0)
    log = RenderLog(monkeypatch)
    for _ in range(3):  # the first render of these counts records its passes, a repeat replays
        first, pilot = route.run_pilot(scene, spp=300, seed=3, tile=TILE)
        assert first.cost_ratio == route.DEFAULT_COST_RATIO
        route.render_route(scene, first, pilot, spp=300, seed=4)
        gradient = log.results[-2]  # the rest: offsets outside the tiles, then plain samples
        learned = route.learned_cost_ratio(scene, {})
        if not gradient.metadata["recorded_passes"]:
            break
        assert learned is None
    assert learned is not None and route.COST_RATIO_RANGE[0] <= learned <= route.COST_RATIO_RANGE[1]
    second, _ = route.run_pilot(scene, spp=300, seed=5, tile=TILE)
    assert second.cost_ratio == learned
    assert second.pilot["gradient_spp"] == route.pilot_gradient_spp(300, learned)
    other, _ = route.run_pilot(scene, spp=300, seed=5, tile=TILE, max_depth=5)
    assert other.cost_ratio == route.DEFAULT_COST_RATIO


def test_a_learned_ratio_moves_only_past_the_relearn_share():
    scene, props = object(), {"max_depth": 6}
    route.learn_cost_ratio(scene, props, 2.0)
    route.learn_cost_ratio(scene, props, 2.0 * (1 + 0.9 * route.RELEARN))
    assert route.learned_cost_ratio(scene, props) == 2.0
    route.learn_cost_ratio(scene, props, 2.0 * (1 + 1.1 * route.RELEARN))
    assert route.learned_cost_ratio(scene, props) == pytest.approx(2.0 * (1 + 1.1 * route.RELEARN))
    assert route.learned_cost_ratio(object(), props) is None


def _fake_gradient_route(monkeypatch) -> tuple[list[int], type]:
    """Renders of the gradient route replaced by a ``Fake`` class (its ``metadata``: 0.5 s, a
    recording, changeable) whose counts are logged in the returned list; merging and pooling
    return the last render."""
    counts: list[int] = []

    class Fake:
        metadata = {"render_seconds": 0.5, "recorded_passes": 1}

    def fake_render(scene, *, spp, seed, **kwargs):
        counts.append(spp)
        return Fake()

    monkeypatch.setattr(route.rendering, "render", fake_render)
    monkeypatch.setattr(route, "merge_renders", lambda parts: parts[-1])
    monkeypatch.setattr(route, "pool_primal", lambda gradient, plain: plain)
    return counts, Fake


def test_a_deadline_sizes_the_gradient_routes_plain_samples_from_the_time_left(monkeypatch):
    """With a deadline (``render_and_denoise(seconds=...)``), the gradient route's pooled plain
    samples fill what is left of the budget after the renders so far and before what followed
    them last time (``fuse``'s reconstruction, the pooling; nothing before a reconstruction
    was measured), at the pilot's seconds per plain sample, then at those of the route's last
    pooled samples that replayed their passes; without a deadline, the count left of ``spp``."""
    counts, Fake = _fake_gradient_route(monkeypatch)
    info = {"cost_spp": 20.0, "gradient_spp": 8, "share": 0.2, "seconds_per_spp": 0.01}
    choice = route.RouteChoice("gradient", "fuse", "test", pilot=info)
    pilot = route.Pilot(Fake(), torch.zeros(4, 4, dtype=torch.bool))
    scene = object()
    by_count = round(100 - 20 - 0.5 / 0.01)  # spp less the pilot and the gradient pass: 30
    route.render_route(scene, choice, pilot, spp=100, seed=0, deadline=time.perf_counter() + 1.3)
    assert 125 <= counts[-1] <= 130  # no reconstruction measured yet: 1.3 s at 0.01 s
    route.learn_reconstruct_seconds(scene, {}, "fuse", 0.3)
    route.render_route(scene, choice, pilot, spp=100, seed=0)
    assert counts[-1] == by_count  # no deadline: by the count
    route.render_route(scene, choice, pilot, spp=100, seed=0, deadline=time.perf_counter() + 1.3)
    assert 95 <= counts[-1] <= 100  # 1.3 s less fuse's 0.3 s at 0.01 s per sample
    assert route.learned_plain_samples(scene, {}, "gradient") is None  # recordings
    Fake.metadata = {"render_seconds": 0.5, "recorded_passes": 0}  # replays: 0.5 s / 100 spp
    monkeypatch.setattr(route, "pool_primal", lambda gradient, plain: time.sleep(0.2) or plain)
    route.render_route(scene, choice, pilot, spp=100, seed=0)
    assert route.learned_plain_samples(scene, {}, "gradient").per_spp == pytest.approx(0.5 / 30)
    assert route.learned_merge_seconds(scene, {}, "gradient") >= 0.2
    route.render_route(scene, choice, pilot, spp=100, seed=0, deadline=time.perf_counter() + 1.3)
    assert 45 <= counts[-1] <= 48  # 1.3 s less fuse's 0.3 s and the pooling's 0.2 s at 1/60 s
    route.forget_cost_ratios(scene)
    assert route.learned_reconstruct_seconds(scene, {}, "fuse") is None
    assert route.learned_merge_seconds(scene, {}, "gradient") == 0.0


def test_the_gradient_routes_fill_is_held_by_the_pilots_plain_pass(monkeypatch):
    """The gradient route times its last plain samples by a line through its replayed fills
    and the pilot's pooled plain pass (same sampling, a large count, timed in this render)
    where that pass replayed: small fills (a cost model's probes: 0.02 s per sample) alone
    would leave half the time unused."""
    counts, Fake = _fake_gradient_route(monkeypatch)
    scene = object()
    route._learn(scene, {}, "plain_samples gradient", route.TimeModel.fit([(2, 0.05), (4, 0.09)]))
    route.learn_reconstruct_seconds(scene, {}, "fuse", 0.3)
    info = {"cost_spp": 20.0, "gradient_spp": 8, "share": 0.2, "seconds_per_spp": 0.01}
    pilot = route.Pilot(Fake(), torch.zeros(4, 4, dtype=torch.bool))
    for replayed, low, high in ((False, 46, 49), (True, 92, 100)):
        choice = route.RouteChoice(
            "gradient",
            "fuse",
            "test",
            pilot={**info, "primal_spp": 100, "primal_replayed": replayed},
        )
        route.render_route(
            scene, choice, pilot, spp=100, seed=0, deadline=time.perf_counter() + 1.3
        )
        assert low <= counts[-1] <= high, (replayed, counts[-1])  # 1.0 s: 0.02 s or 0.01 s each
    route.forget_cost_ratios(scene)


def test_a_deadline_sizes_the_plain_routes_samples_from_the_time_left(monkeypatch):
    """With a deadline, the plain route's samples fill what is left of the budget after the
    pilot and before its denoiser's last measured seconds (a slow denoiser: fewer samples than
    the count left of ``spp``, which would end past the deadline), at the seconds per sample of
    the line through its last renders that replayed their passes (not those that recorded them:
    a render's own overhead is not charged to every sample), else at the pilot's (before the
    denoiser was measured, up to the deadline); without a deadline, the count left of ``spp``."""
    counts: list[int] = []
    recorded = [1]

    class Fake:
        def __init__(self, spp=0):
            self.metadata = {"render_seconds": 0.005 * spp + (0.5 if recorded[0] else 0.1)}
            self.metadata["recorded_passes"] = recorded[0]

        def replace(self, **kwargs):
            return self

        def present(self):
            return ()

    def fake_render(scene, *, spp, seed, **kwargs):
        counts.append(spp)
        return Fake(spp)

    monkeypatch.setattr(route.rendering, "render", fake_render)
    monkeypatch.setattr(route, "merge_renders", lambda parts: parts[-1])
    denoiser = methods.primal_only()[0]
    info = {"cost_spp": 20.0, "gradient_spp": 8, "share": 0.2, "seconds_per_spp": 0.01}
    choice = route.RouteChoice("plain", denoiser, "test", pilot=info)
    pilot = route.Pilot(Fake(), torch.zeros(4, 4, dtype=torch.bool))
    scene = object()
    route.render_route(scene, choice, pilot, spp=100, seed=0, deadline=time.perf_counter() + 1.2)
    assert 115 <= counts[-1] <= 120  # no denoiser measured yet: 1.2 s at the pilot's 0.01 s
    assert route.learned_plain_samples(scene, {}, "plain") is None  # it recorded its passes
    route.learn_reconstruct_seconds(scene, {}, "fuse", 0.6)  # another route's reconstruction
    route.render_route(scene, choice, pilot, spp=100, seed=0, deadline=time.perf_counter() + 1.2)
    assert 115 <= counts[-1] <= 120
    route.learn_reconstruct_seconds(scene, {}, denoiser, 0.6)
    route.render_route(scene, choice, pilot, spp=100, seed=0)
    assert counts[-1] == 80  # no deadline: by the count
    merged = route.render_route(
        scene, choice, pilot, spp=100, seed=0, deadline=time.perf_counter() + 1.2
    )
    assert 55 <= counts[-1] <= 60  # 1.2 s less the denoiser's 0.6 s at the pilot's 0.01 s
    assert merged.metadata["plain_fill"] == {"spp": counts[-1], "count_spp": 80}
    recorded[0] = 0  # replays: 0.1 s and 0.005 s per sample
    route.render_route(scene, choice, pilot, spp=100, seed=0)  # 80 spp in 0.5 s
    assert route.learned_plain_samples(scene, {}, "plain").per_spp == pytest.approx(0.5 / 80)
    route.render_route(scene, choice, pilot, spp=100, seed=0, deadline=time.perf_counter() + 0.9)
    assert 45 <= counts[-1] <= 48  # 0.9 s less 0.6 s at 0.5 s / 80 spp
    route.render_route(scene, choice, pilot, spp=120, seed=0)  # 100 spp in 0.6 s: the line
    route.render_route(scene, choice, pilot, spp=100, seed=0, deadline=time.perf_counter() + 0.9)
    assert 38 <= counts[-1] <= 40  # 0.3 s less the 0.1 s of a render at 0.005 s (by 0.6 s/100: 50)
    route.forget_cost_ratios(scene)
    assert route.learned_plain_samples(scene, {}, "plain") is None
