"""Equal-time evaluation: error against measured wall time, per scene, method and budget.

For each scene and time budget, every method of :data:`gdpt.methods.EVAL_METHODS` gets the
sample count whose *measured* render + reconstruction time matches the budget on this machine,
in this run (calibrated by timing, never assumed), and its image is compared with a high-spp
reference by the metrics of :mod:`gdpt.metrics`::

    from gdpt.evaluate import PRESETS, evaluate

    results = evaluate(["../shared/scenes/cornell-box"], "out/eval", PRESETS["quick"])

Protocol, per scene:

1. Load the scene at ``resolution`` pixels on the long side. Mitsuba XML scenes whose film uses
   a non-box pixel filter get ``<rfilter type="box"/>`` (the gradient-domain integrators need
   it); the override is recorded in the results and the report, and the reference uses the
   same film, so every method is compared on the same image formation.
2. Render the reference once: path tracing (``gdpt`` primal only) at ``reference_spp``, in
   chunks whose running mean is saved, so an interrupted reference resumes; the finished file
   is cached with its spp, seed and resolution in its name and metadata.
3. Per method: warm up (1 and 2 spp, untimed, compiles the kernels), then fit
   ``t(spp) = a + b * spp`` from a median of 1-spp runs and geometrically growing probe runs
   (:func:`calibrate`), solve for each budget, render and check the achieved time; if it is off
   by more than ``tolerance`` the model is corrected and the cell rendered again
   (``max_rounds`` times at most). Achieved times, every attempt and kernel compilation
   (excluded from the times) are recorded.
4. Metrics of every cell; ``results.json`` is rewritten after each cell, so an interrupted run
   resumes without recomputing finished cells.

Failures are data: a scene that fails to load or render, or a method that cannot run (package
missing, no shipped model), is recorded with the reason and the study continues.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
import statistics
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any

import torch

from gdpt.methods import EVAL_METHODS, EvalMethod, MethodResult, MethodUnavailable

__all__ = [
    "PRESETS",
    "EvalScene",
    "EvaluateConfig",
    "SceneSpec",
    "TimeModel",
    "calibrate",
    "evaluate",
    "load_eval_scene",
    "render_reference",
    "resolve_scenes",
    "run_at_budget",
]

#: Format tag of ``results.json``.
RESULTS_FORMAT = "gdpt-evaluate/1"

#: Pixel filter the gradient-domain integrators need.
BOX_FILTER = "box"

#: Max depth used when neither the config nor the scene sets one.
DEFAULT_MAX_DEPTH = 6

#: Config fields that must match for a run directory to be resumed.
_RESUME_KEYS = ("resolution", "reference_spp", "seed", "max_depth", "metrics", "metric_options")


@dataclass
class EvaluateConfig:
    """Options of :func:`evaluate`."""

    budgets: tuple[float, ...] = (4.0, 16.0, 64.0)
    """Wall-clock budgets in seconds (sampling + reconstruction) per image."""
    resolution: int = 320
    """Pixels on the long side of the film (the aspect ratio of the scene is kept)."""
    reference_spp: int = 8192
    """Samples per pixel of the path-traced reference."""
    reference_chunk_spp: int = 256
    """The reference is rendered and checkpointed in chunks of this many spp."""
    max_depth: int | None = None
    """Longest path; ``None`` uses the scene's integrator ``max_depth`` (else 6)."""
    metrics: tuple[str, ...] = (
        "relmse", "mse", "smape", "one_minus_ssim", "flip_hdr", "flip_ldr", "elpips"
    )
    """Names from :data:`gdpt.metrics.METRICS`; the first one ranks methods and is plotted."""
    metric_options: dict[str, dict[str, Any]] = field(
        default_factory=lambda: {"elpips": {"samples": 50}}
    )
    """Per-metric keyword options (only for metrics in ``metrics``)."""
    methods: tuple[str, ...] = ()
    """Names from :data:`gdpt.methods.EVAL_METHODS`; empty means all registered."""
    seed: int = 0
    """Base seed; every cell and the reference derive distinct seeds from it."""
    tolerance: float = 0.2
    """Relative deviation of the achieved time from the budget that triggers a re-render."""
    max_rounds: int = 3
    """Renders per cell at most (the first plus corrections)."""
    probe_fraction: float = 0.5
    """The calibration probe aims at this fraction of the smallest budget."""
    reference_dir: Path | None = None
    """Reference cache; ``None`` means ``<out>/references`` (share it between runs)."""
    profile: str = "custom"
    """Name of the preset this config came from (recorded only)."""

    def __post_init__(self) -> None:
        self.budgets = tuple(sorted(float(b) for b in self.budgets))
        self.metrics = tuple(self.metrics)
        self.methods = tuple(self.methods)
        if not self.budgets or min(self.budgets) <= 0:
            raise ValueError(f"budgets must be positive seconds, got {self.budgets}")
        if self.resolution < 8:
            raise ValueError(f"resolution must be >= 8 pixels, got {self.resolution}")
        if self.reference_spp < 1 or self.reference_chunk_spp < 1:
            raise ValueError("reference_spp and reference_chunk_spp must be >= 1")
        if not self.metrics:
            raise ValueError("at least one metric is needed")
        # options of metrics not requested are dropped (e.g. elpips when --metrics omits it)
        self.metric_options = {k: v for k, v in self.metric_options.items() if k in self.metrics}
        if not 0 < self.tolerance < 1 or self.max_rounds < 1:
            raise ValueError("tolerance must be in (0, 1) and max_rounds >= 1")

    def to_json(self) -> dict[str, Any]:
        """The config as a JSON-serialisable dict."""
        out = dataclasses.asdict(self)
        out["reference_dir"] = None if self.reference_dir is None else str(self.reference_dir)
        return json.loads(json.dumps(out))  # tuples -> lists, as read back from results.json


