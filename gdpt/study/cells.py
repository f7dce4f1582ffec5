"""The study's unit of work: a *cell*, every method of one (scene, budget, replicate seed).

A cell calibrates and runs all its methods back to back on one worker (:func:`run_cell`), so a
change of machine speed or load between cells hits every method of a cell alike; timings are
compared only within a cell, never between cells (they may run on different workers). Inside a
cell:

* the methods run in the study's order on even replicates and in reverse order on odd ones
  (:func:`method_order`: A B, B A, A B, ...), the counterbalanced "ABBA" design that cancels a
  linear drift of speed within a cell pair (Fisher, *The Design of Experiments*, 1935, ch. 4;
  the same alternation as the ABBA benchmark protocol of Kalibera and Jones, "Rigorous
  Benchmarking in Reasonable Time", ISMM 2013);
* each render configuration (:func:`~gdpt.study.calibration.configuration_key`) takes its
  sample count when its first method's turn comes, in the cell, from the configuration's cost
  model in its current state (:func:`~gdpt.study.calibration.configuration_model`: probed by
  :func:`~gdpt.study.calibration.calibrate` in the configuration's first cell on the worker,
  refined by every timed run since), timed by its runner
  (:func:`~gdpt.study.calibration.run_at_budget`, which redoes a miss at the refitted count):
  methods that render the same thing still get the same sample count; a method that fills
  a budget in seconds itself (``auto`` under ``total``:
  :func:`~gdpt.study.calibration.fills_seconds`) is given the budget, as a user gives it;
* every replicate records its timed run against the budget: ``charged_seconds``,
  ``relative_error``, the 1-minute load average before it (``os.getloadavg``), and
  ``cpu_seconds`` / ``wall_seconds`` / ``cpu_per_wall`` of the timed run (the process's CPU
  time over its wall time: near the thread count when the machine is free, lower when other
  work takes the cores). A replicate that misses its budget by more than
  :data:`MISS_TOLERANCE` is rendered once more with the same seed: at the same spp when the
  method ran its own calibration, at the same budget when it chooses its count (its miss is
  the machine's: a slow-down that passed), at a count corrected by the miss when it shares
  another method's calibration (its miss is its own cost: :func:`redo_spp`); if it misses
  again it is kept with ``missed_budget: true`` and the report lists it.

:func:`run_cell` returns plain data (the cell record and the first replicate's images), written
into ``results.json`` by the driver (:func:`apply_cell`) in one atomic write, so a worker that
dies mid-cell leaves nothing half-written and the cell is run again.
"""

from __future__ import annotations

import dataclasses
import math
import os
import platform
import time
from collections.abc import Iterator, Sequence
from typing import Any

import torch

from gdpt.interrupt import caused_by_interrupt
from gdpt.pipeline import release_scene
from gdpt.study.calibration import (
    calibration_runner,
    charged_seconds,
    configuration_key,
    configuration_model,
    fills_seconds,
    run_at_budget,
    timed_run,
)
from gdpt.study.config import EvaluateConfig
from gdpt.study.methods import EvalMethod, MethodResult, MethodUnavailable
from gdpt.study.results import budget_key, cell_seed, replicate_seed
from gdpt.study.scenes import EvalScene, SceneSpec, load_eval_scene
from gdpt.study.scoring import interval_too_wide, score, summarise

__all__ = [
    "MISS_TOLERANCE",
    "apply_cell",
    "method_order",
    "pending_cells",
    "redo_spp",
    "run_cell",
    "set_threads",
    "thread_counts",
    "worker_scene",
]

#: A replicate whose charged seconds differ from the budget by more than this share is
#: rendered once more, then flagged (``missed_budget``). The calibration inside a cell aims at
#: ``min(cfg.tolerance, MISS_TOLERANCE)``.
MISS_TOLERANCE = 0.15


