"""gdpt.study cells, chunked references, threads and the Ray engine (gdpt.study.cells,
gdpt.study.references, gdpt.study.engine)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import sys
from pathlib import Path

import pytest
import torch

from gdpt.cli import main
from gdpt.study.cells import (
    MISS_TOLERANCE,
    TORCH_THREADS,
    _timed_replicate,
    method_order,
    redo_spp,
)
from gdpt.study.config import EvaluateConfig
from gdpt.study.evaluate import evaluate
from gdpt.study.methods import EVAL_METHODS, EvalMethod, MethodResult
from gdpt.study.references import reference_chunks, render_reference
from gdpt.study.scenes import SceneSpec, load_eval_scene

SAME = {"integrator": "gdpt", "features": True, "reconstruction": "x"}


@pytest.fixture(scope="module")
def variant():
    import drjit as dr

    import gdpt

    gdpt.set_variant("llvm_ad_rgb")
    flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    yield
    dr.set_flag(dr.JitFlag.KernelHistory, flag)


def _cfg(**changes) -> EvaluateConfig:
    base = dict(
        budgets=(0.1, 0.2),
        resolution=16,
        reference_spp=4,
        reference_chunk_spp=2,
        metrics=("relmse", "smape"),
        metric_options={},
    )
    return EvaluateConfig(**{**base, **changes})


class Clock:
    """Fake methods: ``seconds = (0.05 + 0.01 * spp) * scale`` (``scale`` per method, and
    ``slow``: extra factors for its next calls, warm-ups included), a black image; every call
    is logged as ``(name, spp, seed)``."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, int, int]] = []
        self.scale: dict[str, float] = {}
        self.slow: dict[str, list[float]] = {}

    def method(self, name: str, configuration=None) -> EvalMethod:
        def run(scene, *, spp: int, seed: int) -> MethodResult:
            self.calls.append((name, spp, seed))
            width, height = scene.resolution
            factor = self.scale.get(name, 1.0)
            if self.slow.get(name):
                factor *= self.slow[name].pop(0)
            seconds = (0.05 + 0.01 * spp) * factor
            return MethodResult(torch.zeros(height, width, 3), seconds=seconds)

        method = EvalMethod(name, f"fake {name}", run)
        if configuration is not None:
            method = dataclasses.replace(method, configuration=lambda: dict(configuration))
        return method


def test_method_order_reverses_on_odd_replicates():
    assert method_order(["a", "b", "c"], 0) == ["a", "b", "c"]
    assert method_order(["a", "b", "c"], 1) == ["c", "b", "a"]
    assert method_order(["a", "b"], 2) == ["a", "b"]


def test_cells_run_methods_back_to_back_in_rotated_order_fake_clock(tmp_path, monkeypatch):
    """Every method of a (budget, seed) runs before the next cell starts, A B then B A; each
    cell calibrates its own configuration; threads and load are recorded per replicate."""
    clock = Clock()
    for name in ("fake-a", "fake-b"):
        monkeypatch.setitem(EVAL_METHODS, name, clock.method(name))
    cfg = _cfg(methods=("fake-a", "fake-b"), budgets=(0.2,), seeds=2)
    results = evaluate(["random:3"], tmp_path / "report", cfg, progress=False, report=False)
    assert results["format"] == "gdpt-evaluate/2"
    entry = results["scenes"]["random-3"]
    runs = entry["cell_runs"]
    assert set(runs) == {"0.2/0", "0.2/1"}
    assert runs["0.2/0"]["order"] == ["fake-a", "fake-b"]
    assert runs["0.2/1"]["order"] == ["fake-b", "fake-a"]
    seeds = [runs[f"0.2/{r}"]["seed"] for r in (0, 1)]
    # the timed runs at the replicate seeds, in call order: a, b (seed 0) then b, a (seed 1)
    timed = [(name, seed) for name, _, seed in clock.calls if seed in seeds]
    firsts = list(dict.fromkeys(timed))
    assert firsts == [
        ("fake-a", seeds[0]),
        ("fake-b", seeds[0]),
        ("fake-b", seeds[1]),
        ("fake-a", seeds[1]),
    ]
    for run in runs.values():  # each method calibrated inside the cell (its own config)
        assert set(run["calibrations"]) == {"method fake-a", "method fake-b"}
        assert run["worker"]["threads"] == results["threads"]["per_worker"]
    cell = entry["methods"]["fake-a"]["cells"]["0.2"]
    assert len(cell["replicates"]) == 2 and cell["missed_budget"] == []
    for replicate in cell["replicates"]:
        assert replicate["charged_seconds"] == pytest.approx(0.2, rel=MISS_TOLERANCE)
        assert {"loadavg_1min", "cpu_seconds", "wall_seconds", "cpu_per_wall"} <= set(replicate)
        assert replicate["wall_seconds"] > 0 and not replicate["missed_budget"]