#: Named configurations. ``quick`` finishes in minutes on 2 CPU cores; ``full`` is for long runs.
PRESETS: dict[str, EvaluateConfig] = {
    "quick": EvaluateConfig(
        budgets=(0.5, 1.0, 2.0),
        resolution=128,
        reference_spp=16384,
        metrics=("relmse", "smape", "one_minus_ssim", "flip_ldr"),
        metric_options={},
        profile="quick",
    ),
    "full": EvaluateConfig(profile="full"),
}


# ------------------------------------------------------------------------------------ scenes
@dataclass(frozen=True)
class SceneSpec:
    """Where a scene comes from.

    Attributes:
        name: short name used in the report and in file names.
        source: an XML path, ``builtin:NAME`` or ``random:SEED[:VIEW]``.
    """

    name: str
    source: str


@dataclass
class EvalScene:
    """A loaded scene, ready for the methods.

    Attributes:
        name: short name.
        scene: the ``mi.Scene``.
        max_depth: longest path used by every method and the reference.
        resolution: film ``(width, height)``.
        notes: changes made to the scene when loading it (e.g. the filter override).
        film_filter: ``{"original": ..., "used": "box"}``.
    """

    name: str
    scene: Any
    max_depth: int
    resolution: tuple[int, int]
    notes: list[str] = field(default_factory=list)
    film_filter: dict[str, str | None] = field(default_factory=dict)


def _scene_name(path: Path) -> str:
    return path.parent.name if path.name == "scene.xml" else path.stem


def resolve_scenes(items: Iterable[str | os.PathLike[str]]) -> list[SceneSpec]:
    """Expand scene arguments into :class:`SceneSpec` objects.

    Each item is a Mitsuba XML file; a folder holding ``scene.xml``; a folder of such folders
    (every ``*/scene.xml``, sorted); ``builtin:NAME`` (:func:`gdpt.scenes.builtin_scene`);
    ``random:SEED[:VIEW]`` (a procedural scene from :func:`gdpt.scenes.random_scene`); or a
    comma-separated list of those. A path that does not exist is kept: loading it fails and
    the failure is reported with the results.

    Args:
        items: scene arguments.

    Returns:
        The scenes, in argument order, without duplicates (same name and source).

    Raises:
        ValueError: two different scenes would get the same name.
    """
    specs: list[SceneSpec] = []
    for item in items:
        for part in str(item).split(","):
            part = part.strip()
            if not part:
                continue
            if part.startswith("builtin:"):
                specs.append(SceneSpec(part.split(":", 1)[1], part))
            elif part.startswith("random:"):
                specs.append(SceneSpec("random-" + part.split(":", 1)[1].replace(":", "-"), part))
            else:
                path = Path(part)
                if path.is_dir() and (path / "scene.xml").is_file():
                    path = path / "scene.xml"
                if path.is_dir():
                    subs = sorted(path.glob("*/scene.xml"))
                    specs += [SceneSpec(_scene_name(p), str(p)) for p in subs]
                    if not subs:
                        specs.append(SceneSpec(path.name, str(path)))
                else:
                    specs.append(SceneSpec(_scene_name(path), str(path)))
    unique: dict[str, SceneSpec] = {}
    for spec in specs:
        if spec.name in unique and unique[spec.name] != spec:
            raise ValueError(
                f"two scenes are named {spec.name!r}: {unique[spec.name].source} and {spec.source}"
            )
        unique[spec.name] = spec
    return list(unique.values())


