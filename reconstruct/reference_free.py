"""The relMSE ratio of two images without a reference, from an independent plain render.

Let ``I`` be the true image, ``X`` a method's output and ``P`` an unbiased plain render of the
same scene, independent of ``X``, with per-channel variance ``v_c = Var(P_c)`` per pixel. Per
pixel and channel::

    E[(X_c - P_c)^2 - v_c | X] = (X_c - I_c)^2

so with the relMSE weight ``w = 1 / (eps + L^2)`` (``L`` the channel mean of a fixed image, the
first method's output here, in place of the reference's that :func:`gdpt.metrics.relmse`
uses), ``t_X = w * mean_c((X_c - P_c)^2 - v_c)`` (:func:`error_terms`) is an unbiased estimate
of ``X``'s weighted squared error in that pixel, and the difference of two methods' terms is
unbiased whatever ``v_c`` (the held-out comparison of :mod:`gdpt.reconstruct.held_out`, with a
third render as the held-out one; Bitterli et al. 2016, NFOR, sec. 5). ``v_c`` comes from two
independent halves ``A``, ``B`` of ``P`` (``n_a`` and ``n_b`` samples):
``E[(A_c - B_c)^2] = sigma^2 n / (n_a n_b)`` and ``Var(P_c) = sigma^2 / n``
(:func:`half_variance`, unbiased per pixel; a render of one sample has no second half).

The image sums ``T_X`` of the terms of two methods ``A`` (baseline) and ``B`` estimate their
relMSE up to the same factor; their ratio ``T_B / T_A`` gets a Fieller interval (Fieller 1954,
*Some problems in interval estimation*, J. R. Stat. Soc. B 16; the set of ``rho`` for which
``T_B - rho T_A`` is within ``z`` standard errors of 0), whose covariances come from the spread
of 8 px block sums, which keeps the spatial correlation of reconstructed images inside each
block (as :func:`gdpt.reconstruct.held_out.choose`). The interval excludes 1 exactly when the
difference ``T_B - T_A`` (unbiased whatever ``v``) is separated from 0 at the same level; it is
unbounded when ``T_A`` is not separated from 0 (no ratio can be told).

How many samples ``P`` needs: the part of a difference's variance that ``P`` adds is
``4 w^2 (e_B - e_A)^2 Var(P)`` per pixel (``e`` the methods' errors), which falls as
``1 / n``; :func:`plain_share` estimates that part from ``P``'s halves, so a caller can say
whether more samples in ``P`` or more replicates of the methods would tighten the interval.

Layout: images ``(H, W, C)`` float tensors on one device; per-pixel maps ``(H, W, 1)``; sums in
float64. Only ``torch`` is imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .held_out import BLOCK, EPS, region_sums

__all__ = [
    "Z95",
    "RatioEstimate",
    "block_sums",
    "error_terms",
    "half_variance",
    "plain_share",
    "ratio_interval",
    "relmse_weights",
]

#: Two-sided 95% quantile of the standard normal (the block sums are many: 256 at 128 px).
Z95 = 1.959963984540054


@dataclass(frozen=True)
class RatioEstimate:
    """The estimated relMSE ratio of a method to a baseline (:func:`ratio_interval`).

    Attributes:
        ratio: ``T_B / T_A`` (``nan`` where ``T_A`` is 0).
        low, high: the 95% Fieller interval (``-inf``, ``inf``: unbounded, the baseline's
            estimated error is not separated from 0).
        z: the difference ``T_B - T_A`` over its standard error (< 0: the method looks better;
            ``nan`` when the standard error is 0).
        blocks: how many block sums the standard errors come from.
    """

    ratio: float
    low: float
    high: float
    z: float
    blocks: int

    @property
    def bounded(self) -> bool:
        """Whether the interval is finite."""
        return math.isfinite(self.low) and math.isfinite(self.high)

    @property
    def separated(self) -> bool:
        """Whether the interval excludes 1 (the difference is separated from 0)."""
        return self.bounded and not self.low <= 1.0 <= self.high


def relmse_weights(image: torch.Tensor, *, eps: float = EPS) -> torch.Tensor:
    """``1 / (eps + L^2)`` per pixel, ``L`` the channel mean of ``image`` ``(H, W, C)`` (the
    denominator of :func:`gdpt.metrics.relmse`): ``(H, W, 1)``, the dtype and device of
    ``image``."""
    return 1.0 / (eps + image.mean(-1, keepdim=True).square())


def half_variance(
    plain_a: torch.Tensor, plain_b: torch.Tensor, samples_a: int, samples_b: int
) -> torch.Tensor:
    """Unbiased per-pixel variance of the pooled mean of two independent halves, channel mean.

    Args:
        plain_a, plain_b: ``(H, W, C)`` the halves' means, any float dtype, one device.
        samples_a, samples_b: their sample counts (>= 1 each).

    Returns:
        ``(H, W, 1)`` ``mean_c (A_c - B_c)^2 n_a n_b / n^2``, dtype and device of ``plain_a``.

    Raises:
        ValueError: a half without samples (a render of one sample: no variance).
    """
    if samples_a < 1 or samples_b < 1:
        raise ValueError(
            f"a half has no samples ({samples_a}, {samples_b}): the variance of a render needs "
            "at least 2 samples per pixel"
        )
    n = samples_a + samples_b
    scale = samples_a * samples_b / n**2
    return (plain_a - plain_b).square().mean(-1, keepdim=True) * scale


def error_terms(
    image: torch.Tensor,
    plain: torch.Tensor,
    plain_variance: torch.Tensor,
    weights: torch.Tensor,
) -> torch.Tensor:
    """Per-pixel unbiased estimate of ``image``'s weighted squared error (module docstring).

    Args:
        image: ``(H, W, C)`` a method's output, independent of ``plain``.
        plain: ``(H, W, C)`` an unbiased plain render.
        plain_variance: ``(H, W, 1)`` the channel mean of ``plain``'s per-channel variance
            (:func:`half_variance`).
        weights: ``(H, W, 1)`` :func:`relmse_weights`.

    Returns:
        ``(H, W, 1)`` float64 ``w (mean_c (X_c - P_c)^2 - v)`` on ``image``'s device.
    """
    squared = (image.double() - plain.double()).square().mean(-1, keepdim=True)
    return weights.double() * (squared - plain_variance.double())


def block_sums(terms: torch.Tensor, *, block: int = BLOCK) -> torch.Tensor:
    """Sums of ``terms`` ``(H, W, 1)`` over ``block`` px squares, flattened: ``(nblocks,)``
    float64 on ``terms``' device (the last row and column of blocks clipped)."""
    return region_sums(terms.double(), block).reshape(-1)


