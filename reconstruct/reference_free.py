"""The relMSE ratio of two images without a reference, from an independent plain render.

**The metric.** The study's relMSE of a method's output ``X`` weighs its squared error per pixel
by ``w(I) = 1 / (eps + L_I^2)``, ``L_I`` the channel mean of the true image ``I``
(:func:`gdpt.metrics.relmse`; Rousselle et al. 2011, *Adaptive sampling and reconstruction using
greedy error minimization*; the NGPT convention, ``eps = 1e-3``). In dark pixels (``L_I`` near
``sqrt(eps)``) the weight is up to ``1 / eps``, so dark regions dominate it.

**The estimator.** ``P`` is a plain render (unbiased, independent of every method's output)
rendered as two independent *folds* ``P_1``, ``P_2``, each of two independent halves ``a``,
``b`` (four quarters). Per pixel and channel, for ``X`` independent of ``P_k``::

    E[(X_c - P_k,c)^2 - v_k,c | X] = (X_c - I_c)^2        (v_k,c = Var(P_k,c))

(the held-out comparison of :mod:`gdpt.reconstruct.held_out`; Bitterli et al. 2016, NFOR,
sec. 5), with ``v_k`` from the fold's two halves: ``E[(A_c - B_c)^2] = sigma^2 n / (n_a n_b)``,
``Var(P_k,c) = sigma^2 / n`` (:func:`half_variance`, unbiased per pixel). The weights of fold
``k``'s terms come from the *other* fold (:func:`plain_weights`)::

    w_k = 1 / (eps + max(S(L_a) S(L_b), 0))

``L_a``, ``L_b`` the channel means of the other fold's halves, ``S`` their mean over a square of
:data:`WEIGHT_RADIUS` (0: the pixel alone, ``S(L) = L``). Because the halves are independent and
unbiased, ``E[S(L_a) S(L_b)] = S(L_I)^2`` exactly: the denominator is unbiased for ``eps +
S(L_I)^2`` (the square of a noisy mean, ``S(L)^2``, would be biased by ``Var(S(L))``, large in dark
noisy pixels), and the weight is bounded by ``1 / eps``, the largest true weight. A larger square
trades a blur of ``L_I`` at edges for less variance; the blur biases the weights where it counts
most, next to bright emitters (``benchmarks/advise_weights.py`` measures 1x1, 3x3 and 5x5 px, OIDN's
denoise of the other fold and the baseline's output against references). Since ``w_k`` is
independent of ``P_k``, of ``v_k`` and of every method's output, ``t_X = (w_2 (mean_c (X - P_1)^2 -
v_1) + w_1 (mean_c (X - P_2)^2 - v_2)) / 2`` (:func:`cross_fitted_terms`) has the expectation ``E[w]
mean_c (X - I)^2`` per pixel: no cross term between the weights and the plain image they score
against (weights computed from the same ``P`` would add ``-2 (X - I) Cov(w, P)`` per pixel, which
does not cancel in a difference), and the same ``E[w]`` for every method, so it favours none. Its
only bias is ``E[w] - w(I)``: the blur at edges, and, ``1 / (eps + u)`` being convex in ``u``, by
Jensen's inequality ``E[w] >= 1 / (eps + S(L_I)^2)``, by about ``Var(S(L_a) S(L_b)) / (eps +
S(L_I)^2)^3`` (second order in the halves' noise, capped by the bound); both are the same for every
method. Assumptions: ``P``'s samples are independent between pixels and unbiased (a box pixel
filter, an unbiased integrator), radiance is not negative, and the methods' outputs are independent
of ``P``.

Weights taken from a method's own output ``X_A`` (``w(X_A)``, the denominator of the metric
with the output in place of the reference) are not independent of its error: where ``X_A`` is
too bright in a dark pixel its own error is divided by its own brightness and bounded, while
the other method's is not, so such weights favour ``A`` and, on scenes with dark regions, can
order two methods opposite to the reference-weighted relMSE.

**The ratio.** The image sums ``T_X`` of the terms of two methods ``A`` (baseline) and ``B``
estimate their relMSE up to the same factor; their ratio ``T_B / T_A`` gets a Fieller interval
(Fieller 1954, *Some problems in interval estimation*, J. R. Stat. Soc. B 16; the set of
``rho`` for which ``T_B - rho T_A`` is within ``z`` standard errors of 0), whose covariances
come from the spread of 8 px block sums, which keeps the spatial correlation of reconstructed
images inside each block (as :func:`gdpt.reconstruct.held_out.choose`). The interval excludes
1 exactly when the difference ``T_B - T_A`` is separated from 0 at the same level; it is
unbounded when ``T_A`` is not separated from 0 (no ratio can be told). The normal quantile
assumes the difference is spread over many blocks; where it sits in a handful
(fewer lit blocks than :data:`MIN_LIT_BLOCKS`: an image black but for a few lit pixels), the
estimate is not :attr:`~RatioEstimate.separated`.

How many samples ``P`` needs: the part of a difference's variance that ``P`` adds is about
``4 w^2 (e_B - e_A)^2 Var(P)`` per pixel (``e`` the methods' errors), which falls as
``1 / n``; :func:`plain_share` estimates that part from the two folds, so a caller can say
whether more samples in ``P`` or more replicates of the methods would tighten the interval.

Layout: images ``(H, W, C)`` float tensors on one device; per-pixel maps ``(H, W, 1)``; sums in
float64. Only ``torch`` is imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch.nn import functional as F

from .held_out import BLOCK, EPS, region_sums

__all__ = [
    "MIN_LIT_BLOCKS",
    "WEIGHT_RADIUS",
    "Z95",
    "RatioEstimate",
    "block_sums",
    "cross_fitted_terms",
    "error_terms",
    "half_variance",
    "lit_blocks",
    "plain_share",
    "plain_weights",
    "ratio_interval",
    "relmse_weights",
]

#: Two-sided 95% quantile of the standard normal (the block sums are many: 256 at 128 px).
Z95 = 1.959963984540054

#: Radius of the square over which :func:`plain_weights` averages each half's luminance: 0,
#: each pixel alone (a 3x3 px mean has a ninth of the variance but blurs the weights at edges,
#: where bright emitters next to dark surfaces take the weight of the pixels beside them:
#: ``benchmarks/advise_weights.py``).
WEIGHT_RADIUS = 0

#: Fewest lit blocks (:func:`lit_blocks`) for a separated verdict (a 128 px image has 256
#: blocks, 64 px 64): fewer means a handful of pixels carry the difference (an image black but
#: for a few lit pixels) and the normal quantile of the block sums is not justified.
MIN_LIT_BLOCKS = 16


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
        lit: how many of the blocks are lit (:func:`lit_blocks`; ``None``: not counted).
    """

    ratio: float
    low: float
    high: float
    z: float
    blocks: int
    lit: int | None = None

    @property
    def bounded(self) -> bool:
        """Whether the interval is finite."""
        return math.isfinite(self.low) and math.isfinite(self.high)

    @property
    def concentrated(self) -> bool:
        """Whether a handful of lit blocks carry the difference (fewer than
        :data:`MIN_LIT_BLOCKS`): the interval's normal quantile is not justified."""
        return self.lit is not None and self.lit < MIN_LIT_BLOCKS

    @property
    def separated(self) -> bool:
        """Whether the interval excludes 1 (the difference is separated from 0) and is not
        :attr:`concentrated`."""
        return self.bounded and not self.concentrated and not self.low <= 1.0 <= self.high