def test_a_configuration_probes_once_then_takes_counts_from_its_model_fake_clock(
    tmp_path, monkeypatch
):
    """The first cell of a configuration fits its cost model by probes; the later cells (other
    budgets, other replicates) take their counts from the model, refined by every timed run,
    and render only their timed runs (each after its warm-up)."""
    clock = Clock()
    monkeypatch.setitem(EVAL_METHODS, "fake-a", clock.method("fake-a"))
    cfg = _cfg(methods=("fake-a",), budgets=(0.2, 0.4), seeds=2)
    results = evaluate(["random:3"], tmp_path / "report", cfg, progress=False, report=False)
    runs = results["scenes"]["random-3"]["cell_runs"]
    sources = {u: r["calibrations"]["method fake-a"]["model_source"] for u, r in runs.items()}
    assert sources == {"0.2/0": "calibrated", "0.2/1": "model", "0.4/0": "model", "0.4/1": "model"}
    later = [
        c for c in clock.calls if c[2] in {runs[u]["seed"] for u in ("0.2/1", "0.4/0", "0.4/1")}
    ]
    assert len(clock.calls) - len(later) > 6  # the first cell probed (and timed)
    assert len(later) == 6  # three cells: a warm-up and a timed run each, no probes
    for unit, budget in (("0.2/1", 0.2), ("0.4/0", 0.4), ("0.4/1", 0.4)):
        assert runs[unit]["calibrations"]["method fake-a"]["spp"] == round((budget - 0.05) / 0.01)
    models = [r["calibrations"]["method fake-a"]["model"]["measurements"] for r in runs.values()]
    assert [len(m) for m in models] == sorted(len(m) for m in models)  # each run adds one
    assert len(models[-1]) == len(models[0]) + 3


def test_replicate_over_budget_is_redone_then_flagged_fake_clock(tmp_path, monkeypatch):
    """A method that shares another's calibration and misses the budget by more than
    MISS_TOLERANCE is timed once more at the count corrected by its miss (redo_spp): on time,
    it is kept (the first run under ``redone``); still off, it is flagged in results.json and
    the report."""
    clock = Clock()
    monkeypatch.setitem(EVAL_METHODS, "fake-a", clock.method("fake-a", SAME))
    monkeypatch.setitem(EVAL_METHODS, "fake-b", clock.method("fake-b", SAME))
    clock.scale["fake-b"] = 1.2  # 20% over at fake-a's count: linear, so the redo is on time
    cfg = _cfg(methods=("fake-a", "fake-b"), budgets=(0.2,), seeds=1)
    results = evaluate(["random:3"], tmp_path / "fixed", cfg, progress=False, report=False)
    cells = results["scenes"]["random-3"]["methods"]
    (a,) = cells["fake-a"]["cells"]["0.2"]["replicates"]
    (b,) = cells["fake-b"]["cells"]["0.2"]["replicates"]
    assert not b["missed_budget"] and abs(b["relative_error"]) <= MISS_TOLERANCE
    assert b["redone"]["spp"] == a["spp"] and b["redone"]["relative_error"] > MISS_TOLERANCE
    per_spp = 0.01 * 1.0  # fake-a's seconds per sample, what the shared calibration measured
    assert b["spp"] == a["spp"] - round((b["redone"]["charged_seconds"] - 0.2) / per_spp)

    clock = Clock()
    monkeypatch.setitem(EVAL_METHODS, "fake-a", clock.method("fake-a", SAME))
    monkeypatch.setitem(EVAL_METHODS, "fake-b", clock.method("fake-b", SAME))
    clock.scale["fake-b"] = 3.0  # 3x over: the redo at half the count (the bound) still over
    cfg = _cfg(methods=("fake-a", "fake-b"), budgets=(0.2,), seeds=2)
    out = tmp_path / "report"
    results = evaluate(["random:3"], out, cfg, progress=False)
    flagged = results["scenes"]["random-3"]["methods"]["fake-b"]["cells"]["0.2"]
    assert flagged["missed_budget"] == [0, 1]
    for replicate in flagged["replicates"]:
        assert replicate["missed_budget"] and replicate["relative_error"] > MISS_TOLERANCE
        assert replicate["redone"]["relative_error"] > replicate["relative_error"]
        assert replicate["spp"] == math.ceil(replicate["redone"]["spp"] / 2)
    calls_b = [c for c in clock.calls if c[0] == "fake-b"]
    assert len(calls_b) == 8  # two replicates, each warmed up and timed twice (no third try)
    report = (out / "results.md").read_text()
    assert "missed the budget" in report and "fake-b at 0.2 s, replicate 0" in report


