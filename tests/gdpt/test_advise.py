"""``gdpt advise`` and :func:`gdpt.advise`: end to end on the built-in Cornell box at 32 px
with a small budget or sample count, and every bad input failing in one line before the
renders it would waste."""

from __future__ import annotations

import math
import re

import pytest

import gdpt
from gdpt.cli import main

pytestmark = pytest.mark.usefixtures("variant", "single_thread")

#: A tiny scene: the built-in Cornell box at 32 px.
TINY = ["builtin:cbox-demo", "--long-side", "32", "--no-progress"]

#: The smallest Cornell box whose baseline error the estimator separates from 0: 64 px (64
#: blocks of 8 px), 2 replicates.
SMALL = ["builtin:cbox-demo", "--long-side", "64", "--replicates", "2", "--no-progress"]

#: Fast candidates: the baseline, plain path tracing and OIDN.
METHODS = ["pt+oidn-tuned", "pt", "pt+oidn"]


def one_line_error(err: str) -> str:
    lines = [line for line in err.splitlines() if line.startswith("gdpt ")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.fixture
def no_render(monkeypatch):
    """Any render or calibration fails the test."""
    import gdpt.rendering
    import gdpt.study.calibration

    def forbidden(*args, **kwargs):
        raise AssertionError("rendered despite bad input")

    monkeypatch.setattr(gdpt.rendering, "render", forbidden)
    monkeypatch.setattr(gdpt.study.calibration, "calibrate", forbidden)


def test_smoke_cli_at_equal_spp(capsys):
    """Every method and P render, the report names each method with a ratio or says why it
    cannot tell, and ends with the recommendation, the time and the command."""
    argv = [*["advise", *SMALL, "--spp", "4", "--plain-spp", "64"], "--methods", *METHODS]
    status = main(argv)
    out = capsys.readouterr().out
    assert status == 0, out
    lines = out.splitlines()
    assert lines[0].startswith("advise builtin:cbox-demo: 3 methods at equal spp (64x64")
    assert re.search(r"pt\+oidn-tuned +spp +4 .* 1\.00 \(the baseline\)", out)
    # plain path tracing at 4 spp against a denoiser: far worse, separated from 1
    assert re.search(r"\n  pt  +spp +4 .* higher: separated from 1", out), out
    assert sum(line.startswith("recommended: ") for line in lines) == 1
    assert re.search(r"\ntime: [0-9.]+ s", out)
    assert "render it: gdpt render-and-denoise builtin:cbox-demo --method " in out


def test_feature_api_at_a_budget_with_replicates(cost_clock):
    """At a budget every method gets a calibrated count; replicates pool their blocks. The
    methods' clocks are cost models (``cost_clock``: the counts hold under any load): pt
    4 ms + 4 ms/spp, pt+oidn-tuned 40 ms more for the denoiser."""
    cost_clock("pt", 0.004, 0.004)
    cost_clock("pt+oidn-tuned", 0.04, 0.004)
    advice = gdpt.advise(
        "builtin:cbox-demo",
        budget=0.2,
        methods=METHODS[:2],
        replicates=2,
        plain_spp=256,
        long_side=32,
        progress=False,
    )
    base, plain = advice.methods
    # the counts that fill 0.2 s; pt reconstructs nothing: more samples
    assert (base.spp, plain.spp) == (40, 49)
    assert len(base.seconds) == len(plain.seconds) == 2
    assert plain.estimate is not None and plain.estimate.blocks == 2 * 16
    assert advice.plain_spp == 256 and math.isfinite(plain.estimate.ratio)
    assert advice.recommended in METHODS[:2]
    assert sum(line.startswith("recommended: ") for line in advice.lines) == 1
    assert math.isfinite(advice.seconds) and advice.seconds > 0
    assert advice.command.startswith("gdpt render") and "builtin:cbox-demo" in advice.command


def test_feature_calibration_plan_shares_the_render_of_equal_samples():
    """``pt+oidn`` renders what ``pt+oidn-tuned`` renders: it shares that calibration, and ``P``
    takes its count from it; without a plain candidate ``pt`` is calibrated for ``P``."""
    from gdpt.advice import DEFAULT_METHODS, _calibration_plan
    from gdpt.study.calibration import configuration_key
    from gdpt.study.methods import EVAL_METHODS

    key = {n: configuration_key(EVAL_METHODS[n], "total") for n in ("pt", *DEFAULT_METHODS)}
    candidates = [EVAL_METHODS[n] for n in DEFAULT_METHODS]
    to_calibrate, shared, plain_key = _calibration_plan(candidates, plain=True)
    assert [m.name for m in to_calibrate.values()] == ["pt+oidn-tuned", "gdpt+fuse"]
    assert shared == {key["pt+oidn"]: key["pt+oidn-tuned"]}
    assert plain_key == key["pt+oidn-tuned"]
    to_calibrate, shared, plain_key = _calibration_plan([EVAL_METHODS["gdpt+fuse"]], plain=True)
    assert [m.name for m in to_calibrate.values()] == ["gdpt+fuse", "pt"] and not shared
    assert plain_key == key["pt"]
    to_calibrate, _, plain_key = _calibration_plan(candidates[:2], plain=False)
    assert plain_key is None and len(to_calibrate) == 2


def test_feature_shared_model_shifts_the_fixed_seconds():
    from gdpt.study.calibration import TimeModel

    model = TimeModel.fit([(1, 0.11), (10, 0.2), (100, 1.1)])
    slower = model.shifted(0.5)
    assert slower.per_spp == model.per_spp
    assert slower.fixed == pytest.approx(model.fixed + 0.5)
    assert slower.spp_for(2.0) == model.spp_for(1.5)
    assert model.shifted(-10.0).fixed == 0.0


@pytest.fixture
def calibrated(monkeypatch) -> list[str]:
    """The names of the methods :func:`gdpt.study.calibration.calibrate` probes, in order."""
    import gdpt.study.calibration

    names: list[str] = []
    calibrate = gdpt.study.calibration.calibrate

    def spy(method, *args, **kwargs):
        names.append(method.name)
        return calibrate(method, *args, **kwargs)

    monkeypatch.setattr(gdpt.study.calibration, "calibrate", spy)
    return names


def test_feature_budget_calibrates_each_render_once(calibrated):
    """At a budget, two calibrations for three candidates (``pt+oidn`` shares
    ``pt+oidn-tuned``'s render, ``P`` its cost per sample), and the report keeps ``P``."""
    advice = gdpt.advise(
        "builtin:cbox-demo", budget=0.2, methods=METHODS, long_side=32, progress=False
    )
    assert calibrated == ["pt+oidn-tuned", "pt"]
    assert advice.calibrations == {
        "pt+oidn-tuned": "calibrated",
        "pt": "calibrated",
        "pt+oidn": "shared with pt+oidn-tuned",
        "P": "the cost per sample of pt+oidn-tuned",
    }
    assert advice.plain_spp >= 2 and advice.methods[2].spp >= 1
    assert len(advice.plains) == 1 and advice.plains[0]["variance"].shape[-1] == 1


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        (["--spp", "4", "--budget", "1"], "give --budget or --spp, not both"),
        (["--methods", "pt", "nope"], "unknown method 'nope'; valid names: "),
        (["--methods", "pt"], "give at least two different methods"),
        (["--budget", "-1"], "the budget must be a positive number of seconds"),
        (["--spp", "1", "--plain-spp", "1"], "P would have 1 sample per pixel"),
        (["--replicates", "0"], "replicates must be >= 1"),
    ],
)
def test_exception_bad_input_before_rendering(capsys, no_render, extra, match):
    assert main(["advise", *TINY, *extra]) == 2
    line = one_line_error(capsys.readouterr().err)
    assert line.startswith("gdpt advise: error: ")
    assert re.search(match, line), line