def _long_side(width: int, height: int, long_side: int) -> tuple[int, int]:
    scale = long_side / max(width, height)
    return max(1, round(width * scale)), max(1, round(height * scale))


def _xml_value(element: ET.Element | None, defaults: dict[str, str]) -> str | None:
    if element is None:
        return None
    value = element.get("value")
    if value is not None and value.startswith("$"):
        value = defaults.get(value[1:], value)
    return value


def _load_xml(spec: SceneSpec, resolution: int, max_depth: int | None) -> EvalScene:
    """Load an XML scene with its film resized and its pixel filter set to box."""
    import mitsuba as mi

    path = Path(spec.source)
    if not path.is_file():
        raise FileNotFoundError(f"scene file not found: {path}")
    root = ET.parse(path).getroot()
    defaults = {d.get("name", ""): d.get("value", "") for d in root.iter("default")}
    film = root.find("sensor/film")
    if film is None:
        raise ValueError(f"{path}: no <sensor><film> element (included films are not handled)")
    size = []
    for key, fallback in (("width", "768"), ("height", "576")):  # hdrfilm's defaults
        element = film.find(f"*[@name='{key}']")
        if element is None:
            element = ET.SubElement(film, "integer", {"name": key, "value": fallback})
        size.append((int(_xml_value(element, defaults) or fallback), element))
    (width, w_el), (height, h_el) = size
    new_w, new_h = _long_side(width, height, resolution)
    w_el.attrib.update(value=str(new_w))
    h_el.attrib.update(value=str(new_h))
    notes = [f"film resized from {width}x{height} to {new_w}x{new_h}"]

    rfilter = film.find("rfilter")
    original = "gaussian" if rfilter is None else rfilter.get("type")  # Mitsuba's default
    if rfilter is None:
        rfilter = ET.SubElement(film, "rfilter")
    if original != BOX_FILTER:
        rfilter.attrib.clear()
        rfilter.attrib["type"] = BOX_FILTER
        for child in list(rfilter):
            rfilter.remove(child)
        notes.append(
            f"pixel filter overridden: '{original}' -> 'box' (the gradient-domain integrators "
            "need a box filter; the reference and every method use the same box-filtered film)"
        )

    integrator = root.find("integrator")
    scene_depth = None
    if integrator is not None:
        depth = _xml_value(integrator.find("*[@name='max_depth']"), defaults)
        scene_depth = int(depth) if depth is not None else None
        root.remove(integrator)  # unused: the methods bring their own integrator
    depth = _choose_depth(max_depth, scene_depth, notes)

    resolver = mi.file_resolver()
    saved = mi.FileResolver(resolver)
    resolver.prepend(str(path.parent.resolve()))
    try:
        scene = mi.load_string(ET.tostring(root, encoding="unicode"))
    except Exception as err:  # Mitsuba raises RuntimeError with its parser message
        raise ValueError(f"cannot load scene {path}: {' '.join(str(err).split())}") from err
    finally:
        mi.set_file_resolver(saved)
    return EvalScene(spec.name, scene, depth, (new_w, new_h), notes,
                     {"original": original, "used": BOX_FILTER})


def _choose_depth(configured: int | None, scene_depth: int | None, notes: list[str]) -> int:
    if configured is not None:
        notes.append(f"max_depth {configured} (configured)")
        return configured
    if scene_depth is not None:
        notes.append(f"max_depth {scene_depth} (from the scene's integrator)")
        return scene_depth
    notes.append(f"max_depth {DEFAULT_MAX_DEPTH} (default; the scene sets none)")
    return DEFAULT_MAX_DEPTH