def relmse_weights(image: torch.Tensor, *, eps: float = EPS) -> torch.Tensor:
    """``1 / (eps + L^2)`` per pixel, ``L`` the channel mean of ``image`` ``(H, W, C)`` (the
    denominator of :func:`gdpt.metrics.relmse`, the reference's weights): ``(H, W, 1)``, the
    dtype and device of ``image``."""
    return 1.0 / (eps + image.mean(-1, keepdim=True).square())


def plain_weights(
    plain_a: torch.Tensor, plain_b: torch.Tensor, *, radius: int = WEIGHT_RADIUS, eps: float = EPS
) -> torch.Tensor:
    """The relMSE weights estimated from two independent unbiased halves of a plain render:
    ``1 / (eps + max(S(L_a) S(L_b), 0))``, ``L`` the channel means, ``S`` their mean over the
    ``(2 radius + 1)^2`` px square around each pixel (edges replicated; module docstring: the
    denominator is unbiased for ``eps + S(L_I)^2``, the weight at most ``1 / eps``).

    Args:
        plain_a, plain_b: ``(H, W, C)`` the halves' means, any float dtype, one device.
        radius: of the square (0: each pixel alone, unbiased for the reference's weight's
            denominator but heavy-tailed at few samples).
        eps: the relMSE ``eps`` (that of :func:`gdpt.metrics.relmse`).

    Returns:
        ``(H, W, 1)`` finite weights in ``(0, 1 / eps]``, dtype and device of ``plain_a``
        (a non-finite product counts as 0: the largest weight).
    """

    def local_mean(image: torch.Tensor) -> torch.Tensor:
        luminance = image.mean(-1)[None, None]
        if radius > 0:
            padded = F.pad(luminance, (radius,) * 4, mode="replicate")
            luminance = F.avg_pool2d(padded, 2 * radius + 1, stride=1)
        return luminance[0, 0, ..., None]

    product = local_mean(plain_a) * local_mean(plain_b)
    product = torch.where(torch.isfinite(product), product, 0.0).clamp_min(0.0)
    return 1.0 / (eps + product)


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
        weights: ``(H, W, 1)`` weights independent of ``plain`` (:func:`plain_weights` of
            another render).

    Returns:
        ``(H, W, 1)`` float64 ``w (mean_c (X_c - P_c)^2 - v)`` on ``image``'s device.
    """
    squared = (image.double() - plain.double()).square().mean(-1, keepdim=True)
    return weights.double() * (squared - plain_variance.double())


def cross_fitted_terms(
    image: torch.Tensor,
    plains: tuple[torch.Tensor, torch.Tensor],
    variances: tuple[torch.Tensor, torch.Tensor],
    weights: tuple[torch.Tensor, torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor]:
    """Each fold's :func:`error_terms` of ``image``, weighted by the *other* fold's weights
    (module docstring); their mean is the per-pixel estimate, their difference is ``P``'s
    noise alone (:func:`plain_share`).

    Args:
        image: ``(H, W, C)`` a method's output, independent of both folds.
        plains: the two folds' ``(H, W, C)`` images (independent unbiased plain renders).
        variances: their ``(H, W, 1)`` :func:`half_variance`.
        weights: their ``(H, W, 1)`` :func:`plain_weights` (or, with a reference in place of
            both folds, its :func:`relmse_weights`).

    Returns:
        ``(t_1, t_2)``: ``(H, W, 1)`` float64 terms against fold 1 (weights of fold 2) and
        against fold 2 (weights of fold 1).
    """
    return (
        error_terms(image, plains[0], variances[0], weights[1]),
        error_terms(image, plains[1], variances[1], weights[0]),
    )


def block_sums(terms: torch.Tensor, *, block: int = BLOCK) -> torch.Tensor:
    """Sums of ``terms`` ``(H, W, 1)`` over ``block`` px squares, flattened: ``(nblocks,)``
    float64 on ``terms``' device (the last row and column of blocks clipped)."""
    return region_sums(terms.double(), block).reshape(-1)