@pytest.mark.parametrize(
    ("scene", "match"),
    [
        ("{tmp}/none.xml", "scene file not found: .*none.xml"),
        ("{tmp}/broken.xml", "cannot load scene .*broken.xml"),
        ("builtin:nope", "unknown builtin scene 'nope'"),
    ],
)
def test_exception_scene_does_not_load(tmp_path, capsys, no_render, scene, match):
    (tmp_path / "broken.xml").write_text("<scene version='3.0.0'><shape type='nope'/></scene>")
    assert main(["advise", scene.format(tmp=tmp_path), "--no-progress"]) == 2
    assert re.search(match, one_line_error(capsys.readouterr().err))


def test_exception_budget_too_small_names_the_method(capsys, monkeypatch):
    """A budget below one sample of a method fails after the calibration, before the scored
    renders, naming the method."""
    import gdpt.advice

    def forbidden(*args, **kwargs):
        raise AssertionError("scored renders despite a budget below one sample")

    monkeypatch.setattr(gdpt.advice, "_render_and_score", forbidden)
    argv = ["advise", *TINY, "--budget", "1e-6", "--methods", "pt", "pt+oidn-tuned"]
    assert main(argv) == 2
    line = one_line_error(capsys.readouterr().err)
    assert re.search(r"budget of 1e-06 s is too small for one sample of pt", line), line