def load_eval_scene(
    spec: SceneSpec, *, resolution: int, max_depth: int | None = None
) -> EvalScene:
    """Load a scene for evaluation at ``resolution`` pixels on the long side.

    Args:
        spec: the scene.
        resolution: long side of the film in pixels.
        max_depth: longest path; ``None`` uses the scene's integrator setting (else 6).

    Returns:
        The loaded scene with the notes describing every change made to it.

    Raises:
        FileNotFoundError: the XML file does not exist.
        ValueError: Mitsuba cannot load it, or an unknown builtin/random specification.
    """
    import mitsuba as mi

    from gdpt.backend import set_variant
    from gdpt.integrators import register
    from gdpt.scenes import builtin_scene, random_scene

    if mi.variant() is None:
        set_variant()
    register()
    if spec.source.startswith(("builtin:", "random:")):
        kind, _, arg = spec.source.partition(":")
        notes: list[str] = []
        if kind == "builtin":
            scene_dict = builtin_scene(arg, resolution=(resolution, resolution))
        else:
            seed, _, view = arg.partition(":")
            scene_dict = random_scene(int(seed), view=int(view or 0),
                                      resolution=(resolution, resolution))
        depth = _choose_depth(max_depth, None, notes)
        rfilter = scene_dict["sensor"]["film"].get("rfilter", {}).get("type")
        if rfilter != BOX_FILTER:
            raise ValueError(f"{spec.source}: film filter is {rfilter!r}, expected box")
        width = scene_dict["sensor"]["film"]["width"]
        height = scene_dict["sensor"]["film"]["height"]
        return EvalScene(spec.name, mi.load_dict(scene_dict), depth, (width, height), notes,
                         {"original": BOX_FILTER, "used": BOX_FILTER})
    return _load_xml(spec, resolution, max_depth)


# --------------------------------------------------------------------------------- reference
def _reference_seed(seed: int) -> int:
    return 1_000_003 + seed


def render_reference(
    scene: EvalScene, cache_dir: Path, *, spp: int, chunk_spp: int, seed: int,
    source: str = "", progress: Any = None,
) -> tuple[torch.Tensor, dict[str, Any]]:
    """The path-traced reference, from the cache or rendered (resumably) into it.

    The reference is ``gdpt`` with ``gradients=False`` (plain path tracing) at ``spp``,
    rendered in chunks of ``chunk_spp`` with seeds ``seed * 7919 + spp done``. After each chunk
    the running mean is saved as ``<stem>.partial-<spp done>.exr``, from which an interrupted
    render continues. The finished image is ``<stem>.exr`` with its metadata in ``<stem>.json``,
    ``<stem> = <scene>-<W>x<H>-d<max depth>-<spp>spp-seed<seed>``.

    Args:
        scene: the scene.
        cache_dir: folder of cached references (created if needed).
        spp: samples per pixel.
        chunk_spp: samples per chunk.
        seed: reference seed (distinct from the seeds of the evaluated images).
        source: scene source, recorded; cached files of another source with the same name are
            discarded.
        progress: optional tqdm bar whose postfix shows the reference progress.

    Returns:
        The ``(H, W, 3)`` float32 reference on the CPU and its metadata.
    """
    from gdpt.exr import load_image, save_image
    from gdpt.render import render

    cache_dir.mkdir(parents=True, exist_ok=True)
    width, height = scene.resolution
    stem = f"{scene.name}-{width}x{height}-d{scene.max_depth}-{spp}spp-seed{seed}"
    final, sidecar = cache_dir / f"{stem}.exr", cache_dir / f"{stem}.json"
    meta = {
        "source": source, "scene": scene.name, "spp": spp, "seed": seed,
        "chunk_spp": chunk_spp, "max_depth": scene.max_depth, "resolution": [width, height],
        "film_filter": scene.film_filter, "method": "pt (gdpt integrator, gradients=False)",
    }
    old = json.loads(sidecar.read_text()) if sidecar.is_file() else None
    if old is not None and all(old.get(k) == meta[k] for k in ("source", "film_filter")):
        if final.is_file() and old.get("complete"):
            return load_image(final), {**old, "path": str(final), "cached": True}
        meta["seconds"] = old.get("seconds", 0.0)
    else:  # nothing cached, or the same name for another scene: start over
        for stale in [final, *cache_dir.glob(f"{stem}.partial-*.exr")]:
            stale.unlink(missing_ok=True)
        meta["seconds"] = 0.0
    _write_json(sidecar, meta)

    mean, done = None, 0
    partials = sorted(cache_dir.glob(f"{stem}.partial-*.exr"),
                      key=lambda p: int(p.stem.rsplit("-", 1)[1]))
    if partials:
        mean, done = load_image(partials[-1]).double(), int(partials[-1].stem.rsplit("-", 1)[1])
    while done < spp:
        n = min(chunk_spp, spp - done)
        start = time.perf_counter()
        buffers = render(scene.scene, spp=n, seed=seed * 7919 + done,
                         max_depth=scene.max_depth, gradients=False, features=False)
        chunk = buffers.primal.to("cpu", torch.float64)
        meta["seconds"] += time.perf_counter() - start
        mean = chunk if mean is None else mean + (chunk - mean) * (n / (done + n))
        done += n
        path = cache_dir / f"{stem}.partial-{done}.exr"
        save_image(path, mean, metadata={**meta, "spp_done": done}, force=True)
        _write_json(sidecar, meta)
        for older in partials:
            older.unlink(missing_ok=True)
        partials = [path]
        if progress is not None:
            progress.set_postfix_str(f"{scene.name}: reference {done}/{spp} spp")
    save_image(final, mean, metadata=meta, force=True)
    _write_json(sidecar, {**meta, "complete": True})
    for older in partials:
        older.unlink(missing_ok=True)
    return mean.float(), {**meta, "path": str(final), "cached": False}


