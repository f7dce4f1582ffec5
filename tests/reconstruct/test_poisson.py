"""Tests for gdpt.reconstruct.poisson (screened-Poisson L2 / weighted CG / L1 IRLS).

References used here are independent of the code under test: SciPy's FFT DCT, SciPy sparse
direct solves of explicitly assembled constraint matrices, and an LP (SciPy HiGHS) for the
single-channel L1 minimum.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import pytest
import scipy.fft
import scipy.optimize
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from gdpt.reconstruct import poisson
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

ALPHA = 0.2


# ------------------------------------------------------------------------------------------------
# Independent reference helpers (NumPy / SciPy only)
# ------------------------------------------------------------------------------------------------


def forward_diffs(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project convention: dx[y, x] = I[y, x+1] - I[y, x]; dy[y, x] = I[y+1, x] - I[y, x]."""
    dx = np.zeros_like(img)
    dy = np.zeros_like(img)
    dx[:, :-1] = img[:, 1:] - img[:, :-1]
    dy[:-1] = img[1:] - img[:-1]
    return dx, dy


def difference_matrices(h: int, w: int) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Sparse forward differences over valid pixel pairs (row-major pixel index y*w + x)."""
    idx = np.arange(h * w).reshape(h, w)
    rows, cols, vals = [], [], []
    for k, (a, b) in enumerate(zip(idx[:, :-1].ravel(), idx[:, 1:].ravel(), strict=True)):
        rows += [k, k]
        cols += [a, b]
        vals += [-1.0, 1.0]
    dxm = sp.csr_matrix((vals, (rows, cols)), shape=(h * (w - 1), h * w))
    rows, cols, vals = [], [], []
    for k, (a, b) in enumerate(zip(idx[:-1].ravel(), idx[1:].ravel(), strict=True)):
        rows += [k, k]
        cols += [a, b]
        vals += [-1.0, 1.0]
    dym = sp.csr_matrix((vals, (rows, cols)), shape=((h - 1) * w, h * w))
    return dxm, dym


def sparse_weighted_l2(
    p: np.ndarray,
    dx: np.ndarray,
    dy: np.ndarray,
    alpha: float,
    wp: np.ndarray | None = None,
    wx: np.ndarray | None = None,
    wy: np.ndarray | None = None,
) -> np.ndarray:
    """Direct sparse solve of the (weighted) normal equations; per-pixel weights (H, W)."""
    h, w, c = p.shape
    dxm, dym = difference_matrices(h, w)
    wp = np.ones((h, w)) if wp is None else wp
    wx = np.ones((h, w)) if wx is None else wx
    wy = np.ones((h, w)) if wy is None else wy
    wpv = sp.diags(wp.ravel())
    wxv = sp.diags(wx[:, :-1].ravel())
    wyv = sp.diags(wy[:-1].ravel())
    a = alpha**2 * wpv + dxm.T @ wxv @ dxm + dym.T @ wyv @ dym
    out = np.empty_like(p)
    for ch in range(c):
        rhs = (
            alpha**2 * wpv @ p[..., ch].ravel()
            + dxm.T @ (wxv @ dx[:, :-1, ch].ravel())
            + dym.T @ (wyv @ dy[:-1, :, ch].ravel())
        )
        out[..., ch] = spla.spsolve(sp.csc_matrix(a), rhs).reshape(h, w)
    return out


def l1_lp_minimum(p: np.ndarray, dx: np.ndarray, dy: np.ndarray, alpha: float) -> float:
    """Exact single-channel L1 minimum via linear programming: min sum |P x - b|."""
    h, w = p.shape
    n = h * w
    dxm, dym = difference_matrices(h, w)
    pm = sp.vstack([alpha * sp.eye(n), dxm, dym]).tocsr()
    b = np.concatenate([alpha * p.ravel(), dx[:, :-1].ravel(), dy[:-1].ravel()])
    m = pm.shape[0]
    # variables [x (n), t (m)]: minimise sum t subject to -t <= P x - b <= t
    cost = np.concatenate([np.zeros(n), np.ones(m)])
    eye = sp.eye(m)
    a_ub = sp.vstack([sp.hstack([pm, -eye]), sp.hstack([-pm, -eye])]).tocsc()
    b_ub = np.concatenate([b, -b])
    bounds = [(None, None)] * n + [(0, None)] * m
    res = scipy.optimize.linprog(cost, A_ub=a_ub, b_ub=b_ub, bounds=bounds, method="highs")
    assert res.status == 0, res.message
    return float(res.fun)


def reference_group_l1(
    p: np.ndarray, dx: np.ndarray, dy: np.ndarray, alpha: float, rounds: int = 80
) -> np.ndarray:
    """Multi-channel L1 minimiser: IRLS with exact sparse solves and reg -> 1e-9 (NumPy/SciPy)."""
    x = sparse_weighted_l2(p, dx, dy, alpha)
    for k in range(rounds):
        reg = max(0.1 * 0.75**k, 1e-9)
        ep = alpha * np.linalg.norm(x - p, axis=-1)
        ex = np.zeros(p.shape[:2])
        ey = np.zeros(p.shape[:2])
        ex[:, :-1] = np.linalg.norm(x[:, 1:] - x[:, :-1] - dx[:, :-1], axis=-1)
        ey[:-1] = np.linalg.norm(x[1:] - x[:-1] - dy[:-1], axis=-1)
        x = sparse_weighted_l2(p, dx, dy, alpha, 1 / (ep + reg), 1 / (ex + reg), 1 / (ey + reg))
    return x


def rand_problem(
    h: int, w: int, c: int = 3, *, seed: int = 0, noise: float = 0.0, dtype=torch.float32
) -> tuple[np.ndarray, torch.Tensor, torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    img = rng.uniform(0.0, 1.0, (h, w, c))
    dx, dy = forward_diffs(img)
    p = img + noise * rng.standard_normal(img.shape)
    dx = dx + noise * 0.3 * rng.standard_normal(img.shape)
    dy = dy + noise * 0.3 * rng.standard_normal(img.shape)
    return img, *(torch.tensor(t, dtype=dtype) for t in (p, dx, dy))


def g_pt_like(h: int, w: int, *, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Piecewise-smooth image, noisy primal with fireflies, gradients with sparse outliers."""
    rng = np.random.default_rng(seed)
    yy, xx = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
    img = np.stack([0.5 + 0.3 * np.sin(4 * xx), 0.3 + 0.4 * yy, 0.6 - 0.2 * xx * yy], -1)
    img[(xx - 0.5) ** 2 + (yy - 0.5) ** 2 < 0.05] = (2.0, 1.5, 0.2)
    dx, dy = forward_diffs(img)
    p = img + 0.4 * np.sqrt(img) * rng.standard_normal(img.shape)
    p += (rng.random((h, w, 1)) < 0.01) * 20.0
    for d in (dx, dy):
        d += 0.05 * rng.standard_normal(img.shape)
        d += (rng.random((h, w, 1)) < 0.01) * 10.0 * rng.standard_normal((h, w, 1))
    return tuple(torch.tensor(t, dtype=torch.float32) for t in (p, dx, dy))  # type: ignore


