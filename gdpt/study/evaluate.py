"""Equal-time evaluation: error against measured wall time, per scene, method and budget.

For each scene and time budget, every method of :data:`gdpt.study.methods.EVAL_METHODS` gets the
sample count whose *measured* render + reconstruction time matches the budget on this machine,
in this run (calibrated by timing, never assumed), and its image is compared with a high-spp
reference by the metrics of :mod:`gdpt.metrics`::

    from gdpt.study.config import PRESETS
    from gdpt.study.evaluate import evaluate

    results = evaluate(["builtin:cbox-demo"], "out/eval", PRESETS["quick"])

Protocol, per scene:

1. Load the scene at ``resolution`` pixels on the long side. Mitsuba XML scenes whose film uses
   a non-box pixel filter get ``<rfilter type="box"/>`` (the gradient-domain integrators need
   it); the override is recorded in the results and the report, and the reference uses the
   same film, so every method is compared on the same image formation.
2. Render the reference once: path tracing (``gdpt`` primal only) at ``reference_spp``, in
   chunks whose running mean is saved, so an interrupted reference resumes; the finished file
   is cached with its spp, seed and resolution in its name and metadata.
3. Cells (:mod:`gdpt.study.cells`): per budget and replicate seed, every method is calibrated
   and run back to back in one cell, the order reversed on odd replicates; each render
   configuration (:func:`~gdpt.study.calibration.configuration_key`: methods that render the
   same thing share it; recorded per scene in ``calibrations``; ``auto`` under ``total`` is
   given the budget in seconds instead, :func:`~gdpt.study.calibration.fills_seconds`) is
   calibrated inside the cell by its
   :func:`~gdpt.study.calibration.calibration_runner`: fit ``t(spp) = a + b * spp`` from a
   median of 1-spp runs and geometrically growing probe runs
   (:func:`~gdpt.study.calibration.calibrate`), render at the budget and correct
   (:func:`~gdpt.study.calibration.run_at_budget`). No timed render pays kernel compilation
   (subtracted) or the Python tracing of a frozen pass (the integrators record one per pass
   size and replay it afterwards): a run that recorded passes was the warm-up and runs again
   (:func:`~gdpt.study.calibration.timed_run`; ``auto`` and methods that cannot be split warm
   up before every timed render). A replicate that misses its budget by more than
   :data:`~gdpt.study.cells.MISS_TOLERANCE` is redone once, then flagged.
4. Metrics of every replicate; ``results.json`` is rewritten (atomically) after each cell, so
   an interrupted run resumes without recomputing finished cells. With ``workers`` or
   ``ray_address`` the reference chunks and the cells run as Ray tasks
   (:mod:`gdpt.study.engine`), with the same results.
5. The reference-free estimate of every cell's relMSE ratio to ``pt+oidn-tuned``
   (:mod:`gdpt.study.estimate`), beside the true one; with ``cfg.reference`` off (``gdpt
   evaluate --no-reference``) step 2 and the metrics are skipped and the estimate is the result.

A method that cannot run here (package missing, no shipped model) is recorded with the reason
and skipped. A failure (a scene that fails to load or render its reference, a method that raises
while calibrating or rendering a cell) is recorded too, and then stops the study with
:class:`StudyFailure` naming the scene, method and budget, unless ``cfg.keep_going`` is set:
then it is data and the study continues (:func:`failures` lists them). Either way a resumed run
retries what failed.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from gdpt.interrupt import caused_by_interrupt
from gdpt.pipeline import release_scene
from gdpt.study.calibration import forget_cost_models
from gdpt.study.cells import (
    MISS_TOLERANCE,
    pending_cells,
    run_cell,
    set_threads,
    thread_counts,
)
from gdpt.study.config import PRESETS, EvaluateConfig
from gdpt.study.driver import (
    StudyFailure,
    cells_to_run,
    finish_cell,
    load_into,
    reference_ready,
    runnable_methods,
    scene_failed,
)
from gdpt.study.estimate import estimate_scene
from gdpt.study.methods import EVAL_METHODS, EvalMethod
from gdpt.study.references import reference_seed, render_reference
from gdpt.study.results import (
    CONVENTIONS,
    budget_key,
    cell_keys,
    cells_done,
    load_results,
    machine_info,
    study_cost,
    versions,
    write_json,
)
from gdpt.study.scenes import EvalScene, SceneSpec, load_eval_scene, resolve_scenes

__all__ = ["PROTOCOL_TEXT", "StudyFailure", "evaluate", "failures", "render_references"]

#: What a budget pays for, per protocol, in the words of the results.
PROTOCOL_TEXT = {
    "total": "protocol 'total': a budget pays for sampling and reconstruction",
    "render-time": "protocol 'render-time': a budget pays for sampling only (the paper's "
    "equal-time protocol); reconstruction seconds are reported beside it",
}


def failures(results: dict[str, Any]) -> list[str]:
    """One line per failure recorded in ``results`` (the content of ``results.json``): a scene
    that failed, a method that raised while calibrating, a budget cell that raised."""
    lines = []
    for scene, entry in results["scenes"].items():
        if entry.get("status") == "failed":
            lines.append(f"{scene}: {entry.get('stage')} failed: {entry.get('error')}")
        for method, info in entry.get("methods", {}).items():
            if info.get("failed"):
                lines.append(f"{scene} / {method}: calibration failed: {info['note']}")
            for key, error in info.get("errors", {}).items():
                lines.append(f"{scene} / {method} at {key} s: {error}")
        for unit, error in entry.get("cell_errors", {}).items():
            lines.append(f"{scene}: cell {unit} (budget/replicate): {error}")
    return lines


def _current_methods(cfg: EvaluateConfig) -> EvaluateConfig:
    """``cfg`` with each deprecated method name replaced by its current one (a
    ``DeprecationWarning`` each, naming the caller of :func:`evaluate`)."""
    methods = []
    for name in cfg.methods:  # a loop: before Python 3.12 a comprehension is a frame of its own
        methods.append(EVAL_METHODS.resolve(name, stacklevel=3))
    return dataclasses.replace(cfg, methods=tuple(methods))


def _method_list(cfg: EvaluateConfig) -> list[str]:
    names = list(cfg.methods or EVAL_METHODS)
    for name in names:
        if name not in EVAL_METHODS:
            raise ValueError(f"unknown method {name!r}; valid: {', '.join(EVAL_METHODS)}")
    return names


def _as_specs(scenes: Sequence[str | os.PathLike[str] | SceneSpec]) -> list[SceneSpec]:
    specs: list[SceneSpec] = []
    for item in scenes:
        specs += [item] if isinstance(item, SceneSpec) else resolve_scenes([item])
    return specs


def _study_reference(
    scene: EvalScene,
    spec: SceneSpec,
    cfg: EvaluateConfig,
    cache: Path,
    bar: Any,
    run_chunks: Any = None,
) -> tuple[torch.Tensor, dict[str, Any]]:
    """:func:`render_reference` with the study's settings (shared by every entry point)."""
    return render_reference(
        scene,
        cache,
        spp=cfg.reference_spp,
        chunk_spp=cfg.reference_chunk_spp,
        seed=reference_seed(cfg.seed),
        source=spec.source,
        progress=bar,
        run_chunks=run_chunks,
    )