# ------------------------------------------------------------------------------- calibration
@dataclass
class TimeModel:
    """Linear cost model ``seconds(spp) = fixed + per_spp * spp`` of one method on one scene.

    Attributes:
        fixed: seconds independent of the sample count (reconstruction, launch overheads).
        per_spp: seconds per sample per pixel.
        measurements: the ``(spp, seconds)`` timings the model is fitted to (least squares).
    """

    fixed: float
    per_spp: float
    measurements: list[tuple[int, float]] = field(default_factory=list)

    @classmethod
    def fit(cls, measurements: list[tuple[int, float]]) -> TimeModel:
        """Least-squares line through ``(spp, seconds)`` timings (at least one).

        A non-positive slope (timing noise) falls back to the line through the origin and the
        largest measurement; a negative intercept to the least-squares line through the origin.
        """
        spp = torch.tensor([m[0] for m in measurements], dtype=torch.float64)
        sec = torch.tensor([m[1] for m in measurements], dtype=torch.float64)
        slope = fixed = 0.0
        if len(set(spp.tolist())) > 1:
            ds = spp - spp.mean()
            slope = float((ds * (sec - sec.mean())).sum() / ds.square().sum())
            fixed = float(sec.mean()) - slope * float(spp.mean())
        if slope <= 0:
            largest = int(spp.argmax())
            slope, fixed = float(sec[largest] / spp[largest]), 0.0
        elif fixed < 0:
            slope, fixed = float((spp * sec).sum() / spp.square().sum()), 0.0
        return cls(fixed=fixed, per_spp=max(slope, 1e-9), measurements=list(measurements))

    def spp_for(self, budget: float) -> int:
        """The sample count whose predicted time is closest to ``budget`` (at least 1).

        Extrapolation is capped at 16 times the through-origin estimate from the largest
        measurement, so that a noisy fit cannot ask for an absurd sample count.
        """
        spp = round((budget - self.fixed) / self.per_spp)
        if self.measurements:
            s_max, t_max = max(self.measurements)
            spp = min(spp, math.ceil(16 * s_max * budget / max(t_max, 1e-9)))
        return max(1, spp)

    def update(self, spp: int, seconds: float) -> None:
        """Add a timing and refit."""
        refit = TimeModel.fit([*self.measurements, (spp, seconds)])
        self.fixed, self.per_spp, self.measurements = refit.fixed, refit.per_spp, refit.measurements


def _run(method: EvalMethod, scene: EvalScene, spp: int, seed: int) -> MethodResult:
    return method.run(scene, spp=spp, seed=seed)