def ratio_interval(
    method_blocks: torch.Tensor, baseline_blocks: torch.Tensor, *, z: float = Z95
) -> RatioEstimate:
    """The ratio of two image sums and its Fieller interval from their block sums.

    With ``a = sum(baseline_blocks)``, ``b = sum(method_blocks)`` and the covariances ``V`` of
    the sums (``n`` times the sample covariance of the ``n`` paired blocks), the interval is
    the set of ``rho`` with ``(b - rho a)^2 <= z^2 (V_bb - 2 rho V_ab + rho^2 V_aa)``: bounded
    when ``a^2 > z^2 V_aa``, else ``(-inf, inf)``; a negative lower end is raised to 0 (the
    ratio of two expected squared errors is not negative).

    Args:
        method_blocks: ``(n,)`` block sums of the method's :func:`error_terms` (replicates
            concatenated).
        baseline_blocks: ``(n,)`` the baseline's, paired with ``method_blocks``.
        z: the normal quantile of the interval (:data:`Z95`).

    Returns:
        The :class:`RatioEstimate`.

    Raises:
        ValueError: shapes differ, or fewer than 2 blocks.
    """
    if method_blocks.shape != baseline_blocks.shape or method_blocks.dim() != 1:
        raise ValueError(
            f"block sums must be paired 1-D tensors, got {tuple(method_blocks.shape)} and "
            f"{tuple(baseline_blocks.shape)}"
        )
    n = method_blocks.numel()
    if n < 2:
        raise ValueError(f"a standard error needs at least 2 blocks, got {n}")
    pair = torch.stack([baseline_blocks.double(), method_blocks.double()])
    a, b = (float(s) for s in pair.sum(-1))
    cov = n * torch.cov(pair)
    v_aa, v_ab, v_bb = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])
    v_diff = v_aa - 2.0 * v_ab + v_bb
    ratio = b / a if a != 0 else math.nan
    z_diff = (b - a) / math.sqrt(v_diff) if v_diff > 0 else math.nan
    c2 = a * a - z * z * v_aa
    c1 = a * b - z * z * v_ab
    c0 = b * b - z * z * v_bb
    discriminant = c1 * c1 - c2 * c0
    if c2 <= 0 or discriminant < 0:
        return RatioEstimate(ratio, -math.inf, math.inf, z_diff, n)
    root = math.sqrt(discriminant)  # errors are >= 0: so is their ratio
    return RatioEstimate(ratio, max(0.0, (c1 - root) / c2), (c1 + root) / c2, z_diff, n)


def plain_share(statistic_a: torch.Tensor, statistic_b: torch.Tensor) -> float:
    """Share of the variance of ``T_B - rho T_A`` that comes from the plain render ``P``.

    The statistic computed against ``P``'s two halves separately (the same methods' images,
    the variance map scaled to each half's count) differs between the halves only by ``P``'s
    noise. For the linear part of that noise (the ``2 w (e_B - rho e_A) (P - I)`` term, which
    dominates), the variance of the halves' difference is 4 times what the full ``P`` adds (for
    halves of equal counts), so the share is ``sum (d_a - d_b)^2 / 4`` over the block variance
    of the statistic (estimated from the halves' average). More samples in ``P`` shrink this
    part as ``1 / n``; the rest shrinks only with more renders of the methods.

    Args:
        statistic_a: ``(n,)`` block sums (:func:`block_sums`) of ``t_B - rho t_A`` against half
            ``a`` of ``P`` (replicates concatenated).
        statistic_b: ``(n,)`` the same against half ``b``.

    Returns:
        The share in ``[0, 1]`` (``nan`` where the statistic has no variance).
    """
    n = statistic_a.numel()
    plain_part = float((statistic_a - statistic_b).double().square().sum()) / 4.0
    total = n * float((0.5 * (statistic_a + statistic_b)).double().var()) if n > 1 else 0.0
    if not total > 0:
        return math.nan
    return min(1.0, plain_part / total)