def evaluate(
    scenes: Sequence[str | os.PathLike[str] | SceneSpec],
    out_dir: str | os.PathLike[str],
    cfg: EvaluateConfig | None = None,
    *,
    progress: bool = True,
    report: bool = True,
    command: str | None = None,
    workers: int | None = None,
    ray_address: str | None = None,
) -> dict[str, Any]:
    """Run the equal-time study and write its report into ``out_dir``.

    Args:
        scenes: scene arguments (see :func:`resolve_scenes`) or specs.
        out_dir: report folder; an existing ``results.json`` there is resumed.
        cfg: options; default :data:`PRESETS` ``["full"]``. A deprecated method name in
            ``cfg.methods`` (``gdpt+ngpt``) runs, and is recorded, as its current one
            (``gdpt+oidn-grad``), with a ``DeprecationWarning``.
        progress: show a progress bar over all cells of the study.
        report: write ``results.md``, plots, crops and ``index.html`` at the end.
        command: the command line that started the run (recorded in the results).
        workers: run the reference chunks and cells as tasks of a local Ray instance with this
            many workers (:mod:`gdpt.study.engine`); ``None`` and no ``ray_address``: one cell
            after the other in this process (Ray is not imported).
        ray_address: run them on the Ray cluster at this address (checked before any work).

    Returns:
        The content of ``results.json``. A resumed study says on stderr how many of its cells
        were done.

    Raises:
        ValueError: unknown methods or metrics, or ``out_dir`` holds an incompatible study.
        ConnectionError: ``ray_address`` does not answer (before any work).
    """
    from gdpt.metrics import METRICS

    cfg = _current_methods(cfg or PRESETS["full"])
    METRICS.check(cfg.metrics)
    methods = _method_list(cfg)
    specs = _as_specs(scenes)
    engine = None
    if workers is not None or ray_address is not None:  # connected before any work
        from gdpt.study.engine import RayEngine

        engine = RayEngine(workers=workers, address=ray_address)
    try:
        return _evaluate(specs, methods, Path(out_dir), cfg, progress, report, command, engine)
    finally:
        if engine is not None:
            engine.close()


