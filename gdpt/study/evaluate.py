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
3. Per render configuration (:func:`~gdpt.study.calibration.configuration_key`: methods that
   render the same thing, such as ``auto`` on its plain route and ``pt+oidn-tuned``, share
   it; recorded per scene in ``calibrations``), timed with its
   :func:`~gdpt.study.calibration.calibration_runner`: warm up (1 and 2 spp, untimed, compiles
   the kernels), then fit
   ``t(spp) = a + b * spp`` from a median of 1-spp runs and geometrically growing probe runs
   (:func:`calibrate`), solve for each budget, render and check the achieved time; if it is off
   by more than ``tolerance`` the model is corrected and the cell rendered again
   (``max_rounds`` times at most). Every method of the configuration renders its replicates at
   that sample count, its own times recorded. Every timed render follows an untimed render of
   the same method at the same spp: the integrators record a frozen pass per spp per pass and
   replay it afterwards, so the timed render pays neither kernel compilation nor the Python
   tracing of the path loop, as a repeated render of that configuration does not. Achieved
   times, every attempt and kernel compilation (excluded from the times) are recorded.
4. Metrics of every cell; ``results.json`` is rewritten after each cell, so an interrupted run
   resumes without recomputing finished cells.
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
from gdpt.study.calibration import (
    TimeModel,
    calibrate,
    calibration_runner,
    charged_seconds,
    configuration_key,
    run_at_budget,
    timed_run,
)
from gdpt.study.config import PRESETS, EvaluateConfig
from gdpt.study.estimate import estimate_scene
from gdpt.study.methods import EVAL_METHODS, EvalMethod, MethodResult, MethodUnavailable
from gdpt.study.references import reference_seed, render_reference
from gdpt.study.results import (
    CONVENTIONS,
    budget_key,
    cell_seed,
    cells_done,
    load_results,
    machine_info,
    replicate_seed,
    versions,
    write_json,
)
from gdpt.study.scenes import EvalScene, SceneSpec, load_eval_scene, resolve_scenes
from gdpt.study.scoring import interval_too_wide, replicate_record, score, summarise


class StudyFailure(RuntimeError):
    """A scene or method of the study failed and ``keep_going`` is off (the failure is recorded
    in ``results.json`` first, so that a resumed run retries it)."""


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
    scene: EvalScene, spec: SceneSpec, cfg: EvaluateConfig, cache: Path, bar: Any
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
    )