def test_feature_black_scene_cannot_tell(tmp_path, capsys):
    """A scene without lights: one line says so, nothing is recommended (status 1), and the
    methods are not rendered."""
    (tmp_path / "black.xml").write_text(
        """<scene version="3.0.0">
        <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="16"/>
        <integer name="height" value="16"/><rfilter type="box"/></film></sensor>
        <shape type="sphere"><bsdf type="diffuse"/></shape></scene>"""
    )
    status = main(["advise", str(tmp_path / "black.xml"), "--spp", "4", "--no-progress"])
    out = capsys.readouterr().out
    assert status == 1
    assert "cannot tell: the image is black or nearly black" in out
    assert "recommended: none" in out and "spp" not in out.split("P:")[1].split("\n", 1)[1]


@pytest.mark.slow
def test_feature_interval_covers_the_true_ratio_on_a_rendered_scene():
    """On the Cornell box at 64 px, 12 seeded advise runs (``pt+oidn`` against
    ``pt+oidn-tuned`` at 16 spp, ``P`` 64 spp, 2 replicates): the 95% interval covers the true
    ratio of the same renders (a 4096-spp reference, its weights) in at least 10."""
    from gdpt.reconstruct.reference_free import relmse_weights

    from gdpt.rendering import render
    from gdpt.scenes.loading import read_scene

    scene = read_scene("builtin:cbox-demo", long_side=64).scene
    reference = render(scene, spp=4096, seed=99, max_depth=6, gradients=False, features=False)
    truth = reference.primal.cpu()
    weights = relmse_weights(truth)
    covered = []
    for seed in range(12):
        advice = gdpt.advise(
            "builtin:cbox-demo",
            spp=16,
            plain_spp=64,
            methods=["pt+oidn-tuned", "pt+oidn"],
            replicates=2,
            long_side=64,
            seed=seed,
            progress=False,
        )
        base, other = (advice.images[m] for m in ("pt+oidn-tuned", "pt+oidn"))
        errors = [
            sum(
                float((weights * (x - truth).square().mean(-1, keepdim=True)).sum()) for x in images
            )
            for images in (base, other)
        ]
        e = advice.methods[1].estimate
        covered.append(e.low <= errors[1] / errors[0] <= e.high)
    assert sum(covered) >= 10, covered