def method_order(methods: Sequence[str], replicate: int) -> list[str]:
    """The order of ``methods`` in replicate ``replicate``: as given on even replicates,
    reversed on odd ones (A B, B A, A B, ...)."""
    return list(methods) if replicate % 2 == 0 else list(reversed(methods))


# ----------------------------------------------------------------------------------- threads
def thread_counts() -> dict[str, int]:
    """``{"torch": intra-op threads, "drjit": Dr.Jit's thread pool size}`` of this process."""
    import drjit as dr

    return {"torch": torch.get_num_threads(), "drjit": int(dr.thread_count())}


#: torch's intra-op threads in a study, whatever the worker owns: the reconstructions' tensors
#: are small (128-512 px) and two torch threads beside a busy process wait for each other
#: (``benchmarks/study_under_load.py``, 2 cores, one busy loop: ``fuse``'s reconstruction took
#: 0.13-0.43 s instead of 0.09 s, and the cell's calibration gave it 0.54x its idle count).
TORCH_THREADS = 1


def set_threads(count: int) -> dict[str, int]:
    """Give Dr.Jit (``drjit.set_thread_count``, the pool Mitsuba's LLVM variants render with)
    ``count`` threads and torch (``torch.set_num_threads``) at most :data:`TORCH_THREADS`;
    returns :func:`thread_counts`."""
    import drjit as dr

    count = max(1, int(count))
    torch.set_num_threads(min(count, TORCH_THREADS))
    dr.set_thread_count(count)
    return thread_counts()


def _load_1min() -> float | None:
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else None


def _worker() -> dict[str, Any]:
    return {"host": platform.node(), "pid": os.getpid(), "threads": thread_counts()}


#: Scenes loaded by this process (a worker runs many cells of one scene), by spec and settings.
_SCENES: dict[tuple[SceneSpec, int, int | None], EvalScene] = {}


def worker_scene(spec: SceneSpec, resolution: int, max_depth: int | None) -> EvalScene:
    """:func:`~gdpt.study.scenes.load_eval_scene`, loaded once per process."""
    key = (spec, resolution, max_depth)
    if key not in _SCENES:
        for old in _SCENES.values():  # one scene at a time: scenes can be large, and another
            release_scene(old.scene)  # scene alive can stop Dr.Jit recording frozen passes
        _SCENES.clear()
        _SCENES[key] = load_eval_scene(spec, resolution=resolution, max_depth=max_depth)
    return _SCENES[key]


# -------------------------------------------------------------------------------- timed runs
def _measured(method: EvalMethod) -> tuple[EvalMethod, dict[int, dict[str, Any]]]:
    """``method`` whose ``run`` records, per seed, the 1-minute load average before the run
    and its CPU and wall seconds (``time.process_time``: every thread of this process)."""
    log: dict[int, dict[str, Any]] = {}

    def measured(run: Any, scene: EvalScene, seed: int, **budget: Any) -> MethodResult:
        load = _load_1min()
        cpu, wall = time.process_time(), time.perf_counter()
        result = run(scene, seed=seed, **budget)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        log[seed] = {
            "loadavg_1min": load,
            "cpu_seconds": cpu,
            "wall_seconds": wall,
            "cpu_per_wall": cpu / wall if wall > 0 else None,
        }
        return result

    def run(scene: EvalScene, *, spp: int, seed: int) -> MethodResult:
        return measured(method.run, scene, seed, spp=spp)

    def run_for(scene: EvalScene, *, seconds: float, seed: int) -> MethodResult:
        return measured(method.run_for, scene, seed, seconds=seconds)

    return dataclasses.replace(
        method, run=run, run_for=None if method.run_for is None else run_for
    ), log


#: What a replicate keeps of its first run when it was redone (under ``redone``).
_REDONE_KEYS = (
    "spp",
    "seconds",
    "charged_seconds",
    "relative_error",
    "loadavg_1min",
    "cpu_per_wall",
)


