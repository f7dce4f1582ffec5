"""The conjugate-gradient core of gdpt.reconstruct.poisson (``cg.pcg``): an operator and a
preconditioner that write into buffers allocated once per solve."""

from __future__ import annotations

import pytest
import torch
from gdpt.reconstruct.poisson import cg


def _system(seed: int, spread: float):
    """A random SPD 5-point stencil on ``(2, 3, 9, 11)`` (diagonally dominant: the couplings
    sum to less than the diagonal), ``spread`` decades between the smallest and largest row
    scale, a right-hand side and a start."""
    gen = torch.Generator().manual_seed(seed)
    shape = (2, 3, 9, 11)
    scale = 10.0 ** (spread * torch.rand(2, 1, 9, 11, generator=gen, dtype=torch.float64))
    wx = torch.rand(2, 1, 9, 10, generator=gen, dtype=torch.float64)
    wy = torch.rand(2, 1, 8, 11, generator=gen, dtype=torch.float64)
    # symmetric scaling S (D + couplings) S keeps the matrix SPD
    wx = wx * scale[..., :-1].sqrt() * scale[..., 1:].sqrt()
    wy = wy * scale[..., :-1, :].sqrt() * scale[..., 1:, :].sqrt()
    diag = 4.5 * scale
    b = torch.randn(shape, generator=gen, dtype=torch.float64)
    x0 = torch.randn(shape, generator=gen, dtype=torch.float64)
    return diag, wx, wy, b, x0


@pytest.mark.parametrize("tol", [0.0, 1e-6])
def test_operators_that_write_into_buffers_give_the_same_iterates(tol):
    """An operator and a preconditioner that take ``out`` (written into pcg's buffers) give
    the allocating ones' result bit for bit, with and without early stopping."""
    diag, wx, wy, b, x0 = _system(1, spread=2.0)
    inv = diag.reciprocal()
    runs = []
    for apply_a, precond in (
        (
            lambda x, out=None: cg.apply_stencil(diag, wx, wy, x, out=out),
            lambda r, out=None: torch.mul(r, inv, out=out),
        ),
        (lambda x: cg.apply_stencil(diag, wx, wy, x), lambda r: r * inv),
    ):
        runs.append(cg.pcg(apply_a, b, x0, max_iter=12, tol=tol, precond=precond))
    (x_w, its_w, res_w), (x_a, its_a, res_a) = runs
    assert torch.equal(x_w, x_a)
    assert (its_w, res_w) == (its_a, res_a)
    assert not torch.equal(x_w, x0)  # x0 itself is not overwritten
    assert torch.equal(x0, _system(1, spread=2.0)[4])


def test_the_shipped_operator_and_jacobi_preconditioner_write_into_buffers():
    """:class:`cg.Operator` and the ``"jacobi"`` preconditioner take ``out`` (pcg's buffers)
    and write there what they return otherwise."""
    from gdpt.reconstruct.poisson import dct, precond, problem

    gen = torch.Generator().manual_seed(4)
    p, dx, dy = (torch.rand(6, 7, 3, generator=gen) for _ in range(3))
    prob = problem.prepare(p, dx, dy, 0.2)
    w = cg.Weights(
        torch.rand(1, 1, 6, 7, generator=gen),
        torch.rand(1, 1, 6, 6, generator=gen),
        torch.rand(1, 1, 5, 7, generator=gen),
    )
    op = cg.Operator(prob, w)
    jacobi = precond.make_precond("jacobi", prob, w, dct.LaplaceDCT(6, 7, prob.p), op)
    for fn in (op, jacobi):
        out = torch.full_like(prob.p, float("nan"))
        assert fn(prob.p, out=out) is out
        assert torch.equal(out, fn(prob.p))