def ratio_interval(
    method_blocks: torch.Tensor,
    baseline_blocks: torch.Tensor,
    *,
    z: float = Z95,
    lit: torch.Tensor | None = None,
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
        lit: ``(n,)`` bool, which blocks are lit (:func:`lit_blocks`; counted into
            :attr:`RatioEstimate.lit`).

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
    count = None if lit is None else int(lit.sum())
    c2 = a * a - z * z * v_aa
    c1 = a * b - z * z * v_ab
    c0 = b * b - z * z * v_bb
    discriminant = c1 * c1 - c2 * c0
    if c2 <= 0 or discriminant < 0:
        return RatioEstimate(ratio, -math.inf, math.inf, z_diff, n, count)
    root = math.sqrt(discriminant)  # errors are >= 0: so is their ratio
    low, high = max(0.0, (c1 - root) / c2), (c1 + root) / c2
    return RatioEstimate(ratio, low, high, z_diff, n, count)


def lit_blocks(plain: torch.Tensor, *, eps: float = EPS, block: int = BLOCK) -> torch.Tensor:
    """Which blocks of ``plain`` ``(H, W, C)`` hold a pixel whose channel mean is above
    ``sqrt(eps)`` (where the relMSE weight is half its largest): ``(nblocks,)`` bool, in the
    order of :func:`block_sums`."""
    lit = (plain.mean(-1, keepdim=True) > math.sqrt(eps)).double()
    return block_sums(lit, block=block) > 0


def plain_share(statistic_a: torch.Tensor, statistic_b: torch.Tensor) -> float:
    """Share of the variance of ``T_B - rho T_A`` that comes from the plain render ``P``.

    The statistic per fold (:func:`cross_fitted_terms`: the same methods' images against fold
    ``k``, weighted by the other fold) differs between the two folds only by ``P``'s noise.
    For the linear part of that noise (the ``2 w (e_B - rho e_A) (P_k - I)`` term, which
    dominates), the folds' parts are independent and alike, so the variance of their
    difference is 4 times the part in their mean (the statistic), and the share is
    ``sum (d_1 - d_2)^2 / 4`` over the block variance of the statistic (estimated from the
    folds' mean). More samples in ``P`` shrink this part as ``1 / n``; the rest shrinks only
    with more renders of the methods.

    Args:
        statistic_a: ``(n,)`` block sums (:func:`block_sums`) of ``t_B - rho t_A`` against
            fold 1 of ``P`` (replicates concatenated).
        statistic_b: ``(n,)`` the same against fold 2.

    Returns:
        The share in ``[0, 1]`` (``nan`` where the statistic has no variance).
    """
    n = statistic_a.numel()
    plain_part = float((statistic_a - statistic_b).double().square().sum()) / 4.0
    total = n * float((0.5 * (statistic_a + statistic_b)).double().var()) if n > 1 else 0.0
    if not total > 0:
        return math.nan
    return min(1.0, plain_part / total)
