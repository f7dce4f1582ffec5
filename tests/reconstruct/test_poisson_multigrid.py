"""The aggregation-multigrid preconditioner of the weighted screened-Poisson system."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from gdpt.reconstruct import poisson
from gdpt.reconstruct.poisson import cg, multigrid

A2 = 0.04


def random_weights(h: int, w: int, *, span: float, seed: int) -> cg.Weights:
    """Log-uniform weights in ``[10^-span, 10^span]`` (IRLS weights span many orders)."""
    rng = np.random.default_rng(seed)

    def draw(*shape: int) -> torch.Tensor:
        return torch.tensor(10.0 ** rng.uniform(-span, span, shape))

    return cg.Weights(draw(1, 1, h, w), draw(1, 1, h, w - 1), draw(1, 1, h - 1, w))


def dense(apply: Callable[[torch.Tensor], torch.Tensor], h: int, w: int) -> np.ndarray:
    """Matrix of a linear map on ``(1, 1, h, w)`` images (row-major pixel order)."""
    eye = torch.eye(h * w, dtype=torch.float64).reshape(h * w, 1, h, w)
    return np.stack([apply(e[None]).reshape(-1).numpy() for e in eye], axis=1)


def difference_matrices(h: int, w: int) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Sparse forward differences over valid pixel pairs (row-major pixel index y*w + x)."""
    dx1 = sp.diags([-np.ones(w - 1), np.ones(w - 1)], [0, 1], shape=(w - 1, w))
    dy1 = sp.diags([-np.ones(h - 1), np.ones(h - 1)], [0, 1], shape=(h - 1, h))
    return sp.kron(sp.identity(h), dx1).tocsr(), sp.kron(dy1, sp.identity(w)).tocsr()


def sparse_a(wts: cg.Weights, h: int, w: int, a2: float = A2) -> sp.csr_matrix:
    """``a2 Wp + Dx^T Wx Dx + Dy^T Wy Dy`` for ``(1, 1, ., .)`` weights."""
    dxm, dym = difference_matrices(h, w)
    return (
        a2 * sp.diags(wts.p.reshape(-1).numpy())
        + dxm.T @ sp.diags(wts.x.reshape(-1).numpy()) @ dxm
        + dym.T @ sp.diags(wts.y.reshape(-1).numpy()) @ dym
    )


@pytest.mark.parametrize("shape", [(8, 6), (7, 9), (5, 1)])
def test_coarse_level_is_galerkin_product(shape: tuple[int, int]) -> None:
    h, w = shape
    wts = random_weights(h, w, span=2, seed=1)
    mg = multigrid.Multigrid(A2, wts, torch.zeros(1, 1, h, w, dtype=torch.float64))
    fine, coarse = mg.levels[0], mg.levels[1]
    hc, wc = coarse.diag.shape[-2:]
    a = dense(fine.apply, h, w)
    np.testing.assert_allclose(a, sparse_a(wts, h, w).toarray(), rtol=1e-12)
    # P: piecewise-constant interpolation from 2x2 aggregates.
    p = dense(lambda e: multigrid.prolong_add_(torch.zeros(1, 1, h, w, dtype=e.dtype), e), hc, wc)
    r = dense(multigrid.restrict, h, w)
    np.testing.assert_array_equal(r, p.T)
    np.testing.assert_allclose(dense(coarse.apply, hc, wc), p.T @ a @ p, rtol=1e-12, atol=1e-14)


def test_v_cycle_is_symmetric_positive_definite() -> None:
    h, w = 11, 10
    wts = random_weights(h, w, span=3, seed=2)
    mg = multigrid.Multigrid(A2, wts, torch.zeros(1, 1, h, w, dtype=torch.float64))
    b = dense(mg, h, w)
    np.testing.assert_allclose(b, b.T, rtol=1e-10, atol=1e-14)
    assert np.linalg.eigvalsh(0.5 * (b + b.T)).min() > 0