def test_a_method_that_fills_seconds_is_given_the_budget_not_a_count_fake_clock(tmp_path):
    """``auto`` under ``total`` (a method with ``run_for``): each replicate is given the
    budget in seconds, warmed up and timed at its seed, never a calibrated count; its count is
    its own choice, recorded; a miss is redone at the same budget. Under ``render-time`` it
    takes its configuration's calibrated count as before."""
    clock, given = Clock(), []

    def run_for(scene, *, seconds: float, seed: int) -> MethodResult:
        given.append((seconds, seed))
        width, height = scene.resolution
        slow = 1.3 if len(given) == 2 else 1.0  # the first timed run 30% over: redone
        return MethodResult(torch.zeros(height, width, 3), seconds * slow, spp=int(seconds * 100))

    fills = dataclasses.replace(clock.method("fake-s", SAME), run_for=run_for)
    cfg = _cfg(methods=("fake-a", "fake-s"), budgets=(0.2,), seeds=1)
    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(EVAL_METHODS, "fake-a", clock.method("fake-a", SAME))
        patch.setitem(EVAL_METHODS, "fake-s", fills)
        results = evaluate(["random:3"], tmp_path / "total", cfg, progress=False, report=False)
    assert not [c for c in clock.calls if c[0] == "fake-s"]  # no count given, no probes
    (record,) = results["scenes"]["random-3"]["methods"]["fake-s"]["cells"]["0.2"]["replicates"]
    seed = record["seed"]
    assert given == [(0.2, seed)] * 4  # warm-up and timed, twice (the miss redone)
    assert record["spp"] == 20 and record["charged_seconds"] == pytest.approx(0.2)
    assert record["redone"]["relative_error"] == pytest.approx(0.3)
    assert record["calibration"] == "method fake-s (seconds)" and not record["missed_budget"]

    given.clear()
    cfg = _cfg(methods=("fake-a", "fake-s"), budgets=(0.2,), seeds=1, protocol="render-time")
    with pytest.MonkeyPatch.context() as patch:
        patch.setitem(EVAL_METHODS, "fake-a", clock.method("fake-a", SAME))
        patch.setitem(EVAL_METHODS, "fake-s", fills)
        evaluate(["random:3"], tmp_path / "render-time", cfg, progress=False, report=False)
    assert given == [] and [c for c in clock.calls if c[0] == "fake-s"]


def test_redo_of_a_large_miss_keeps_at_least_half_the_count():
    """A miss that large is the machine's (a first try of 53.8 s at 436 spp for 8 s): the redo
    keeps half the count at least, not the 1 spp the miss alone would leave (and at most
    twice the count for a run far under)."""
    per_spp = 8.0 / 436
    assert redo_spp(436, 53.8, 8.0, per_spp) == 218
    assert redo_spp(436, 1.0, 8.0, per_spp / 2) == 872
    assert redo_spp(436, 9.6, 8.0, per_spp) == 436 - round(1.6 / per_spp)  # a small miss


def test_replicate_of_its_own_calibration_is_redone_at_the_same_count_fake_clock(tmp_path):
    """A method timed at its own calibration's count that misses (a slow-down of the machine)
    is redone at the same count: the redo on time is kept, the slow run recorded."""
    clock = Clock()
    clock.slow["fake-a"] = [1.0, 2.0]  # its warm-up on time, its first timed run slow
    scene = load_eval_scene(SceneSpec("random-3", "random:3"), resolution=16)
    record, _ = _timed_replicate(clock.method("fake-a"), scene, 15, 7, 0.2, "total", None)
    assert record["spp"] == record["redone"]["spp"] == 15
    assert record["redone"]["relative_error"] > 0.5
    assert not record["missed_budget"] and abs(record["relative_error"]) <= MISS_TOLERANCE


