"""Statistical comparison of gradient-domain renders with a converged ``path`` reference."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Agreement:
    """z statistics of one buffer against its reference.

    Attributes:
        z: per-pixel z scores (channel-mean difference / standard error).
        z_total: z score of the sum over all pixels (detects a small bias spread everywhere).
    """

    z: np.ndarray
    z_total: float

    @property
    def max_abs_z(self) -> float:
        return float(np.abs(self.z).max())

    def outlier_fraction(self, threshold: float = 3.29) -> float:
        """Fraction of pixels beyond ``threshold`` (3.29: two-sided p = 0.001)."""
        return float((np.abs(self.z) > threshold).mean())


def agreement(test: np.ndarray, ref: np.ndarray, var_test: np.ndarray, var_ref: np.ndarray):
    """Compare ``test`` (H, W, 3) with ``ref`` given variances of the means (H, W)."""
    diff = test.mean(-1) - ref.mean(-1)
    var = var_test + var_ref + 1e-12
    return Agreement(z=diff / np.sqrt(var), z_total=float(diff.sum() / np.sqrt(var.sum())))


def forward_differences(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``dx[:, :-1]`` and ``dy[:-1]`` (the meaningful parts) of an (H, W, C) image."""
    return img[:, 1:] - img[:, :-1], img[1:] - img[:-1]