# ------------------------------------------------------------------------------------------------
# DCT
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (6, 1), (13, 17), (8, 8), (2, 3, 9, 10)])
def test_dct2_matches_scipy_ortho(shape: tuple[int, ...]) -> None:
    a = np.random.default_rng(1).standard_normal(shape)
    ref = scipy.fft.dctn(a, type=2, axes=(-2, -1), norm="ortho")
    got = poisson.dct2(torch.tensor(a)).numpy()
    np.testing.assert_allclose(got, ref, atol=1e-12)
    back = poisson.idct2(torch.tensor(ref)).numpy()
    np.testing.assert_allclose(back, a, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# Exact recovery and agreement between solvers
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", ["l2", "l2-cg", "l1", "l1-fast"])
def test_exact_inputs_recover_image(method: str) -> None:
    img, p, dx, dy = rand_problem(24, 31, seed=2)
    x = poisson.solve(p, dx, dy, solver=method)
    assert x.dtype == torch.float32 and x.shape == p.shape
    rel = np.linalg.norm(x.numpy() - img) / np.linalg.norm(img)
    assert rel < 1e-4


def test_l1_recovers_image_from_exact_gradients_and_sparsely_corrupted_primal() -> None:
    # Starts away from the answer: the primal (the warm start) has large sparse errors.
    img, _, dx, dy = rand_problem(20, 22, seed=3)
    rng = np.random.default_rng(3)
    p = img + (rng.random(img.shape[:2] + (1,)) < 0.05) * 5.0
    x = poisson.solve_l1(torch.tensor(p, dtype=torch.float64), dx.double(), dy.double())
    assert np.abs(x.numpy() - img).max() < 1e-3
    x2 = poisson.solve_l2(torch.tensor(p, dtype=torch.float64), dx.double(), dy.double())
    assert np.abs(x2.numpy() - img).max() > 0.05  # L2 cannot (sanity of the test itself)


def test_dct_l2_equals_cg_equals_sparse_direct_float64() -> None:
    img, p, dx, dy = rand_problem(13, 17, seed=4, noise=0.5, dtype=torch.float64)
    ref = sparse_weighted_l2(p.numpy(), dx.numpy(), dy.numpy(), ALPHA)
    x_dct = poisson.solve_l2(p, dx, dy, alpha=ALPHA)
    assert x_dct.dtype == torch.float64
    np.testing.assert_allclose(x_dct.numpy(), ref, atol=1e-12, rtol=0)
    for pre in ("none", "jacobi", "dct"):
        x_cg, info = poisson.solve_weighted_cg(
            p, dx, dy, alpha=ALPHA, tol=1e-13, max_iter=2000, precondition=pre, return_info=True
        )
        np.testing.assert_allclose(x_cg.numpy(), ref, atol=1e-9, rtol=0)
        assert info.relative_residual <= 1e-13


def test_dct_l2_float32_close_to_sparse_direct() -> None:
    _, p, dx, dy = rand_problem(13, 17, seed=5, noise=0.5)
    ref = sparse_weighted_l2(*(t.double().numpy() for t in (p, dx, dy)), ALPHA)
    x = poisson.solve_l2(p, dx, dy)
    assert x.dtype == torch.float32
    np.testing.assert_allclose(x.numpy(), ref, atol=2e-5 * np.abs(ref).max(), rtol=0)


def test_weighted_cg_matches_sparse_weighted_solve() -> None:
    _, p, dx, dy = rand_problem(11, 9, seed=6, noise=0.5, dtype=torch.float64)
    rng = np.random.default_rng(6)
    wp, wx, wy = (rng.uniform(0.01, 10.0, (11, 9)) for _ in range(3))
    ref = sparse_weighted_l2(p.numpy(), dx.numpy(), dy.numpy(), 0.3, wp, wx, wy)
    x = poisson.solve_weighted_cg(
        p,
        dx,
        dy,
        alpha=0.3,
        weights_primal=torch.tensor(wp)[..., None],
        weights_dx=torch.tensor(wx)[..., None],
        weights_dy=torch.tensor(wy)[..., None],
        tol=1e-13,
        max_iter=5000,
    )
    np.testing.assert_allclose(x.numpy(), ref, atol=1e-9, rtol=0)


def test_alpha_enters_squared() -> None:
    alpha = 0.35
    _, p, dx, dy = rand_problem(9, 12, c=1, seed=7, noise=1.0, dtype=torch.float64)
    x = poisson.solve_l2(p, dx, dy, alpha=alpha)[..., 0].numpy().ravel()
    dxm, dym = difference_matrices(9, 12)
    lap = dxm.T @ dxm + dym.T @ dym
    g = dxm.T @ dx[:, :-1, 0].numpy().ravel() + dym.T @ dy[:-1, :, 0].numpy().ravel()
    pv = p[..., 0].numpy().ravel()

    def normal_residual(s: float) -> float:
        return float(np.abs((s * sp.eye(lap.shape[0]) + lap) @ x - s * pv - g).max())

    assert normal_residual(alpha**2) < 1e-10
    assert normal_residual(alpha) > 1e-3  # linear alpha would be a different problem
    # The energy helper uses alpha^2 as well, and x minimises it.
    e = poisson.l2_energy(torch.tensor(x.reshape(9, 12, 1)), p, dx, dy, alpha=alpha)
    rx, ry = dxm @ x - dx[:, :-1, 0].numpy().ravel(), dym @ x - dy[:-1, :, 0].numpy().ravel()
    hand = alpha**2 * np.sum((x - pv) ** 2) + np.sum(rx**2) + np.sum(ry**2)
    assert e == pytest.approx(hand, rel=1e-12)
    bumped = torch.tensor(x.reshape(9, 12, 1)) + 1e-3
    assert poisson.l2_energy(bumped, p, dx, dy, alpha=alpha) > e


def test_unused_last_column_and_row_have_no_effect() -> None:
    _, p, dx, dy = rand_problem(10, 14, seed=8, noise=0.3)
    dx2, dy2 = dx.clone(), dy.clone()
    dx2[:, -1] = 1e3
    dy2[-1, :] = -1e3
    for method in ("l2", "l1-fast"):
        a = poisson.solve(p, dx, dy, solver=method)
        b = poisson.solve(p, dx2, dy2, solver=method)
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert poisson.l1_energy(p, p, dx, dy) == poisson.l1_energy(p, p, dx2, dy2)


def test_gradient_sign_convention() -> None:
    # A horizontal ramp increasing to the right has dx = +1; a flat primal must be pulled up
    # on the right and down on the left.
    h, w = 5, 8
    p = torch.zeros(h, w, 1)
    dx = torch.ones(h, w, 1)
    dy = torch.zeros(h, w, 1)
    x = poisson.solve_l2(p, dx, dy)
    assert torch.all(x[:, 1:] > x[:, :-1])
    assert float(x.mean()) == pytest.approx(0.0, abs=1e-5)  # the screening keeps the mean


# ------------------------------------------------------------------------------------------------
# L1 behaviour
# ------------------------------------------------------------------------------------------------


def test_l1_beats_l2_on_sparse_gradient_outliers() -> None:
    img, _, dx, dy = rand_problem(32, 40, seed=9, dtype=torch.float64)
    rng = np.random.default_rng(9)
    p = torch.tensor(img + 0.05 * rng.standard_normal(img.shape))
    for d in (dx, dy):
        mask = torch.tensor(rng.random((32, 40, 1)) < 0.03)
        d += mask * torch.tensor(rng.choice([-8.0, 8.0], size=(32, 40, 1)))
    err = {}
    for method in ("l2", "l1", "l1-fast"):
        x = poisson.solve(p, dx, dy, solver=method).numpy()
        err[method] = np.sqrt(np.mean((x - img) ** 2))
    assert err["l1"] < 0.3 * err["l2"]
    assert err["l1-fast"] < 0.3 * err["l2"]


def test_fast_preset_energy_not_above_reference_preset() -> None:
    p, dx, dy = g_pt_like(48, 64, seed=10)
    x_ref, info_ref = poisson.solve_l1(p, dx, dy, preset="l1", return_info=True)
    x_fast, info_fast = poisson.solve_l1(p, dx, dy, preset="fast", return_info=True)
    e_ref = poisson.l1_energy(x_ref, p, dx, dy)
    e_fast = poisson.l1_energy(x_fast, p, dx, dy)
    assert info_ref.energy == pytest.approx(e_ref, rel=1e-5)
    assert e_fast <= e_ref * (1 + 1e-4)
    assert info_fast.cg_iterations < 0.3 * info_ref.cg_iterations
    # Both are far below the L2 solution's L1 energy.
    assert e_fast < 0.9 * poisson.l1_energy(poisson.solve_l2(p, dx, dy), p, dx, dy)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fast_preset_robust_to_huge_outliers(dtype: torch.dtype) -> None:
    # Exact data plus two outliers 1e5x the signal: the L2 start spreads them over the whole
    # image; the fast preset's adaptive early rounds must remove that completely.
    img, p, dx, dy = rand_problem(8, 9, seed=16, dtype=dtype)
    dx[2, 3] = 1e5
    p[4, 4] = -1e5
    x = poisson.solve_l1(p, dx, dy, preset="fast")
    np.testing.assert_allclose(x.numpy(), img, atol=1e-3)
    p[4, 4], dx[2, 3] = -1e3, 1e3  # the reference schedule copes with milder outliers
    x = poisson.solve_l1(p, dx, dy, preset="l1")
    np.testing.assert_allclose(x.numpy(), img, atol=1e-3)


def test_l1_presets_close_to_lp_minimum_single_channel() -> None:
    rng = np.random.default_rng(11)
    img = rng.uniform(0, 1, (7, 9))
    dx, dy = forward_diffs(img)
    p = img + 0.3 * rng.standard_normal(img.shape)
    dx += (rng.random(img.shape) < 0.1) * rng.standard_normal(img.shape) * 3
    dy += 0.05 * rng.standard_normal(img.shape)
    e_min = l1_lp_minimum(p, dx, dy, ALPHA)
    pt, dxt, dyt = (torch.tensor(t) for t in (p, dx, dy))  # (H, W) single-channel layout
    for preset in ("l1", "fast"):
        x = poisson.solve_l1(pt, dxt, dyt, preset=preset)
        assert x.shape == (7, 9)
        e = poisson.l1_energy(x, pt, dxt, dyt)
        assert e_min - 1e-9 <= e <= e_min * 1.01


def test_l1_presets_close_to_group_l1_minimum_rgb() -> None:
    # Multi-channel: the IRLS weights must use the Euclidean norm of each RGB constraint.
    rng = np.random.default_rng(24)
    img = rng.uniform(0, 1, (8, 9, 3))
    dx, dy = forward_diffs(img)
    p = img + 0.3 * rng.standard_normal(img.shape)
    for d in (dx, dy):
        d += (rng.random((8, 9, 1)) < 0.15) * rng.standard_normal((8, 9, 3)) * 2
        d += 0.05 * rng.standard_normal(img.shape)
    t = [torch.tensor(a) for a in (p, dx, dy)]
    e_min = poisson.l1_energy(torch.tensor(reference_group_l1(p, dx, dy, ALPHA)), *t)
    for preset in ("l1", "fast"):
        e = poisson.l1_energy(poisson.solve_l1(*t, preset=preset), *t)
        assert e_min * (1 - 1e-6) <= e <= e_min * (1 + 1.5e-3)


def test_l1_energy_matches_hand_computation_with_channel_norms() -> None:
    _, p, dx, dy = rand_problem(5, 6, seed=12, noise=0.5, dtype=torch.float64)
    x = torch.tensor(np.random.default_rng(12).standard_normal((5, 6, 3)))
    xn, pn, dxn, dyn = (t.numpy() for t in (x, p, dx, dy))
    ep = ALPHA * np.linalg.norm(xn - pn, axis=-1).sum()
    ex = np.linalg.norm((xn[:, 1:] - xn[:, :-1]) - dxn[:, :-1], axis=-1).sum()
    ey = np.linalg.norm((xn[1:] - xn[:-1]) - dyn[:-1], axis=-1).sum()
    assert poisson.l1_energy(x, p, dx, dy) == pytest.approx(ep + ex + ey, rel=1e-12)


# ------------------------------------------------------------------------------------------------
# Property tests
# ------------------------------------------------------------------------------------------------

_dims = st.integers(min_value=1, max_value=12)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(h=_dims, w=_dims, c=st.integers(1, 4), seed=st.integers(0, 2**16))
def test_property_l2_solves_normal_equations(h: int, w: int, c: int, seed: int) -> None:
    _, p, dx, dy = rand_problem(h, w, c, seed=seed, noise=1.0, dtype=torch.float64)
    ref = sparse_weighted_l2(p.numpy(), dx.numpy(), dy.numpy(), ALPHA)
    x = poisson.solve_l2(p, dx, dy)
    np.testing.assert_allclose(x.numpy(), ref, atol=1e-10, rtol=0)
    x32 = poisson.solve_l2(p.float(), dx.float(), dy.float())
    assert x32.dtype == torch.float32 and x32.shape == (h, w, c)
    np.testing.assert_allclose(x32.numpy(), ref, atol=1e-4 * max(1.0, np.abs(ref).max()))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(h=_dims, w=_dims, seed=st.integers(0, 2**16), shift=st.floats(-50, 50))
def test_property_l1_fast_finite_and_shift_equivariant(
    h: int, w: int, seed: int, shift: float
) -> None:
    _, p, dx, dy = rand_problem(h, w, 3, seed=seed, noise=1.0, dtype=torch.float64)
    x = poisson.solve_l1(p, dx, dy, preset="fast")
    assert torch.isfinite(x).all() and x.shape == p.shape
    # A constant offset of the primal moves the minimiser by that constant (gradients unchanged).
    x2 = poisson.solve_l1(p + shift, dx, dy, preset="fast")
    e1 = poisson.l1_energy(x, p, dx, dy)
    e2 = poisson.l1_energy(x2 - shift, p, dx, dy)
    assert e2 == pytest.approx(e1, rel=1e-3, abs=1e-6)
    # The L1 energy never ends above that of the L2 solution it started from.
    el2 = poisson.l1_energy(poisson.solve_l2(p, dx, dy), p, dx, dy)
    assert e1 <= el2 * (1 + 1e-6) + 1e-9


@pytest.mark.parametrize("shape", [(1, 1, 3), (1, 9, 3), (9, 1, 3), (1, 2, 1), (2, 1, 2)])
@pytest.mark.parametrize("method", list(poisson.SOLVERS))
def test_degenerate_thin_images_work(shape: tuple[int, int, int], method: str) -> None:
    img, p, dx, dy = rand_problem(*shape, seed=13)
    x = poisson.solve(p, dx, dy, solver=method)
    assert x.shape == shape and torch.isfinite(x).all()
    np.testing.assert_allclose(x.numpy(), img, atol=1e-4)  # exact data -> exact answer
    if shape[:2] == (1, 1):  # no gradient constraints at all: x = primal
        torch.testing.assert_close(x, p)


def test_batched_input_equals_separate_solves() -> None:
    probs = [g_pt_like(12, 16, seed=s) for s in (20, 21)]
    p, dx, dy = (torch.stack([pr[i] for pr in probs]) for i in range(3))
    for method in ("l2", "l1-fast"):
        xb = poisson.solve(p, dx, dy, solver=method)
        for i, pr in enumerate(probs):
            xi = poisson.solve(*pr, solver=method)
            torch.testing.assert_close(xb[i], xi, rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------------------------------------
# Dtypes, scale, dispatcher
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("dtype", "expected"),
    [
        (torch.float32, torch.float32),
        (torch.float64, torch.float64),
        (torch.float16, torch.float32),
    ],
)
def test_output_dtype(dtype: torch.dtype, expected: torch.dtype) -> None:
    _, p, dx, dy = rand_problem(6, 7, seed=14, noise=0.2)
    for method in poisson.SOLVERS:
        x = poisson.solve(p.to(dtype), dx.to(dtype), dy.to(dtype), solver=method)
        assert x.dtype == expected


@pytest.mark.parametrize("scale", [2.0**-100, 2.0**60])
def test_scale_equivariance_and_no_overflow(scale: float) -> None:
    _, p, dx, dy = rand_problem(10, 12, seed=15, noise=0.5)
    ps, dxs, dys = p * scale, dx * scale, dy * scale
    x = poisson.solve_l2(p, dx, dy)
    xs = poisson.solve_l2(ps, dxs, dys)
    assert torch.isfinite(xs).all()
    torch.testing.assert_close(xs / scale, x, rtol=1e-4, atol=1e-5)
    # IRLS regularisers are absolute (image units, as in the reference), so L1 is equivariant
    # only when the regulariser is scaled along; without that the results differ.
    for name in ("l1", "fast"):
        pr = poisson.L1_PRESETS[name]
        pr_s = dataclasses.replace(pr, reg_init=pr.reg_init * scale)
        x = poisson.solve_l1(p, dx, dy, preset=pr)
        xs = poisson.solve_l1(ps, dxs, dys, preset=pr_s)
        assert torch.isfinite(xs).all()
        torch.testing.assert_close(xs / scale, x, rtol=1e-4, atol=1e-5)
    xu = poisson.solve_l1(ps, dxs, dys, preset="fast") / scale
    assert not torch.allclose(xu, x, rtol=1e-3, atol=1e-3)


def test_huge_values_give_finite_output() -> None:
    img, p, dx, dy = rand_problem(8, 9, seed=16)
    for big in (1e10, 3e38):
        ph, dxh = p.clone(), dx.clone()
        dxh[2, 3] = big
        ph[4, 4] = -big
        for method in ("l2", "l2-cg"):
            x = poisson.solve(ph, dxh, dy, solver=method)
            assert torch.isfinite(x).all()
            assert float(x[4, 4].max()) < -big / 1e3  # the data were used, not flushed to zero
        for method in ("l1", "l1-fast"):
            # (Robustness of L1 to large outliers: test_fast_preset_robust_to_huge_outliers.)
            x = poisson.solve(ph, dxh, dy, solver=method)
            assert torch.isfinite(x).all()


def test_reconstruct_progress_and_info() -> None:
    _, p, dx, dy = rand_problem(8, 10, seed=17, noise=0.3)
    calls: list[tuple[int, int]] = []
    x, info = poisson.solve(
        p, dx, dy, solver="l1-fast", progress=lambda d, t: calls.append((d, t)), return_info=True
    )
    rounds = poisson.L1_PRESETS["fast"].rounds
    assert calls == [(k, rounds) for k in range(1, rounds + 1)]
    assert info.solver == "l1-fast" and info.preset == "fast"
    assert info.energy == pytest.approx(poisson.l1_energy(x, p, dx, dy), rel=1e-5)
    assert info.n_missing == {"primal": 0, "dx": 0, "dy": 0}


# ------------------------------------------------------------------------------------------------
# Non-finite inputs
# ------------------------------------------------------------------------------------------------


def test_nonfinite_constraints_are_dropped_l2() -> None:
    _, p, dx, dy = rand_problem(9, 11, seed=18, noise=0.5, dtype=torch.float64)
    p[3, 4, 1] = math.nan
    dx[5, 2, 0] = math.inf
    dy[1, 7, 2] = -math.inf
    dy[8, 3, 0] = math.nan  # last row: not a constraint anyway
    with pytest.warns(poisson.NonFiniteInputWarning, match="1 primal, 1 dx, 1 dy"):
        x, info = poisson.solve_l2(p, dx, dy, tol=1e-12, return_info=True)
    assert info.n_missing == {"primal": 1, "dx": 1, "dy": 1}
    assert torch.isfinite(x).all()
    wp, wx, wy = np.ones((9, 11)), np.ones((9, 11)), np.ones((9, 11))
    wp[3, 4] = poisson.MISSING_PRIMAL_WEIGHT
    wx[5, 2] = 0.0
    wy[1, 7] = 0.0
    # Policy: a constraint with any non-finite channel is dropped as a whole.
    clean = [t.numpy().copy() for t in (p, dx, dy)]
    for t in clean:
        t[~np.isfinite(t).all(axis=-1)] = 0.0
    ref = sparse_weighted_l2(*clean, ALPHA, wp, wx, wy)
    np.testing.assert_allclose(x.numpy(), ref, atol=1e-8, rtol=0)


@pytest.mark.parametrize("method", list(poisson.SOLVERS))
def test_nonfinite_everywhere_never_returns_nan(method: str) -> None:
    img, p, dx, dy = rand_problem(10, 10, seed=19)
    rng = np.random.default_rng(19)
    for t in (p, dx, dy):
        t[torch.tensor(rng.random(t.shape) < 0.2)] = math.nan
    with pytest.warns(poisson.NonFiniteInputWarning):
        x = poisson.solve(p, dx, dy, solver=method)
    assert torch.isfinite(x).all()
    # The remaining data are exact and consistent, so every pixel with a present primal sample
    # is still recovered (pixels with no information at all go to 0 - nothing to recover).
    present = torch.isfinite(p).all(-1).numpy()
    assert present.mean() > 0.3
    np.testing.assert_allclose(x.numpy()[present], img[present], atol=1e-3)
    allnan = torch.full_like(p, math.nan)
    with pytest.warns(poisson.NonFiniteInputWarning):
        x = poisson.solve(allnan, allnan, allnan, solver=method)
    assert torch.isfinite(x).all()


def test_finite_inputs_whose_sum_overflows_are_not_missing() -> None:
    """The finiteness check sums first; finite float32 values whose sum overflows are still
    checked value by value: nothing missing, no warning."""
    _, p, dx, dy = rand_problem(6, 7, seed=23)
    p[:2] = 3e38
    assert not torch.isfinite(p.sum())
    with warnings.catch_warnings():
        warnings.simplefilter("error", poisson.NonFiniteInputWarning)
        _, info = poisson.solve_l2(p, dx, dy, return_info=True)
    assert info.n_missing == {"primal": 0, "dx": 0, "dy": 0}


def test_missing_single_pixel_filled_from_gradients_l1() -> None:
    img, p, dx, dy = rand_problem(12, 12, seed=22)
    p[6, 6] = math.inf
    with pytest.warns(poisson.NonFiniteInputWarning):
        x = poisson.solve_l1(p, dx, dy, preset="fast")
    assert abs(float(x[6, 6, 0]) - img[6, 6, 0]) < 1e-3


# ------------------------------------------------------------------------------------------------
# Bad input
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("alpha", [0.0, -0.2, math.nan, math.inf])
@pytest.mark.parametrize("method", list(poisson.SOLVERS))
def test_bad_alpha(alpha: float, method: str) -> None:
    _, p, dx, dy = rand_problem(4, 5)
    with pytest.raises(ValueError, match="alpha"):
        poisson.solve(p, dx, dy, solver=method, alpha=alpha)
    with pytest.raises(ValueError, match="alpha"):
        poisson.l1_energy(p, p, dx, dy, alpha=alpha)


def test_mismatched_shapes_name_buffers() -> None:
    _, p, dx, dy = rand_problem(4, 5)
    with pytest.raises(ValueError, match=r"primal \(4, 5, 3\), dx \(4, 6, 3\), dy \(4, 5, 3\)"):
        poisson.solve_l2(p, torch.zeros(4, 6, 3), dy)
    with pytest.raises(ValueError, match=r"dy \(4, 5, 1\)"):
        poisson.solve_l1(p, dx, torch.zeros(4, 5, 1))
    with pytest.raises(ValueError, match=r"x .*\(4, 5\).*primal \(4, 5, 3\)"):
        poisson.l2_energy(torch.zeros(4, 5), p, dx, dy)
    with pytest.raises(ValueError, match="weights_dx"):
        poisson.solve_weighted_cg(p, dx, dy, weights_dx=torch.ones(3, 5, 1))
    with pytest.raises(ValueError, match="x0"):
        poisson.solve_weighted_cg(p, dx, dy, x0=torch.zeros(4, 4, 3))


@pytest.mark.parametrize("shape", [(0, 5, 3), (4, 0, 3), (4, 5, 0), (0, 0)])
def test_empty_image_rejected(shape: tuple[int, ...]) -> None:
    z = torch.zeros(shape)
    with pytest.raises(ValueError, match="empty"):
        poisson.solve(z, z, z)


def test_other_bad_inputs() -> None:
    _, p, dx, dy = rand_problem(4, 5)
    with pytest.raises(ValueError, match=r"(?s)unknown L1 preset 'nope'.*'l1'.*'fast'"):
        poisson.solve_l1(p, dx, dy, preset="nope")
    with pytest.raises(ValueError, match=r"(?s)unknown reconstruction method.*'l2'.*'l1-fast'"):
        poisson.solve(p, dx, dy, solver="l3")
    with pytest.raises(ValueError, match="preconditioner"):
        poisson.solve_weighted_cg(p, dx, dy, precondition="ilu")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="weights_primal"):
        poisson.solve_weighted_cg(p, dx, dy, weights_primal=-torch.ones(4, 5, 1))
    with pytest.raises(TypeError, match="primal"):
        poisson.solve_l2(p.numpy(), dx, dy)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="shape"):
        poisson.solve_l2(torch.zeros(5), torch.zeros(5), torch.zeros(5))
    with pytest.raises(ValueError, match="rounds"):
        poisson.L1Preset("bad", rounds=0, reg_init=0.05, reg_decay=0.5, cg_iters=10)


def test_clean_input_emits_no_warning() -> None:
    _, p, dx, dy = rand_problem(6, 6, seed=23, noise=0.1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for method in poisson.SOLVERS:
            poisson.solve(p, dx, dy, solver=method)
