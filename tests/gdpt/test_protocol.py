"""The study's two equal-time protocols: a budget pays for sampling + reconstruction
(``total``) or for sampling only (``render-time``, the paper's), on a fake clock whose render and
reconstruction costs are known."""

from __future__ import annotations

import types

import pytest
import torch

from gdpt.study.calibration import calibrate, charged_seconds, run_at_budget
from gdpt.study.config import EvaluateConfig
from gdpt.study.methods import EvalMethod, MethodResult

SCENE = types.SimpleNamespace(name="fake", resolution=(4, 3))

#: Fake costs: sampling 0.01 s per spp, reconstruction a fixed 0.5 s.
PER_SPP, RECONSTRUCT = 0.01, 0.5


def slow_denoiser() -> EvalMethod:
    """A method whose sampling costs ``PER_SPP * spp`` and whose reconstruction costs
    ``RECONSTRUCT`` seconds (reported, not slept)."""

    def run(scene, *, spp: int, seed: int) -> MethodResult:
        render = PER_SPP * spp
        return MethodResult(
            torch.zeros(3, 4, 3),
            seconds=render + RECONSTRUCT,
            render_seconds=render,
            reconstruct_seconds=RECONSTRUCT,
        )

    return EvalMethod("slow", "fake method with a slow reconstruction", run)


@pytest.mark.parametrize(("protocol", "spp"), [("total", 50), ("render-time", 100)])
def test_a_budget_pays_for_what_the_protocol_says(protocol, spp):
    method = slow_denoiser()
    model = calibrate(method, SCENE, budget=1.0, seed=1, protocol=protocol)
    _, record = run_at_budget(method, SCENE, model, budget=1.0, seed=2, protocol=protocol)
    assert record["spp"] == spp and record["protocol"] == protocol
    assert record["charged_seconds"] == pytest.approx(1.0)
    assert record["render_seconds"] == pytest.approx(PER_SPP * spp)
    assert record["reconstruct_seconds"] == pytest.approx(RECONSTRUCT)
    assert record["within_tolerance"] and abs(record["relative_error"]) < 1e-6


def test_under_render_time_a_slow_reconstruction_is_not_over_budget():
    method = slow_denoiser()
    for protocol, over in (("total", True), ("render-time", False)):
        model = calibrate(method, SCENE, budget=0.2, seed=1, protocol=protocol)
        _, record = run_at_budget(method, SCENE, model, budget=0.2, seed=2, protocol=protocol)
        assert record["over_budget_at_1spp"] is over, protocol


def test_an_unknown_protocol_is_refused_by_name():
    result = MethodResult(torch.zeros(1, 1, 3), seconds=1.0)
    with pytest.raises(ValueError, match="'wall'.*total, render-time"):
        charged_seconds(result, "wall")
    with pytest.raises(ValueError, match="protocol 'wall'"):
        EvaluateConfig(protocol="wall")


def test_render_time_calibration_skips_the_reconstruction_where_the_method_splits():
    """Under ``render-time`` the probes only sample; a run at a count new on the scene is the
    timing unless it recorded frozen passes (then it is the warm-up and runs again), and a
    count already run there is not warmed up again. The fake records at a count never
    rendered before (by either function)."""
    calls, rendered = [], set()

    def recorded(spp: int) -> bool:
        new = spp not in rendered
        rendered.add(spp)
        return new

    def run(scene, *, spp: int, seed: int) -> MethodResult:
        calls.append(("run", spp))
        return MethodResult(
            torch.zeros(3, 4, 3),
            seconds=PER_SPP * spp + 9.0,
            render_seconds=PER_SPP * spp,
            reconstruct_seconds=9.0,
            recorded=recorded(spp),
        )

    def render(scene, *, spp: int, seed: int) -> MethodResult:
        calls.append(("render", spp))
        return MethodResult(
            torch.zeros(3, 4, 3),
            seconds=PER_SPP * spp,
            render_seconds=PER_SPP * spp,
            recorded=recorded(spp),
        )

    method = EvalMethod("split", "fake split method", run, render=render)
    scene = types.SimpleNamespace(name="fake", resolution=(4, 3), warm=set())
    model = calibrate(method, scene, budget=1.0, seed=1, protocol="render-time")
    assert {kind for kind, _ in calls} == {"render"} and model.per_spp == pytest.approx(PER_SPP)
    probe = calls[4][1]
    assert calls[:6] == [("render", 1)] * 4 + [("render", probe)] * 2  # each recorded once
    calls.clear()
    _, record = run_at_budget(method, scene, model, budget=1.0, seed=2, protocol="render-time")
    spp = record["spp"]
    assert calls == [("run", spp)] * 2 and record["reconstruct_seconds"] == 9.0  # recorded
    calls.clear()
    calibrate(method, scene, budget=20.0, seed=1, protocol="total")
    # every timed run is charged in full; 1 spp was recorded by the render-time probes: timed
    # at once (no warm-up); 2 spp (its first probe here) never was: run twice
    assert probe != 2 and calls[:5] == [("run", 1)] * 3 + [("run", 2)] * 2