def redo_spp(spp: int, charged: float, budget: float, per_spp: float) -> int:
    """The sample count of a redo of a method that ran at a count calibrated for another
    (``auto`` at ``pt+oidn-tuned``'s under ``render-time``): ``spp`` less the seconds it missed
    ``budget`` by (``charged - budget``, negative when under) at the calibration's ``per_spp``
    seconds per sample, kept within half and twice ``spp`` (a miss that large is a slow-down
    of the machine, not the method's own cost: a count near nothing would be charged for it).
    Its own fixed costs stay in the redo, so they are what it is charged beyond the other
    method's."""
    if per_spp <= 0.0:
        return spp
    corrected = spp - round((charged - budget) / per_spp)
    return min(2 * spp, max(math.ceil(spp / 2), corrected))


def _timed_replicate(
    method: EvalMethod,
    scene: EvalScene,
    spp: int | None,
    seed: int,
    budget: float,
    protocol: str,
    done: tuple[MethodResult, dict[str, Any]] | None,
    shared_per_spp: float | None = None,
) -> tuple[dict[str, Any], MethodResult]:
    """One replicate's timed run (``done``: the calibration's run of this seed, reused), redone
    once if it misses ``budget`` by more than :data:`MISS_TOLERANCE`: at the same ``spp``, or,
    for a method that shares another method's calibration (``shared_per_spp``: that
    calibration's seconds per sample), at :func:`redo_spp`; with ``spp`` ``None``, the
    method's :attr:`~gdpt.study.methods.EvalMethod.run_for` at ``budget``, again at ``budget``
    (its own model refined by the miss)."""
    own_count = False
    attempts: list[dict[str, Any]] = []
    run = None
    for attempt in range(2):
        if attempt == 0 and done is not None:
            run, measured = done
        elif spp is None or own_count:  # the budget in seconds (redone at the same budget)
            own_count = True
            wrapped, log = _measured(method)
            run = timed_run(wrapped, scene, None, seed, seconds=budget)
            spp, measured = run.spp, log[seed]
        else:
            if attempt == 1 and shared_per_spp is not None:
                spp = redo_spp(spp, attempts[0]["charged_seconds"], budget, shared_per_spp)
            wrapped, log = _measured(method)
            run = timed_run(wrapped, scene, spp, seed)
            measured = log[seed]
        charged = charged_seconds(run, protocol)
        attempts.append(
            {
                "seed": seed,
                "spp": spp,
                "seconds": run.seconds,
                "render_seconds": run.render_seconds,
                "reconstruct_seconds": run.reconstruct_seconds,
                **({"route": run.route} if run.route is not None else {}),
                "budget": budget,
                "charged_seconds": charged,
                "relative_error": (charged - budget) / budget,
                **measured,
            }
        )
        hopeless = spp == 1 and charged > budget  # even 1 spp is over: a redo cannot help
        if abs(attempts[-1]["relative_error"]) <= MISS_TOLERANCE or hopeless:
            break
    assert run is not None
    record = attempts[-1]
    if len(attempts) > 1:
        record["redone"] = {k: attempts[0][k] for k in _REDONE_KEYS}
    record["missed_budget"] = abs(record["relative_error"]) > MISS_TOLERANCE
    return record, run


def _seconds_replicate(
    method: EvalMethod,
    scene: EvalScene,
    seed: int,
    budget: float,
    protocol: str,
    record: dict[str, Any],
) -> tuple[str, dict[str, Any], MethodResult]:
    """The replicate of a method given its budget in seconds
    (:func:`~gdpt.study.calibration.fills_seconds`): :func:`_timed_replicate` at ``budget``,
    its count its own, recorded in the cell's ``record["calibrations"]`` under
    ``"method NAME (seconds)"`` (no model of the study's: the method keeps its own). Returns
    that key, the replicate record and the run."""
    key = f"method {method.name} (seconds)"
    replicate_record, run = _timed_replicate(method, scene, None, seed, budget, protocol, None)
    record["calibrations"][key] = {
        **{k: replicate_record[k] for k in ("spp", "seed", "seconds", "charged_seconds")},
        "relative_error": replicate_record["relative_error"],
        "within_tolerance": not replicate_record["missed_budget"],
        "protocol": protocol,
        "runner": method.name,
        "configuration": None,
        "model": None,
        "model_source": "its own (render_and_denoise(seconds=...))",
        "methods": [method.name],
    }
    return key, replicate_record, run


