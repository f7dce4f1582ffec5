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
    if result.route.route == "plain":
        assert not result.buffers.has_gradients and result.buffers.spp == spp
    with pytest.raises(ValueError, match="pilot_spp must be >= 2"):
        route.choose_route(scene, spp=1000, pilot_spp=1)


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
