"""``method="auto"`` (gdpt.auto_route): the decision rule, the pilot on scenes whose answer is
known, and the replicate statistics of the study that measures it."""

from __future__ import annotations

import math

import pytest
import scipy.stats
import torch

import gdpt
from gdpt import auto_route as route
from gdpt.scenes import builtin_scene
from gdpt.statistics import mean_interval
from gdpt.study.results import replicate_seed

pytestmark = pytest.mark.usefixtures("variant", "single_thread")


@pytest.fixture(autouse=True)
def _no_remembered_statistics_cost(monkeypatch):
    """Each test starts without a measured statistics cost (a pilot always looks first)."""
    monkeypatch.setattr(route, "_STATISTICS_SECONDS_PER_PIXEL", {})


@pytest.mark.parametrize(
    "gain, cost, expected",
    [(0.5, 2.0, "gradient"), (0.9, 2.0, "plain"), (0.9, 1.0, "gradient"), (1.0, 1.0, "plain")],
)
def test_decision_weighs_the_predicted_gain_against_the_samples_gradients_cost(
    gain, cost, expected
):
    chosen, ratio = route.decide(gain, cost, factor=2.5)
    assert chosen == expected
    assert ratio == pytest.approx(3.5 / (cost + 2.5))


def test_a_black_scene_takes_the_plain_route_and_says_why():
    film = {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}
    scene = {
        "type": "scene",
        "sensor": {"type": "perspective", "film": film},
        "shape": {"type": "sphere", "bsdf": {"type": "diffuse"}},  # no emitter anywhere
    }
    choice = route.choose_route(gdpt.load_scene(scene), spp=1000, seed=1)
    assert choice.route == "plain" and "rendered black" in choice.reason


def test_pilot_on_glass_takes_the_plain_route():
    """Caustics through a glass sphere: gradients are unreliable there, the plain route wins."""
    scene = gdpt.load_scene(builtin_scene("glass", resolution=(32, 32)))
    choice = route.choose_route(scene, spp=1000, seed=2)
    assert choice.route == "plain", choice.reason
    assert 1.0 <= choice.cost_ratio <= 4.0 and choice.pilot_seconds > 0


def test_auto_records_its_choice_and_renders_what_the_route_reads():
    scene = gdpt.load_scene(builtin_scene("cbox-demo"), long_side=16)
    spp = route.pilot_threshold()  # auto is the default; a pilot from this spp on
    result = gdpt.render_and_denoise(scene, spp=spp)
    assert result.route is not None and result.buffers.metadata["route"]["route"] in (
        "gradient",
        "plain",
    )
    assert result.timings["pilot"] > 0 and torch.isfinite(result.image).all()
    if result.route.route == "plain":  # the pilot's samples and what is left of spp
        pilot = result.route.pilot
        kept = pilot["gradient_spp"] + pilot["primal_spp"] + pilot["held_out_spp"]
        rest = max(1, round(spp - pilot["cost_spp"]))
        assert not result.buffers.has_gradients and result.buffers.spp == kept + rest
    with pytest.raises(ValueError, match="pilot_spp must be >= 2"):
        route.choose_route(scene, spp=1000, pilot_spp=1)


def test_the_pilots_time_is_charged_to_the_main_render(monkeypatch):
    """Equal time: what the pilot costs beyond the samples the image keeps (here statistics
    that take a second, far more than the warm render of 200 spp) is taken from the main
    render, which is left with one sample; uncharged, it would render the rest of ``spp``."""
    import time

    def slow_measure(*args, **kwargs):
        time.sleep(1.0)
        return route.PilotEvidence(
            error=1.0, error_half=2.0, delta=0.0, delta_se=1.0, model_pilot=1.0, model_main=1.0
        )  # no gain seen: the plain route

    scene = gdpt.load_scene(builtin_scene("cbox-demo"), long_side=16)
    gdpt.render_and_denoise(scene, spp=200)  # warm: the pilot's renders replay their passes
    monkeypatch.setattr(route, "measure", slow_measure)
    monkeypatch.setattr(route, "STATISTICS_SHARE", 1e9)  # it looks, whatever looking costs
    result = gdpt.render_and_denoise(scene, spp=200)
    pilot = result.route.pilot
    assert result.route.route == "plain" and pilot["cost_spp"] > 200
    kept = pilot["gradient_spp"] + pilot["primal_spp"] + pilot["held_out_spp"]
    assert result.buffers.spp == kept + 1


