"""``render_and_denoise(seconds=...)``: the sample count from the cost model
(:mod:`gdpt.cost_model`), with a fake clock (each run "takes" ``FIXED + PER_SPP * spp``
seconds) so that the counts are exact on any machine under any load."""

from __future__ import annotations

import math

import pytest
import torch

import gdpt.pipeline as pipeline
from gdpt.cost_model import MODELS, SceneModels, TimeModel, fit_by_probing

pytestmark = pytest.mark.usefixtures("variant")

FIXED, PER_SPP = 0.3, 0.01


@pytest.fixture
def fake_runs(monkeypatch):
    """Replaces the render at a count by one that renders nothing and reports
    ``FIXED + PER_SPP * spp`` seconds; returns the ``(spp, seed)`` of every run, in order."""
    calls: list[tuple[int, int]] = []

    def run(scene, spp, method, seed, alpha, bar, props, budget=None):
        calls.append((spp, seed))
        total = FIXED + PER_SPP * spp
        timings = {"render": total - FIXED, "reconstruct": FIXED, "total": total, "compile": 0.0}
        return pipeline.RenderResult(torch.zeros(2, 2, 3), None, spp=spp, timings=timings)

    monkeypatch.setattr(pipeline, "_render_at", run)
    return calls


@pytest.fixture
def scene():
    from gdpt.scenes import builtin_scene
    from gdpt.scenes.loading import load_scene

    scene = load_scene(builtin_scene("diffuse-box", resolution=(8, 8)))
    yield scene
    MODELS.forget(scene)


def test_seconds_fill_the_budget_from_the_model(fake_runs, scene):
    result = pipeline.render_and_denoise(scene, seconds=2.0, method="l2", seed=5)
    assert result.spp == round((2.0 - FIXED) / PER_SPP)  # 170: the exact line, probed
    assert result.budget == 2.0 and result.timings["total"] == pytest.approx(2.0)
    assert "setup" in result.timings and fake_runs[-1] == (170, 5)  # the main run, its seed
    assert fake_runs[-2] == (170, 5)  # warmed up at its count first (records its passes)
    probes = [spp for spp, seed in fake_runs[:-2]]
    assert len(set(probes)) >= 3  # three probe counts at least (the line needs two)

    fake_runs.clear()  # the same scene again: the model is kept, no probes, no warm-up
    again = pipeline.render_and_denoise(scene, seconds=2.0, method="l2", seed=6)
    assert fake_runs == [(170, 6)] and again.spp == 170
    fake_runs.clear()
    pipeline.render_and_denoise(scene, seconds=1.0, method="l2", seed=7)
    assert fake_runs == [(70, 7), (70, 7)]  # a new count: warmed up, then timed


def test_each_timed_run_refines_the_model(fake_runs, scene, monkeypatch):
    pipeline.render_and_denoise(scene, seconds=2.0, method="l2")
    model = MODELS.get(scene, pipeline.configuration_key("l2", 0.2, {}))
    assert model is not None and model.measurements[-1] == (170, pytest.approx(2.0))
    before = len(model.measurements)
    pipeline.render_and_denoise(scene, seconds=2.0, method="l2", seed=1)
    assert len(model.measurements) == before + 1


def test_a_configuration_has_its_own_model(fake_runs, scene):
    pipeline.render_and_denoise(scene, seconds=1.0, method="l2")
    fake_runs.clear()
    pipeline.render_and_denoise(scene, seconds=1.0, method="l2", max_depth=3)  # other props
    assert len(fake_runs) > 2  # probed anew


@pytest.mark.parametrize(
    ("budget", "match"),
    [
        ({"spp": 4, "seconds": 1.0}, "give spp .* or seconds .*: both given"),
        ({}, "give spp .* or seconds .*: neither given"),
        ({"seconds": 0.0}, "seconds must be a finite number > 0, got 0.0"),
        ({"seconds": -1}, "seconds must be a finite number > 0, got -1"),
        ({"seconds": math.nan}, "seconds must be a finite number > 0, got nan"),
        ({"seconds": math.inf}, "seconds must be a finite number > 0, got inf"),
        ({"seconds": True}, "seconds must be a finite number > 0, got True"),
        ({"spp": 0}, "spp must be an int >= 1, got 0"),
    ],
)
def test_bad_budgets_fail_before_rendering(fake_runs, scene, budget, match):
    with pytest.raises(ValueError, match=match):
        pipeline.render_and_denoise(scene, method="l2", **budget)
    assert fake_runs == []