def test_threads_are_set_recorded_and_restored(tmp_path, monkeypatch):
    import drjit as dr

    clock = Clock()
    monkeypatch.setitem(EVAL_METHODS, "fake-a", clock.method("fake-a"))
    owned = len(os.sched_getaffinity(0))
    before = (torch.get_num_threads(), dr.thread_count())
    torch.set_num_threads(owned + 1)  # not what the study owns
    try:
        cfg = _cfg(methods=("fake-a",), budgets=(0.1,))
        results = evaluate(["random:3"], tmp_path / "report", cfg, progress=False, report=False)
        assert torch.get_num_threads() == owned + 1  # restored
    finally:
        torch.set_num_threads(before[0])
        dr.set_thread_count(before[1])
    assert results["threads"] == {
        "engine": "sequential",
        "workers": 1,
        "per_worker": {"torch": min(owned, TORCH_THREADS), "drjit": owned},
    }
    (run,) = results["scenes"]["random-3"]["cell_runs"].values()
    assert run["worker"]["threads"] == {"torch": min(owned, TORCH_THREADS), "drjit": owned}


def test_format_1_results_are_read_and_resumed(tmp_path, monkeypatch):
    """A study written before cells (format 1) is read, and its finished cells are not rerun."""
    clock = Clock()
    monkeypatch.setitem(EVAL_METHODS, "fake-a", clock.method("fake-a"))
    cfg = _cfg(methods=("fake-a",), budgets=(0.1,))
    out = tmp_path / "report"
    evaluate(["random:3"], out, cfg, progress=False, report=False)
    old = json.loads((out / "results.json").read_text())
    old["format"] = "gdpt-evaluate/1"
    del old["scenes"]["random-3"]["cell_runs"]
    (out / "results.json").write_text(json.dumps(old))
    clock.calls.clear()
    again = evaluate(["random:3"], out, cfg, progress=False, report=False)
    assert clock.calls == [] and again["format"] == "gdpt-evaluate/2"


# -------------------------------------------------------------------------------- references
def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_reference_chunks_cover_the_samples_with_index_seeds():
    chunks = reference_chunks(10, 4, seed=3)
    assert [(c.index, c.spp, c.seed) for c in chunks] == [
        (0, 4, 3 * 7919),
        (1, 4, 3 * 7919 + 4),
        (2, 2, 3 * 7919 + 8),
    ]
    assert {c.count for c in chunks} == {3}


def test_chunked_reference_is_bit_identical_in_any_order_and_resumes_after_a_kill(
    variant, tmp_path
):
    """The same reference whatever the order and thread count the chunks were rendered with
    (one worker of 2 threads, chunks in order; "two workers" of one thread each, in reverse),
    and after a render killed mid-way (finished chunks kept, a torn temporary file removed)."""
    import drjit as dr

    from gdpt.study.references import render_chunk

    scene = load_eval_scene(SceneSpec("cbox", "builtin:cbox-demo"), resolution=16)
    kwargs = dict(spp=12, chunk_spp=2, seed=5)
    _, meta = render_reference(scene, tmp_path / "one", **kwargs)
    expected = _sha(Path(meta["path"]))

    threads = dr.thread_count()

    def reversed_one_thread(scene, chunks):
        dr.set_thread_count(1)
        try:
            for chunk in reversed(chunks):
                yield chunk, render_chunk(scene, chunk)
        finally:
            dr.set_thread_count(threads)

    _, meta = render_reference(scene, tmp_path / "two", run_chunks=reversed_one_thread, **kwargs)
    assert _sha(Path(meta["path"])) == expected

    cache = tmp_path / "killed"

    def killed_after_one(scene, chunks):
        yield chunks[0], render_chunk(scene, chunks[0])
        (cache / f".{Path(meta['path']).stem}.chunk-00001-of-00006.exr.x.tmp").write_bytes(b"t")
        raise KeyboardInterrupt  # the second chunk dies while rendering

    with pytest.raises(KeyboardInterrupt):
        render_reference(scene, cache, run_chunks=killed_after_one, **kwargs)
    assert len(list(cache.glob("*.chunk-*.exr"))) == 1 and not list(cache.glob("*spp-seed5.exr"))
    rendered = []

    def counting(scene, chunks):
        for chunk in chunks:
            rendered.append(chunk.index)
            yield chunk, render_chunk(scene, chunk)

    _, meta = render_reference(scene, cache, run_chunks=counting, **kwargs)
    assert rendered == [1, 2, 3, 4, 5]  # resumed chunk by chunk
    assert _sha(Path(meta["path"])) == expected
    assert not list(cache.glob("*.chunk-*.exr")) and not list(cache.glob(".*.tmp"))


