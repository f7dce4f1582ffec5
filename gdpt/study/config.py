"""Configuration of the equal-time study: :class:`EvaluateConfig` and its :data:`PRESETS`."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: What a time budget pays for (:func:`gdpt.study.calibration.charged_seconds`).
PROTOCOLS = ("total", "render-time")


@dataclass
class EvaluateConfig:
    """Options of :func:`evaluate`."""

    budgets: tuple[float, ...] = (4.0, 16.0, 64.0)
    """Wall-clock budgets in seconds per image (what they pay for: :attr:`protocol`)."""
    protocol: str = "total"
    """``"total"``: a budget pays for sampling + reconstruction; ``"render-time"``: for
    sampling only, reconstruction time reported beside it (the paper's protocol)."""
    resolution: int = 320
    """Pixels on the long side of the film (the aspect ratio of the scene is kept)."""
    reference_spp: int = 8192
    """Samples per pixel of the path-traced reference."""
    reference_chunk_spp: int = 256
    """The reference is rendered and checkpointed in chunks of this many spp."""
    max_depth: int | None = None
    """Longest path; ``None`` uses the scene's integrator ``max_depth`` (else 6)."""
    metrics: tuple[str, ...] = (
        "relmse",
        "mse",
        "smape",
        "one_minus_ssim",
        "flip_hdr",
        "flip_ldr",
        "elpips",
    )
    """Names from :data:`gdpt.metrics.METRICS`; the first one ranks methods and is plotted."""
    metric_options: dict[str, dict[str, Any]] = field(
        default_factory=lambda: {"elpips": {"samples": 50}}
    )
    """Per-metric keyword options (only for metrics in ``metrics``)."""
    methods: tuple[str, ...] = ()
    """Names from :data:`gdpt.study.methods.EVAL_METHODS`; empty means all registered."""
    seed: int = 0
    """Base seed; every cell and the reference derive distinct seeds from it."""
    seeds: int = 1
    """Replicates per cell, paired across methods (replicate ``r`` of a scene and budget has
    the same seed for every method); a cell reports their mean and a 95% interval."""
    until_interval: float | None = None
    """Add replicates to a cell (paired seeds, up to :attr:`max_seeds`) while the 95% interval
    of its first metric is wider than this share of its mean on either side; ``None``: exactly
    :attr:`seeds` replicates."""
    max_seeds: int = 8
    """Most replicates per cell with :attr:`until_interval`."""
    tolerance: float = 0.05
    """Relative deviation of a cell's calibration run from the budget that triggers a render at
    a re-chosen count (up to :attr:`max_rounds`; the replicates' miss check is
    :data:`~gdpt.study.cells.MISS_TOLERANCE`). At 15% a loaded 2-core machine let two methods'
    counts lean apart by up to a quarter (``benchmarks/study_under_load.py``)."""
    max_rounds: int = 3
    """Renders per cell at most (the first plus corrections)."""
    probe_fraction: float = 0.5
    """The calibration probe aims at this fraction of the smallest budget."""
    reference_dir: Path | None = None
    """Reference cache; ``None`` means ``<out>/references`` (share it between runs)."""
    profile: str = "custom"
    """Name of the preset this config came from (recorded only)."""
    reference: bool = True
    """Render a reference and score against it; off (``gdpt evaluate --no-reference``): the
    cells get only the reference-free estimate of their relMSE ratio to ``pt+oidn-tuned``
    (:mod:`gdpt.study.estimate`), which is recorded beside the true ratio otherwise."""
    keep_going: bool = False
    """Record a failed scene, method or cell and continue; off: the study stops at the first
    failure (:class:`gdpt.study.evaluate.StudyFailure`), after recording it."""

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
        if self.seeds < 1:
            raise ValueError(f"seeds must be >= 1, got {self.seeds}")
        if self.until_interval is not None and not self.until_interval > 0:
            raise ValueError(f"until_interval must be > 0, got {self.until_interval}")
        if self.max_seeds < self.seeds:
            raise ValueError(f"max_seeds ({self.max_seeds}) must be >= seeds ({self.seeds})")
        # options of metrics not requested are dropped (e.g. elpips when --metrics omits it)
        self.metric_options = {k: v for k, v in self.metric_options.items() if k in self.metrics}
        if self.protocol not in PROTOCOLS:
            raise ValueError(f"unknown protocol {self.protocol!r}; valid: {', '.join(PROTOCOLS)}")
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