def test_probing_finds_a_linear_cost():
    seen = []

    def timed(spp, offset):
        seen.append(spp)
        return FIXED + PER_SPP * spp

    model = fit_by_probing(timed, budget=3.0, repeats=1, probe_fraction=0.3)
    assert model.fixed == pytest.approx(FIXED) and model.per_spp == pytest.approx(PER_SPP)
    assert FIXED + PER_SPP * max(seen) >= 0.3 * 3.0  # probed up to the share of the budget
    assert model.spp_for(3.0) == 270


def test_scene_models_forget_and_keep_few():
    models, scenes = SceneModels(size=2), [object() for _ in range(3)]
    for s in scenes:
        models.set(s, "k", TimeModel(0.0, 1.0))
        models.mark_warm(s, "k", 4)
    assert models.get(scenes[0], "k") is None and not models.is_warm(scenes[0], "k", 4)
    assert models.get(scenes[2], "k") is not None and models.is_warm(scenes[2], "k", 4)
    models.forget(scenes[2])
    assert models.get(scenes[2], "k") is None and not models.is_warm(scenes[2], "k", 4)


def test_auto_warms_up_again_after_its_cost_ratio_was_relearned(fake_runs, scene, monkeypatch):
    learned = {"ratio": None}  # what auto's next render sizes its gradient count with
    monkeypatch.setattr(pipeline.auto_route, "learned_cost_ratio", lambda *_: learned["ratio"])
    pipeline.render_and_denoise(scene, seconds=2.0)
    assert fake_runs[0][0] == pipeline.auto_route.pilot_threshold()  # probes start at the pilot
    fake_runs.clear()
    pipeline.render_and_denoise(scene, seconds=2.0, seed=1)
    assert len(fake_runs) == 1  # warm: the timed run only
    learned["ratio"] = 2.4
    fake_runs.clear()
    pipeline.render_and_denoise(scene, seconds=2.0, seed=2)
    assert len(fake_runs) == 2 and fake_runs[0] == fake_runs[1]  # warmed up at its seed first


def test_seconds_bar_shows_its_stages_and_outlives_its_budget(capsys):
    import time

    from gdpt.seconds_bar import SecondsBar

    with SecondsBar(0.2, "pilot", interval=0.01) as bar:
        time.sleep(0.8)  # past the budget by more than tqdm allows (0.5): the bar stays full
        bar.stage("reconstruct (fuse)")
        time.sleep(0.05)
    err = capsys.readouterr().err
    assert "pilot" in err and "reconstruct (fuse)" in err and "0.2/0.2 s budget" in err


def test_auto_without_room_for_its_pilot_takes_the_count_below_it(scene, monkeypatch):
    """``auto`` costs 1.5 s more from its pilot threshold on (the pilot): a budget the pilot
    does not fit gets the largest count below the threshold, from a model of those counts."""
    threshold, calls = pipeline.auto_route.pilot_threshold(), []

    def run(scene, spp, method, seed, alpha, bar, props, budget=None):
        calls.append(spp)
        total = (1.5 if spp >= threshold else 0.3) + PER_SPP * spp
        return pipeline.RenderResult(torch.zeros(2, 2, 3), None, spp=spp, timings={"total": total})

    monkeypatch.setattr(pipeline, "_render_at", run)
    assert pipeline.render_and_denoise(scene, seconds=1.0).spp == threshold - 1
    assert pipeline.render_and_denoise(scene, seconds=3.0).spp == round((3.0 - 1.5) / PER_SPP)
    calls.clear()
    assert pipeline.render_and_denoise(scene, seconds=1.0, seed=1).spp == threshold - 1
    assert calls == [threshold - 1]  # both models kept: no probes


def test_a_warm_count_near_the_models_is_rendered_without_a_warm_up(fake_runs, scene):
    pipeline.render_and_denoise(scene, seconds=2.0, method="l2")  # 170 spp, warm
    fake_runs.clear()
    result = pipeline.render_and_denoise(scene, seconds=2.04, method="l2", seed=3)  # 174 spp
    assert result.spp == 170 and fake_runs == [(170, 3)]  # within 3%: replays, no warm-up


def test_study_auto_leaves_out_the_compilation_render_and_denoise_drained(monkeypatch):
    import time
    import types

    from gdpt.auto_route import RouteChoice
    from gdpt.study.methods import EVAL_METHODS

    def fake(scene, **kwargs):
        time.sleep(0.3)  # of which 0.25 s compiled kernels (drained by the pipeline itself)
        timings = {"reconstruct": 0.0, "compile": 0.25}
        route = RouteChoice("plain", "oidn-tuned", "fake")
        return pipeline.RenderResult(
            torch.zeros(2, 2, 3), None, spp=8, timings=timings, route=route
        )

    monkeypatch.setattr(pipeline, "render_and_denoise", fake)
    result = EVAL_METHODS["auto"].run(types.SimpleNamespace(scene=None, max_depth=3), spp=8, seed=0)
    assert result.compile_seconds >= 0.25 and result.seconds < 0.3 - 0.2


