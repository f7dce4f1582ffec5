"""The relMSE ratio of two images without a reference, from an independent plain render.

**The metric.** The study's relMSE of a method's output ``X`` weighs its squared error per pixel
by ``w(I) = 1 / (eps + L_I^2)``, ``L_I`` the channel mean of the true image ``I``
(:func:`gdpt.metrics.relmse`; Rousselle et al. 2011, *Adaptive sampling and reconstruction using
greedy error minimization*; the NGPT convention, ``eps = 1e-3``). In dark pixels (``L_I`` near
``sqrt(eps)``) the weight is up to ``1 / eps``, so dark regions dominate it.

**The estimator.** ``P`` is a plain render (unbiased, independent of every method's output)
rendered as four independent *quarters* ``Q_0 .. Q_3`` (two folds of two halves: fold 1 is
``Q_0``, ``Q_1``). For two of them, ``Q_i`` and ``Q_j``, pooled into ``P_ij`` (``n_ij``
samples), per pixel and channel, for ``X`` independent of both::

    E[(X_c - P_ij,c)^2 - v_ij,c | X] = (X_c - I_c)^2        (v_ij,c = Var(P_ij,c))

(the held-out comparison of :mod:`gdpt.reconstruct.held_out`; Bitterli et al. 2016, NFOR,
sec. 5), with ``v_ij`` from the two quarters: ``E[(Q_i - Q_j)^2] = sigma^2 n_ij / (n_i n_j)``,
``Var(P_ij) = sigma^2 / n_ij`` (:func:`half_variance`, unbiased per pixel; for ``n_i = n_j``
the term is ``(X - Q_i)(X - Q_j)``, the product of two independent errors). The term of pair
``ij`` is weighted by the *other two* quarters ``k``, ``l`` (:func:`plain_weights`)::

    w_kl = 1 / (eps + max(S(L_k) S(L_l), 0))

``L_k``, ``L_l`` their channel means, ``S`` their mean over a square of :data:`WEIGHT_RADIUS`
(0: the pixel alone, ``S(L) = L``). Because the quarters are independent and unbiased,
``E[S(L_k) S(L_l)] = S(L_I)^2`` exactly: the denominator is unbiased for ``eps + S(L_I)^2``
(the square of a noisy mean, ``S(L)^2``, would be biased by ``Var(S(L))``, large in dark noisy
pixels), and the weight is bounded by ``1 / eps``, the largest true weight. ``1 / (eps + u)``
being convex in ``u``, by Jensen's inequality ``E[w] >= 1 / (eps + S(L_I)^2)``, by about
``Var(S(L_k) S(L_l)) / (eps + S(L_I)^2)^3`` (second order in the quarters' noise, capped by the
bound): where a pixel's radiance comes from rare bright paths (a sunlit room's dark corners,
the pixels an emitter's edge crosses) a quarter that missed them makes the weight many times
the true one, a heavy tail that widens the interval. Designs that cut the tail (a larger
square, floors tied to a luminance quantile, to the mean luminance or to the 3x3 px mean, the
3x3 median, OIDN's denoise of the other quarters) blur or lower the weights next to bright
emitters, where the methods' errors concentrate at few samples, and move the estimate off the
reference-weighted ratio there, or do not cut it (``benchmarks/advise_weights.py``); the
unbiased denominator stays. All six pairs of quarters (:data:`PAIRS`, :func:`plain_pairs`)
score ``X``, each weighted by its complement, and the per-pixel estimate is the mean of the six
terms (:func:`cross_fitted_terms`)::

    t_X = mean_ij w_kl (mean_c (X - P_ij)^2 - v_ij)

Since ``w_kl`` is independent of ``Q_i``, ``Q_j`` and of every method's output, each term has
the expectation ``E[w_kl] mean_c (X - I)^2`` per pixel: no cross term between the weights and
the plain image they score against (weights from the same quarters would add
``-2 (X - I) Cov(w, P)`` per pixel, which does not cancel in a difference), and the same
``E[w]`` for every method, so it favours none. Its only bias is ``E[w] - w(I)`` (the blur at
edges with a larger square, and the Jensen term above), the same for every method: the ratio of
two methods' sums is that of their relMSE under the weights ``E[w]``. The six pairs make ``t_X``
a U-statistic of the four quarters (Hoeffding 1948, *A class of statistics with asymptotically
normal distribution*, Ann. Math. Stat. 19): with the error ``d = X - I`` small against ``P``'s
noise (a denoised method against a plain render of about its sample count), the variance of a
pair's term is mostly ``P``'s noise squared, ``s^2`` (``s`` a quarter's variance), and the mean
of six pairs has a third of the ``s^2`` part of the mean of the two folds' pairs alone
(``s^2 / 6`` against ``s^2 / 2`` per pixel, weights aside), the part linear in ``d`` unchanged.
Where it matters: in a sunlit room whose denoised baseline's error is far below ``P``'s noise
(``random:193`` at 128 px, ``P`` and the methods 512 spp), the baseline's estimated error was
often within 2 standard errors of 0 with the folds' pairs alone (an unbounded interval), even
with the reference's own weights in place of ``P``'s, which no weight design can beat
(``benchmarks/advise_weights.py``). Assumptions: ``P``'s samples are independent between pixels
and unbiased (a box pixel filter, an unbiased integrator), radiance is not negative, and the
methods' outputs are independent of ``P``.

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
``1 / n``; :func:`plain_share` estimates that part from the two folds' pairs (fold 1's terms
against fold 2's: ``P``'s noise alone), so a caller can say
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
    "PAIRS",
    "WEIGHT_RADIUS",
    "Z95",
    "RatioEstimate",
    "block_sums",
    "cross_fitted_terms",
    "error_terms",
    "half_variance",
    "lit_blocks",
    "PlainPair",
    "plain_pairs",
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

#: The six pairs of ``P``'s four quarters (fold 1: quarters 0 and 1, fold 2: 2 and 3), as three
#: matchings of two pairs each: each pair's complement (the quarters that weight its terms) is
#: its neighbour, and the first matching is the two folds.
PAIRS = ((0, 1), (2, 3), (0, 2), (1, 3), (0, 3), (1, 2))


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


@dataclass(frozen=True)
class PlainPair:
    """Two of ``P``'s quarters pooled, and the weights of the other two (:func:`plain_pairs`).

    Attributes:
        image: ``(H, W, C)`` the two quarters' pooled mean.
        variance: ``(H, W, 1)`` its :func:`half_variance`.
        weights: ``(H, W, 1)`` :func:`plain_weights` of the other two quarters (independent of
            ``image``).
    """

    image: torch.Tensor
    variance: torch.Tensor
    weights: torch.Tensor


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


def plain_pairs(
    quarters: tuple[torch.Tensor, ...] | list[torch.Tensor],
    counts: tuple[int, ...] | list[int],
    *,
    radius: int = WEIGHT_RADIUS,
    eps: float = EPS,
) -> tuple[PlainPair, ...]:
    """Every pair of :data:`PAIRS` of ``P``'s four independent quarters, pooled, with its
    variance and the weights of its complement (module docstring).

    Args:
        quarters: four ``(H, W, C)`` independent unbiased renders' means (fold 1's halves,
            then fold 2's), any float dtype, one device.
        counts: their sample counts (>= 1 each).
        radius, eps: of :func:`plain_weights`.

    Returns:
        Six :class:`PlainPair`, in the order of :data:`PAIRS`, dtype and device of the
        quarters.

    Raises:
        ValueError: not four quarters, or a quarter without samples.
    """
    if len(quarters) != 4 or len(counts) != 4:
        raise ValueError(f"P needs 4 quarters and 4 counts, got {len(quarters)} and {len(counts)}")
    pairs = []
    for first, second in PAIRS:
        k, m = (q for q in range(4) if q not in (first, second))
        n_1, n_2 = counts[first], counts[second]
        pairs.append(
            PlainPair(
                image=(n_1 * quarters[first] + n_2 * quarters[second]) / (n_1 + n_2),
                variance=half_variance(quarters[first], quarters[second], n_1, n_2),
                weights=plain_weights(quarters[k], quarters[m], radius=radius, eps=eps),
            )
        )
    return tuple(pairs)


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
    image: torch.Tensor, pairs: tuple[PlainPair, ...] | list[PlainPair]
) -> tuple[torch.Tensor, ...]:
    """Each pair's :func:`error_terms` of ``image``, weighted by the pair's complement (module
    docstring): their mean is the per-pixel estimate; the first two terms (fold 1's and fold
    2's, :data:`PAIRS`) differ by ``P``'s noise alone (:func:`plain_share`).

    Args:
        image: ``(H, W, C)`` a method's output, independent of ``P``.
        pairs: :func:`plain_pairs` of ``P`` (or, with a reference in place of every quarter,
            pairs of the reference, zero variance and its :func:`relmse_weights`).

    Returns:
        One ``(H, W, 1)`` float64 term per pair, in its order.
    """
    return tuple(error_terms(image, p.image, p.variance, p.weights) for p in pairs)


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


def plain_share(
    statistic_a: torch.Tensor, statistic_b: torch.Tensor, statistic: torch.Tensor | None = None
) -> float:
    """Share of the variance of ``T_B - rho T_A`` that comes from the plain render ``P``.

    The statistic against one fold (:func:`cross_fitted_terms`' first two terms: the same
    methods' images against fold ``k``, weighted by the other fold) differs between the two
    folds only by ``P``'s noise. For the linear part of that noise (the ``2 w (e_B - rho e_A)
    (P - I)`` term, which dominates where the methods' errors are not small against ``P``'s
    noise), the folds' parts are independent and alike, so the variance of their difference is
    4 times the part in their mean, which is also the linear part of the mean over all pairs
    (each quarter is in half of the pairs); the share is ``sum (d_1 - d_2)^2 / 4`` over the
    block variance of ``statistic``. More samples in ``P`` shrink this part as ``1 / n``; the
    rest shrinks only with more renders of the methods.

    Args:
        statistic_a: ``(n,)`` block sums (:func:`block_sums`) of ``t_B - rho t_A`` against
            fold 1 of ``P`` (replicates concatenated).
        statistic_b: ``(n,)`` the same against fold 2.
        statistic: ``(n,)`` the block sums of the statistic itself (the mean over all pairs);
            ``None``: the folds' mean.

    Returns:
        The share in ``[0, 1]`` (``nan`` where the statistic has no variance).
    """
    n = statistic_a.numel()
    if statistic is None:
        statistic = 0.5 * (statistic_a + statistic_b)
    plain_part = float((statistic_a - statistic_b).double().square().sum()) / 4.0
    total = n * float(statistic.double().var()) if n > 1 else 0.0
    if not total > 0:
        return math.nan
    return min(1.0, plain_part / total)