@pytest.mark.parametrize(("span", "factor"), [(0.0, 0.25), (3.0, 0.65)])
def test_one_v_cycle_reduces_the_residual(span: float, factor: float) -> None:
    # One V-cycle from zero on a random right-hand side: ||b - A B b|| <= factor ||b||
    # (measured 0.22 with uniform weights, 0.61 with weights over 6 orders of magnitude).
    h, w = 64, 48
    wts = random_weights(h, w, span=span, seed=3)
    ref = torch.zeros(1, 1, h, w, dtype=torch.float64)
    mg = multigrid.Multigrid(A2, wts, ref)
    diag = cg.diag_of(A2, wts, ref)
    b = torch.randn(1, 2, h, w, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    r = b - cg.apply_stencil(diag, wts.x, wts.y, mg(b))
    assert float(r.norm() / b.norm()) <= factor


def test_multigrid_pcg_needs_far_fewer_iterations_than_jacobi() -> None:
    # Weights over 2 orders of magnitude: measured 35 iterations against Jacobi's 169 (i.i.d.
    # weights over 6 orders, the hardest case for aggregation: 434 against 1008).
    h, w = 96, 80
    wts = random_weights(h, w, span=1, seed=4)
    ref = torch.zeros(1, 1, h, w, dtype=torch.float64)
    diag = cg.diag_of(A2, wts, ref)

    def op(x: torch.Tensor) -> torch.Tensor:
        return cg.apply_stencil(diag, wts.x, wts.y, x)

    b = torch.randn(1, 3, h, w, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    x0 = torch.zeros_like(b)
    exact = spla.spsolve(sp.csc_matrix(sparse_a(wts, h, w)), b[0, 0].reshape(-1).numpy())
    iters = {}
    for name, pre in (
        ("jacobi", lambda r: r / diag),
        ("multigrid", multigrid.Multigrid(A2, wts, ref)),
    ):
        x, iters[name], res = cg.pcg(op, b, x0, max_iter=5000, tol=1e-10, precond=pre)
        assert res <= 1e-10
        np.testing.assert_allclose(x[0, 0].reshape(-1).numpy(), exact, rtol=1e-7, atol=1e-9)
    assert iters["multigrid"] * 4 < iters["jacobi"]


def test_weighted_cg_with_multigrid_matches_sparse_weighted_solve() -> None:
    h, w, alpha = 13, 10, 0.3
    rng = np.random.default_rng(6)
    p, dx, dy = (rng.standard_normal((h, w, 2)) for _ in range(3))
    wts = random_weights(h, w, span=3, seed=6)
    dxm, dym = difference_matrices(h, w)
    a = sp.csc_matrix(sparse_a(wts, h, w, alpha**2))
    ref = np.empty_like(p)
    for c in range(2):
        rhs = (
            alpha**2 * wts.p.reshape(-1).numpy() * p[..., c].ravel()
            + dxm.T @ (wts.x.reshape(-1).numpy() * dx[:, :-1, c].ravel())
            + dym.T @ (wts.y.reshape(-1).numpy() * dy[:-1, :, c].ravel())
        )
        ref[..., c] = spla.spsolve(a, rhs).reshape(h, w)
    x, info = poisson.solve_weighted_cg(
        *(torch.tensor(t) for t in (p, dx, dy)),
        alpha=alpha,
        weights_primal=wts.p[0, 0, :, :, None],
        weights_dx=torch.nn.functional.pad(wts.x, (0, 1))[0, 0, :, :, None],
        weights_dy=torch.nn.functional.pad(wts.y, (0, 0, 0, 1))[0, 0, :, :, None],
        tol=1e-13,
        max_iter=500,
        precondition="multigrid",
        return_info=True,
    )
    np.testing.assert_allclose(x.numpy(), ref, atol=1e-9, rtol=0)
    assert info.cg_iterations < 60