def _evaluate(
    specs: list[SceneSpec],
    methods: list[str],
    out: Path,
    cfg: EvaluateConfig,
    progress: bool,
    report: bool,
    command: str | None,
    engine: Any,
) -> dict[str, Any]:
    import drjit as dr
    from tqdm.auto import tqdm

    from gdpt.backend import ensure_variant

    started = time.perf_counter()
    forget_cost_models()
    out.mkdir(parents=True, exist_ok=True)
    (out / "images").mkdir(exist_ok=True)
    results_path = out / "results.json"
    results = load_results(results_path, cfg)

    ensure_variant()
    results.update(
        config=cfg.to_json(),
        machine=machine_info(),
        versions=versions(),
        conventions=CONVENTIONS,
        methods={m: _method_info(EVAL_METHODS[m]) for m in methods},
        protocol=(
            f"{PROTOCOL_TEXT[cfg.protocol]}; "
            "per scene, budget and replicate seed, one cell calibrates and runs every method back "
            "to back on one worker (order reversed on odd replicates; timings compare only "
            "within a cell); each render configuration's spp is calibrated by timing inside "
            "the cell and shared by every method that renders it ('calibrations' per scene; "
            "auto is given the budget in seconds under total; "
            "t = a + b*spp fitted to 1-spp medians and growing probes, then verified and "
            f"re-rendered if off by more than {min(cfg.tolerance, MISS_TOLERANCE):.0%}); a "
            f"replicate that misses its budget by more than {MISS_TOLERANCE:.0%} is redone "
            "once, then flagged (missed_budget); no timed render pays kernel compilation or "
            "frozen-pass recording (a run that recorded passes is run again); reference: "
            f"path tracing at {cfg.reference_spp} spp on the same box-filtered film"
        ),
    )
    results["runs"].append(
        {
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "command": command,
            "scenes": [s.source for s in specs],
        }
    )
    cache = Path(cfg.reference_dir) if cfg.reference_dir else out / "references"

    total = len(specs) * len(methods) * len(cfg.budgets)
    done = cells_done(results, [s.name for s in specs], methods, cfg.budgets)
    if done:  # to stderr, as the progress bar
        print(f"{results_path}: resuming: {done} of {total} cells done", file=sys.stderr)
    units = len(specs) * len(cfg.budgets) * cfg.seeds  # one cell: every method of a seed
    bar = tqdm(total=units, unit="cell", desc="evaluate", disable=not progress, dynamic_ncols=True)
    history_flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    before = thread_counts()
    cells_before = cell_keys(results)
    try:
        if engine is None:  # this process owns the machine's usable cores
            owned = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
            threads = set_threads(owned or os.cpu_count() or 1)
            results["threads"] = {"engine": "sequential", "workers": 1, "per_worker": threads}
            for spec in specs:
                _evaluate_scene(spec, methods, cfg, results, results_path, cache, out, bar)
        else:
            results["threads"] = engine.describe()
            engine.run_study(specs, methods, cfg, results, results_path, cache, out, bar)
    finally:
        set_threads_back(before)
        dr.set_flag(dr.JitFlag.KernelHistory, history_flag)
        bar.close()
        results["runs"][-1]["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        results["runs"][-1]["cost"] = study_cost(
            results, cells_before, time.perf_counter() - started
        )
        if hasattr(os, "getloadavg"):
            results["machine"]["loadavg_at_end"] = list(os.getloadavg())
        write_json(results_path, results)
    if report:
        from gdpt.study.report import write_report

        write_report(results, out)
    return results