def test_no_pilot_below_its_share_of_the_render(monkeypatch):
    """Below ``pilot_threshold()`` plain spp (the pilot's samples over ``PILOT_SHARE``) nothing
    is rendered for the decision: the plain route, with the assumed cost ratio, says why."""
    scene = gdpt.load_scene(builtin_scene("cbox-demo"), long_side=16)
    monkeypatch.setattr(gdpt.rendering, "render", _no_render)
    limit = route.pilot_threshold()
    choice = route.choose_route(scene, spp=limit - 1)
    assert choice.route == "plain" and choice.pilot_seconds == 0.0
    assert choice.cost_ratio == route.DEFAULT_COST_RATIO and f">= {limit}" in choice.reason
    with pytest.raises(AssertionError, match="pilot rendered"):
        route.choose_route(scene, spp=limit)


@pytest.mark.parametrize("cost_ratio", [2.0, 3.0])
def test_both_routes_spend_the_samples_of_spp_plain_ones(cost_ratio):
    """``spp`` plain samples, or gradient samples that cost as much: each ``cost_ratio`` plain
    ones plus the plain samples pooled into their primal."""
    plain = route.RouteChoice("plain", "oidn", 1.0, 0.8, cost_ratio, 0.0, "")
    gradient = route.RouteChoice("gradient", "fuse", 0.5, 0.8, cost_ratio, 0.0, "")
    assert route.route_sampling(plain, 450)["spp"] == 450
    sampling = route.route_sampling(gradient, 450)
    assert sampling["gradients"] and sampling["variance"] and sampling["halves"]
    cost = sampling["spp"] * cost_ratio + sampling["primal_spp"]
    assert abs(cost - 450) <= cost_ratio + 2.5  # rounding to whole gradient samples


def test_pilot_statistics_on_the_centre_window(monkeypatch):
    """The pilot's denoises see the centre ``PILOT_WINDOW`` square (each side at most that),
    cut from the pilot render's buffers; an image that fits is passed whole."""
    from gdpt import methods

    shapes = []

    def denoiser(buffers, method, **kwargs):
        shapes.append((buffers.height, buffers.width))
        return buffers.primal

    monkeypatch.setattr(route, "PILOT_WINDOW", 8)
    monkeypatch.setattr(methods, "reconstruct_image", denoiser)
    film = builtin_scene("cbox-demo", resolution=(20, 6))
    route.choose_route(gdpt.load_scene(film), spp=1000, seed=3)
    assert shapes == [(6, 8)] * 3


def test_pilot_with_infinite_gradient_variances_predicts_no_gain(monkeypatch):
    """An infinite gradient variance means no information: a pilot whose gradients all have one
    predicts no gain from them and takes the plain route (read as zero variance, it would
    predict a large gain)."""
    from gdpt import methods
    from gdpt.buffers import GradientBuffers

    gen = torch.Generator().manual_seed(5)
    image = 0.5 + 0.1 * torch.rand(12, 12, 3, generator=gen)
    inf = torch.full((12, 12, 1), float("inf"))

    def pilot(*args, **kwargs):
        noisy = [image + 0.05 * torch.randn(image.shape, generator=gen) for _ in range(2)]
        metadata = {"render_seconds": 3.0, "primal_only": {"render_seconds": 1.0}}
        return GradientBuffers(
            primal=image, dx=torch.zeros_like(image), dy=torch.zeros_like(image), var_dx=inf,
            var_dy=inf, primal_a=noisy[0], primal_b=noisy[1], spp=4,
            metadata={**metadata, "half_spp": [2, 2]},
        )  # fmt: skip

    monkeypatch.setattr(gdpt.rendering, "render", pilot)
    monkeypatch.setattr(methods, "reconstruct_image", lambda buffers, method: buffers.primal)
    choice = route.choose_route(object(), spp=route.pilot_threshold())
    assert choice.gain == 1.0 and choice.route == "plain"