def _error_text(err: BaseException) -> str:
    return f"{type(err).__name__}: {' '.join(str(err).split())}"


def run_cell(
    scene: EvalScene,
    reference: torch.Tensor | None,
    methods: dict[str, EvalMethod],
    budget: float,
    replicate: int,
    cfg: EvaluateConfig,
    *,
    added: str | None = None,
) -> dict[str, Any]:
    """Calibrate and run every method of one cell back to back, then score them.

    Args:
        scene: the scene.
        reference: ``(H, W, 3)`` float32 CPU reference, or ``None`` (no metrics).
        methods: name -> method, in the study's order (:func:`method_order` rotates it).
        budget: seconds per image (charged under ``cfg.protocol``).
        replicate: replicate index; its seed (:func:`~gdpt.study.results.replicate_seed`) is
            the same for every method (paired).
        cfg: the study's options (``keep_going`` off: the cell stops at the first error).
        added: why the replicate was added (``"until_interval"``), recorded per replicate.

    Returns:
        ``{"record": ..., "images": {method: (H, W, 3) float32}}`` (images of replicate 0
        only). The record: ``budget``, ``replicate``, ``seed``, ``order``, ``calibrations``
        (configuration key -> the :func:`run_at_budget` record plus ``runner``,
        ``configuration``, ``model``, ``methods``), ``replicates`` (method -> replicate record,
        :func:`_timed_replicate`, scored), ``skipped`` (method -> reason), ``errors`` (method
        -> ``{"stage": "calibration" | "run", "error"}``), ``worker`` (host, pid, threads),
        ``loadavg_start`` / ``loadavg_end`` (1 minute) and ``seconds`` (the cell's wall time).
    """
    key = budget_key(budget)
    seed = replicate_seed(cfg.seed, scene.name, key, replicate)
    order = method_order(list(methods), replicate)
    record: dict[str, Any] = {
        "budget": budget,
        "replicate": replicate,
        "seed": seed,
        "order": order,
        "calibrations": {},
        "replicates": {},
        "skipped": {},
        "errors": {},
        "worker": _worker(),
        "loadavg_start": _load_1min(),
    }
    start = time.perf_counter()
    calibrations: dict[str, tuple[EvalMethod, MethodResult, dict[str, Any], dict]] = {}
    runs: dict[str, MethodResult] = {}
    for name in order:
        method, stage = methods[name], "calibration"
        try:
            if fills_seconds(method, cfg.protocol):  # given the seconds, as a user gives them
                stage, runner = "run", method
                config_key, replicate_record, run = _seconds_replicate(
                    method, scene, seed, budget, cfg.protocol, record
                )
            else:
                config_key = configuration_key(method, cfg.protocol)
                if config_key not in calibrations:
                    runner = calibration_runner(method, cfg.protocol)
                    wrapped, log = _measured(runner)
                    model, source = configuration_model(  # probed in its first cell here
                        wrapped,
                        scene,
                        config_key,
                        budget=budget,
                        seed=cell_seed(cfg.seed, scene.name, runner.name, key, str(replicate)),
                        probe_fraction=cfg.probe_fraction,
                        protocol=cfg.protocol,
                    )
                    stage = "run"  # the method runs; a failure from here on is one of this cell
                    result, at_budget = run_at_budget(
                        wrapped,
                        scene,
                        model,
                        budget=budget,
                        seed=seed,
                        tolerance=min(cfg.tolerance, MISS_TOLERANCE),
                        max_rounds=cfg.max_rounds,
                        protocol=cfg.protocol,
                    )
                    if at_budget["within_tolerance"]:  # a miss was added by run_at_budget
                        model.update(at_budget["spp"], at_budget["charged_seconds"])
                    calibrations[config_key] = (runner, result, at_budget, log)
                    configuration = runner.configuration() if runner.configuration else None
                    record["calibrations"][config_key] = {
                        **at_budget,
                        "runner": runner.name,
                        "configuration": configuration,
                        "model": dataclasses.asdict(model),
                        "model_source": source,
                        "methods": [],
                    }
                runner, result, at_budget, log = calibrations[config_key]
                record["calibrations"][config_key]["methods"].append(name)
                stage = "run"
                reuse = runner.name == name and at_budget["seed"] == seed
                shared = runner.name != name
                replicate_record, run = _timed_replicate(
                    method,
                    scene,
                    at_budget["spp"],
                    seed,
                    budget,
                    cfg.protocol,
                    (result, log[seed]) if reuse else None,
                    record["calibrations"][config_key]["model"]["per_spp"] if shared else None,
                )
        except MethodUnavailable as err:
            record["skipped"][name] = str(err)
            continue
        except Exception as err:  # recorded; the driver stops the study unless keep_going
            if caused_by_interrupt(err):  # Ctrl-C inside a Dr.Jit frozen function
                raise
            record["errors"][name] = {"stage": stage, "error": _error_text(err)}
            if not cfg.keep_going:
                break
            continue
        replicate_record.update(calibration=config_key, calibrated_by=runner.name)
        if added:
            replicate_record["added"] = added
        record["replicates"][name] = replicate_record
        runs[name] = run
    record["seconds"] = time.perf_counter() - start  # the timed part; scoring follows
    record["loadavg_end"] = _load_1min()
    for name, run in runs.items():  # scored after the timed runs: they stay back to back
        replicate_record = record["replicates"][name]
        replicate_record["skipped_metrics"] = score(replicate_record, run.image, reference, cfg)
        replicate_record["nonfinite_pixels"] = int((~torch.isfinite(run.image)).any(-1).sum())
    images = {name: run.image for name, run in runs.items()} if replicate == 0 else {}
    return {"record": record, "images": images}


