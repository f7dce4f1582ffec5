"""Per-pixel z-tests of gradient-domain estimators against independent oracles.

Every buffer is estimated by ``runs`` independent renders (distinct seeds). Per pixel and channel,

    z = (mean_test - mean_ref) / sqrt(var_test / n_test + var_ref / n_ref),

with the sample variances (ddof 1) of the per-run means, so heavy-tailed per-sample estimates
enter through their run-to-run spread (no per-sample variance estimate is trusted). The gradient
oracle is the forward difference of a converged primal taken per run (``ref[:, 1:] -
ref[:, :-1]``), so its variance includes the correlation of neighbouring pixels. A pixel-channel
where both sides are constant and equal (black background, the zero last column of ``dx``) has
z = 0; the standard error has a floor of float32 rounding (:data:`FLOAT32_ROUNDING` relative).

Two estimators rendered with the same seeds share random numbers (``gdpt`` and ``gdpt_rr`` trace
the same base paths), so their runs are positively correlated and the formula above, which
assumes independence, overstates the standard error of the difference (``|z|`` too small). Such
pairs use :func:`paired_z`: per pixel and channel, the z of the mean of the per-run differences,

    z = mean(d) / sqrt(var(d) / n),   d_i = test_i - ref_i,

which is exact whatever the correlation (the runs, not the two sides, are independent).

Summaries: the share of pixel-channels with ``|z| > 3.29`` (two-sided p = 0.001 for a normal
z) and the largest ``|z|``. Both are calibrated by self-tests of an oracle against itself
(independent seeds), which the suites run next to every comparison.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: |z| above which a pixel-channel counts as an outlier (two-sided p = 0.001).
Z_OUTLIER = 3.29
#: Relative error of a float32 per-pixel mean accumulated in a different order.
FLOAT32_ROUNDING = 1e-5


@dataclass
class PixelZ:
    """Per-pixel z scores of one buffer, shape (H, W, C), with their summaries."""

    z: np.ndarray

    @property
    def share(self) -> float:
        """Fraction of pixel-channels with ``|z| > Z_OUTLIER``."""
        return float((np.abs(self.z) > Z_OUTLIER).mean())

    @property
    def max_abs(self) -> float:
        return float(np.abs(self.z).max())

    def where(self, k: int = 5) -> list[tuple[int, int, int, float]]:
        """The ``k`` largest ``|z|`` as (row, column, channel, z), for failure messages."""
        flat = np.argsort(np.abs(self.z), axis=None)[::-1][:k]
        return [(*map(int, np.unravel_index(i, self.z.shape)), float(self.z.flat[i])) for i in flat]

    def __str__(self) -> str:
        return f"{100 * self.share:.2f}% |z|>{Z_OUTLIER}, max |z| {self.max_abs:.1f}"


def pixel_z(test: np.ndarray, ref: np.ndarray) -> PixelZ:
    """z of ``test`` (runs_t, H, W, C) against ``ref`` (runs_r, H, W, C), run means as samples."""
    if test.shape[1:] != ref.shape[1:]:
        raise ValueError(f"shapes differ: {test.shape[1:]} vs {ref.shape[1:]}")
    if min(len(test), len(ref)) < 2:
        raise ValueError("need at least two runs per side for a variance")
    test = test.astype(np.float64)
    ref = ref.astype(np.float64)
    mean_t, mean_r = test.mean(0), ref.mean(0)
    diff = mean_t - mean_r
    # float32 rounding of the renders: a pixel both sides see as constant (a directly visible
    # emitter) may still differ in the last bits
    rounding = FLOAT32_ROUNDING * np.maximum(np.abs(mean_t), np.abs(mean_r))
    se = np.sqrt(test.var(0, ddof=1) / len(test) + ref.var(0, ddof=1) / len(ref) + rounding**2)
    return _z(diff, se)


def paired_z(test: np.ndarray, ref: np.ndarray) -> PixelZ:
    """z of ``test`` against ``ref``, both (runs, H, W, C) and rendered pairwise with the same
    seeds (run ``i`` of each side from seed ``i``): the mean of the per-run differences over its
    standard error (variance ddof 1)."""
    if test.shape != ref.shape:
        raise ValueError(f"paired runs need equal shapes: {test.shape} vs {ref.shape}")
    if len(test) < 2:
        raise ValueError("need at least two runs for a variance")
    test = test.astype(np.float64)
    ref = ref.astype(np.float64)
    diff = test - ref
    mean = diff.mean(0)
    rounding = FLOAT32_ROUNDING * np.maximum(np.abs(test.mean(0)), np.abs(ref.mean(0)))
    return _z(mean, np.sqrt(diff.var(0, ddof=1) / len(diff) + rounding**2))


def _z(diff: np.ndarray, se: np.ndarray) -> PixelZ:
    """``diff / se``; 0 where both are 0, infinite where only ``se`` is."""
    return PixelZ(
        np.where(se > 0, diff / np.where(se > 0, se, 1.0), np.where(diff == 0, 0.0, np.inf))
    )


def forward_dx(primal: np.ndarray) -> np.ndarray:
    """``dx`` of (runs, H, W, C) images, with the image layout of the integrators' ``dx``
    (last column 0)."""
    dx = np.zeros_like(primal)
    dx[:, :, :-1] = primal[:, :, 1:] - primal[:, :, :-1]
    return dx


def forward_dy(primal: np.ndarray) -> np.ndarray:
    """``dy`` of (runs, H, W, C) images (last row 0)."""
    dy = np.zeros_like(primal)
    dy[:, :-1] = primal[:, 1:] - primal[:, :-1]
    return dy


def render_runs(scene, integrator, runs: int, spp: int, seed: int) -> dict[str, np.ndarray]:
    """``runs`` renders of ``scene`` with a loaded Mitsuba ``integrator``.

    Returns ``{"primal": (runs, H, W, 3)}`` for Mitsuba's own integrators; for ``gdpt`` and
    ``gdpt_rr`` also ``dx`` and ``dy`` (when the integrator traces gradients), float32 numpy.
    """
    out: dict[str, list[np.ndarray]] = {}
    channels = integrator.channels() if hasattr(integrator, "channels") else [("primal", 3)]
    for i in range(runs):
        image = np.array(integrator.render(scene, seed=seed + i, spp=spp))
        start = 0
        for name, c in channels:
            if name in ("primal", "dx", "dy"):
                out.setdefault(name, []).append(image[..., start : start + c])
            start += c
    return {name: np.stack(v) for name, v in out.items()}


@dataclass
class Oracle:
    """Converged reference runs of one scene: the primal and its forward differences."""

    primal: np.ndarray  # (runs, H, W, 3)

    @property
    def dx(self) -> np.ndarray:
        return forward_dx(self.primal)

    @property
    def dy(self) -> np.ndarray:
        return forward_dy(self.primal)

    def compare(self, test: dict[str, np.ndarray]) -> dict[str, PixelZ]:
        """z of every buffer of ``test`` (see :func:`render_runs`) against this oracle."""
        return {name: pixel_z(runs, getattr(self, name)) for name, runs in test.items()}
