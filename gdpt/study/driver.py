"""The study's driver side, shared by the sequential study (:mod:`gdpt.study.evaluate`) and the
Ray engine (:mod:`gdpt.study.engine`): which methods run, loading a scene into its
``results.json`` entry, recording failures and references, and merging a finished cell
(:func:`finish_cell`, the only writer of ``results.json`` and the images)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from gdpt.interrupt import caused_by_interrupt
from gdpt.study.cells import apply_cell, pending_cells
from gdpt.study.config import EvaluateConfig
from gdpt.study.methods import EVAL_METHODS
from gdpt.study.results import budget_key, write_json
from gdpt.study.scenes import EvalScene, SceneSpec, load_eval_scene

__all__ = [
    "StudyFailure",
    "cells_to_run",
    "finish_cell",
    "load_into",
    "reference_ready",
    "runnable_methods",
    "scene_failed",
]


class StudyFailure(RuntimeError):
    """A scene or method of the study failed and ``keep_going`` is off (the failure is recorded
    in ``results.json`` first, so that a resumed run retries it)."""


def runnable_methods(methods: list[str], entry: dict[str, Any]) -> list[str]:
    """The methods of ``methods`` that can run here; the others are recorded in ``entry`` as
    skipped with the reason (package or model missing)."""
    names = []
    for name in methods:
        if reason := EVAL_METHODS[name].check():
            info = entry["methods"].setdefault(name, {"cells": {}})
            info.update(status="skipped", note=reason, failed=False)
        else:
            names.append(name)
    return names


def cells_to_run(entry: dict[str, Any], runnable: list[str], cfg: EvaluateConfig) -> int:
    """How many of the scene's ``budgets x seeds`` cells are still to run (0: the scene is
    done, or nothing can run)."""
    if entry.get("status") != "ok" or not runnable:
        return 0 if not runnable and entry.get("status") == "ok" else len(cfg.budgets) * cfg.seeds
    return sum(1 for _, _, added in pending_cells(entry, runnable, cfg, set()) if added is None)


def load_into(spec: SceneSpec, cfg: EvaluateConfig, entry: dict[str, Any]) -> EvalScene:
    """Load ``spec`` for the study and record its film and notes in ``entry``."""
    scene = load_eval_scene(spec, resolution=cfg.resolution, max_depth=cfg.max_depth)
    entry.update(
        resolution=list(scene.resolution),
        max_depth=scene.max_depth,
        notes=scene.notes,
        film_filter=scene.film_filter,
    )
    return scene


def scene_failed(
    name: str, entry: dict[str, Any], stage: str, err: Exception, cfg: EvaluateConfig
) -> None:
    """Record a scene that failed at ``stage``; :class:`StudyFailure` unless ``keep_going``.
    The caller writes ``results.json`` first (``finally``)."""
    if caused_by_interrupt(err):  # Ctrl-C inside a Dr.Jit frozen function
        raise err
    entry.update(status="failed", stage=stage, error=f"{type(err).__name__}: {err}")
    entry.pop("reference", None)
    if not cfg.keep_going:
        raise StudyFailure(f"{name}: {stage} failed: {entry['error']}") from err


def reference_ready(
    name: str,
    entry: dict[str, Any],
    reference: torch.Tensor | None,
    meta: dict[str, Any] | None,
    out: Path,
) -> None:
    """Record the scene's reference in ``entry`` and save it beside the images."""
    from gdpt.io.exr import save_image
    from gdpt.io.images import save_png

    entry.update(status="ok", reference=meta)
    entry.pop("error", None)
    entry.pop("stage", None)
    image_dir = out / "images" / name
    image_dir.mkdir(parents=True, exist_ok=True)
    if reference is not None:
        save_image(image_dir / "reference.exr", reference, metadata=meta, force=True)
        save_png(image_dir / "reference.png", reference, force=True)


def finish_cell(
    name: str,
    entry: dict[str, Any],
    output: dict[str, Any],
    runnable: list[str],
    cfg: EvaluateConfig,
    results: dict[str, Any],
    results_path: Path,
    out: Path,
) -> None:
    """Save a finished cell's images, merge it into the results (:func:`apply_cell`) and
    write ``results.json`` (atomically).

    Raises:
        StudyFailure: a method of the cell failed and ``cfg.keep_going`` is off.
    """
    from gdpt.io.exr import save_image
    from gdpt.io.images import save_png

    record = output["record"]
    key = budget_key(record["budget"])
    for method, image in output["images"].items():
        replicate = record["replicates"][method]
        path = out / "images" / name / f"{method}-{key}s.exr"
        metadata = {"method": method, "spp": replicate["spp"], "budget": record["budget"]}
        save_image(path, image, metadata={**metadata, "seed": replicate["seed"]}, force=True)
        save_png(path.with_suffix(".png"), image, force=True)
    messages = apply_cell(name, entry, output, runnable, cfg)
    write_json(results_path, results)
    if messages and not cfg.keep_going:
        raise StudyFailure(messages[0])
