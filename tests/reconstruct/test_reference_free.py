"""The reference-free relMSE ratio (:mod:`gdpt.reconstruct.reference_free`): unbiased error
terms, the variance of two halves, and the Fieller interval's coverage of a known ratio, on
synthetic images whose error is known exactly (pure torch, seeded, CPU)."""

from __future__ import annotations

import math

import pytest
import torch
from gdpt.reconstruct.reference_free import (
    PAIRS,
    RatioEstimate,
    block_sums,
    error_terms,
    half_variance,
    plain_pairs,
    plain_share,
    plain_weights,
    ratio_interval,
    relmse_weights,
)

pytestmark = pytest.mark.usefixtures("single_thread")


def scene(generator: torch.Generator, size: int = 32) -> torch.Tensor:
    """A true image ``(size, size, 3)``: smooth gradient times a random tint, in (0.05, 2)."""
    ramp = torch.linspace(0.05, 1.5, size).view(1, size, 1).expand(size, size, 3)
    return ramp * (0.5 + torch.rand(1, 1, 3, generator=generator))


def plain_halves(
    truth: torch.Tensor, sigma: torch.Tensor, counts: tuple[int, int], g: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Two independent unbiased halves of ``counts`` samples of per-sample deviation ``sigma``
    and their pooled mean ``(P, A, B)``."""
    a = truth + sigma / math.sqrt(counts[0]) * torch.randn(truth.shape, generator=g)
    b = truth + sigma / math.sqrt(counts[1]) * torch.randn(truth.shape, generator=g)
    return (counts[0] * a + counts[1] * b) / sum(counts), a, b


class TestHalfVariance:
    def test_cardinality(self):
        v = half_variance(torch.zeros(4, 5, 3), torch.ones(4, 5, 3), 2, 2)
        assert v.shape == (4, 5, 1) and v.dtype == torch.float32

    def test_exception(self):
        with pytest.raises(ValueError, match="at least 2 samples"):
            half_variance(torch.zeros(2, 2, 3), torch.zeros(2, 2, 3), 1, 0)

    @pytest.mark.parametrize("counts", [(4, 4), (3, 2)])
    def test_feature_unbiased(self, counts):
        """The mean over many draws matches ``sigma^2 / n`` per pixel and channel."""
        g = torch.Generator().manual_seed(1)
        truth = torch.full((8, 8, 3), 0.5)
        sigma = torch.tensor([0.3, 0.6, 0.9])
        draws = [
            half_variance(*plain_halves(truth, sigma, counts, g)[1:], *counts) for _ in range(4000)
        ]
        expected = float(sigma.square().mean()) / sum(counts)
        assert float(torch.stack(draws).mean()) == pytest.approx(expected, rel=0.02)


class TestPlainPairs:
    def test_cardinality(self):
        """Six pairs of four quarters, each pair's pooled image, variance and the weights of
        the other two quarters."""
        g = torch.Generator().manual_seed(6)
        quarters = [torch.rand(5, 6, 3, generator=g) for _ in range(4)]
        pairs = plain_pairs(quarters, [3, 1, 2, 2])
        assert len(pairs) == len(PAIRS) == 6
        assert len({frozenset(p) for p in PAIRS}) == 6  # every pair once
        for (i, j), pair in zip(PAIRS, pairs, strict=True):
            k, m = (q for q in range(4) if q not in (i, j))
            counts = [3, 1, 2, 2]
            pooled = (counts[i] * quarters[i] + counts[j] * quarters[j]) / (counts[i] + counts[j])
            assert torch.allclose(pair.image, pooled)
            assert pair.variance.shape == pair.weights.shape == (5, 6, 1)
            assert torch.equal(pair.weights, plain_weights(quarters[k], quarters[m]))

    def test_exception(self):
        with pytest.raises(ValueError, match="4 quarters"):
            plain_pairs([torch.zeros(2, 2, 3)] * 3, [1, 1, 1])
        with pytest.raises(ValueError, match="at least 2 samples"):
            plain_pairs([torch.zeros(2, 2, 3)] * 4, [1, 0, 1, 1])


class TestErrorTerms:
    def test_cardinality(self):
        x = torch.rand(6, 7, 3)
        terms = error_terms(x, x, torch.zeros(6, 7, 1), relmse_weights(x))
        assert terms.shape == (6, 7, 1) and terms.dtype == torch.float64
        assert block_sums(terms, block=4).shape == (4,)

    def test_feature_unbiased(self):
        """The image sum of the terms estimates ``sum w mean_c (X - I)^2`` without bias, and
        the difference of two methods' sums does so whatever the variance subtracted."""
        g = torch.Generator().manual_seed(2)
        truth = scene(g)
        method_a = truth + 0.05 * torch.randn(truth.shape, generator=g)
        method_b = truth * 1.04  # a biased method: its error is known exactly too
        weights = relmse_weights(method_a)
        exact = [
            float((weights * (m - truth).square().mean(-1, keepdim=True)).sum())
            for m in (method_a, method_b)
        ]
        sigma = 0.4 * truth.mean(-1, keepdim=True).sqrt()
        sums, sums_no_variance = [], []
        for _ in range(3000):
            plain, a, b = plain_halves(truth, sigma, (8, 8), g)
            variance = half_variance(a, b, 8, 8)
            sums.append(
                [
                    float(error_terms(m, plain, variance, weights).sum())
                    for m in (method_a, method_b)
                ]
            )
            zero = torch.zeros_like(variance)
            sums_no_variance.append(
                [float(error_terms(m, plain, zero, weights).sum()) for m in (method_a, method_b)]
            )
        mean = torch.tensor(sums, dtype=torch.float64).mean(0)
        stderr = torch.tensor(sums, dtype=torch.float64).std(0) / math.sqrt(len(sums))
        for i in range(2):
            assert abs(float(mean[i]) - exact[i]) < 4 * float(stderr[i]), (mean, exact, stderr)
        biased = torch.tensor(sums_no_variance, dtype=torch.float64)
        assert float(biased[:, 0].mean()) > exact[0] + 10 * float(stderr[0])  # v matters alone
        difference = biased[:, 1] - biased[:, 0]
        spread = float(difference.std()) / math.sqrt(len(difference))
        assert abs(float(difference.mean()) - (exact[1] - exact[0])) < 4 * spread


class TestRatioInterval:
    def test_exception(self):
        with pytest.raises(ValueError, match="paired"):
            ratio_interval(torch.ones(3), torch.ones(4))
        with pytest.raises(ValueError, match="at least 2 blocks"):
            ratio_interval(torch.ones(1), torch.ones(1))

    def test_smoke_exact_ratio(self):
        """Blocks in an exact ratio give that ratio and a zero-width interval around it."""
        base = torch.rand(64, generator=torch.Generator().manual_seed(3), dtype=torch.float64) + 1
        e = ratio_interval(0.5 * base, base)
        assert isinstance(e, RatioEstimate) and e.bounded and e.separated
        assert e.ratio == pytest.approx(0.5) and e.low == pytest.approx(0.5)
        assert e.high == pytest.approx(0.5) and e.z < 0

    def test_feature_unbounded_when_the_baseline_is_not_separated_from_0(self):
        g = torch.Generator().manual_seed(4)
        base = torch.randn(64, generator=g, dtype=torch.float64)
        e = ratio_interval(torch.rand(64, generator=g, dtype=torch.float64), base - base.mean())
        assert not e.bounded and not e.separated

    def test_feature_coverage(self):
        """On 200 seeded synthetic scenes with two methods of spatially correlated error
        (errors constant over 2 px squares) and an independent plain render, the 95% interval
        covers the true ratio of the same images (weights from the baseline's output) in 90% to
        99% of the cases, and is separated from 1 where the ratio is far from it."""
        covered, separated = 0, 0
        trials = 200
        for seed in range(trials):
            g = torch.Generator().manual_seed(100 + seed)
            truth = scene(g)

            def noise(scale: float, g: torch.Generator = g) -> torch.Tensor:
                coarse = scale * torch.randn(16, 16, 3, generator=g)
                return coarse.repeat_interleave(2, 0).repeat_interleave(2, 1)

            base = truth + noise(0.06) * truth
            method = truth + noise(0.045) * truth  # true ratio about 0.56
            weights = relmse_weights(base)
            true = [
                float((weights * (m - truth).square().mean(-1, keepdim=True)).sum())
                for m in (base, method)
            ]
            plain, a, b = plain_halves(truth, 0.3 * truth, (16, 16), g)
            variance = half_variance(a, b, 16, 16)
            blocks = [block_sums(error_terms(m, plain, variance, weights)) for m in (base, method)]
            e = ratio_interval(blocks[1], blocks[0])
            covered += e.low <= true[1] / true[0] <= e.high
            separated += e.separated
        assert 0.90 * trials <= covered <= 0.99 * trials, covered
        assert separated >= 0.9 * trials, separated


class TestPlainShare:
    def test_feature_falls_with_more_plain_samples(self):
        """More samples in ``P``: a smaller share of the statistic's variance from ``P``."""
        g = torch.Generator().manual_seed(5)
        truth = scene(g, 64)
        base = truth * (1 + 0.05 * torch.randn(truth.shape, generator=g))
        method = truth * (1 + 0.03 * torch.randn(truth.shape, generator=g))
        weights = relmse_weights(base)
        shares = []
        for n in (4, 4096):
            _, a, b = plain_halves(truth, 0.5 * truth, (n, n), g)
            variance = half_variance(a, b, n, n) * 2  # each half's
            stats = [
                block_sums(
                    error_terms(method, h, variance, weights)
                    - 0.36 * error_terms(base, h, variance, weights)
                )
                for h in (a, b)
            ]
            shares.append(plain_share(*stats))
        assert 0.0 <= shares[1] < 0.5 < shares[0] <= 1.0, shares