# ------------------------------------------------------------------------------- the driver
def _unit(key: str, replicate: int) -> str:
    return f"{key}/{replicate}"


def pending_cells(
    entry: dict[str, Any], methods: Sequence[str], cfg: EvaluateConfig, attempted: set[str]
) -> Iterator[tuple[float, int, str | None]]:
    """The cells of one scene still to run: ``(budget, replicate, added)``.

    A budget is done when every method in ``methods`` (those that can run) has its cell in
    ``entry`` (``results["scenes"][scene]``, also a study of format 1) and, with
    ``cfg.until_interval``, the interval of every method's first metric is narrow enough or
    ``cfg.max_seeds`` replicates ran. A cell is not offered twice in one run (``attempted``:
    unit names ``"<budget>/<replicate>"``): one that failed is retried by the next run.
    """
    runs = entry.get("cell_runs", {})
    for budget in cfg.budgets:
        key = budget_key(budget)
        cells = [entry.get("methods", {}).get(m, {}).get("cells", {}).get(key) for m in methods]
        if methods and all(c is not None for c in cells):
            count = min(len(c["replicates"]) for c in cells)
            wide = any(interval_too_wide(c["replicates"], cfg) for c in cells)
            unit = _unit(key, count)
            if wide and count < cfg.max_seeds and unit not in attempted:
                yield budget, count, "until_interval"
            continue
        for replicate in range(cfg.seeds):
            unit = _unit(key, replicate)
            ok = unit in runs and not runs[unit].get("errors")
            if not ok and unit not in attempted:
                yield budget, replicate, None