@pytest.mark.parametrize("iterations", [0, 1, 7])
def test_jacobi_scaled_cg_runs_the_iterations_of_jacobi_pcg(iterations):
    """CG on the symmetrically scaled system gives Jacobi-PCG's iterate after the same number
    of iterations (float64, rows scaled over 3 decades) and leaves the start alone."""
    from gdpt.reconstruct.poisson import problem

    gen = torch.Generator().manual_seed(5)
    p, dx, dy = (torch.rand(2, 7, 9, 3, generator=gen, dtype=torch.float64) for _ in range(3))
    prob = problem.prepare(p, dx, dy, 0.2)
    w = cg.Weights(
        10.0 ** (3 * torch.rand(2, 1, 7, 9, generator=gen, dtype=torch.float64)),
        10.0 ** (3 * torch.rand(2, 1, 7, 8, generator=gen, dtype=torch.float64)),
        torch.rand(2, 1, 6, 9, generator=gen, dtype=torch.float64),
    )
    op = cg.Operator(prob, w)
    b = cg.rhs(prob, w)
    x0 = prob.p + 0.1
    start = x0.clone()
    expected = cg.pcg(op, b, x0, max_iter=iterations, tol=0.0, precond=lambda r: r / op.diag)
    x, its, res = cg.jacobi_scaled_cg(op, b, x0, iterations=iterations, tol=0.0)
    assert torch.equal(x0, start)
    assert its == expected[1] == iterations
    torch.testing.assert_close(x, expected[0], rtol=1e-10, atol=1e-12)
    assert res == pytest.approx(expected[2], rel=1e-8)
    if iterations:
        assert not torch.allclose(x, x0)


def test_fixed_iterations_needs_the_jacobi_preconditioner():
    from gdpt.reconstruct import poisson

    p = torch.rand(4, 5, 3, generator=torch.Generator().manual_seed(6))
    with pytest.raises(ValueError, match=r"fixed_iterations.*precondition='dct'"):
        poisson.solve_weighted_cg(p, p, p, precondition="dct", fixed_iterations=True)
    fixed, info = poisson.solve_weighted_cg(
        p, p, p, max_iter=3, tol=0.0, fixed_iterations=True, return_info=True
    )
    assert info.cg_iterations == 3
    torch.testing.assert_close(fixed, poisson.solve_weighted_cg(p, p, p, max_iter=3, tol=0.0))


@pytest.mark.parametrize("shape", [(2, 3, 9, 11), (1, 3, 1, 7), (1, 2, 5, 1)])
def test_a_unit_diagonal_stencil_is_the_product_with_diagonal_one(shape):
    """``apply_stencil(None, ...)`` (the copy of ``x`` folded into the first coupling) equals
    the product with an explicit diagonal of ones, into a buffer or a new tensor, and a
    matrix product with the stencil's dense matrix; one-row and one-column images included."""
    gen = torch.Generator().manual_seed(3)
    b, c, h, w = shape
    wx = torch.rand(b, 1, h, w - 1, generator=gen, dtype=torch.float64)
    wy = torch.rand(b, 1, h - 1, w, generator=gen, dtype=torch.float64)
    x = torch.randn(shape, generator=gen, dtype=torch.float64)
    ones = torch.ones(b, 1, h, w, dtype=torch.float64)
    expected = cg.apply_stencil(ones, wx, wy, x)
    buffer = torch.full_like(x, float("nan"))
    assert torch.equal(cg.apply_stencil(None, wx, wy, x, out=buffer), expected)
    assert torch.equal(buffer, expected)
    assert torch.equal(cg.apply_stencil(None, wx, wy, x), expected)
    dense = torch.zeros(b, h * w, h * w, dtype=torch.float64)
    index = torch.arange(h * w).view(h, w)
    dense[:, index.flatten(), index.flatten()] = 1.0
    for weights, here, there in (
        (wx, index[:, :-1], index[:, 1:]),
        (wy, index[:-1, :], index[1:, :]),
    ):
        for i, j in ((here, there), (there, here)):
            dense[:, i.flatten(), j.flatten()] = -weights[:, 0].flatten(1)
    by_matrix = torch.einsum("bij,bcj->bci", dense, x.flatten(2)).view(shape)
    assert torch.allclose(expected, by_matrix, rtol=1e-12, atol=1e-12)