def calibrate(
    method: EvalMethod, scene: EvalScene, *, budget: float, seed: int, repeats: int = 3,
    probe_fraction: float = 0.5, max_probe_spp: int = 1 << 16,
) -> TimeModel:
    """Fit a :class:`TimeModel` by timing ``method`` on ``scene``.

    Warms up at 1 and 2 spp (untimed: the kernels compile), takes the median of ``repeats``
    1-spp runs, then raises the sample count geometrically (x2 to x8, aiming at the target)
    until a run takes at least ``probe_fraction * budget`` (and at least two probes ran); the
    least-squares line through these timings is the model.

    Args:
        method: the method.
        scene: the scene.
        budget: the smallest budget the model will be used for (seconds).
        seed: seed of the calibration renders (their images are discarded).
        repeats: number of 1-spp timings whose median is used.
        probe_fraction: the probing stops at this fraction of ``budget``.
        max_probe_spp: the probing stops at this sample count.

    Returns:
        The fitted model.

    Raises:
        MethodUnavailable: the method cannot run here.
    """
    _run(method, scene, 1, seed)
    _run(method, scene, 2, seed)
    t = statistics.median(_run(method, scene, 1, seed + i).seconds for i in range(repeats))
    measurements = [(1, t)]
    spp, target = 1, probe_fraction * budget
    while (t < target or len(measurements) < 3) and spp < max_probe_spp:
        spp = min(max_probe_spp, spp * min(8, max(2, round(target / max(t, 1e-6)))))
        t = _run(method, scene, spp, seed + spp).seconds
        measurements.append((spp, t))
    return TimeModel.fit(measurements)


def run_at_budget(
    method: EvalMethod, scene: EvalScene, model: TimeModel, *, budget: float, seed: int,
    tolerance: float = 0.2, max_rounds: int = 3,
) -> tuple[MethodResult, dict[str, Any]]:
    """Render ``method`` with the sample count that fills ``budget``, checking the time.

    Renders at ``model.spp_for(budget)``; while the achieved time misses the budget by more
    than ``tolerance`` (relative) and rounds remain, the per-spp cost is re-estimated from the
    achieved time (:meth:`TimeModel.update`) and the cell rendered again. The run closest to
    the budget is returned; the model keeps the last estimate.

    Args:
        method: the method.
        scene: the scene.
        model: its calibrated cost model.
        budget: seconds.
        seed: seed of the first attempt (attempt ``k`` uses ``seed + k``).
        tolerance: accepted relative deviation.
        max_rounds: renders at most.

    Returns:
        The chosen run and a record: ``spp``, ``seconds``, ``relative_error``, ``attempts``
        (``[{"spp", "seconds", "seed", "compile_seconds"}]``), ``within_tolerance``,
        ``over_budget_at_1spp``.
    """
    attempts: list[dict[str, Any]] = []
    best: tuple[float, MethodResult, int, int] | None = None
    spp = model.spp_for(budget)
    for k in range(max_rounds):
        result = _run(method, scene, spp, seed + k)
        attempts.append({"spp": spp, "seconds": result.seconds, "seed": seed + k,
                         "compile_seconds": result.compile_seconds})
        error = abs(result.seconds - budget) / budget
        if best is None or error < best[0]:
            best = (error, result, spp, seed + k)
        if error <= tolerance:
            break
        model.update(spp, result.seconds)
        new_spp = model.spp_for(budget)
        if new_spp == spp:
            break
        spp = new_spp
    assert best is not None
    error, result, spp, seed_used = best
    record = {
        "spp": spp,
        "seed": seed_used,
        "seconds": result.seconds,
        "render_seconds": result.render_seconds,
        "reconstruct_seconds": result.reconstruct_seconds,
        "compile_seconds": result.compile_seconds,
        "relative_error": (result.seconds - budget) / budget,
        "within_tolerance": error <= tolerance,
        "over_budget_at_1spp": spp == 1 and result.seconds > budget * (1 + tolerance),
        "attempts": attempts,
    }
    return result, record


# ---------------------------------------------------------------------------------- the study
def machine_info() -> dict[str, Any]:
    """CPU model, core counts, memory, OS, load average (a shared machine skews timings)."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    memory = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                memory = round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return {
        "cpu": cpu,
        "logical_cores": os.cpu_count(),
        "usable_cores": affinity,
        "memory_gib": memory,
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "torch_threads": torch.get_num_threads(),
        "loadavg_at_start": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


def versions() -> dict[str, str | None]:
    """Versions of gdpt and the packages that influence the numbers."""
    out: dict[str, str | None] = {}
    for dist in ("gdpt", "mitsuba", "drjit", "torch", "numpy", "pyoidn", "flip-evaluator"):
        try:
            out[dist] = importlib_metadata.version(dist)
        except importlib_metadata.PackageNotFoundError:
            out[dist] = None
    return out


#: Metric conventions stated in the results (see :mod:`gdpt.metrics`).
CONVENTIONS = {
    "relmse": "mean (p - r)^2 / (1e-3 + mean_c(r)^2): NGPT convention, greyscale reference",
    "mse": "mean (p - r)^2 over pixels and channels, linear HDR",
    "smape": "mean |p - r| / (|p| + |r| + 1e-2): OIDN convention",
    "one_minus_ssim": "1 - SSIM (11x11 Gaussian, sigma 1.5) on sRGB(clamp(Reinhard(x)))",
    "flip_hdr": "mean HDR-FLIP (flip-evaluator, ACES, ppd 67.02)",
    "flip_ldr": "mean LDR-FLIP (flip-evaluator) on sRGB(clamp(Reinhard(x)))",
    "elpips": "E-LPIPS (weights from GDPT_ELPIPS_WEIGHTS) on sRGB(clamp(Reinhard(x)))",
    "seconds": "wall time of sampling + reconstruction, kernel compilation excluded",
}


def _cell_seed(base: int, *parts: str) -> int:
    return (base * 1_000_003 + zlib.crc32("/".join(parts).encode())) % 2**31


def _budget_key(budget: float) -> str:
    return f"{budget:g}"


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _write_json(path: Path, data: dict[str, Any]) -> None:
    """Write ``data`` atomically (a crash leaves the previous file intact)."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".json")
    with os.fdopen(fd, "w") as f:
        json.dump(data, f, indent=1)
    os.replace(tmp, path)


