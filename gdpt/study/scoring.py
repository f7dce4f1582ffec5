"""A study cell's replicates scored against the reference, and their summary.

Each replicate of a cell (one method, scene and budget at one seed) is a record ``{"seed",
"spp", "seconds", "render_seconds", "reconstruct_seconds", ["route"], "metrics",
"companions"}``; the cell's summary is the mean and 95% interval of each metric over its
replicates (:func:`gdpt.statistics.mean_interval`).
"""

from __future__ import annotations

from typing import Any

import torch

from gdpt.statistics import mean_interval
from gdpt.study.config import EvaluateConfig
from gdpt.study.methods import MethodResult
from gdpt.study.results import finite

__all__ = ["interval_too_wide", "replicate_record", "score", "summarise"]


def replicate_record(run: MethodResult, seed: int, spp: int) -> dict[str, Any]:
    """The timing fields of one replicate's record (``route`` where the method chose one)."""
    return {
        "seed": seed,
        "spp": spp,
        "seconds": run.seconds,
        "render_seconds": run.render_seconds,
        "reconstruct_seconds": run.reconstruct_seconds,
        **({"route": run.route} if run.route is not None else {}),
    }


def score(
    replicate: dict[str, Any],
    image: torch.Tensor,
    reference: torch.Tensor | None,
    cfg: EvaluateConfig,
) -> dict[str, str]:
    """Set ``replicate["metrics"]`` (``cfg.metrics``) and ``replicate["companions"]`` (the
    robust companion of each headline metric that has one, :data:`gdpt.metrics.COMPANIONS`)
    of ``image`` against ``reference`` (both ``(H, W, 3)``; ``None``: a study without a
    reference, both empty); returns the metrics skipped, with the reason."""
    from gdpt.metrics import COMPANIONS, compute_metrics

    if reference is None:
        replicate.update(metrics={}, companions={})
        return {}

    values = compute_metrics(image, reference, cfg.metrics, options=cfg.metric_options)
    replicate["metrics"] = {k: finite(v) for k, v in values.values.items()}
    replicate["companions"] = {
        name: finite(function(image, reference))
        for metric, (name, function) in COMPANIONS.items()
        if metric in values.values
    }
    return values.skipped


def interval_too_wide(replicates: list[dict[str, Any]], cfg: EvaluateConfig) -> bool:
    """Whether ``cfg.until_interval`` asks for another replicate: the 95% interval of the
    first metric over ``replicates`` reaches further than that share of its mean (a single
    replicate has no interval: too wide)."""
    if cfg.until_interval is None:
        return False
    values = [r["metrics"].get(cfg.metrics[0]) for r in replicates]
    if None in values or not cfg.reference:
        return False
    mean, low, high = mean_interval(values)
    return len(values) < 2 or max(high - mean, mean - low) > cfg.until_interval * abs(mean)


def summarise(replicates: list[dict[str, Any]]) -> dict[str, Any]:
    """``{"metrics", "interval", "companions"}`` of a cell: per metric (and companion) defined
    in every replicate, the mean and its 95% interval over the scored ``replicates``."""
    summary = {
        k: mean_interval([r["metrics"][k] for r in replicates])
        for k in replicates[0]["metrics"]
        if all(r["metrics"][k] is not None for r in replicates)
    }
    companions = {
        k: mean_interval([r["companions"][k] for r in replicates])
        for k in replicates[0].get("companions", {})
        if all(r["companions"][k] is not None for r in replicates)
    }
    return {
        "metrics": {k: finite(v[0]) for k, v in summary.items()},
        "interval": {k: [finite(v[1]), finite(v[2])] for k, v in summary.items()},
        "companions": {
            k: {"mean": finite(v[0]), "interval": [finite(v[1]), finite(v[2])]}
            for k, v in companions.items()
        },
    }
