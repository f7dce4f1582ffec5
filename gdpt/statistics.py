"""Interval statistics shared by the study (:mod:`gdpt.study`) and training reports
(:mod:`gdpt.training`): the mean of a sample with its two-sided 95% Student-t interval.

A geometric mean of ratios and its interval is :func:`mean_interval` of the log ratios,
exponentiated.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

#: Two-sided 95% quantiles of Student's t for 1..30 degrees of freedom (beyond: normal).
_T975 = (
    12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228,
    2.201, 2.179, 2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086,
    2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042,
)  # fmt: skip


def mean_interval(values: Sequence[float]) -> tuple[float, float, float]:
    """Mean of ``values`` and its two-sided 95% Student-t interval ``(mean, low, high)``
    (``low == high == mean`` for a single value: no interval)."""
    n = len(values)
    mean = sum(values) / n
    if n < 2:
        return mean, mean, mean
    sd = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1))
    half = (_T975[n - 2] if n - 1 <= len(_T975) else 1.96) * sd / math.sqrt(n)
    return mean, mean - half, mean + half
