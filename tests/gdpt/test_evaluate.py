"""gdpt.study: equal-time calibration, scene loading, the report files, resume, bad input."""

from __future__ import annotations

import dataclasses
import json
import statistics
import sys
import types

import pytest
import torch
from shared_scenes import SHARED_SCENES

from gdpt.cli import main
from gdpt.methods import METHODS
from gdpt.study.calibration import TimeModel, calibrate, run_at_budget
from gdpt.study.config import EvaluateConfig
from gdpt.study.evaluate import StudyFailure, evaluate, render_references
from gdpt.study.methods import EVAL_METHODS, EvalMethod, MethodResult
from gdpt.study.results import read_results
from gdpt.study.scenes import SceneSpec, load_eval_scene, resolve_scenes

#: A stand-in scene for the fake-clock tests (only its film size is read, ``(width, height)``).
SCENE = types.SimpleNamespace(name="fake", resolution=(4, 3))

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


@pytest.mark.slow
@pytest.mark.parametrize("name", ["pt", "gdpt+l2"])
def test_calibration_meets_budget(variant, name):
    """Wall clock: the chosen spp takes the budget within 20% (median of 3 re-timings); slow, as
    its outcome depends on the machine's load (the fast suite checks the calibration's logic on
    reported times: ``test_calibration_*_fake_clock``).

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


def test_quick_cli_writes_every_output(variant, tmp_path, capsys, cost_clock):
    """Every output of a quick study; the methods' clocks are cost models (``cost_clock``), so
    their sample counts hold under any load: pt 4 + 4 ms/spp, gdpt+l2 10 + 8 ms/spp."""
    cost_clock("pt", 0.004, 0.004)
    cost_clock("gdpt+l2", 0.01, 0.008)
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
    for method in ("pt", "gdpt+l2"):  # every requested method has every cell
        info = results["scenes"]["random-3"]["methods"][method]
        cells = info["cells"]
        assert info["status"] == "ok" and not info.get("errors"), (method, info)
        assert set(cells) == {"0.1", "0.2"} and cells["0.2"]["spp"] > cells["0.1"]["spp"]
        expected = {"pt": (24, 49), "gdpt+l2": (11, 24)}[method]  # (budget - fixed) / per spp
        assert (cells["0.1"]["spp"], cells["0.2"]["spp"]) == expected, method
        assert set(cells["0.1"]["metrics"]) == {"relmse", "smape", "one_minus_ssim", "flip_ldr"}
        for cell in cells.values():
            assert (out / cell["image"]).is_file(), (method, cell["image"])
    assert "| random-3 |" in (out / "results.md").read_text()
    assert "wrote" in capsys.readouterr().out
    cost = results["runs"][-1]["cost"]  # every timed render on the cost clocks, one attempt each
    per_seed = (
        (0.004 + 0.004 * 24) + (0.004 + 0.004 * 49) + (0.01 + 0.008 * 11) + (0.01 + 0.008 * 24)
    )
    assert cost["timed_seconds"] == pytest.approx(results["config"]["seeds"] * per_seed)
    assert cost["ratio"] == pytest.approx(cost["wall_seconds"] / cost["timed_seconds"])
    assert "The study's own cost (last run): " in (out / "results.md").read_text()


def test_bad_input_is_reported_and_resume_skips_done_cells(variant, tmp_path, monkeypatch):
    broken = tmp_path / "broken" / "scene.xml"
    broken.parent.mkdir()
    broken.write_text(GAUSSIAN_XML.format(bsdf="no_such_bsdf"))
    monkeypatch.setitem(sys.modules, "mitsuba_oidn", None)  # "not installed"
    monkeypatch.delitem(METHODS, "oidn-grad", raising=False)
    scenes = ["builtin:cbox-demo", str(tmp_path / "missing.xml"), str(broken.parent)]
    cfg = _tiny_cfg(methods=("pt", "pt+oidn", "gdpt+oidn-grad"), keep_going=True)
    out = tmp_path / "report"
    results = evaluate(scenes, out, cfg, progress=False)

    assert results["scenes"]["missing"]["status"] == "failed"
    assert "not found" in results["scenes"]["missing"]["error"]
    assert results["scenes"]["broken"]["status"] == "failed"
    assert "no_such_bsdf" in results["scenes"]["broken"]["error"]
    methods = results["scenes"]["cbox-demo"]["methods"]
    assert (
        methods["pt+oidn"]["status"] == "skipped" and "mitsuba-oidn" in methods["pt+oidn"]["note"]
    )
    skipped = methods["gdpt+oidn-grad"]
    assert skipped["status"] == "skipped" and "oidn-grad" in skipped["note"]
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

    # without keep_going, the first failed scene stops the study (recorded first)
    with pytest.raises(StudyFailure, match=r"^missing: load failed: .*not found"):
        evaluate(scenes, out, dataclasses.replace(cfg, keep_going=False), progress=False)
    assert json.loads((out / "results.json").read_text())["scenes"]["missing"]["status"] == "failed"


def test_method_that_failed_is_retried_on_resume(variant, tmp_path, monkeypatch):
    """A method that raised stops the study (recorded first) and runs again on resume."""
    cfg = _tiny_cfg(methods=("pt",))
    out = tmp_path / "report"
    working = EVAL_METHODS["pt"]

    def broken(*args, **kwargs):
        raise RuntimeError("transient failure")

    monkeypatch.setitem(EVAL_METHODS, "pt", dataclasses.replace(working, run=broken))
    expected = r"^cbox-demo / pt: calibration: could not run: RuntimeError: transient failure$"
    with pytest.raises(StudyFailure, match=expected):
        evaluate(["builtin:cbox-demo"], out, cfg, progress=False, report=False)
    info = json.loads((out / "results.json").read_text())["scenes"]["cbox-demo"]["methods"]["pt"]
    assert info["status"] == "skipped" and info["failed"] and "transient failure" in info["note"]

    monkeypatch.setitem(EVAL_METHODS, "pt", working)
    again = evaluate(["builtin:cbox-demo"], out, cfg, progress=False, report=False)
    info = again["scenes"]["cbox-demo"]["methods"]["pt"]
    assert info["status"] == "ok" and set(info["cells"]) == {"0.1", "0.2"}


class FakeClock:
    """Methods whose reported times come from a cost model instead of the wall clock.

    A method made by :meth:`method` returns a black ``(H, W, 3)`` image of its scene and
    ``seconds = fixed + per_spp * spp`` (``cost``, changeable between calls), records every call
    as ``(name, spp, seed)`` in :attr:`calls`, and raises ``RuntimeError`` when ``fail(spp,
    seed)`` is true.
    """

    def __init__(self, fixed: float = 0.05, per_spp: float = 0.01) -> None:
        self.cost = (fixed, per_spp)
        self.calls: list[tuple[str, int, int]] = []

    def method(self, name: str, fail=lambda spp, seed: False) -> EvalMethod:
        def run(scene, *, spp: int, seed: int) -> MethodResult:
            self.calls.append((name, spp, seed))
            if fail(spp, seed):
                raise RuntimeError("out of memory")
            width, height = getattr(scene, "resolution", (4, 3))
            fixed, per_spp = self.cost
            return MethodResult(torch.zeros(height, width, 3), seconds=fixed + per_spp * spp)

        return EvalMethod(name, f"fake method {name}", run)


def test_failed_method_or_cell_exits_1_naming_it_unless_keep_going(
    variant, tmp_path, monkeypatch, capsys
):
    """``gdpt evaluate``: a requested method that raises in a budget cell is a failure naming
    the scene, method and budget, exit status 1; with ``--keep-going`` the other cells run, the
    failure is printed and recorded, exit status 0; a later run retries the cell."""
    clock = FakeClock()
    broken = {"on": True}
    too_many = clock.method("fake-oom", fail=lambda spp, seed: broken["on"] and spp > 10)
    monkeypatch.setitem(EVAL_METHODS, "fake-oom", too_many)
    monkeypatch.setitem(EVAL_METHODS, "fake-ok", clock.method("fake-ok"))
    args = ["evaluate", "--scenes", "random:3", "--resolution", "24", "--budgets", "0.1", "0.2"]
    args += ["--reference-spp", "16", "--methods", "fake-oom", "fake-ok", "--quick"]
    args += ["--no-progress", "--out", str(tmp_path / "report")]
    assert main(args) == 1  # 0.2 s is 15 spp: it fails
    err = capsys.readouterr().err
    assert "gdpt evaluate: failed: random-3 / fake-oom at 0.2 s: RuntimeError: out of memory" in err
    assert "Traceback" not in err and "--keep-going" in err
    assert not (tmp_path / "report" / "results.md").exists()  # stopped before the report
    # stopped at once: cells run every method of a budget together, the failing one first
    failed_at = next(i for i, (name, spp, _) in enumerate(clock.calls) if spp > 10)
    assert clock.calls[failed_at][0] == "fake-oom" and failed_at == len(clock.calls) - 1

    assert main([*args, "--keep-going"]) == 0
    printed = capsys.readouterr().out
    assert "FAILED random-3 / fake-oom at 0.2 s: RuntimeError: out of memory" in printed
    results = json.loads((tmp_path / "report" / "results.json").read_text())
    methods = results["scenes"]["random-3"]["methods"]
    assert set(methods["fake-ok"]["cells"]) == {"0.1", "0.2"}
    assert set(methods["fake-oom"]["cells"]) == {"0.1"} and "0.2" in methods["fake-oom"]["errors"]

    broken["on"] = False  # a resumed run retries the failed cell
    assert main(args) == 0
    assert "FAILED" not in capsys.readouterr().out


def test_method_failing_at_calibration_is_named(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(
        EVAL_METHODS, "fake-broken", FakeClock().method("fake-broken", lambda *_: True)
    )
    args = ["evaluate", "--scenes", "random:3", "--resolution", "16", "--budgets", "0.1"]
    args += ["--reference-spp", "4", "--methods", "fake-broken", "--no-progress", "--quick"]
    assert main([*args, "--out", str(tmp_path / "report")]) == 1
    expected = "random-3 / fake-broken: calibration: could not run: RuntimeError: out of memory"
    assert expected in capsys.readouterr().err


def test_deprecated_study_name_is_run_and_read_as_the_new_one(tmp_path, monkeypatch):
    """``--methods gdpt+ngpt`` runs ``gdpt+oidn-grad`` (warned) and records it under that name;
    an earlier study's ``results.json`` that has ``gdpt+ngpt`` is read, and resumed by
    :func:`evaluate` given the old name, under the new name."""
    clock = FakeClock()
    monkeypatch.setitem(EVAL_METHODS, "gdpt+oidn-grad", clock.method("gdpt+oidn-grad"))
    out = tmp_path / "report"
    args = ["evaluate", "--scenes", "random:3", "--resolution", "16", "--budgets", "0.1", "0.2"]
    args += ["--reference-spp", "4", "--no-progress", "--quick", "--out", str(out)]
    expected = r"method 'gdpt\+ngpt' is deprecated; use 'gdpt\+oidn-grad'"
    with pytest.warns(DeprecationWarning, match=expected):
        assert main([*args, "--methods", "gdpt+ngpt"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["config"]["methods"] == ["gdpt+oidn-grad"]
    assert list(results["scenes"]["random-3"]["methods"]) == ["gdpt+oidn-grad"]

    earlier = json.loads((out / "results.json").read_text())
    for entry in (earlier, earlier["scenes"]["random-3"]):
        entry["methods"] = {"gdpt+ngpt": entry["methods"].pop("gdpt+oidn-grad")}
    earlier["config"]["methods"] = ["gdpt+ngpt"]
    (out / "results.json").write_text(json.dumps(earlier))
    assert read_results(out / "results.json") == results
    clock.calls.clear()
    cfg = _tiny_cfg(resolution=16, reference_spp=4, methods=("gdpt+ngpt",))
    with pytest.warns(DeprecationWarning, match=expected) as caught:
        again = evaluate(["random:3"], out, cfg, progress=False, report=False)
    assert caught[0].filename == __file__  # the warning names the caller's line
    assert clock.calls == []  # its cells were found under the new name
    assert again["config"]["methods"] == ["gdpt+oidn-grad"]
    assert list(again["scenes"]["random-3"]["methods"]) == ["gdpt+oidn-grad"]


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


def test_calibration_fits_the_cost_and_warms_up_every_timed_render_fake_clock():
    """:func:`calibrate` on reported times ``0.05 + 0.01 spp``: it recovers the line, every timed
    render follows an untimed one at the same spp and seed, and the probes
    grow from 1 spp until one takes half the budget."""
    clock = FakeClock(fixed=0.05, per_spp=0.01)
    model = calibrate(clock.method("fake"), SCENE, budget=2.0, seed=3)
    assert model.fixed == pytest.approx(0.05) and model.per_spp == pytest.approx(0.01)
    calls = [(spp, seed) for _, spp, seed in clock.calls]
    warm_ups, timed = calls[::2], calls[1::2]
    assert len(warm_ups) == len(timed)
    for (warm_spp, warm_seed), (spp, seed) in zip(warm_ups, timed, strict=True):
        assert warm_spp == spp and warm_seed == seed
    timed_spp = [spp for spp, _ in timed]
    assert timed_spp[:5] == [1, 2, 1, 1, 1]  # warm-up at 1 and 2 spp, then 3 timings at 1 spp
    probes = timed_spp[4:]
    assert all(2 <= b / a <= 8 for a, b in zip(probes, probes[1:], strict=False))
    assert [s for s, _ in model.measurements] == probes
    times = [t for _, t in model.measurements]
    assert times[-1] >= 0.5 * 2.0 > times[-2]  # stopped at the first probe of half the budget


def test_run_at_budget_meets_and_corrects_fake_clock():
    """:func:`run_at_budget`: with the true cost the first render meets the budget exactly; on a
    machine twice as slow as calibrated it re-renders with the corrected model until within the
    tolerance, at the same seed (and keeps the closest run); a budget below 1 spp is flagged."""
    clock = FakeClock(fixed=0.05, per_spp=0.01)
    method = clock.method("fake")
    model = TimeModel.fit([(1, 0.06), (64, 0.69)])
    result, record = run_at_budget(method, SCENE, model, budget=1.0, seed=5)
    assert record["spp"] == 95 and record["seconds"] == pytest.approx(1.0)
    assert record["within_tolerance"] and len(record["attempts"]) == 1
    assert result.image.shape == (3, 4, 3)

    clock.cost = (0.1, 0.02)  # the machine is twice as slow as the model says
    _, record = run_at_budget(method, SCENE, model, budget=1.0, seed=5, tolerance=0.2)
    attempts = record["attempts"]
    assert attempts[0]["spp"] == 95 and attempts[0]["seconds"] == pytest.approx(2.0)
    assert [a["seed"] for a in attempts] == [5] * len(attempts)  # the replicate's seed
    assert 2 <= len(attempts) <= 3 and attempts[1]["spp"] < 95
    errors = [abs(a["seconds"] - 1.0) for a in attempts]
    assert abs(record["seconds"] - 1.0) == pytest.approx(min(errors))  # the closest run
    assert record["within_tolerance"] and abs(record["relative_error"]) <= 0.2

    clock.cost = (3.0, 0.01)  # even 1 spp takes 3 budgets
    model = TimeModel.fit([(1, 3.01), (4, 3.04)])
    _, record = run_at_budget(method, SCENE, model, budget=1.0, seed=0)
    assert record["spp"] == 1 and record["over_budget_at_1spp"] and not record["within_tolerance"]


def test_a_study_cell_redoes_a_calibration_ten_percent_off_fake_clock():
    """A study cell's calibration (the default :attr:`EvaluateConfig.tolerance`) does not keep
    a run 10% over its budget: it renders again at a count re-chosen by the refined model and
    keeps the run within 5% (a 15% tolerance let a loaded machine lean two methods' counts
    apart by up to a quarter)."""
    clock = FakeClock(fixed=0.05, per_spp=0.011)  # 10% slower per sample than the model says
    model = TimeModel.fit([(1, 0.06), (8, 0.13), (64, 0.69)])
    tolerance = EvaluateConfig().tolerance
    _, record = run_at_budget(
        clock.method("fake"), SCENE, model, budget=1.0, seed=5, tolerance=tolerance
    )
    first, *_ = record["attempts"]
    assert first["spp"] == 95 and first["seconds"] > 1.09
    assert len(record["attempts"]) >= 2 and abs(record["relative_error"]) <= 0.05


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
    before = {id(r): set(r) for r in (METHODS, EVAL_METHODS)}
    yield
    for registry in (METHODS, EVAL_METHODS):
        for name in set(registry) - before[id(registry)]:
            del registry[name]


def test_model_option_compares_a_checkpoint(variant, tmp_path, capsys, registries_restored):
    from gdpt.reconstruct.oidn_finetune import DESIGNS, base_model, encode_delta

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


def test_methods_of_one_render_configuration_share_one_calibration_fake_clock(
    tmp_path, monkeypatch
):
    """Two methods that render the same thing (equal ``configuration``) get the same sample
    count at every budget from one calibration, timed on the first registered of them and
    recorded per scene; each still renders its own replicates and reports its own times."""
    # fake-b 10% dearer per sample: within MISS_TOLERANCE at fake-a's count (no corrected redo)
    first, second = FakeClock(fixed=0.05, per_spp=0.01), FakeClock(fixed=0.05, per_spp=0.011)
    same = {"integrator": "gdpt", "features": True, "reconstruction": "x"}
    for name, clock in (("fake-a", first), ("fake-b", second)):
        method = dataclasses.replace(clock.method(name), configuration=lambda: dict(same))
        monkeypatch.setitem(EVAL_METHODS, name, method)
    cfg = _tiny_cfg(resolution=16, reference_spp=4, methods=("fake-b", "fake-a"), seeds=2)
    results = evaluate(["random:3"], tmp_path / "report", cfg, progress=False, report=False)
    scene = results["scenes"]["random-3"]
    cells = {m: scene["methods"][m]["cells"] for m in ("fake-a", "fake-b")}
    for key in ("0.1", "0.2"):
        assert cells["fake-a"][key]["spp"] == cells["fake-b"][key]["spp"]
        assert [r["spp"] for r in cells["fake-b"][key]["replicates"]] == [
            cells["fake-a"][key]["spp"]
        ] * 2
    assert cells["fake-b"]["0.2"]["seconds"] > cells["fake-a"]["0.2"]["seconds"]  # its own
    assert set(cells["fake-a"]["0.2"]["companions"]) == {"relmse_trimmed"}
    (calibration,) = scene["calibrations"].values()
    assert calibration["runner"] == "fake-a" and set(calibration["methods"]) == {"fake-a", "fake-b"}
    assert calibration["configuration"] == same
    spps = {spp for _, spp, _ in second.calls}
    assert spps == {cells["fake-b"][k]["spp"] for k in ("0.1", "0.2")}  # no probes of its own


def test_auto_shares_the_calibration_of_its_plain_route():
    """``auto``'s ``spp`` are its plain route's samples: its render configuration is that of
    ``pt+`` the primal-only denoiser, which is timed for both where ``auto`` takes a count
    (``render-time``; under ``total`` it is given the seconds)."""
    from gdpt.study.calibration import fills_seconds

    assert fills_seconds(EVAL_METHODS["auto"], "total")
    assert not fills_seconds(EVAL_METHODS["auto"], "render-time")
    assert not fills_seconds(EVAL_METHODS["pt+oidn-tuned"], "total")
    from gdpt.adapters import plain_denoiser
    from gdpt.study.calibration import calibration_runner, configuration_key

    plain = EVAL_METHODS[f"pt+{plain_denoiser()}"]
    for protocol in ("total", "render-time"):
        key = configuration_key(EVAL_METHODS["auto"], protocol)
        assert key == configuration_key(plain, protocol)
    assert calibration_runner(EVAL_METHODS["auto"], "total") is plain
    assert configuration_key(EVAL_METHODS["pt"], "total") != configuration_key(plain, "total")
    assert configuration_key(EVAL_METHODS["gdpt+fuse"], "total") != configuration_key(
        plain, "total"
    )


def test_replicates_are_added_while_the_interval_is_wide_fake_clock(tmp_path, monkeypatch):
    """``until_interval``: a cell whose replicates scatter gets paired replicates (the seeds
    every method uses for that index) up to ``max_seeds``; a tight enough cell keeps ``seeds``."""
    clock = FakeClock()

    def run(scene, *, spp: int, seed: int) -> MethodResult:
        width, height = scene.resolution
        value = 1.0 + (seed % 7) / 3  # a different error per seed
        return MethodResult(torch.full((height, width, 3), value), seconds=0.05 + 0.01 * spp)

    monkeypatch.setitem(EVAL_METHODS, "fake-noisy", EvalMethod("fake-noisy", "noisy", run))
    monkeypatch.setitem(EVAL_METHODS, "fake", clock.method("fake"))
    cells = {}
    for share, out in ((0.01, "wide"), (100.0, "loose")):
        cfg = _tiny_cfg(
            resolution=16, reference_spp=4, methods=("fake-noisy",), budgets=(0.1,), seeds=2
        )
        cfg = dataclasses.replace(cfg, until_interval=share, max_seeds=5)
        results = evaluate(["random:3"], tmp_path / out, cfg, progress=False, report=False)
        cells[out] = results["scenes"]["random-3"]["methods"]["fake-noisy"]["cells"]["0.1"]
    assert len(cells["wide"]["replicates"]) == 5 and len(cells["loose"]["replicates"]) == 2
    seeds = [r["seed"] for r in cells["wide"]["replicates"]]
    assert seeds[:2] == [r["seed"] for r in cells["loose"]["replicates"]] and len(set(seeds)) == 5
    with pytest.raises(ValueError, match="max_seeds"):
        EvaluateConfig(seeds=4, max_seeds=3)
