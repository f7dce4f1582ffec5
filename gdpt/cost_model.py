"""What a render costs in seconds: a linear model per scene and render configuration
(:class:`TimeModel`), fitted from timed probe renders (:func:`fit_by_probing`) and refined by
every timed run, and the kernel compilation to leave out of a timing
(:func:`drain_compile_seconds`).

``seconds(spp) = fixed + per_spp * spp``: the fixed part holds the reconstruction at the film's
size and the launch overheads, the slope the samples. :func:`gdpt.render_and_denoise` reads it
to turn ``seconds=`` into a sample count (:data:`MODELS`, per scene object and configuration);
the study (:mod:`gdpt.study.calibration`) fits and refines the same model per cell.
"""

from __future__ import annotations

import math
import statistics
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import torch


# ----------------------------------------------------------------------------- compilation
def drain_compile_seconds() -> float:
    """Seconds of kernel compilation (code generation and backend) Dr.Jit recorded since the
    last call, clearing its history; 0 unless :data:`drjit.JitFlag.KernelHistory` is on
    (:func:`kernel_history`)."""
    import drjit as dr

    if not dr.flag(dr.JitFlag.KernelHistory):
        return 0.0
    history = dr.kernel_history()
    return sum(k.get("codegen_time", 0.0) + k.get("backend_time", 0.0) for k in history) / 1e3


@contextmanager
def kernel_history() -> Iterator[None]:
    """Dr.Jit's kernel history on inside the block (its previous setting restored after), so
    that :func:`drain_compile_seconds` sees the compilation."""
    import drjit as dr

    flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        yield
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, flag)


# ----------------------------------------------------------------------------------- model
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

    def seconds_for(self, spp: int) -> float:
        """The predicted seconds of ``spp`` samples per pixel."""
        return self.fixed + self.per_spp * spp

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

    def rescale(self, spp: int, seconds: float) -> None:
        """Scale the whole line (and its measurements) so that it passes through ``(spp,
        seconds)``: a timing that shows every earlier one off by one factor (the machine was
        slower or faster for all of them)."""
        scale = seconds / max(self.seconds_for(spp), 1e-12)
        self.fixed *= scale
        self.per_spp *= scale
        self.measurements = [(n, t * scale) for n, t in self.measurements]

    def shifted(self, difference: float) -> TimeModel:
        """This model for a render with another reconstruction, ``difference`` seconds slower
        (or faster): the same seconds per sample, every timing shifted by ``difference``."""
        return TimeModel(
            fixed=max(0.0, self.fixed + difference),
            per_spp=self.per_spp,
            measurements=[(spp, max(1e-9, t + difference)) for spp, t in self.measurements],
        )

    def update(self, spp: int, seconds: float) -> None:
        """Add a timing and refit."""
        refit = TimeModel.fit([*self.measurements, (spp, seconds)])
        self.fixed, self.per_spp, self.measurements = refit.fixed, refit.per_spp, refit.measurements


#: :func:`fit_by_probing` aims each probe at this multiple of its target (a probe that lands
#: just short of the target would take one more, the largest).
PROBE_AIM = 1.2


def fit_by_probing(
    timed: Callable[[int, int], float],
    *,
    budget: float,
    first_spp: int = 1,
    repeats: int = 3,
    probe_fraction: float = 0.5,
    max_probe_spp: int = 1 << 16,
) -> TimeModel:
    """Fit a :class:`TimeModel` from probe timings: the median of ``repeats`` runs at
    ``first_spp`` (1; ``auto`` starts where its pilot runs, whose cost the line must hold),
    then sample counts raised geometrically (x2 to x8, aiming at :data:`PROBE_AIM` times the
    target: the count the line through the timings so far puts there, or the time ratio while
    one count was timed;
    a large fixed cost, such as a reconstruction, then takes fewer probes) until a run takes
    at least ``probe_fraction * budget`` and at least three timings exist (or ``max_probe_spp``
    is reached).

    Args:
        timed: ``timed(spp, seed_offset) -> seconds`` of one run, compilation and pass
            recording excluded (the caller warms the count up); ``seed_offset`` is ``i`` for
            the ``i``-th run at ``first_spp``, else the probe's ``spp``.
        budget: the smallest budget the model will be used for (seconds).
        repeats, probe_fraction, max_probe_spp: see above.

    Returns:
        The least-squares model through the timings.
    """
    t = statistics.median(timed(first_spp, i) for i in range(repeats))
    measurements = [(first_spp, t)]
    spp, target = first_spp, probe_fraction * budget
    aim = PROBE_AIM * target  # a probe just short of the target would take another
    while (t < target or len(measurements) < 3) and spp < max_probe_spp:
        step = aim / max(t, 1e-6)
        if len({n for n, _ in measurements}) > 1:  # aim with the line so far
            line = TimeModel.fit(measurements)
            step = (aim - line.fixed) / line.per_spp / spp
        spp = min(max_probe_spp, spp * min(8, max(2, math.ceil(step))))
        t = timed(spp, spp)
        measurements.append((spp, t))
    return TimeModel.fit(measurements)


# ------------------------------------------------------------------------------ per scene
class SceneModels:
    """Cost models per scene object and configuration key, and the sample counts whose frozen
    passes were recorded (warm: a timed render of them replays), the ``size`` most recently
    used scenes kept (each scene is referenced, so that its id stays unique until
    :meth:`forget`)."""

    def __init__(self, size: int = 8):
        self._models: OrderedDict[int, tuple[Any, dict[str, TimeModel]]] = OrderedDict()
        self._warm: dict[int, set[tuple[str, Hashable]]] = {}
        self._size = size

    def is_warm(self, scene: Any, key: str, spp: Hashable) -> bool:
        """Whether ``spp`` of ``key`` (a count, or what the count's passes depend on) was
        rendered on ``scene`` since it was kept."""
        return (key, spp) in self._warm.get(id(scene), ())

    def mark_warm(self, scene: Any, key: str, spp: Hashable) -> None:
        """Note that ``spp`` of ``key`` was rendered on ``scene`` (the scene is kept)."""
        self._models.setdefault(id(scene), (scene, {}))
        self._warm.setdefault(id(scene), set()).add((key, spp))
        self._trim()

    def _trim(self) -> None:
        while len(self._models) > self._size:
            dropped, _ = self._models.popitem(last=False)
            self._warm.pop(dropped, None)

    def get(self, scene: Any, key: str) -> TimeModel | None:
        """The model of ``key`` on ``scene``, ``None`` before one was set."""
        if id(scene) not in self._models:
            return None
        self._models.move_to_end(id(scene))
        return self._models[id(scene)][1].get(key)

    def set(self, scene: Any, key: str, model: TimeModel) -> None:
        """Keep ``model`` for ``key`` on ``scene``."""
        self._models.setdefault(id(scene), (scene, {}))[1][key] = model
        self._models.move_to_end(id(scene))
        self._trim()

    def forget(self, scene: Any) -> None:
        """Drop every model and warm count of ``scene`` (and the reference to it)."""
        self._models.pop(id(scene), None)
        self._warm.pop(id(scene), None)


#: The models :func:`gdpt.render_and_denoise` fits for ``seconds=`` in this process.
MODELS = SceneModels()