def _no_render(*args, **kwargs):
    raise AssertionError("pilot rendered")


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


def _evidence(**changes) -> route.PilotEvidence:
    """A pilot where ``fuse`` beat ``D`` by half, clearly, and the model keeps that ratio."""
    base = dict(
        error=0.01, error_half=0.02, delta=-0.005, delta_se=0.0005, model_pilot=0.5, model_main=0.5
    )
    return route.PilotEvidence(**{**base, **changes})


@pytest.mark.parametrize(
    "changes, expected, why",
    [
        ({}, "gradient", "predicted 0.50"),  # 0.5 < 0.78 (sample ratio at cost 2)
        ({"model_main": 0.25}, "gradient", "predicted 0.25"),  # carried to the main counts
        ({"delta": 0.002}, "plain", "no significant gain"),  # fuse lost on the pilot
        ({"delta": -0.001, "delta_se": 0.001}, "plain", "no significant gain"),  # not visible
        ({"delta": -0.001, "delta_se": 1e-5}, "plain", "predicted 0.90"),  # gain < sample price
        ({"error": 0.0}, "plain", "cannot decide"),  # nothing measurable
        ({"error": float("nan")}, "plain", "cannot decide"),
    ],
)
def test_route_rule_on_pilot_evidence(changes, expected, why):
    chosen, gain, decay, reason = route.predict(_evidence(**changes), cost_ratio=2.0)
    assert chosen == expected and why in reason, reason
    assert 0.0 <= decay <= 1.0 and 0.0 < gain <= 1.0


def test_route_rule_weighs_the_sample_price_by_the_denoisers_error_decay():
    """A denoiser whose error barely falls with samples (``beta`` near 0) makes the gradient
    route's fewer primal samples cheap: a 0.9 gain is worth taking there, not at ``beta = 1``."""
    slow = _evidence(delta=-0.001, delta_se=1e-5, error_half=0.0101)
    assert route.predict(slow, cost_ratio=2.0)[0] == "gradient"
    assert route.predict(_evidence(delta=-0.001, delta_se=1e-5), cost_ratio=2.0)[0] == "plain"


def _pilot_pair(gradient_noise: float, seed: int = 0):
    """Synthetic pilot and held-out renders of a smooth image: the primal carries noise of
    variance 0.01, the gradients are exact plus noise of ``gradient_noise`` variance (as
    reported)."""
    from gdpt.buffers import GradientBuffers

    gen = torch.Generator().manual_seed(seed)
    y, x = torch.meshgrid(torch.linspace(0, 1, 48), torch.linspace(0, 1, 48), indexing="ij")
    truth = (0.3 + 0.5 * x * y).unsqueeze(-1).expand(48, 48, 3).contiguous()

    def noisy(var):
        return torch.randn(truth.shape, generator=gen) * var**0.5

    dx = torch.zeros_like(truth)
    dy = torch.zeros_like(truth)
    dx[:, :-1] = truth[:, 1:] - truth[:, :-1]
    dy[:-1] = truth[1:] - truth[:-1]
    halves = [truth + noisy(0.02) for _ in range(2)]
    var = lambda v: torch.full((48, 48, 1), v)  # noqa: E731
    pilot = GradientBuffers(
        primal=(halves[0] + halves[1]) / 2, dx=dx + noisy(gradient_noise),
        dy=dy + noisy(gradient_noise), var_primal=var(0.01), var_dx=var(gradient_noise),
        var_dy=var(gradient_noise), primal_a=halves[0], primal_b=halves[1], spp=4,
        metadata={"half_spp": [2, 2]},
    )  # fmt: skip
    held = [truth + noisy(0.02) for _ in range(2)]
    held_out = GradientBuffers(
        primal=(held[0] + held[1]) / 2, var_primal=var(0.01), primal_a=held[0],
        primal_b=held[1], spp=4, metadata={"half_spp": [2, 2]},
    )  # fmt: skip
    return pilot, held_out


