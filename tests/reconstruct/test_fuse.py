"""Tests for gdpt.reconstruct.fuse: the fusion against a SciPy sparse direct solve of the same
energy, its limits (exact gradients, unusable gradients), the trust rule, the guards, and the
cross-half error estimate against its expectation."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from gdpt.reconstruct import fuse as F

GEN = torch.Generator().manual_seed(7)


def smooth_image(h: int = 16, w: int = 20) -> torch.Tensor:
    y, x = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    img = torch.stack([0.5 + 0.4 * torch.sin(3 * x + c) * torch.cos(2 * y) for c in range(3)], -1)
    return img.float()


def forward(img: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    dx, dy = torch.zeros_like(img), torch.zeros_like(img)
    dx[:, :-1] = img[:, 1:] - img[:, :-1]
    dy[:-1] = img[1:] - img[:-1]
    return dx, dy


def sparse_solve(d, dx, dy, w_d, w_x, w_y) -> np.ndarray:
    """Minimiser of sum w_d (I - D)^2 + sum w_x (Dx I - dx)^2 + sum w_y (Dy I - dy)^2, per
    channel, by assembling the normal equations in SciPy (independent of the CG solver)."""
    h, w, c = d.shape
    n = h * w
    idx = np.arange(n).reshape(h, w)
    rows, cols, vals = [], [], []
    for r, (a, b) in enumerate(zip(idx[:, :-1].ravel(), idx[:, 1:].ravel(), strict=True)):
        rows += [r, r]
        cols += [a, b]
        vals += [-1.0, 1.0]
    gx = sp.csr_matrix((vals, (rows, cols)), shape=(h * (w - 1), n))
    rows, cols, vals = [], [], []
    for r, (a, b) in enumerate(zip(idx[:-1].ravel(), idx[1:].ravel(), strict=True)):
        rows += [r, r]
        cols += [a, b]
        vals += [-1.0, 1.0]
    gy = sp.csr_matrix((vals, (rows, cols)), shape=((h - 1) * w, n))
    wd = sp.diags(w_d.double().numpy().ravel())
    wx = sp.diags(w_x[:, :-1].double().numpy().ravel())
    wy = sp.diags(w_y[:-1].double().numpy().ravel())
    a = (wd + gx.T @ wx @ gx + gy.T @ wy @ gy).tocsc()
    out = np.empty((h, w, c))
    for ch in range(c):
        rhs = wd @ d[..., ch].double().numpy().ravel()
        rhs += gx.T @ (wx @ dx[:, :-1, ch].double().numpy().ravel())
        rhs += gy.T @ (wy @ dy[:-1, :, ch].double().numpy().ravel())
        out[..., ch] = spla.spsolve(a, rhs).reshape(h, w)
    return out


def test_fusion_equals_a_direct_sparse_solve():
    img = smooth_image()
    d = img + 0.05 * torch.randn(img.shape, generator=GEN)
    dx, dy = forward(img + 0.02 * torch.randn(img.shape, generator=GEN))
    error = 0.002 * (1 + torch.rand(img.shape[:2] + (1,), generator=GEN))
    var_x = 0.001 * (1 + torch.rand(error.shape, generator=GEN))
    var_y = 0.001 * (1 + torch.rand(error.shape, generator=GEN))
    out, info = F.fuse(d, dx, dy, var_x, var_y, error, trust_ratio=4.0, max_iter=2000, tol=1e-7)
    w_d, w_x, w_y, trusted, _ = F.fusion_weights(
        error, var_x, var_y, trust_ratio=4.0, error_floor=1e-8
    )
    assert trusted == 1.0 and info.trusted == 1.0
    expected = sparse_solve(d, dx, dy, w_d, w_x, w_y)
    np.testing.assert_allclose(out.double().numpy(), expected, atol=2e-5)
    # and the fusion moved the image: not a test of the identity
    assert (out - d).abs().max() > 0.01


def test_exact_gradients_with_zero_variance_recover_the_image():
    img = smooth_image()
    d = img + 0.05 * torch.randn(img.shape, generator=GEN)
    dx, dy = forward(img)
    zero = torch.zeros(img.shape[:2] + (1,))
    error = torch.full_like(zero, 0.05**2)
    out, info = F.fuse(d, dx, dy, zero, zero, error, max_iter=2000, tol=1e-8)
    # exact up to the weighted mean error of D (a constant per channel)
    offset = (d - img).mean((0, 1))
    mse_d = float((d - img).square().mean())
    assert float((out - img - offset).square().mean()) < 1e-3 * mse_d
    assert info.guards["weight_ratio_cap"] > 0  # zero variances: weights capped, counted


def test_infinite_gradient_variance_returns_the_denoised_image_exactly():
    img = smooth_image()
    dx, dy = forward(img + torch.randn(img.shape, generator=GEN))
    inf = torch.full(img.shape[:2] + (1,), float("inf"))
    error = torch.full_like(inf, 0.01)
    out, info = F.fuse(img, dx, dy, inf, inf, error)
    assert torch.equal(out, img)
    assert info.trusted == 0.0 and info.guards["variance_nonfinite"] == 2 * inf.numel()


@pytest.mark.parametrize("noise, trusted", [(0.0, 1.0), (1.0, 0.0)])
def test_trust_rule_uses_exact_gradients_and_ignores_noise(noise, trusted):
    img = smooth_image()
    dx, dy = forward(img)
    dx, dy = dx + noise * torch.randn(dx.shape, generator=GEN), dy + noise * torch.randn(dy.shape)
    var = torch.full(img.shape[:2] + (1,), noise**2 / 1.0 + 1e-6)  # the gradients' own variance
    error = torch.full_like(var, 1e-3)  # D's error: far below pure-noise gradients
    _, info = F.fuse(img, dx, dy, var, var, error, trust_ratio=4.0)
    assert info.trusted == trusted


@pytest.mark.parametrize("value", [0.0, 0.7])
def test_constant_and_black_images_give_finite_results_and_count_guards(value):
    img = torch.full((8, 9, 3), value)
    dx, dy = forward(img)
    zero = torch.zeros(8, 9, 1)
    out, info = F.fuse(img, dx, dy, zero, zero, zero, error_floor=1e-6)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, img, atol=1e-6, rtol=0)
    assert info.guards["error_floor"] == zero.numel()  # every zero error was floored


def test_bad_inputs_are_named():
    img = smooth_image()
    dx, dy = forward(img)
    v = torch.ones(img.shape[:2] + (1,))
    with pytest.raises(ValueError, match="var_dx has shape"):
        F.fuse(img, dx, dy, v[:, :-1], v, v)
    with pytest.raises(ValueError, match="error_floor must be > 0"):
        F.fuse(img, dx, dy, v, v, v, error_floor=0.0)


def test_cross_half_error_is_unbiased_for_the_half_denoise_error():
    n, truth = 20000, 0.5
    bias, sd_d, sd_p = 0.1, 0.05, 0.3
    gen = torch.Generator().manual_seed(3)
    shape = (1, n, 3)
    p_a = truth + sd_p * torch.randn(shape, generator=gen)
    p_b = truth + sd_p * torch.randn(shape, generator=gen)
    d_a = truth + bias + sd_d * torch.randn(shape, generator=gen)  # independent of half b
    d_b = truth + bias + sd_d * torch.randn(shape, generator=gen)
    est = F.cross_half_error(d_a, d_b, p_a, p_b, radius=0)
    expected = bias**2 + sd_d**2
    assert abs(float(est.mean()) - expected) < 0.1 * expected
    # the spread of the two half denoises alone sees the variance, not the bias
    assert float((d_a - d_b).square().mean() / 4) < 0.2 * expected


def test_edge_aware_mean_does_not_mix_across_guide_edges():
    x = torch.zeros(8, 8, 1)
    x[:, 4:] = 100.0
    guide = torch.zeros(8, 8, 1)
    guide[:, 4:] = 5.0
    out = F.edge_aware_mean(x, guide, 2, 0.3)
    assert float(out[:, :4].max()) < 1e-6 and float(out[:, 4:].min()) > 100 - 1e-3
    assert float(F.box_mean(x, 2)[:, 3].min()) > 10  # a plain box does mix


@pytest.mark.parametrize(("h", "w", "c", "radius"), [(9, 13, 1, 2), (5, 4, 3, 4), (1, 6, 2, 3)])
def test_edge_aware_mean_is_the_weighted_window_mean(h, w, c, radius):
    """Against the definition, pixel by pixel: neighbours inside the image only (windows
    larger than the image included), weights from the guide difference."""
    x = torch.rand(h, w, c, generator=GEN)
    guide = torch.rand(h, w, 1, generator=GEN)
    out = F.edge_aware_mean(x, guide, radius, 0.3)
    expected = torch.empty_like(x)
    for i in range(h):
        for j in range(w):
            num, den = torch.zeros(c), 0.0
            for k in range(max(0, i - radius), min(h, i + radius + 1)):
                for m in range(max(0, j - radius), min(w, j + radius + 1)):
                    wgt = float(torch.exp(-((guide[k, m, 0] - guide[i, j, 0]) ** 2) / 0.18))
                    num, den = num + wgt * x[k, m], den + wgt
            expected[i, j] = num / den
    torch.testing.assert_close(out, expected, rtol=1e-5, atol=1e-6)


def test_predicted_gain_is_one_without_trusted_gradients_and_below_with_them():
    img = smooth_image()
    error = torch.full(img.shape[:2] + (1,), 1e-3)
    inf = torch.full_like(error, float("inf"))
    assert F.predicted_gain(img, error, inf, inf) == 1.0
    assert F.predicted_gain(img, error, error / 10, error / 10) < 0.1


def test_wrong_statistics_move_no_pixel_beyond_the_trust_region():
    img = smooth_image()
    dx, dy = forward(img + 5.0 * torch.randn(img.shape, generator=GEN))  # pure noise...
    tiny = torch.full(img.shape[:2] + (1,), 1e-6)  # ...claimed exact
    error = torch.full_like(tiny, 1e-4)
    out, info = F.fuse(img, dx, dy, tiny, tiny, error)
    assert float((out - img).abs().max()) <= F.CORRECTION_BOUND * 1e-2 + 1e-6
    assert info.guards["correction_bound"] > 0


@pytest.mark.parametrize("bad", [float("inf"), float("nan")])
def test_nonfinite_variance_is_no_information(bad):
    """A non-finite gradient variance gives that gradient zero weight (it stays ``inf`` through
    the local average, which also leaves it out of its neighbours' averages) and is counted."""
    img = smooth_image()
    dx, dy = forward(img)
    var = torch.full(img.shape[:2] + (1,), 1e-4)
    var[5, 7] = bad
    parts = {"full": img, "a": img + 0.01, "b": img - 0.01}
    stats = F.fusion_statistics(parts.__getitem__, img + 0.01, img - 0.01, var, var.clone())
    assert torch.isinf(stats.var_dx[5, 7]).all() and torch.isinf(stats.var_dy[5, 7]).all()
    finite = torch.isfinite(stats.var_dx)
    assert int((~finite).sum()) == 1
    # its neighbours average only finite variances: the constant, not something smaller
    torch.testing.assert_close(stats.var_dx[finite], torch.full_like(stats.var_dx[finite], 1e-4))
    _, info = F.fuse_statistics(stats, dx, dy)
    assert info.guards["variance_nonfinite"] == 2


def test_the_solves_stop_at_their_iteration_cap():
    """``fuse_statistics`` and ``fuse_checked`` run at most ``iterations`` CG iterations
    (default :data:`SOLVE_ITERATIONS`) where the solve has not converged."""
    img = smooth_image(64, 64)
    dx, dy = forward(img)
    var = torch.full(img.shape[:2] + (1,), 1e-9)
    # D off by a ramp that only exact gradients fix: a long-range correction, slow for CG
    d = img + 0.3 * torch.linspace(0, 1, 64).view(1, 64, 1)
    parts = {"full": d, "a": d + 0.01, "b": d - 0.01}
    stats = F.fusion_statistics(parts.__getitem__, d + 0.01, d - 0.01, var, var.clone())
    assert F.fuse_statistics(stats, dx, dy)[1].cg_iterations == F.SOLVE_ITERATIONS
    assert F.fuse_statistics(stats, dx, dy, iterations=4)[1].cg_iterations == 4
    halves = ((dx, dy), (dx, dy))
    _, info = F.fuse_checked(stats, dx, dy, halves, (img, img), (2.0, 2.0), iterations=5)
    assert info.cg_iterations == 5