def test_running_mean_partial_of_an_older_version_resumes_as_its_first_chunks(variant, tmp_path):
    """A ``<stem>.partial-<done>.exr`` of the former running-mean reference (same seeds) counts
    as the first ``done / chunk_spp`` chunks: only the rest is rendered."""
    from gdpt.io.exr import save_image
    from gdpt.study.references import merge_chunks, reference_stem, render_chunk

    scene = load_eval_scene(SceneSpec("cbox", "builtin:cbox-demo"), resolution=8)
    chunks = reference_chunks(8, 2, seed=1)
    first = merge_chunks([(c.spp, render_chunk(scene, c)) for c in chunks[:2]])
    stem = reference_stem(scene, 8, 1)
    cache = tmp_path / "refs"
    cache.mkdir()
    save_image(cache / f"{stem}.partial-4.exr", first, force=True)
    sidecar = {"source": "builtin:cbox-demo", "film_filter": scene.film_filter, "seconds": 1.0}
    (cache / f"{stem}.json").write_text(json.dumps(sidecar))
    rendered = []

    def counting(scene, todo):
        for chunk in todo:
            rendered.append(chunk.index)
            yield chunk, render_chunk(scene, chunk)

    image, meta = render_reference(
        scene, cache, spp=8, chunk_spp=2, seed=1, source="builtin:cbox-demo", run_chunks=counting
    )
    assert rendered == [2, 3] and not meta["cached"]
    whole = merge_chunks([(c.spp, render_chunk(scene, c)) for c in chunks]).float()
    assert torch.allclose(image, whole, rtol=1e-5, atol=1e-7)
    assert not list(cache.glob("*.partial-*")) and not list(cache.glob("*.chunk-*"))


def test_cached_reference_is_found_under_another_name_of_the_same_file(
    variant, tmp_path, monkeypatch
):
    """A reference recorded with a relative scene path is the same scene given by its absolute
    path (a study run from another folder); another file of that name is not."""
    scene = load_eval_scene(SceneSpec("cbox", "builtin:cbox-demo"), resolution=8)
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "scene.xml").write_text("<scene/>")
    (tmp_path / "b.xml").write_text("<scene/>")
    monkeypatch.chdir(tmp_path / "a")
    kwargs = dict(spp=2, chunk_spp=1, seed=1)
    _, meta = render_reference(scene, tmp_path / "refs", source="../a/scene.xml", **kwargs)
    assert not meta["cached"]
    same = str(tmp_path / "a" / "scene.xml")
    assert render_reference(scene, tmp_path / "refs", source=same, **kwargs)[1]["cached"]
    other = str(tmp_path / "b.xml")
    assert not render_reference(scene, tmp_path / "refs", source=other, **kwargs)[1]["cached"]


