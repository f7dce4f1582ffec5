"""The weights and pairs of the shared reference-free estimate
(:func:`gdpt.study.estimate.estimate_ratios`, :func:`gdpt.reconstruct.reference_free.plain_pairs`)
on synthetic images whose truth is known: they order two methods that differ only in dark
pixels as the reference-weighted relMSE does (weights from the baseline's own output do not),
their denominator is unbiased, the six pairs of quarters have less variance than the folds'
two, and an image black but for a few lit pixels gives "cannot tell" (pure torch, seeded,
CPU)."""

from __future__ import annotations

import pytest
import torch
from gdpt.reconstruct.held_out import EPS
from gdpt.reconstruct.reference_free import (
    MIN_LIT_BLOCKS,
    PAIRS,
    PlainPair,
    block_sums,
    cross_fitted_terms,
    error_terms,
    plain_weights,
    ratio_interval,
    relmse_weights,
)

from gdpt.advice import MethodAdvice
from gdpt.advice_report import method_line, recommend
from gdpt.study.estimate import estimate_ratios, plain_record

pytestmark = pytest.mark.usefixtures("single_thread")

SIZE = 64


def plain_mean(truth: torch.Tensor, samples: int, g: torch.Generator) -> torch.Tensor:
    """The mean of ``samples`` unbiased non-negative samples per pixel (``truth`` times an
    exponential draw, the same for the three channels, like a grey path's throughput; finite)."""
    uniform = torch.rand((samples, *truth.shape[:2], 1), generator=g)
    draws = -uniform.clamp_min(torch.finfo(uniform.dtype).tiny).log()  # rand can return 0
    return truth * draws.mean(0)


def plain(truth: torch.Tensor, samples: int, g: torch.Generator) -> dict:
    """A :func:`~gdpt.study.estimate.plain_render` record of ``truth``: two folds of two
    halves of ``samples / 4`` samples each."""
    quarter = samples // 4
    folds = [
        (plain_mean(truth, quarter, g), plain_mean(truth, quarter, g), [quarter, quarter])
        for _ in range(2)
    ]
    return plain_record(folds)


def reference_errors(truth: torch.Tensor, images: list[torch.Tensor]) -> list[float]:
    """The reference-weighted squared errors (relMSE times the pixel count)."""
    w = relmse_weights(truth)
    return [float((w * (x - truth).square().mean(-1, keepdim=True)).sum()) for x in images]


