"""Ray as the study's engine: reference chunks and cells as tasks (``gdpt evaluate --workers N``
or ``--ray-address ADDR``).

* A reference chunk (:func:`gdpt.study.references.render_chunk`) is a task of one CPU; chunks
  run in parallel with anything, and the driver writes each one to the cache as it arrives, so
  a reference resumes chunk by chunk.
* A cell (:func:`gdpt.study.cells.run_cell`: every method of one scene, budget and replicate
  seed) is a task of one CPU and one unit of the custom resource :data:`CELL_RESOURCE`, which
  each node offers once: at most one timed cell per node at a time. Timings are compared only
  within a cell, so nodes of different speeds give comparable cells.
* Each task sets torch's and Dr.Jit's thread counts to its share of the node (usable cores x
  its CPUs / the node's Ray CPUs) and records them (``cell_runs[*].worker.threads``).
* Only the driver writes: ``results.json`` (atomically, after each cell), the images and the
  reference chunks. A worker that dies mid-cell leaves nothing behind; Ray runs the task again
  (``max_retries``). The results, report and resume are those of the sequential study.

The tasks are Ray remote functions (Moritz et al., "Ray: A Distributed Framework for Emerging
AI Applications", OSDI 2018; custom resources: https://docs.ray.io/en/latest/ray-core/scheduling/resources.html).
"""

from __future__ import annotations

import os
import socket
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

from gdpt.study.cells import pending_cells, run_cell, set_threads, worker_scene
from gdpt.study.config import EvaluateConfig
from gdpt.study.references import ReferenceChunk, reference_seed, render_chunk, render_reference
from gdpt.study.results import budget_key, write_json
from gdpt.study.scenes import SceneSpec

__all__ = ["CELL_RESOURCE", "RayEngine", "check_address"]

#: The Ray resource a timed cell holds; every node offers one (``ray start ... --resources
#: '{"gdpt_timed_cell": 1}'``; a local instance of :class:`RayEngine` does it itself).
CELL_RESOURCE = "gdpt_timed_cell"

#: Runs of a task whose worker died (killed, out of memory) before the study gives up on it.
MAX_RETRIES = 3


def check_address(address: str, timeout: float = 5.0) -> None:
    """Check that something answers at a Ray address (``HOST:PORT`` or ``ray://HOST:PORT``;
    ``auto`` is left to Ray).

    Raises:
        ConnectionError: one line: the address is malformed or nothing answers in ``timeout``
            seconds.
    """
    if address == "auto":
        return
    host, _, port = address.split("://", 1)[-1].rpartition(":")
    if not host or not port.isdigit():
        expected = "expected HOST:PORT, ray://HOST:PORT or auto"
        raise ConnectionError(f"Ray address {address!r}: {expected}")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            pass
    except OSError as err:
        reason = err.strerror or type(err).__name__
        raise ConnectionError(f"Ray address {address} does not answer ({reason})") from None


# -------------------------------------------------------------------------------- the tasks
_NODE_CPUS: dict[str, float] = {}


