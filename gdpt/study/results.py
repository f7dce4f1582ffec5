"""The ``results.json`` schema: format tag, machine and version records, conventions, seeds,
reading (an earlier study's deprecated method names mapped to the current ones), resumable
loading and the atomic write."""

from __future__ import annotations

import json
import math
import os
import platform
import sys
import zlib
from collections.abc import Sequence
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any

import torch

from gdpt.deprecated import EVAL_METHOD_ALIASES
from gdpt.io.atomic import atomic_write
from gdpt.machine import cpu_name
from gdpt.study.config import EvaluateConfig

#: Format 2 adds the cells (``scenes[*]["cell_runs"]``: every method of one budget and
#: replicate seed, :mod:`gdpt.study.cells`), per-replicate load and budget records and
#: ``threads``; the per-method ``cells`` are those of format 1, which is read as it is.
RESULTS_FORMAT = "gdpt-evaluate/2"

#: Formats :func:`read_results` reads (a format-1 study resumes as format 2).
READABLE_FORMATS = ("gdpt-evaluate/1", RESULTS_FORMAT)


#: Config fields that must match for a run directory to be resumed.
_RESUME_KEYS = (
    "protocol",
    "resolution",
    "reference_spp",
    "seed",
    "seeds",
    "max_depth",
    "metrics",
    "metric_options",
    "reference",
)


# ---------------------------------------------------------------------------------- the study
def machine_info() -> dict[str, Any]:
    """CPU model, core counts, memory, OS, load average (a shared machine skews timings)."""
    memory = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                memory = round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return {
        "cpu": cpu_name(),
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
    for dist in ("gdpt", "mitsuba", "drjit", "torch", "numpy", "mitsuba-oidn", "flip-evaluator"):
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
    "seconds": "wall time of sampling + reconstruction after an untimed render at the same spp "
    "(kernel compilation and frozen-pass recording excluded)",
}


def cell_seed(base: int, *parts: str) -> int:
    return (base * 1_000_003 + zlib.crc32("/".join(parts).encode())) % 2**31


def replicate_seed(base: int, scene: str, budget: str, replicate: int) -> int:
    """Seed of replicate ``replicate`` of a cell: the same for every method (paired)."""
    return cell_seed(base, scene, budget, f"replicate-{replicate}")


def budget_key(budget: float) -> str:
    return f"{budget:g}"


def cells_done(
    results: dict[str, Any],
    scenes: Sequence[str] | None = None,
    methods: Sequence[str] | None = None,
    budgets: Sequence[float] | None = None,
) -> int:
    """Number of finished cells in ``results``, among the given scenes, methods and budgets
    (``None``: all of them)."""
    return sum(
        1
        for scene, entry in results.get("scenes", {}).items()
        if scenes is None or scene in scenes
        for method, info in entry.get("methods", {}).items()
        if methods is None or method in methods
        for key in info.get("cells", {})
        if budgets is None or key in {budget_key(b) for b in budgets}
    )


def finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


def write_json(path: Path, data: dict[str, Any]) -> None:
    """Write ``data`` atomically (a crash leaves the previous file intact)."""
    atomic_write(path, json.dumps(data, indent=1))


def read_results(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The content of a ``results.json``, with the methods an earlier study recorded under a
    deprecated name (:data:`gdpt.deprecated.EVAL_METHOD_ALIASES`, e.g. ``gdpt+ngpt``)
    under their current name (``gdpt+oidn-grad``): in the scenes, ``methods`` and
    ``config.methods``.

    Raises:
        ValueError: the file is not a gdpt evaluation (its format tag).
    """
    results = json.loads(Path(path).read_text())
    if results.get("format") not in READABLE_FORMATS:
        raise ValueError(f"{path} is not a gdpt evaluation ({results.get('format')!r})")
    current = EVAL_METHOD_ALIASES
    for entry in [*results.get("scenes", {}).values(), results]:
        if isinstance(entry.get("methods"), dict):
            entry["methods"] = {current.get(k, k): v for k, v in entry["methods"].items()}
    if "methods" in results.get("config", {}):
        results["config"]["methods"] = [current.get(m, m) for m in results["config"]["methods"]]
    return results


def load_results(path: Path, cfg: EvaluateConfig) -> dict[str, Any]:
    """The previous ``results.json`` (:func:`read_results`) if compatible with ``cfg``, else a
    new skeleton."""
    if path.is_file():
        old = read_results(path)
        new = cfg.to_json()
        # studies before protocols: "total"; before --no-reference: with a reference
        made = {"protocol": "total", "reference": True, **old["config"]}
        diff = [k for k in _RESUME_KEYS if made.get(k) != new.get(k)]
        if diff:
            raise ValueError(
                f"{path} was made with different settings ({', '.join(diff)}); use another "
                "--out folder or delete it"
            )
        return {**old, "format": RESULTS_FORMAT}
    return {"format": RESULTS_FORMAT, "scenes": {}, "runs": []}


def study_cost(results: dict[str, Any], before: set[tuple[str, str]], wall: float) -> dict:
    """The cost of one run of a study: ``wall_seconds`` (``wall``), ``timed_seconds`` (the
    seconds of every timed render of the cells it added, redone ones included: the charged
    seconds of each attempt) and ``ratio`` (wall over timed; ``None`` without timed renders).
    ``before``: the ``(scene, cell)`` keys of ``cell_runs`` before the run (left out)."""
    timed = 0.0
    for scene, entry in results.get("scenes", {}).items():
        for unit, record in entry.get("cell_runs", {}).items():
            if (scene, unit) in before:
                continue
            for replicate in record.get("replicates", {}).values():
                attempts = replicate.get("attempts") or [replicate]
                timed += sum(a.get("charged_seconds", a.get("seconds", 0.0)) for a in attempts)
    return {
        "wall_seconds": wall,
        "timed_seconds": timed,
        "ratio": wall / timed if timed > 0 else None,
    }


def cell_keys(results: dict[str, Any]) -> set[tuple[str, str]]:
    """The ``(scene, cell)`` keys of every ``cell_runs`` record in ``results``."""
    return {
        (scene, unit)
        for scene, entry in results.get("scenes", {}).items()
        for unit in entry.get("cell_runs", {})
    }
