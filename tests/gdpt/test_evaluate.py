"""gdpt.study: equal-time calibration, scene loading, the report files, resume, bad input."""

from __future__ import annotations

import dataclasses
import json
import statistics
import sys

import pytest
from shared_scenes import SHARED_SCENES

from gdpt import denoise
from gdpt.cli import main
from gdpt.study.calibration import TimeModel, calibrate, run_at_budget
from gdpt.study.config import EvaluateConfig
from gdpt.study.evaluate import evaluate, render_references
from gdpt.study.methods import EVAL_METHODS
from gdpt.study.scenes import SceneSpec, load_eval_scene, resolve_scenes

GAUSSIAN_XML = """<scene version="3.0.0">
    <default name="res" value="64"/>
    <integrator type="path"><integer name="max_depth" value="4"/></integrator>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/>
        </transform>
        <film type="hdrfilm">
            <integer name="width" value="$res"/>
            <integer name="height" value="32"/>
            <rfilter type="gaussian"/>
        </film>
    </sensor>
    <emitter type="constant"/>
    <shape type="sphere"><bsdf type="{bsdf}"/></shape>
</scene>
"""


@pytest.fixture(scope="module")
def variant():
    import drjit as dr

    import gdpt

    gdpt.set_variant("llvm_ad_rgb")
    flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)  # as in evaluate(): compile time is excluded
    yield
    dr.set_flag(dr.JitFlag.KernelHistory, flag)


def test_xml_filter_override_and_resolution(variant, tmp_path):
    path = tmp_path / "scene.xml"
    path.write_text(GAUSSIAN_XML.format(bsdf="diffuse"))
    scene = load_eval_scene(SceneSpec("s", str(path)), resolution=20)
    assert scene.resolution == (20, 10)  # 64x32 ($res default) scaled to 20 on the long side
    assert scene.film_filter == {"original": "gaussian", "used": "box"}
    assert any("pixel filter overridden: 'gaussian' -> 'box'" in n for n in scene.notes)
    assert scene.max_depth == 4  # from the scene's integrator
    assert scene.scene.sensors()[0].film().rfilter().is_box_filter()


@pytest.mark.shared_scenes
def test_real_scene_loads_with_box_filter(variant):
    (spec,) = resolve_scenes([SHARED_SCENES / "cornell-box"])
    scene = load_eval_scene(spec, resolution=16)
    assert spec.name == "cornell-box" and scene.resolution == (16, 16)
    assert scene.film_filter["original"] == "gaussian"


@pytest.mark.parametrize("name", ["pt", "gdpt+l2"])
def test_calibration_meets_budget(variant, name):
    """The chosen spp takes the budget within 20% (median of 3 re-timings).

    20% is the tolerance of the issue. Budgets of 1 s keep the relative timing noise of a
    shared 2-core machine well below it; the median of 3 repeats removes single outliers. A
    transient load during the few seconds of calibration (seen once in CI: calibrated 25% slow,
    re-timed at steady state) invalidates that attempt, so the whole calibrate-and-verify runs
    at most twice and must succeed once; a systematically wrong calibration fails both.
    """
    method = EVAL_METHODS[name]
    scene = load_eval_scene(SceneSpec("cbox", "builtin:cbox-demo"), resolution=32)
    budget = 1.0
    failures = []
    for attempt in range(2):
        model = calibrate(method, scene, budget=budget, seed=1 + 10 * attempt)
        _, record = run_at_budget(method, scene, model, budget=budget, seed=2 + 10 * attempt)
        assert record["spp"] > 1
        again = statistics.median(
            method.run(scene, spp=record["spp"], seed=100 + 10 * attempt + i).seconds
            for i in range(3)
        )
        errors = (abs(again - budget) / budget, abs(record["seconds"] - budget) / budget)
        if max(errors) <= 0.2:
            return
        failures.append((record, again))
    pytest.fail(f"calibration missed the {budget} s budget by more than 20% twice: {failures}")


def _tiny_cfg(**changes) -> EvaluateConfig:
    base = dict(
        budgets=(0.1, 0.2),
        resolution=24,
        reference_spp=64,
        reference_chunk_spp=32,
        metrics=("relmse", "smape", "one_minus_ssim", "flip_ldr"),
        metric_options={},
        methods=("pt", "gdpt+l2"),
    )
    return EvaluateConfig(**{**base, **changes})