def test_the_recommended_command_is_in_seconds_at_a_budget():
    from gdpt.advice_report import render_command

    options = {"long_side": 128, "box_filter": False, "max_depth": None}
    timed = render_command("gdpt+fuse", 40, "builtin:cbox-demo", options, "cbox", 4.0)
    assert "--method fuse --time 4 --long-side 128" in timed and "--spp" not in timed
    counted = render_command("gdpt+fuse", 40, "builtin:cbox-demo", options, "cbox", None)
    assert "--method fuse --spp 40" in counted and "--time" not in counted
    assert "--spp 40" in render_command("pt", 40, "x.xml", options, "x", 4.0)  # gdpt render


def test_feature_a_second_advice_takes_its_counts_from_the_kept_models(
    cost_clock, calibrated, capsys
):
    """The candidates' cost models are the study's, kept per scene, resolution and
    configuration in the process: a second ``advise`` probes nothing and takes the same
    counts (the clocks are exact lines). Its progress is one bar in seconds per stage and its
    ``time:`` line says where the seconds went."""
    cost_clock("pt", 0.004, 0.004)
    cost_clock("pt+oidn-tuned", 0.04, 0.004)
    options = {"budget": 0.2, "methods": METHODS[:2], "plain_spp": 64, "long_side": 32}
    first = gdpt.advise("builtin:cbox-demo", progress=True, **options)
    assert calibrated == ["pt+oidn-tuned", "pt"] and first.calibrations["pt"] == "calibrated"
    err = capsys.readouterr().err
    assert "calibration (pt+oidn-tuned)" in err and "/0.2 s budget" in err
    calibrated.clear()
    second = gdpt.advise("builtin:cbox-demo", seed=1, progress=False, **options)
    assert calibrated == [] and second.calibrations["pt+oidn-tuned"] == "model"
    assert [m.spp for m in second.methods] == [m.spp for m in first.methods] == [40, 49]
    time_line = next(line for line in second.lines if line.startswith("time: "))
    assert re.search(r"calibration [0-9.]+ s, 1 x 2 renders [0-9.]+ s, 1 plain", time_line)
    assert second.stage_seconds["calibration"] < first.stage_seconds["calibration"]


def test_feature_plain_count_keeps_three_pass_sizes():
    """``P``'s count from a budget keeps its three highest bits (its passes: three sizes to
    trace at most), losing under a quarter of the samples."""
    from gdpt.study.estimate import few_pass_sizes

    for spp in range(1, 2000):
        kept = few_pass_sizes(spp)
        assert bin(kept).count("1") <= 3 and 0.75 * spp < kept <= spp
    assert few_pass_sizes(109) == 104 and few_pass_sizes(7) == 7


def test_feature_a_recording_is_said_and_replays_are_shown(monkeypatch):
    """A candidate's line shows the seconds of its renders that replayed their frozen passes;
    where every render recorded them, its seconds hold their tracing and the line says so."""
    import dataclasses

    from gdpt.study.methods import EVAL_METHODS

    def clock(name: str, recorded: list[bool], seconds: list[float]) -> None:
        method, calls = EVAL_METHODS[name], iter(zip(recorded, seconds, strict=True))

        def run(scene, *, spp: int, seed: int):
            result = method.run(scene, spp=spp, seed=seed)
            was_recorded, took = next(calls)
            return dataclasses.replace(result, recorded=was_recorded, seconds=took)

        monkeypatch.setitem(EVAL_METHODS, name, dataclasses.replace(method, run=run))

    clock("pt+oidn-tuned", [True, False], [5.0, 1.0])
    clock("pt", [True, True], [9.0, 7.0])
    advice = gdpt.advise(
        "builtin:cbox-demo",
        spp=4,
        methods=METHODS[:2],
        replicates=2,
        plain_spp=64,
        long_side=32,
        progress=False,
    )
    lines = {line.split()[0]: line for line in advice.lines if line.startswith("  ")}
    assert "1.00 s  1.00 (the baseline)" in lines["pt+oidn-tuned"]  # its replay only
    assert "8.00 s (with pass recording)" in lines["pt"]