def test_a_warm_up_short_of_the_budget_corrects_a_slow_probe(scene, monkeypatch):
    """Probes slowed 3x (other work on the machine) make the model too slow; the warm-up at its
    count, short of the budget even with its recording, refits it and the count is chosen
    again (warmed up, then timed)."""
    calls = []

    def run(scene, spp, method, seed, alpha, bar, props, budget=None):
        calls.append(spp)
        slow = 3.0 if len(calls) <= 8 else 1.0  # the probes and their warm-ups
        total = slow * (FIXED + PER_SPP * spp)
        return pipeline.RenderResult(torch.zeros(2, 2, 3), None, spp=spp, timings={"total": total})

    monkeypatch.setattr(pipeline, "_render_at", run)
    result = pipeline.render_and_denoise(scene, seconds=3.0, method="l2")
    assert abs(result.timings["total"] - 3.0) <= 0.15 * 3.0, (calls, result.spp)
    assert calls[-1] == calls[-2] == result.spp  # the new count warmed up, then timed


def test_auto_timed_render_gets_its_deadline_and_its_route_learns_its_reconstruction(
    scene, monkeypatch
):
    """The timed render of ``seconds=`` hands ``auto``'s route the end of the budget (from the
    start of its pilot), its count is the cost model's plus what the route's fill rendered
    beyond it, and each route's reconstruction time (``fuse``, the plain route's denoiser) is
    learned under its method for the next deadline (the untimed renders of the setup have
    none)."""
    import time
    import types

    from gdpt.adapters import plain_denoiser
    from gdpt.auto_route import RouteChoice, learned_reconstruct_seconds
    from gdpt.seconds_bar import SecondsBar

    deadlines = []

    def render_route(scene, choice, pilot, *, spp, seed, deadline=None, **props):
        deadlines.append(deadline)
        fill = {"spp": 30, "count_spp": 20 if deadline else 30}  # 10 more before the deadline
        return types.SimpleNamespace(metadata={"plain_fill": fill})

    def reconstruct(buffers, method, alpha):
        time.sleep(0.05)
        return torch.zeros(2, 2, 3)

    route = RouteChoice("gradient", "fuse", "test")
    monkeypatch.setattr(pipeline.auto_route, "run_pilot", lambda scene, **kw: (route, None))
    monkeypatch.setattr(pipeline.auto_route, "render_route", render_route)
    monkeypatch.setattr(pipeline, "reconstruct_image", reconstruct)
    quiet = SecondsBar(None, disable=True)
    start = time.perf_counter()
    result = pipeline._render_at(scene, 8, "auto", 0, 0.2, quiet, {"max_depth": 4}, 2.0)
    assert start + 2.0 <= deadlines[-1] <= time.perf_counter() + 2.0
    assert result.spp == 8 + 10
    assert learned_reconstruct_seconds(scene, {"max_depth": 4}, "fuse") >= 0.05
    result = pipeline._render_at(scene, 8, "auto", 0, 0.2, quiet, {"max_depth": 4})
    assert deadlines[-1] is None and result.spp == 8
    denoiser = plain_denoiser()
    assert learned_reconstruct_seconds(scene, {"max_depth": 4}, denoiser) is None
    route = RouteChoice("plain", denoiser, "test")
    pipeline._render_at(scene, 8, "auto", 0, 0.2, quiet, {"max_depth": 4})
    assert learned_reconstruct_seconds(scene, {"max_depth": 4}, denoiser) >= 0.05
    pipeline.release_scene(scene)
    assert learned_reconstruct_seconds(scene, {"max_depth": 4}, "fuse") is None


def test_probing_aims_with_the_line_past_a_large_fixed_cost():
    """A reconstruction's fixed seconds dominate the first probes: aiming with the line (not
    the time ratio, which would take 1, 5, 20, 40 spp) past the target (2 s) reaches it in
    three."""
    seen = []

    def timed(spp, offset):
        seen.append(spp)
        return 0.5 + 0.05 * spp

    model = fit_by_probing(timed, budget=4.0, repeats=1, probe_fraction=0.5)
    assert seen == [1, 5, 40] and model.spp_for(4.0) == 70