def test_quick_cli_writes_every_output(variant, tmp_path, capsys):
    out = tmp_path / "report"
    status = main(
        [
            "evaluate",
            "--scenes",
            "random:3",
            "--out",
            str(out),
            "--quick",
            "--resolution",
            "24",
            "--budgets",
            "0.1",
            "0.2",
            "--reference-spp",
            "64",
            "--methods",
            "pt",
            "gdpt+l2",
            "--no-progress",
        ]
    )
    assert status == 0
    results = json.loads((out / "results.json").read_text())
    for name in ("results.md", "index.html", "plots/random-3.png", "crops/random-3.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert list((out / "references").glob("random-3-24x24-d6-64spp-seed*.exr"))
    assert results["config"]["profile"] == "quick"
    assert results["machine"]["cpu"] and results["versions"]["mitsuba"]
    cells = results["scenes"]["random-3"]["methods"]["pt"]["cells"]
    assert set(cells) == {"0.1", "0.2"} and cells["0.2"]["spp"] > cells["0.1"]["spp"]
    assert set(cells["0.1"]["metrics"]) == {"relmse", "smape", "one_minus_ssim", "flip_ldr"}
    assert "| random-3 |" in (out / "results.md").read_text()
    assert "wrote" in capsys.readouterr().out


def test_bad_input_is_reported_and_resume_skips_done_cells(variant, tmp_path, monkeypatch):
    broken = tmp_path / "broken" / "scene.xml"
    broken.parent.mkdir()
    broken.write_text(GAUSSIAN_XML.format(bsdf="no_such_bsdf"))
    monkeypatch.setitem(sys.modules, "pyoidn", None)  # "not installed"
    monkeypatch.delitem(denoise.METHODS, "ngpt", raising=False)
    scenes = ["builtin:cbox-demo", str(tmp_path / "missing.xml"), str(broken.parent)]
    cfg = _tiny_cfg(methods=("pt", "pt+oidn", "gdpt+ngpt"))
    out = tmp_path / "report"
    results = evaluate(scenes, out, cfg, progress=False)

    assert results["scenes"]["missing"]["status"] == "failed"
    assert "not found" in results["scenes"]["missing"]["error"]
    assert results["scenes"]["broken"]["status"] == "failed"
    assert "no_such_bsdf" in results["scenes"]["broken"]["error"]
    methods = results["scenes"]["cbox-demo"]["methods"]
    assert methods["pt+oidn"]["status"] == "skipped" and "pyoidn" in methods["pt+oidn"]["note"]
    assert methods["gdpt+ngpt"]["status"] == "skipped" and "ngpt" in methods["gdpt+ngpt"]["note"]
    assert not results["methods"]["pt+oidn"]["available"]
    assert set(methods["pt"]["cells"]) == {"0.1", "0.2"}
    report = (out / "results.md").read_text()
    assert "**Failed**" in report and "pt+oidn: skipped" in report

    def forbidden(*args, **kwargs):
        raise AssertionError("a finished cell was recomputed")

    monkeypatch.setitem(EVAL_METHODS, "pt", dataclasses.replace(EVAL_METHODS["pt"], run=forbidden))
    again = evaluate(["builtin:cbox-demo"], out, cfg, progress=False)
    assert again["scenes"]["cbox-demo"]["methods"]["pt"]["cells"] == methods["pt"]["cells"]
    assert len(again["runs"]) == 2

    with pytest.raises(ValueError, match="different settings"):
        evaluate(["builtin:cbox-demo"], out, _tiny_cfg(resolution=16), progress=False)


def test_method_that_failed_is_retried_on_resume(variant, tmp_path, monkeypatch):
    """A method skipped after an error (not for being unavailable) runs again on resume."""
    cfg = _tiny_cfg(methods=("pt",))
    out = tmp_path / "report"
    working = EVAL_METHODS["pt"]

    def broken(*args, **kwargs):
        raise RuntimeError("transient failure")

    monkeypatch.setitem(EVAL_METHODS, "pt", dataclasses.replace(working, run=broken))
    first = evaluate(["builtin:cbox-demo"], out, cfg, progress=False, report=False)
    info = first["scenes"]["cbox-demo"]["methods"]["pt"]
    assert info["status"] == "skipped" and "transient failure" in info["note"]

    monkeypatch.setitem(EVAL_METHODS, "pt", working)
    again = evaluate(["builtin:cbox-demo"], out, cfg, progress=False, report=False)
    info = again["scenes"]["cbox-demo"]["methods"]["pt"]
    assert info["status"] == "ok" and set(info["cells"]) == {"0.1", "0.2"}


def test_references_only_then_cells_reuse_them(variant, tmp_path, monkeypatch, capsys):
    cache = tmp_path / "refs"
    status = main(
        [
            "evaluate",
            "--scenes",
            "random:3",
            str(tmp_path / "missing.xml"),
            "--out",
            str(tmp_path / "report"),
            "--references",
            str(cache),
            "--resolution",
            "24",
            "--reference-spp",
            "64",
            "--references-only",
            "--no-progress",
        ]
    )
    assert status == 1  # one scene failed, and says so
    printed = capsys.readouterr().out
    assert "missing: failed" in printed and "not found" in printed
    assert not (tmp_path / "report" / "results.json").exists()  # nothing was timed
    (exr,) = cache.glob("random-3-24x24-d6-64spp-seed*.exr")

    cfg = _tiny_cfg(methods=("pt",), reference_dir=cache)
    assert render_references(["random:3"], cache, cfg, progress=False) == {"random-3": str(exr)}
    results = evaluate(["random:3"], tmp_path / "report", cfg, progress=False, report=False)
    assert results["scenes"]["random-3"]["reference"]["cached"] is True
    assert set(results["scenes"]["random-3"]["methods"]["pt"]["cells"]) == {"0.1", "0.2"}


def test_time_model_fit_and_noise_guard():
    model = TimeModel.fit([(1, 0.30), (2, 0.32), (4, 0.36), (8, 0.44)])  # 0.28 s + 0.02 s/spp
    assert model.fixed == pytest.approx(0.28) and model.per_spp == pytest.approx(0.02)
    assert model.spp_for(2.28) == 100
    # noise made the probe faster than 1 spp: no absurd extrapolation (a past bug: 250k spp)
    noisy = TimeModel.fit([(1, 0.046), (6, 0.035)])
    assert noisy.fixed == 0.0 and noisy.spp_for(0.3) <= 16 * 6 * 0.3 / 0.035 + 1


@pytest.fixture
def registries_restored():
    """Methods registered during the test are removed afterwards."""
    before = {id(r): set(r) for r in (denoise.METHODS, EVAL_METHODS)}
    yield
    for registry in (denoise.METHODS, EVAL_METHODS):
        for name in set(registry) - before[id(registry)]:
            del registry[name]


def test_model_option_compares_a_checkpoint(variant, tmp_path, capsys, registries_restored):
    pytest.importorskip("pyoidn")
    from gdpt.reconstruct.oidn_ngpt import DESIGNS, base_model, encode_delta

    from gdpt.training.checkpoint import write_checkpoint

    checkpoint = tmp_path / "mine" / "model"
    card = {"sampling": {"primal_spp_factor": 1.0}}
    name = "oidn-grad-pool"
    write_checkpoint(checkpoint, *encode_delta(base_model(DESIGNS[name]), name, card))
    out = tmp_path / "report"
    args = ["evaluate", "--scenes", "random:3", "--out", str(out), "--resolution", "24"]
    args += ["--budgets", "0.2", "--reference-spp", "64", "--methods", "pt", "--no-progress"]
    status = main([*args, "--model", f"mine={checkpoint}.safetensors"])
    assert status == 0
    results = json.loads((out / "results.json").read_text())
    assert "gdpt+mine" in results["config"]["methods"]
    assert "oidn-grad-pool" in results["methods"]["gdpt+mine"]["description"]
    cell = results["scenes"]["random-3"]["methods"]["gdpt+mine"]["cells"]["0.2"]
    assert cell["spp"] >= 1 and cell["metrics"]["relmse"] < 1.0

    for bad, message in (
        ("mine", "expected NAME=CHECKPOINT"),
        (f"other={tmp_path / 'none.safetensors'}", "none.safetensors"),
        (f"l1={checkpoint}.safetensors", "'l1' is already registered"),
    ):
        assert main([*args, "--model", bad]) == 2
        assert message in capsys.readouterr().err