def _load_results(path: Path, cfg: EvaluateConfig) -> dict[str, Any]:
    """The previous ``results.json`` if compatible with ``cfg``, else a new skeleton."""
    if path.is_file():
        old = json.loads(path.read_text())
        if old.get("format") != RESULTS_FORMAT:
            raise ValueError(f"{path} is not a gdpt evaluation ({old.get('format')!r})")
        new = cfg.to_json()
        diff = [k for k in _RESUME_KEYS if old["config"].get(k) != new.get(k)]
        if diff:
            raise ValueError(
                f"{path} was made with different settings ({', '.join(diff)}); use another "
                "--out folder or delete it"
            )
        return old
    return {"format": RESULTS_FORMAT, "scenes": {}, "runs": []}


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


def _study_reference(scene: EvalScene, spec: SceneSpec, cfg: EvaluateConfig, cache: Path,
                     bar: Any) -> tuple[torch.Tensor, dict[str, Any]]:
    """:func:`render_reference` with the study's settings (shared by every entry point)."""
    return render_reference(
        scene, cache, spp=cfg.reference_spp, chunk_spp=cfg.reference_chunk_spp,
        seed=_reference_seed(cfg.seed), source=spec.source, progress=bar,
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
        cfg: options; default :data:`PRESETS` ``["full"]``.
        progress: show a progress bar over all cells of the study.
        report: write ``results.md``, plots, crops and ``index.html`` at the end.
        command: the command line that started the run (recorded in the results).

    Returns:
        The content of ``results.json``.

    Raises:
        ValueError: unknown methods or metrics, or ``out_dir`` holds an incompatible study.
    """
    import drjit as dr
    from tqdm.auto import tqdm

    from gdpt.backend import set_variant
    from gdpt.metrics import get_metric

    cfg = cfg or PRESETS["full"]
    for name in cfg.metrics:
        get_metric(name)
    methods = _method_list(cfg)
    specs = _as_specs(scenes)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "images").mkdir(exist_ok=True)
    results_path = out / "results.json"
    results = _load_results(results_path, cfg)
    import mitsuba as mi

    if mi.variant() is None:
        set_variant()
    results.update(
        config=cfg.to_json(), machine=machine_info(), versions=versions(),
        conventions=CONVENTIONS,
        methods={m: _method_info(EVAL_METHODS[m]) for m in methods},
        protocol=(
            "per scene and budget, each method's spp is calibrated by timing on this machine "
            "in this run (t = a + b*spp fitted to 1-spp medians and growing probes, then "
            f"verified and re-rendered if off by more than {cfg.tolerance:.0%}); reference: "
            f"path tracing at {cfg.reference_spp} spp on the same box-filtered film"
        ),
    )
    results["runs"].append({"started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                            "command": command, "scenes": [s.source for s in specs]})
    cache = Path(cfg.reference_dir) if cfg.reference_dir else out / "references"

    total = len(specs) * len(methods) * len(cfg.budgets)
    bar = tqdm(total=total, unit="cell", desc="evaluate", disable=not progress,
               dynamic_ncols=True)
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
        _write_json(results_path, results)
    if report:
        from gdpt.eval_report import write_report

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
        if any(_budget_key(b) not in info.get("cells", {}) for b in cfg.budgets):
            return False
    return True


def _evaluate_scene(
    spec: SceneSpec, methods: list[str], cfg: EvaluateConfig, results: dict[str, Any],
    results_path: Path, cache: Path, out: Path, bar: Any,
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
        entry.update(resolution=list(scene.resolution), max_depth=scene.max_depth,
                     notes=scene.notes, film_filter=scene.film_filter)
        stage = "reference"
        reference, ref_meta = _study_reference(scene, spec, cfg, cache, bar)
    except Exception as err:  # a broken scene is a result, not the end of the study
        entry.update(status="failed", stage=stage, error=f"{type(err).__name__}: {err}")
        entry.pop("reference", None)
        _write_json(results_path, results)
        bar.update(len(methods) * len(cfg.budgets))
        return
    entry.update(status="ok", reference=ref_meta)
    entry.pop("error", None)
    entry.pop("stage", None)
    _write_json(results_path, results)
    image_dir = out / "images" / spec.name
    image_dir.mkdir(parents=True, exist_ok=True)
    from gdpt.exr import save_image
    from gdpt.images import save_png

    save_image(image_dir / "reference.exr", reference, metadata=ref_meta, force=True)
    save_png(image_dir / "reference.png", reference, force=True)
    for name in methods:
        _evaluate_method(EVAL_METHODS[name], scene, reference, cfg, entry, results,
                         results_path, image_dir, bar)


def _evaluate_method(
    method: EvalMethod, scene: EvalScene, reference: torch.Tensor, cfg: EvaluateConfig,
    entry: dict[str, Any], results: dict[str, Any], results_path: Path, image_dir: Path,
    bar: Any,
) -> None:
    """Calibrate one method on one scene and fill its missing budget cells."""
    from gdpt.exr import save_image
    from gdpt.images import save_png
    from gdpt.metrics import compute_metrics

    info = entry["methods"].setdefault(method.name, {"cells": {}})
    info.setdefault("cells", {})
    todo = [b for b in cfg.budgets if _budget_key(b) not in info["cells"]]
    bar.update(len(cfg.budgets) - len(todo))
    if not todo:
        return
    bar.set_postfix_str(f"{scene.name}/{method.name}: calibrating")
    reason = method.check()
    model = None
    if reason is None:
        try:
            seed = _cell_seed(cfg.seed, scene.name, method.name, "calibration")
            model = calibrate(method, scene, budget=min(todo), seed=seed,
                              probe_fraction=cfg.probe_fraction)
        except MethodUnavailable as err:
            reason = str(err)
        except Exception as err:  # e.g. a model that fails to load, an unsupported plugin
            reason = f"could not run: {type(err).__name__}: {' '.join(str(err).split())}"
    if model is None:
        info.update(status="skipped", note=reason)
        _write_json(results_path, results)
        bar.update(len(todo))
        return
    info.update(status="ok", note=None, calibration=dataclasses.asdict(model))
    for budget in todo:
        key = _budget_key(budget)
        bar.set_postfix_str(f"{scene.name}/{method.name}: {key} s")
        seed = _cell_seed(cfg.seed, scene.name, method.name, key)
        try:
            result, record = run_at_budget(method, scene, model, budget=budget, seed=seed,
                                           tolerance=cfg.tolerance, max_rounds=cfg.max_rounds)
        except Exception as err:  # e.g. out of memory at a large spp: report, retry on resume
            info.setdefault("errors", {})[key] = f"{type(err).__name__}: {err}"
            _write_json(results_path, results)
            bar.update(1)
            continue
        info.get("errors", {}).pop(key, None)
        metrics = compute_metrics(result.image, reference, cfg.metrics,
                                  options=cfg.metric_options)
        record.update(
            budget=budget,
            metrics={k: _finite(v) for k, v in metrics.values.items()},
            skipped_metrics=metrics.skipped,
            nonfinite_pixels=int((~torch.isfinite(result.image)).any(-1).sum()),
            image=f"images/{scene.name}/{method.name}-{key}s.exr",
        )
        save_image(image_dir / f"{method.name}-{key}s.exr", result.image,
                   metadata={"method": method.name, "spp": record["spp"], "budget": budget,
                             "seed": record["seed"]}, force=True)
        save_png(image_dir / f"{method.name}-{key}s.png", result.image, force=True)
        info["cells"][key] = record
        info["calibration"] = dataclasses.asdict(model)
        _write_json(results_path, results)
        bar.update(1)