def _owned_threads() -> int:
    """This task's share of its node: usable cores x its Ray CPUs / the node's Ray CPUs."""
    import ray

    context = ray.get_runtime_context()
    node = context.get_node_id()
    if node not in _NODE_CPUS:
        found = [n["Resources"].get("CPU", 1.0) for n in ray.nodes() if n["NodeID"] == node]
        _NODE_CPUS[node] = found[0] if found else 1.0
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assigned = context.get_assigned_resources().get("CPU", 1.0)
    return max(1, int((usable or 1) * assigned // _NODE_CPUS[node]))


def _set_up(variant: str) -> dict[str, int]:
    import drjit as dr
    import mitsuba as mi

    from gdpt.backend import ensure_variant, set_variant

    if mi.variant() != variant:
        set_variant(variant)
    ensure_variant()
    dr.set_flag(dr.JitFlag.KernelHistory, True)  # compilation is excluded from timings
    return set_threads(_owned_threads())


def _chunk_task(spec: SceneSpec, cfg: EvaluateConfig, chunk: ReferenceChunk, variant: str) -> Any:
    _set_up(variant)
    return render_chunk(worker_scene(spec, cfg.resolution, cfg.max_depth), chunk)


def _cell_task(
    spec: SceneSpec,
    methods: dict[str, Any],
    budget: float,
    replicate: int,
    added: str | None,
    cfg: EvaluateConfig,
    reference: Any,
    variant: str,
) -> dict[str, Any]:
    _set_up(variant)
    scene = worker_scene(spec, cfg.resolution, cfg.max_depth)
    return run_cell(scene, reference, methods, budget, replicate, cfg, added=added)


# ------------------------------------------------------------------------------- the engine
class RayEngine:
    """A connection to Ray (a local instance of ``workers`` CPUs, or the cluster at
    ``address``) that runs a study (:meth:`run_study`).

    Raises:
        ConnectionError: ``address`` does not answer, or no node offers :data:`CELL_RESOURCE`.
        ValueError: ``workers`` below 1.
    """

    def __init__(self, *, workers: int | None = None, address: str | None = None) -> None:
        if workers is not None and workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        if address is not None:
            check_address(address)
        import ray

        self.workers, self.address, self._ray = workers, address, ray
        self._owned = not ray.is_initialized()
        if self._owned:
            try:
                if address is None:
                    ray.init(
                        num_cpus=workers,
                        resources={CELL_RESOURCE: 1},
                        include_dashboard=False,
                        log_to_driver=False,
                    )
                else:
                    ray.init(address=address, log_to_driver=False)
            except (ConnectionError, TimeoutError, RuntimeError) as err:
                first = (str(err).strip().splitlines() or [type(err).__name__])[0]
                hint = (
                    ""
                    if address is None
                    else " (it answers: are the Ray versions the same, "
                    "and has this process the head's token, RAY_AUTH_TOKEN_PATH?)"
                )
                raise ConnectionError(f"Ray address {address}: {first}{hint}") from None
        if not ray.cluster_resources().get(CELL_RESOURCE):
            self.close()
            raise ConnectionError(
                f"no node of the Ray cluster offers the resource {CELL_RESOURCE!r}; start each "
                f"node with: ray start ... --resources='{{\"{CELL_RESOURCE}\": 1}}'"
            )
        self._chunk = ray.remote(num_cpus=1, max_retries=MAX_RETRIES)(_chunk_task)
        self._cell = ray.remote(num_cpus=1, resources={CELL_RESOURCE: 1}, max_retries=MAX_RETRIES)(
            _cell_task
        )
        self._stop = threading.Event()

    def close(self) -> None:
        """Stop the local Ray instance this engine started (a cluster is left running)."""
        self._stop = getattr(self, "_stop", threading.Event())
        self._stop.set()
        if self._owned and self._ray.is_initialized():
            self._ray.shutdown()

    def describe(self) -> dict[str, Any]:
        """``results["threads"]``: the engine, its workers and the cluster's resources (each
        cell records its own threads)."""
        resources = self._ray.cluster_resources()
        return {
            "engine": "ray",
            "workers": self.workers,
            "address": self.address,
            "cluster_cpus": resources.get("CPU"),
            "timed_cell_slots": resources.get(CELL_RESOURCE),
            "per_worker": "set per task to its share of the node: cell_runs[*].worker.threads",
        }

    def chunks(self, spec: SceneSpec, cfg: EvaluateConfig, variant: str) -> Any:
        """A ``run_chunks`` of :func:`~gdpt.study.references.render_reference`: the chunks
        of ``spec``'s reference as tasks, yielded as they finish."""
        ray = self._ray

        def run(scene: Any, chunks: list[ReferenceChunk]) -> Any:
            pending = {self._chunk.remote(spec, cfg, c, variant): c for c in chunks}
            try:
                while pending:
                    if self._stop.is_set():
                        raise RuntimeError("the study stopped")
                    ready, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
                    for ref in ready:
                        yield pending.pop(ref), ray.get(ref)
            finally:
                for ref in pending:
                    ray.cancel(ref, force=True)

        return run

    def run_study(
        self,
        specs: list[SceneSpec],
        methods: list[str],
        cfg: EvaluateConfig,
        results: dict[str, Any],
        results_path: Path,
        cache: Path,
        out: Path,
        bar: Any,
    ) -> None:
        """:func:`gdpt.study.evaluate.evaluate`'s work on Ray: references (chunks) and cells as
        tasks, results merged and written by this process; the reference-free estimates
        last, in this process, after every timed cell."""
        from gdpt.backend import ensure_variant
        from gdpt.study import driver as study
        from gdpt.study.estimate import estimate_scene
        from gdpt.study.methods import EVAL_METHODS

        ray, variant = self._ray, ensure_variant()
        states: dict[str, dict[str, Any]] = {}
        references: dict[Future, str] = {}
        cells: dict[Any, tuple[str, str]] = {}
        pool = ThreadPoolExecutor(max_workers=max(1, len(specs)), thread_name_prefix="reference")

        def submit(state: dict[str, Any]) -> None:
            entry, runnable = state["entry"], state["runnable"]
            if not runnable:
                return
            chosen = {m: EVAL_METHODS[m] for m in runnable}
            for budget, replicate, added in list(
                pending_cells(entry, runnable, cfg, state["attempted"])
            ):
                unit = f"{budget_key(budget)}/{replicate}"
                state["attempted"].add(unit)
                bar.total += 1 if added else 0
                ref = self._cell.remote(
                    state["spec"], chosen, budget, replicate, added, cfg, state["ref"], variant
                )
                cells[ref] = (state["spec"].name, unit)

        try:
            for spec in specs:
                entry = results["scenes"].setdefault(
                    spec.name, {"source": spec.source, "methods": {}}
                )
                entry.setdefault("methods", {})
                runnable = study.runnable_methods(methods, entry)
                todo = study.cells_to_run(entry, runnable, cfg)
                bar.update(len(cfg.budgets) * cfg.seeds - todo)
                if entry.get("status") == "ok" and not any(
                    pending_cells(entry, runnable, cfg, set())
                ):
                    continue
                try:
                    scene = study.load_into(spec, cfg, entry)
                except Exception as err:
                    try:
                        study.scene_failed(spec.name, entry, "load", err, cfg)
                    finally:
                        write_json(results_path, results)
                        bar.update(todo)
                    continue
                state = {"spec": spec, "entry": entry, "runnable": runnable, "scene": scene}
                state.update(attempted=set(), todo=todo, ref=None)
                states[spec.name] = state
                if cfg.reference:
                    job = pool.submit(
                        render_reference,
                        scene,
                        cache,
                        spp=cfg.reference_spp,
                        chunk_spp=cfg.reference_chunk_spp,
                        seed=reference_seed(cfg.seed),
                        source=spec.source,
                        run_chunks=self.chunks(spec, cfg, variant),
                    )
                    references[job] = spec.name
                else:
                    study.reference_ready(spec.name, entry, None, None, out)
                    submit(state)
            while references or cells:
                for job in [j for j in references if j.done()]:
                    state = states[references.pop(job)]
                    name, entry = state["spec"].name, state["entry"]
                    try:
                        reference, meta = job.result()
                    except Exception as err:
                        try:
                            study.scene_failed(name, entry, "reference", err, cfg)
                        finally:
                            write_json(results_path, results)
                            bar.update(state["todo"])
                        continue
                    study.reference_ready(name, entry, reference, meta, out)
                    write_json(results_path, results)
                    state["ref"] = ray.put(reference)
                    submit(state)
                if not cells:
                    time.sleep(0.1)
                    continue
                ready, _ = ray.wait(list(cells), num_returns=1, timeout=0.2)
                for ref in ready:
                    name, unit = cells.pop(ref)
                    state = states[name]
                    try:
                        output = ray.get(ref)
                    except Exception as err:  # the task failed MAX_RETRIES times
                        if getattr(err, "cause", None) and isinstance(err.cause, KeyboardInterrupt):
                            raise
                        text = f"{type(err).__name__}: {' '.join(str(err).split())[:300]}"
                        state["entry"].setdefault("cell_errors", {})[unit] = text
                        write_json(results_path, results)
                        bar.update(1)
                        if not cfg.keep_going:
                            raise study.StudyFailure(f"{name}: cell {unit}: {text}") from err
                        continue
                    state["entry"].get("cell_errors", {}).pop(unit, None)
                    try:
                        study.finish_cell(
                            name, state["entry"], output, state["runnable"], cfg, results,
                            results_path, out,
                        )  # fmt: skip
                    finally:
                        bar.update(1)
                    submit(state)
            for state in states.values():  # after every timed cell: no load beside them
                if state["entry"].get("status") == "ok":
                    estimate_scene(state["scene"], state["entry"], cfg, out, bar)
                    write_json(results_path, results)
        finally:
            self._stop.set()
            for ref in cells:
                ray.cancel(ref, force=True)
            pool.shutdown(wait=True, cancel_futures=True)