def render_references(
    scenes: Sequence[str | os.PathLike[str] | SceneSpec],
    cache_dir: str | os.PathLike[str],
    cfg: EvaluateConfig | None = None,
    *,
    progress: bool = True,
    workers: int | None = None,
    ray_address: str | None = None,
) -> dict[str, str]:
    """Render (or finish) the cached references of a study without timing anything.

    References take most of a study's compute but no timing, so they can be rendered while the
    machine is busy; the timed cells (:func:`evaluate` with ``reference_dir=cache_dir``) then
    run later on an idle machine and find them cached.

    Args:
        scenes: as for :func:`evaluate`.
        cache_dir: reference cache folder (:func:`render_reference`).
        cfg: options (``resolution``, ``max_depth``, ``reference_spp``, ``reference_chunk_spp``,
            ``seed``); default :data:`PRESETS` ``["full"]``.
        progress: show a progress bar over the scenes.
        workers: render the chunks as tasks of a local Ray instance with this many workers
            (one CPU each); ``None``: in this process.
        ray_address: render them on the Ray cluster at this address.

    Returns:
        Scene name -> path of its reference EXR, or ``"failed: <error>"`` for a scene that does
        not load or render (the others still run).

    Raises:
        ConnectionError: ``ray_address`` does not answer (before any work).
    """
    from tqdm.auto import tqdm

    from gdpt.backend import ensure_variant

    cfg = cfg or PRESETS["full"]
    specs = _as_specs(scenes)
    engine = None
    if workers is not None or ray_address is not None:
        from gdpt.study.engine import RayEngine

        engine = RayEngine(workers=workers, address=ray_address)
    done: dict[str, str] = {}
    bar = tqdm(specs, unit="scene", desc="references", disable=not progress, dynamic_ncols=True)
    try:
        for spec in bar:
            try:
                scene = load_eval_scene(spec, resolution=cfg.resolution, max_depth=cfg.max_depth)
                chunks = None if engine is None else engine.chunks(spec, cfg, ensure_variant())
                _, meta = _study_reference(scene, spec, cfg, Path(cache_dir), bar, chunks)
                done[spec.name] = meta["path"]
            except Exception as err:  # reported, the other scenes still run
                if caused_by_interrupt(err):  # Ctrl-C inside a Dr.Jit frozen function
                    raise
                done[spec.name] = f"failed: {type(err).__name__}: {err}"
    finally:
        if engine is not None:
            engine.close()
    return done


def set_threads_back(counts: dict[str, int]) -> None:
    """Restore torch's and Dr.Jit's thread counts (:func:`~gdpt.study.cells.thread_counts`)."""
    import drjit as dr

    torch.set_num_threads(counts["torch"])
    dr.set_thread_count(counts["drjit"])


def _method_info(method: EvalMethod) -> dict[str, Any]:
    reason = method.check()
    return {"description": method.description, "available": reason is None, "note": reason}


def _evaluate_scene(
    spec: SceneSpec,
    methods: list[str],
    cfg: EvaluateConfig,
    results: dict[str, Any],
    results_path: Path,
    cache: Path,
    out: Path,
    bar: Any,
) -> None:
    """Reference and cells of one scene, one cell after the other in this process (results
    updated and saved in place)."""
    entry = results["scenes"].setdefault(spec.name, {"source": spec.source, "methods": {}})
    entry.setdefault("methods", {})
    runnable = runnable_methods(methods, entry)
    per_scene = len(cfg.budgets) * cfg.seeds
    todo = cells_to_run(entry, runnable, cfg)
    bar.update(per_scene - todo)
    if (
        entry.get("status") == "ok"
        and not todo
        and not any(pending_cells(entry, runnable, cfg, set()))
    ):
        return
    stage = "load"
    try:
        bar.set_postfix_str(f"{spec.name}: loading")
        scene = load_into(spec, cfg, entry)
        stage = "reference"
        no_reference = (None, None)
        reference, ref_meta = (
            _study_reference(scene, spec, cfg, cache, bar) if cfg.reference else no_reference
        )
    except Exception as err:  # a broken scene is a result, not the end of the study
        try:
            scene_failed(spec.name, entry, stage, err, cfg)
        finally:
            write_json(results_path, results)
            bar.update(todo)
        return
    reference_ready(spec.name, entry, reference, ref_meta, out)
    write_json(results_path, results)
    try:
        _run_cells(spec, scene, reference, runnable, entry, cfg, results, results_path, out, bar)
    finally:  # the next scene renders with this one freed (frozen passes record; see there)
        release_scene(scene.scene)


def _run_cells(
    spec: SceneSpec,
    scene: EvalScene,
    reference: torch.Tensor | None,
    runnable: list[str],
    entry: dict[str, Any],
    cfg: EvaluateConfig,
    results: dict[str, Any],
    results_path: Path,
    out: Path,
    bar: Any,
) -> None:
    """The cells of one loaded scene, one after the other, then its reference-free estimates."""
    chosen = {m: EVAL_METHODS[m] for m in runnable}
    attempted: set[str] = set()
    while runnable and (cell := next(pending_cells(entry, runnable, cfg, attempted), None)):
        budget, replicate, added = cell
        attempted.add(f"{budget_key(budget)}/{replicate}")
        if added:
            bar.total += 1
        bar.set_postfix_str(f"{spec.name}: {budget_key(budget)} s, replicate {replicate}")
        output = run_cell(scene, reference, chosen, budget, replicate, cfg, added=added)
        try:
            finish_cell(spec.name, entry, output, runnable, cfg, results, results_path, out)
        finally:
            bar.update(1)
    estimate_scene(scene, entry, cfg, out, bar)  # the reference-free estimate of every cell
    write_json(results_path, results)
