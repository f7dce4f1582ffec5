"""Tests for the held-out safeguard of ``fuse`` (gdpt.reconstruct.fuse.fuse_checked and
gdpt.reconstruct.held_out): on synthetic renders with known truth, the fusion gains where the
gradients are exact and costs nothing beyond the tolerance where they are heavy-tailed noise or
where the half buffers are far noisier than the denoise's error."""

from __future__ import annotations

import math

import pytest
import torch
from gdpt.reconstruct import fuse as F
from gdpt.reconstruct import held_out

#: ``fuse`` may be this much worse than its ``D`` (relMSE ratio).
TOLERANCE = 1.03


def texture(h: int = 64, w: int = 64) -> torch.Tensor:
    y, x = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    base = torch.stack([0.5 + 0.3 * torch.sin(9 * x + c) * torch.cos(7 * y) for c in range(3)], -1)
    return (base + 0.3 * ((x * 12).floor() % 2)[..., None]).float()


def forward(img: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    dx, dy = torch.zeros_like(img), torch.zeros_like(img)
    dx[:, :-1] = img[:, 1:] - img[:, :-1]
    dy[:-1] = img[1:] - img[:-1]
    return dx, dy


def relmse(image: torch.Tensor, truth: torch.Tensor) -> float:
    return float(((image - truth).square() / (1e-3 + truth.mean(-1, keepdim=True).square())).mean())


def synthetic(
    seed: int,
    *,
    primal_sd: float,
    gradient_noise,
    reported_sd: float,
    denoise_sd: float | None = None,
):
    """``(truth, D, old fuse, new fuse, info)`` of a synthetic render: two noisy half primals,
    a box-filter denoiser (or, with ``denoise_sd``, the truth plus that much independent error
    per half), half gradients ``exact + gradient_noise(shape, generator)`` whose variance is
    reported as ``reported_sd^2``."""
    gen = torch.Generator().manual_seed(seed)
    truth = texture()
    p_a, p_b = (truth + primal_sd * torch.randn(truth.shape, generator=gen) for _ in range(2))
    if denoise_sd is None:
        parts = {"a": p_a, "b": p_b, "full": 0.5 * (p_a + p_b)}
        parts = {k: F.box_mean(v, 2) for k, v in parts.items()}
    else:
        e_a, e_b = (denoise_sd * torch.randn(truth.shape, generator=gen) for _ in range(2))
        parts = {"a": truth + e_a, "b": truth + e_b, "full": truth + 0.5 * (e_a + e_b)}
    gx, gy = forward(truth)
    halves = tuple(
        (gx + gradient_noise(truth.shape, gen), gy + gradient_noise(truth.shape, gen))
        for _ in range(2)
    )
    dx, dy = (0.5 * (halves[0][i] + halves[1][i]) for i in range(2))
    var = torch.full(truth.shape[:2] + (1,), reported_sd**2)
    stats = F.fusion_statistics(parts.__getitem__, p_a, p_b, var, var.clone())
    old, _ = F.fuse_statistics(stats, dx, dy)
    new, info = F.fuse_checked(stats, dx, dy, halves, (p_a, p_b), (2.0, 2.0))
    return truth, parts["full"], old, new, info


def no_noise(shape, gen):
    return torch.zeros(shape)


def heavy_tailed(shape, gen):
    """Symmetric Lomax (Pareto II) noise with tail index 1.2 (infinite variance), scale 0.02."""
    u = torch.rand(shape, generator=gen).clamp_min(1e-12)
    sign = torch.where(torch.rand(shape, generator=gen) < 0.5, -1.0, 1.0)
    return 0.02 * sign * (u.pow(-1.0 / 1.2) - 1.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_exact_gradients_are_kept_and_gain(seed):
    truth, d, _, new, info = synthetic(
        seed, primal_sd=0.1, gradient_noise=no_noise, reported_sd=1e-4
    )
    assert info.held_out["kept"] == 1.0 and info.held_out["statistic"] < -2.0
    assert relmse(new, truth) < 0.1 * relmse(d, truth)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_heavy_tailed_gradients_cost_nothing_beyond_the_tolerance(seed):
    truth, d, old, new, info = synthetic(
        seed, primal_sd=0.1, gradient_noise=heavy_tailed, reported_sd=0.004
    )
    assert relmse(old, truth) > 1.3 * relmse(d, truth)  # the unchecked fusion loses here
    assert relmse(new, truth) <= TOLERANCE * relmse(d, truth)
    assert info.held_out["kept"] == 0.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_half_buffers_far_noisier_than_the_denoise_cost_nothing(seed):
    """The held-out primal's noise (sd 2) dwarfs ``D``'s error (sd 0.02): the held-out sum
    cannot tell, so ``D`` is kept."""
    truth, d, old, new, info = synthetic(
        seed,
        primal_sd=2.0,
        gradient_noise=lambda shape, gen: 0.05 * torch.randn(shape, generator=gen),
        reported_sd=0.005,
        denoise_sd=0.02,
    )
    assert relmse(old, truth) > 1.3 * relmse(d, truth)
    assert relmse(new, truth) <= TOLERANCE * relmse(d, truth)
    assert info.held_out["statistic"] > -2.0


def test_nonfinite_held_out_terms_are_counted_never_propagated():
    truth, _, _, new, info = synthetic(0, primal_sd=0.1, gradient_noise=no_noise, reported_sd=1e-4)
    gen = torch.Generator().manual_seed(0)
    p_a, p_b = (truth + 0.1 * torch.randn(truth.shape, generator=gen) for _ in range(2))
    p_b[3, 4, 1] = math.nan
    p_a[10, 11, 0] = math.inf
    candidate = truth.clone()
    terms, nonfinite = held_out.held_out_terms(
        candidate, truth, candidate, truth, p_a, p_b, truth.mean(-1, keepdim=True)
    )
    assert nonfinite == 2 and torch.isfinite(terms).all()
    choice = held_out.choose(terms, nonfinite=nonfinite)
    assert choice.nonfinite == 2 and torch.isfinite(held_out.apply(candidate, truth, choice)).all()


def test_a_tile_choice_keeps_the_candidate_only_where_it_is_better():
    gen = torch.Generator().manual_seed(5)
    terms = 0.01 * torch.randn(64, 64, 1, generator=gen)
    terms[:, :32] -= 0.05  # the candidate is better on the left half
    terms[:, 32:] += 0.05
    choice = held_out.choose(terms, tile=32, margin=2.0)
    assert choice.kept == 0.5
    assert bool((choice.keep[:, :32] == 1).all()) and bool((choice.keep[:, 32:] == 0).all())
    assert held_out.choose(terms, tile=0).kept in (0.0, 1.0)


def test_bad_choice_options_are_named():
    terms = torch.zeros(16, 16, 1)
    with pytest.raises(ValueError, match="margin must be >= 0"):
        held_out.choose(terms, margin=-1.0)
    with pytest.raises(ValueError, match="tile must be 0 or a multiple of block 8"):
        held_out.choose(terms, tile=12)


def test_zero_terms_keep_the_baseline():
    choice = held_out.choose(torch.zeros(16, 24, 1))
    assert choice.kept == 0.0 and math.isnan(choice.statistic)


def test_an_image_that_passes_its_own_test_keeps_every_tile():
    gen = torch.Generator().manual_seed(6)
    terms = 0.01 * torch.randn(64, 64, 1, generator=gen) - 0.004
    terms[:32, :32] = 0.01 * torch.randn(32, 32, 1, generator=gen)  # no gain in one tile
    per_tile = held_out.choose(terms, tile=32, margin=2.0)
    gated = held_out.choose(terms, tile=32, margin=2.0, image_margin=2.0)
    assert per_tile.kept < 1.0 and gated.kept == 1.0