# --------------------------------------------------------------------------------------- ray
def test_ray_address_that_does_not_answer_is_one_line_before_any_work(tmp_path, capsys):
    out = tmp_path / "report"
    args = ["evaluate", "--scenes", "builtin:cbox-demo", "--out", str(out), "--quick"]
    assert main([*args, "--ray-address", "127.0.0.1:9", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "127.0.0.1:9 does not answer" in err, err
    assert not out.exists()  # nothing was done
    assert main([*args, "--workers", "0"]) == 2


def _keys(value, prefix=""):
    """Every key path of a JSON value (dict keys; lists by their first element), without the
    ``redone`` records (which replicates are redone depends on the machine)."""
    if isinstance(value, dict):
        return {
            k
            for key, v in value.items()
            if key != "redone"
            for k in {prefix + key} | _keys(v, prefix + key + ".")
        }
    if isinstance(value, list) and value:
        return _keys(value[0], prefix + "[]")
    return set()


def _dies_once(flag: str):
    def run(scene, *, spp: int, seed: int) -> MethodResult:
        if not os.path.exists(flag):  # the worker is killed in its first cell
            Path(flag).write_text("killed once")
            os._exit(1)
        width, height = scene.resolution
        return MethodResult(torch.zeros(height, width, 3), seconds=0.05 + 0.01 * spp)

    return run


def _noisy(scene, *, spp: int, seed: int) -> MethodResult:
    width, height = scene.resolution
    value = 1.0 + (seed % 7) / 3  # a different error per seed: a wide interval
    return MethodResult(torch.full((height, width, 3), value), seconds=0.05 + 0.01 * spp)


@pytest.mark.slow
def test_ray_workers_give_the_sequential_results_and_rerun_a_killed_cell(
    variant, tmp_path, monkeypatch
):
    """``--workers 2``: the same results.json keys as the sequential study, the same reference
    bits (chunks from two workers), a cell whose worker was killed run again, and replicates
    added while an interval is wide (``until_interval``) as in the sequential study."""
    import ray.cloudpickle

    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    flag = tmp_path / "killed"
    method = EvalMethod("fake-dies", "killed once", _dies_once(str(flag)))
    monkeypatch.setitem(EVAL_METHODS, "fake-dies", method)
    monkeypatch.setitem(EVAL_METHODS, "fake-noisy", EvalMethod("fake-noisy", "noisy", _noisy))
    cfg = _cfg(methods=("pt", "fake-dies", "fake-noisy"), budgets=(0.1,), reference_spp=16, seeds=2)
    cfg = dataclasses.replace(cfg, until_interval=0.01, max_seeds=3)
    flag.write_text("not in the sequential run")
    alone = evaluate(["builtin:cbox-demo"], tmp_path / "seq", cfg, progress=False)
    flag.unlink()
    ray_run = evaluate(["builtin:cbox-demo"], tmp_path / "ray", cfg, progress=False, workers=2)
    assert flag.is_file()  # a worker died ...
    entry = ray_run["scenes"]["cbox-demo"]
    units = {"0.1/0", "0.1/1", "0.1/2"}  # the third added: fake-noisy's interval is wide
    assert set(entry["cell_runs"]) == set(alone["scenes"]["cbox-demo"]["cell_runs"]) == units
    assert entry["cell_runs"]["0.1/2"]["replicates"]["pt"]["added"] == "until_interval"
    assert not entry.get("cell_errors")
    assert _keys(alone) - {"threads.per_worker.torch", "threads.per_worker.drjit"} == _keys(
        ray_run
    ) - {"threads.address", "threads.cluster_cpus", "threads.timed_cell_slots"}
    assert ray_run["threads"]["engine"] == "ray"
    for run in entry["cell_runs"].values():
        assert run["worker"]["threads"] == {"torch": 1, "drjit": 1}  # 2 cores / 2 workers
    references = [
        _sha(Path(study["scenes"]["cbox-demo"]["reference"]["path"])) for study in (alone, ray_run)
    ]
    assert references[0] == references[1]
    assert "compare timings only within a cell" in (tmp_path / "ray" / "results.md").read_text()


def test_a_study_whose_renders_shared_the_machine_is_reported_busy():
    """The run summary warns where the render-bound timed runs got a median under
    ``BUSY_SHARE`` of their Dr.Jit threads' CPU time; reconstruction-bound runs (one torch
    thread) do not count, and an idle study gets no warning."""
    from gdpt.study.report import BUSY_SHARE, _busy_line

    def study(cpu_per_wall: float, render_share: float = 0.95) -> dict:
        replicate = {"cpu_per_wall": cpu_per_wall, "seconds": 2.0}
        replicate["render_seconds"] = render_share * 2.0
        run = {"worker": {"threads": {"drjit": 2}}, "replicates": {"pt": replicate}}
        return {"scenes": {"a": {"cell_runs": {"2/0": run, "2/1": run}}}}

    assert _busy_line(study(1.97)) is None
    assert "median 60%" in _busy_line(study(1.2))
    assert _busy_line(study(2 * BUSY_SHARE)) is None
    assert _busy_line(study(1.0, render_share=0.3)) is None  # its reconstruction's one thread
    assert _busy_line({"scenes": {}}) is None