def evaluate(
    scenes: Sequence[str | os.PathLike[str] | SceneSpec],
    out_dir: str | os.PathLike[str],
    cfg: EvaluateConfig | None = None,
    *,
    progress: bool = True,
    report: bool = True,
    command: str | None = None,
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

    Returns:
        The content of ``results.json``. A resumed study says on stderr how many of its cells
        were done.

    Raises:
        ValueError: unknown methods or metrics, or ``out_dir`` holds an incompatible study.
    """
    import drjit as dr
    from tqdm.auto import tqdm

    from gdpt.backend import ensure_variant
    from gdpt.metrics import METRICS

    cfg = _current_methods(cfg or PRESETS["full"])
    METRICS.check(cfg.metrics)
    methods = _method_list(cfg)
    specs = _as_specs(scenes)
    out = Path(out_dir)
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
            "per scene and budget, each render configuration's spp is calibrated by timing on "
            "this machine in this run, once, and shared by every method that renders it "
            "('calibrations' per scene; t = a + b*spp fitted to 1-spp medians and growing "
            f"probes, then verified and re-rendered if off by more than {cfg.tolerance:.0%}); "
            "every timed "
            "render follows an untimed one at the same spp (kernel compilation and frozen-pass "
            "recording are paid once per configuration, not timed); reference: "
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
    bar = tqdm(total=total, unit="cell", desc="evaluate", disable=not progress, dynamic_ncols=True)
    history_flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for spec in specs:
            _evaluate_scene(spec, methods, cfg, results, results_path, cache, out, bar)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, history_flag)
        bar.close()
        results["runs"][-1]["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
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

    Returns:
        Scene name -> path of its reference EXR, or ``"failed: <error>"`` for a scene that does
        not load or render (the others still run).
    """
    from tqdm.auto import tqdm

    cfg = cfg or PRESETS["full"]
    specs = _as_specs(scenes)
    done: dict[str, str] = {}
    bar = tqdm(specs, unit="scene", desc="references", disable=not progress, dynamic_ncols=True)
    for spec in bar:
        try:
            scene = load_eval_scene(spec, resolution=cfg.resolution, max_depth=cfg.max_depth)
            _, meta = _study_reference(scene, spec, cfg, Path(cache_dir), bar)
            done[spec.name] = meta["path"]
        except Exception as err:  # reported, the other scenes still run
            if caused_by_interrupt(err):  # Ctrl-C inside a Dr.Jit frozen function
                raise
            done[spec.name] = f"failed: {type(err).__name__}: {err}"
    return done


def _method_info(method: EvalMethod) -> dict[str, Any]:
    reason = method.check()
    return {"description": method.description, "available": reason is None, "note": reason}


def _scene_done(entry: dict[str, Any], methods: list[str], cfg: EvaluateConfig) -> bool:
    if entry.get("status") != "ok":
        return False
    for m in methods:
        info = entry["methods"].get(m, {})
        # skipped because unavailable (package, model): done; skipped after an error: retried
        if info.get("status") == "skipped" and EVAL_METHODS[m].check() is not None:
            continue
        if any(budget_key(b) not in info.get("cells", {}) for b in cfg.budgets):
            return False
    return True


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
    """Reference, calibration and cells of one scene (results updated and saved in place)."""
    entry = results["scenes"].setdefault(spec.name, {"source": spec.source, "methods": {}})
    entry.setdefault("methods", {})
    if _scene_done(entry, methods, cfg):
        bar.update(len(methods) * len(cfg.budgets))
        return
    stage = "load"
    try:
        bar.set_postfix_str(f"{spec.name}: loading")
        scene = load_eval_scene(spec, resolution=cfg.resolution, max_depth=cfg.max_depth)
        entry.update(
            resolution=list(scene.resolution),
            max_depth=scene.max_depth,
            notes=scene.notes,
            film_filter=scene.film_filter,
        )
        stage = "reference"
        no_reference = (None, None)
        reference, ref_meta = (
            _study_reference(scene, spec, cfg, cache, bar) if cfg.reference else no_reference
        )
    except Exception as err:  # a broken scene is a result, not the end of the study
        if caused_by_interrupt(err):  # Ctrl-C inside a Dr.Jit frozen function
            raise
        entry.update(status="failed", stage=stage, error=f"{type(err).__name__}: {err}")
        entry.pop("reference", None)
        write_json(results_path, results)
        bar.update(len(methods) * len(cfg.budgets))
        if not cfg.keep_going:
            raise StudyFailure(f"{spec.name}: {stage} failed: {entry['error']}") from err
        return
    entry.update(status="ok", reference=ref_meta)
    entry.pop("error", None)
    entry.pop("stage", None)
    write_json(results_path, results)
    image_dir = out / "images" / spec.name
    image_dir.mkdir(parents=True, exist_ok=True)
    from gdpt.io.exr import save_image
    from gdpt.io.images import save_png

    if reference is not None:
        save_image(image_dir / "reference.exr", reference, metadata=ref_meta, force=True)
        save_png(image_dir / "reference.png", reference, force=True)
    for name in methods:
        _evaluate_method(
            EVAL_METHODS[name], scene, reference, cfg, entry, results, results_path, image_dir, bar
        )
    estimate_scene(scene, entry, cfg, out, bar)  # the reference-free estimate of every cell
    write_json(results_path, results)


#: Fields of a cell record that describe the timed run itself (the evaluated method's, where
#: the sample count came from a shared calibration).
RUN_FIELDS = ("seconds", "render_seconds", "reconstruct_seconds", "compile_seconds")


def _shared_calibration(
    method: EvalMethod, scene: EvalScene, cfg: EvaluateConfig, entry: dict[str, Any], todo: list
) -> tuple[EvalMethod, str, dict[str, Any], TimeModel]:
    """The calibration ``method`` shares on this scene (:func:`configuration_key`): its runner,
    key, record in ``entry["calibrations"]`` (``runner``, ``configuration``, ``model``,
    ``budgets``: the :func:`run_at_budget` record per budget) and the time model, fitted by
    timing the runner unless an earlier method of the configuration did.

    Raises:
        MethodUnavailable: the runner cannot run here.
    """
    runner = calibration_runner(method, cfg.protocol)
    key = configuration_key(method, cfg.protocol)
    shared = entry.setdefault("calibrations", {}).setdefault(key, {"budgets": {}})
    if "model" in shared:
        model = TimeModel(
            shared["model"]["fixed"],
            shared["model"]["per_spp"],
            [(int(s), float(t)) for s, t in shared["model"]["measurements"]],
        )
    else:
        model = calibrate(
            runner,
            scene,
            budget=min(todo),
            seed=cell_seed(cfg.seed, scene.name, runner.name, "calibration"),
            probe_fraction=cfg.probe_fraction,
            protocol=cfg.protocol,
        )
    configuration = method.configuration() if method.configuration is not None else None
    shared.update(runner=runner.name, configuration=configuration, model=dataclasses.asdict(model))
    shared.setdefault("methods", [])
    if method.name not in shared["methods"]:
        shared["methods"].append(method.name)
    return runner, key, shared, model


def _run_replicates(
    method: EvalMethod,
    scene: EvalScene,
    calibration: tuple[EvalMethod, str, dict[str, Any], TimeModel],
    budget: float,
    cfg: EvaluateConfig,
) -> tuple[MethodResult, dict[str, Any], list[dict[str, Any]]]:
    """One budget cell: the sample count that fills ``budget`` for the method's configuration
    (:func:`run_at_budget` on the calibration's runner, once per configuration, scene and
    budget), then ``cfg.seeds`` replicates of ``method`` at that count with the paired seeds of
    :func:`~gdpt.study.results.replicate_seed`.

    Returns:
        The first replicate's result (its image is saved), the cell record (the
        :func:`run_at_budget` record, its timings those of ``method``'s first replicate, plus
        ``calibration``: the configuration key and ``calibrated_by``: the runner) and per
        replicate ``{"seed", "spp", "seconds", "render_seconds", "reconstruct_seconds",
        "result"}``.
    """
    runner, config_key, shared, model = calibration
    key = budget_key(budget)
    seeds = [replicate_seed(cfg.seed, scene.name, key, r) for r in range(cfg.seeds)]
    first: MethodResult | None = None
    if key not in shared["budgets"]:
        result, record = run_at_budget(
            runner,
            scene,
            model,
            budget=budget,
            seed=seeds[0],
            tolerance=cfg.tolerance,
            max_rounds=cfg.max_rounds,
            protocol=cfg.protocol,
        )
        shared["budgets"][key] = record
        shared["model"] = dataclasses.asdict(model)
        if runner is method and record["seed"] == seeds[0]:
            first = result
    record = {**shared["budgets"][key], "calibration": config_key, "calibrated_by": runner.name}
    spp = record["spp"]
    runs = [first] + [None] * (cfg.seeds - 1)
    runs = [r or timed_run(method, scene, spp, seed) for r, seed in zip(runs, seeds, strict=True)]
    if first is None:  # the timings of this method's own run
        charged = charged_seconds(runs[0], cfg.protocol)
        record.update({f: getattr(runs[0], f) for f in RUN_FIELDS})
        record.update(charged_seconds=charged, relative_error=(charged - budget) / budget)
        record["within_tolerance"] = abs(record["relative_error"]) <= cfg.tolerance
    replicates = [
        {**replicate_record(run, seed, spp), "result": run}
        for run, seed in zip(runs, seeds, strict=True)
    ]
    record["seed"] = seeds[0]
    return runs[0], record, replicates


def _evaluate_method(
    method: EvalMethod,
    scene: EvalScene,
    reference: torch.Tensor | None,
    cfg: EvaluateConfig,
    entry: dict[str, Any],
    results: dict[str, Any],
    results_path: Path,
    image_dir: Path,
    bar: Any,
) -> None:
    """Calibrate one method on one scene and fill its missing budget cells."""
    from gdpt.io.exr import save_image
    from gdpt.io.images import save_png

    info = entry["methods"].setdefault(method.name, {"cells": {}})
    info.setdefault("cells", {})
    todo = [b for b in cfg.budgets if budget_key(b) not in info["cells"]]
    bar.update(len(cfg.budgets) - len(todo))
    if not todo:
        return
    bar.set_postfix_str(f"{scene.name}/{method.name}: calibrating")
    reason = method.check()
    calibration = None
    error = None
    if reason is None:
        try:
            calibration = _shared_calibration(method, scene, cfg, entry, todo)
        except MethodUnavailable as err:
            reason = str(err)
        except Exception as err:  # e.g. a model that fails to load, an unsupported plugin
            if caused_by_interrupt(err):  # Ctrl-C inside a Dr.Jit frozen function
                raise
            reason = f"could not run: {type(err).__name__}: {' '.join(str(err).split())}"
            error = err
    if calibration is None:
        info.update(status="skipped", note=reason, failed=error is not None)
        write_json(results_path, results)
        bar.update(len(todo))
        if error is not None and not cfg.keep_going:
            raise StudyFailure(f"{scene.name} / {method.name}: calibration: {reason}") from error
        return
    model = calibration[3]
    info.update(
        status="ok",
        note=None,
        failed=False,
        calibration=dataclasses.asdict(model),
        calibration_key=calibration[1],
    )
    for budget in todo:
        key = budget_key(budget)
        bar.set_postfix_str(f"{scene.name}/{method.name}: {key} s")
        try:
            result, record, replicates = _run_replicates(method, scene, calibration, budget, cfg)
        except Exception as err:  # e.g. out of memory at a large spp: report, retry on resume
            if caused_by_interrupt(err):  # Ctrl-C inside a Dr.Jit frozen function
                raise
            info.setdefault("errors", {})[key] = f"{type(err).__name__}: {err}"
            write_json(results_path, results)
            bar.update(1)
            if not cfg.keep_going:
                message = f"{scene.name} / {method.name} at {key} s: {info['errors'][key]}"
                raise StudyFailure(message) from err
            continue
        info.get("errors", {}).pop(key, None)
        for replicate in replicates:
            skipped = score(replicate, replicate.pop("result").image, reference, cfg)
        while interval_too_wide(replicates, cfg) and len(replicates) < cfg.max_seeds:
            seed = replicate_seed(cfg.seed, scene.name, key, len(replicates))
            run = timed_run(method, scene, record["spp"], seed)
            replicate = {**replicate_record(run, seed, record["spp"]), "added": "until_interval"}
            score(replicate, run.image, reference, cfg)
            replicates.append(replicate)
        record.update(budget=budget, **summarise(replicates))
        record.update(
            replicates=replicates,
            skipped_metrics=skipped,
            nonfinite_pixels=int((~torch.isfinite(result.image)).any(-1).sum()),
            image=f"images/{scene.name}/{method.name}-{key}s.exr",
        )
        save_image(
            image_dir / f"{method.name}-{key}s.exr",
            result.image,
            metadata={
                "method": method.name,
                "spp": record["spp"],
                "budget": budget,
                "seed": record["seed"],
            },
            force=True,
        )
        save_png(image_dir / f"{method.name}-{key}s.png", result.image, force=True)
        info["cells"][key] = record
        info["calibration"] = dataclasses.asdict(model)
        write_json(results_path, results)
        bar.update(1)