def _cell_of_method(
    entry: dict[str, Any], scene: str, name: str, key: str, cfg: EvaluateConfig
) -> dict[str, Any] | None:
    """The method's cell at budget ``key`` from its replicates in ``entry["cell_runs"]`` (in
    replicate order, contiguous from 0, at least ``cfg.seeds``), else ``None``."""
    runs = entry.get("cell_runs", {})
    replicates, units = [], []
    while (unit := _unit(key, len(replicates))) in runs and name in runs[unit]["replicates"]:
        replicates.append(runs[unit]["replicates"][name])
        units.append(runs[unit])
    if len(replicates) < cfg.seeds:
        return None
    first = replicates[0]
    calibration = units[0]["calibrations"][first["calibration"]]
    cell = {
        key_: calibration[key_]
        for key_ in ("attempts", "over_budget_at_1spp", "protocol")
        if key_ in calibration
    }
    cell.update({k: first[k] for k in ("spp", "seed", "seconds", "render_seconds")})
    cell.update(
        reconstruct_seconds=first["reconstruct_seconds"],
        compile_seconds=calibration.get("compile_seconds", 0.0),
        charged_seconds=first["charged_seconds"],
        relative_error=first["relative_error"],
        within_tolerance=abs(first["relative_error"]) <= cfg.tolerance,
        calibration=first["calibration"],
        calibrated_by=first["calibrated_by"],
        budget=units[0]["budget"],
        **summarise(replicates),
    )
    cell.update(
        replicates=replicates,
        missed_budget=[i for i, r in enumerate(replicates) if r.get("missed_budget")],
        skipped_metrics=first.get("skipped_metrics", {}),
        nonfinite_pixels=first.get("nonfinite_pixels", 0),
        image=f"images/{scene}/{name}-{key}s.exr",
    )
    return cell


def apply_cell(
    scene: str,
    entry: dict[str, Any],
    output: dict[str, Any],
    methods: Sequence[str],
    cfg: EvaluateConfig,
) -> list[str]:
    """Merge a finished cell (:func:`run_cell`'s output, images already saved) into ``entry``
    (``results["scenes"][scene]``): its record under ``cell_runs``, every
    method's cell rebuilt from its replicates, the scene's ``calibrations``, failures recorded
    per method as in a sequential study.

    Returns:
        One message per error of the cell (``"<scene> / <method>: calibration: could not run:
        ..."`` or ``"<scene> / <method> at <budget> s: ..."``).
    """
    record = output["record"]
    key = budget_key(record["budget"])
    entry.setdefault("cell_runs", {})[_unit(key, record["replicate"])] = record
    for config_key, calibration in record["calibrations"].items():
        shared = entry.setdefault("calibrations", {}).setdefault(config_key, {"budgets": {}})
        shared.update({k: calibration[k] for k in ("runner", "configuration", "model")})
        if record["replicate"] == 0 or key not in shared["budgets"]:
            shared["budgets"][key] = {
                k: v
                for k, v in calibration.items()
                if k not in ("runner", "configuration", "model", "methods")
            }
        shared["methods"] = sorted({*shared.get("methods", []), *calibration["methods"]})
    messages = []
    for name in methods:
        info = entry["methods"].setdefault(name, {"cells": {}})
        info.setdefault("cells", {})
        if name in record["skipped"]:
            info.update(status="skipped", note=record["skipped"][name], failed=False)
        elif (error := record["errors"].get(name)) and error["stage"] == "calibration":
            info.update(status="skipped", note=f"could not run: {error['error']}", failed=True)
            messages.append(f"{scene} / {name}: calibration: {info['note']}")
        elif error:
            info.setdefault("errors", {})[key] = error["error"]
            messages.append(f"{scene} / {name} at {key} s: {error['error']}")
        if name in record["replicates"]:
            first = record["replicates"][name]
            calibration = record["calibrations"][first["calibration"]]
            info.update(
                status="ok",
                note=None,
                failed=False,
                calibration=calibration["model"],
                calibration_key=first["calibration"],
            )
        if (cell := _cell_of_method(entry, scene, name, key, cfg)) is not None:
            info["cells"][key] = cell
            if not record["errors"].get(name):
                info.get("errors", {}).pop(key, None)
    return messages