def dark_scene(g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(truth, A, B)``: a bright left half (about 1) and a dark right half (0.01); ``A`` and
    ``B`` agree in the bright half (a small error, the same) and differ only in dark pixels:
    ``A`` is 0.1 too bright in a random half of them and exact elsewhere, ``B`` is off by
    about 0.05 in every one. Reference weights find ``A`` worse (ratio B / A about 0.5); the
    weights of ``A``'s output divide ``A``'s dark errors by ``A``'s own brightness and find
    ``B`` worse (about 3)."""
    truth = torch.full((SIZE, SIZE, 3), 0.01)
    truth[:, : SIZE // 2] = 0.8 + 0.4 * torch.rand((SIZE, SIZE // 2, 3), generator=g)
    shared = truth * (1 + 0.02 * torch.randn(truth.shape, generator=g))
    dark = torch.zeros(SIZE, SIZE, 1, dtype=torch.bool)
    dark[:, SIZE // 2 :] = True
    hit = dark & (torch.rand((SIZE, SIZE, 1), generator=g) < 0.5)
    a = torch.where(hit, truth + 0.1, torch.where(dark, truth, shared))
    b_dark = (truth + 0.05 * torch.randn((SIZE, SIZE, 1), generator=g)).clamp_min(0.0)
    b = torch.where(dark, b_dark, shared)
    return truth, a, b


class TestPlainWeights:
    def test_cardinality(self):
        w = plain_weights(torch.rand(5, 6, 3), torch.rand(5, 6, 3))
        assert w.shape == (5, 6, 1) and w.dtype == torch.float32

    def test_exception_black_and_non_finite_halves_give_finite_bounded_weights(self):
        """Black halves (an unlit region) and non-finite ones give the largest weight,
        ``1 / eps``, never more and never a non-finite one."""
        half = torch.zeros(4, 4, 3)
        other = torch.rand(4, 4, 3)
        other[0, 0] = torch.inf
        other[1, 1] = torch.nan
        for radius in (0, 1):
            w = plain_weights(half, other, radius=radius)
            assert bool(torch.isfinite(w).all()) and float(w.max()) == pytest.approx(1 / EPS)
            w = plain_weights(other, other, radius=radius)
            assert bool(torch.isfinite(w).all()) and float(w.max()) <= 1 / EPS * (1 + 1e-6)

    def test_feature_unbiased_denominator(self):
        """Over many draws of a dark pixel's two halves (4 samples each), the denominator's
        mean is ``eps + L^2``; the square of the pooled mean would exceed it by its variance
        (here about 12% of ``L^2``)."""
        g = torch.Generator().manual_seed(7)
        truth = torch.full((64, 64, 3), 0.03)
        denominators, squares = [], []
        for _ in range(50):
            a, b = plain_mean(truth, 4, g), plain_mean(truth, 4, g)
            denominators.append(1 / plain_weights(a, b, radius=0))
            squares.append(EPS + (0.5 * (a + b)).mean(-1, keepdim=True).square())
        expected = EPS + 0.03**2
        assert float(torch.stack(denominators).mean()) == pytest.approx(expected, rel=0.01)
        assert float(torch.stack(squares).mean()) > expected * 1.04


def test_feature_no_cross_term_between_weights_and_p():
    """Two methods with the same squared error, one too bright and one too dark by 0.02 on a
    dark image (0.05): over 40 draws of a noisy ``P`` (16 spp), the estimated difference of
    their error sums is 0 within 4 standard errors; with each pair weighted by its own
    quarters (the weights correlated with the plain image they score against), the too-dark
    method looks better by more than 4."""
    g = torch.Generator().manual_seed(5)
    truth = torch.full((SIZE, SIZE, 3), 0.05)
    bright, dark = truth + 0.02, truth - 0.02
    crossed, same = [], []
    for _ in range(40):
        record = plain(truth, 16, g)
        quarters = [h for f in record["folds"] for h in f["halves"]]
        own = [
            PlainPair(p.image, p.variance, plain_weights(quarters[i], quarters[j]))
            for p, (i, j) in zip(record["pairs"], PAIRS, strict=True)
        ]
        for out, pairs in ((crossed, record["pairs"]), (same, own)):
            sums = [sum(cross_fitted_terms(x, pairs)).sum() for x in (dark, bright)]
            out.append(float(sums[0] - sums[1]))
    for values, biased in ((crossed, False), (same, True)):
        values = torch.tensor(values, dtype=torch.float64)
        z = float(values.mean() / (values.std() / len(values) ** 0.5))
        assert (z < -4) if biased else abs(z) < 4, (biased, z)


def test_feature_six_pairs_less_noise_than_the_folds():
    """A method far better than ``P`` (error 0.01 on a 0.2 image, ``P`` 64 spp of exponential
    samples): over 60 draws of ``P``, the mean of the six pairs' terms and that of the folds'
    two (the first two, each fold weighted by the other) both estimate the method's weighted
    error without bias (4 standard errors), and the six pairs' image sum varies by less than
    0.7 of the folds' (the ``P``-noise-squared part a third: about 0.58)."""
    g = torch.Generator().manual_seed(8)
    truth = torch.full((SIZE, SIZE, 3), 0.2)
    method = truth + 0.01 * torch.randn(truth.shape, generator=g)
    sums = {"six": [], "folds": []}
    for _ in range(60):
        terms = cross_fitted_terms(method, plain(truth, 64, g)["pairs"])
        sums["six"].append(float((sum(terms) / 6).sum()))
        sums["folds"].append(float((0.5 * (terms[0] + terms[1])).sum()))
    values = {k: torch.tensor(v, dtype=torch.float64) for k, v in sums.items()}
    # E[w] is the weight's mean under the quarters' noise: measured with the method exact
    exact = 0.0
    for _ in range(20):
        pairs = plain(truth, 64, g)["pairs"]
        weight = sum(p.weights for p in pairs) / 6
        exact += float((weight * (method - truth).square().mean(-1, keepdim=True)).sum()) / 20
    for v in values.values():
        assert abs(float(v.mean()) - exact) < 4 * float(v.std()) / len(v) ** 0.5, (v.mean(), exact)
    ratio = float(values["six"].std()) / float(values["folds"].std())
    assert ratio < 0.7, ratio


class TestDarkPixels:
    def test_feature_reference_in_place_of_p_has_the_reference_sign(self):
        """The reference in place of both folds (no noise): the estimated difference is the
        reference-weighted one exactly; the weights of the baseline's output give it the
        opposite sign on the same images."""
        g = torch.Generator().manual_seed(11)
        truth, a, b = dark_scene(g)
        exact = reference_errors(truth, [a, b])
        assert exact[1] < 0.7 * exact[0]  # B is better under reference weights
        zero = torch.zeros(SIZE, SIZE, 1)
        record = plain_record([(truth, truth, [1, 1]), (truth, truth, [1, 1])])
        weights = plain_weights(truth, truth, radius=0)  # = relmse_weights(truth)
        record["pairs"] = [PlainPair(truth, zero, weights)] * len(PAIRS)
        ((estimate, _),) = estimate_ratios([[a], [b]], [record])
        assert estimate.ratio == pytest.approx(exact[1] / exact[0], rel=1e-6)
        own = [float(error_terms(x, truth, zero, relmse_weights(a)).sum()) for x in (a, b)]
        assert own[1] > own[0]  # the baseline's own weights order them the other way

    def test_feature_noisy_p_orders_as_the_reference(self):
        """A noisy ``P`` (64 spp): on 6 seeded scenes the estimate is separated below 1 and
        its interval covers the reference-weighted ratio; the same estimator with weights from
        the baseline's output is separated above 1 (it would recommend the worse method)."""
        for seed in range(6):
            g = torch.Generator().manual_seed(20 + seed)
            truth, a, b = dark_scene(g)
            exact = reference_errors(truth, [a, b])
            record = plain(truth, 64, g)
            ((estimate, _),) = estimate_ratios([[a], [b]], [record])
            assert estimate.separated and estimate.high < 1, (seed, estimate)
            assert estimate.low <= exact[1] / exact[0] <= estimate.high, (seed, estimate, exact)
            w = relmse_weights(a)
            own = [
                block_sums(error_terms(x, record["image"], record["variance"], w)) for x in (a, b)
            ]
            wrong = ratio_interval(own[1], own[0])
            assert wrong.separated and wrong.low > 1, (seed, wrong)


def test_exception_black_but_for_a_few_pixels_cannot_tell():
    """Candidates and ``P`` black but in six 8 px blocks, where ``B`` is far better: the
    weights stay finite (``1 / eps`` in the black), the six blocks carry the whole
    difference, so the estimate is not separated and advise says "cannot tell" and
    recommends the baseline, not ``B``."""
    g = torch.Generator().manual_seed(3)
    truth = torch.zeros(SIZE, SIZE, 3)
    truth[8:24, 8:32] = 0.5
    a = truth * (1 + 0.3 * torch.randn(truth.shape, generator=g)).clamp_min(0)
    b = truth * (1 + 0.03 * torch.randn(truth.shape, generator=g)).clamp_min(0)
    record = plain(truth, 256, g)
    for pair in record["pairs"]:
        assert bool(torch.isfinite(pair.weights).all())
        assert float(pair.weights.max()) == pytest.approx(1 / EPS)
    ((estimate, share),) = estimate_ratios([[a], [b]], [record])
    assert estimate.bounded and estimate.high < 1  # the interval alone would say "lower"
    assert estimate.lit < MIN_LIT_BLOCKS and not estimate.separated
    methods = [MethodAdvice("pt+oidn-tuned", 4), MethodAdvice("gdpt+fuse", 4, estimate=estimate)]
    methods[1].plain_share = share
    assert "cannot tell" in method_line(methods[1], "pt+oidn-tuned", 16)
    recommended, lines = recommend(methods)
    assert recommended == "pt+oidn-tuned" and "cannot tell" in lines[0], lines