@pytest.mark.parametrize("gradient_noise, expected", [(1e-6, "gradient"), (10.0, "plain")])
def test_pilot_measurement_sees_exact_gradients_win_and_noisy_ones_not(gradient_noise, expected):
    """:func:`measure` on synthetic renders whose denoiser is the identity: near-exact
    gradients make ``fuse`` beat ``D`` on held-out data and the rule takes them; gradients far
    noisier than ``D``'s error are not trusted, ``fuse`` equals ``D`` and the route is plain."""
    pilot, held_out = _pilot_pair(gradient_noise)
    evidence = route.measure(
        pilot, held_out, lambda buffers: buffers.primal, main_primal=40, main_gradient=16
    )
    assert evidence.nonfinite == 0 and evidence.error > 0
    chosen, _, _, reason = route.predict(evidence, cost_ratio=2.0)
    assert chosen == expected, reason
    if expected == "plain":
        assert evidence.delta == 0.0


def test_non_finite_pilot_statistics_are_counted_not_propagated():
    pilot, held_out = _pilot_pair(1e-6)
    held_out.primal[3, 5] = float("nan")
    held_out.primal[7, 9] = float("inf")
    evidence = route.measure(
        pilot, held_out, lambda buffers: buffers.primal, main_primal=40, main_gradient=16
    )
    assert evidence.nonfinite == 2
    values = (evidence.error, evidence.error_half, evidence.delta, evidence.delta_se)
    assert all(math.isfinite(v) for v in values)


def test_merged_renders_are_the_sample_weighted_mean():
    from gdpt.buffers import GradientBuffers, merge_renders

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
    """The gradient route merges the pilot's and the main render's gradient halves (what
    ``fuse``'s held-out check reads), each weighted by its gradient half count."""
    from gdpt.buffers import GradientBuffers, merge_renders

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


def test_no_significant_gain_means_the_plain_route_even_when_gradients_cost_nothing():
    """A pilot that saw no gain takes the plain route even where the gradient route's primal
    would hold as many samples (cost ratio 1, sample ratio >= 1: nothing to lose, nothing
    seen to win)."""
    unseen = _evidence(delta=0.0, delta_se=1.0)
    for ratio in (1.0, 1.2):
        chosen, gain, _, reason = route.predict(unseen, cost_ratio=1.0, sample_ratio=ratio)
        assert chosen == "plain" and gain == 1.0 and "no significant gain" in reason


def test_a_pilot_does_not_look_where_its_statistics_would_cost_more_than_their_share(
    monkeypatch,
):
    """Once a pilot measured what its statistics cost, a render too short to pay that share
    renders only the held-out samples (kept in the image), takes the plain route and says
    why; a long enough render looks again."""
    calls = []
    render = gdpt.rendering.render

    def counting(*args, **kwargs):
        calls.append(kwargs.get("gradients", True))
        return render(*args, **kwargs)

    monkeypatch.setattr(gdpt.rendering, "render", counting)
    scene = gdpt.load_scene(builtin_scene("cbox-demo"), long_side=16)
    route.choose_route(scene, spp=200, seed=1)  # looks: learns what looking costs
    assert route._STATISTICS_SECONDS_PER_PIXEL
    calls.clear()
    monkeypatch.setattr(route, "_STATISTICS_SECONDS_PER_PIXEL", {"oidn-tuned": 1.0, "oidn": 1.0})
    choice, renders = route.run_pilot(scene, spp=200, seed=1)
    assert choice.route == "plain" and "looking would cost" in choice.reason
    assert calls == [False] and len(renders) == 1  # the held-out render only
    assert choice.pilot["cost_spp"] == choice.pilot["held_out_spp"]
    monkeypatch.setattr(route, "STATISTICS_SHARE", 1e9)
    calls.clear()
    route.run_pilot(scene, spp=200, seed=1)
    assert len(calls) == 2
