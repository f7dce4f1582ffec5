"""Gradients of the screened-Poisson solvers (gdpt.reconstruct.poisson): the adjoint solve.

L2 and weighted CG are checked against central finite differences of the solvers themselves
(``torch.autograd.gradcheck``, float64, tiny images). The L1 gradient holds the last IRLS
weights fixed, so it is not the derivative of the whole reweighting: it is checked exactly
where the schedule has no reweighting round, and on what it is for (a gross outlier, which the
L1 solution ignores, gets almost no gradient) elsewhere.
"""

from __future__ import annotations

import warnings

import pytest
import torch
from gdpt.reconstruct import poisson

pytestmark = pytest.mark.usefixtures("single_thread")


def _inputs(*shape: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return tuple(
        torch.rand(*shape, generator=gen, dtype=torch.float64).requires_grad_(True)
        for _ in range(3)
    )


@pytest.mark.parametrize(("shape", "alpha"), [((4, 5, 3), 0.2), ((3, 4), 0.7), ((2, 3, 4, 2), 0.2)])
def test_l2_gradient_matches_finite_differences(shape, alpha):
    assert torch.autograd.gradcheck(
        lambda p, dx, dy: poisson.solve_l2(p, dx, dy, alpha=alpha), _inputs(*shape)
    )


def test_l2_gradient_with_missing_constraints_matches_finite_differences():
    """A NaN primal pixel and an Inf gradient are dropped: their entries get zero gradient and
    the rest is the derivative of the solve without them (CG path of ``solve_l2``)."""
    p0, dx0, _ = (t.detach() for t in _inputs(4, 5, 3, seed=1))
    p0[1, 2, 0] = float("nan")
    dx0[0, 1, 1] = float("inf")

    def solve(p, dx, dy):
        p = torch.where(torch.isfinite(p0), p, p0)
        dx = torch.where(torch.isfinite(dx0), dx, dx0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", poisson.NonFiniteInputWarning)
            return poisson.solve_l2(p, dx, dy)

    assert torch.autograd.gradcheck(solve, _inputs(4, 5, 3, seed=2))
    p, dx = p0.clone().requires_grad_(True), dx0.clone().requires_grad_(True)
    dy = torch.rand(4, 5, 3, dtype=torch.float64, requires_grad=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", poisson.NonFiniteInputWarning)
        (poisson.solve_l2(p, dx, dy) * torch.rand(4, 5, 3, dtype=torch.float64)).sum().backward()
    assert torch.equal(p.grad[1, 2], torch.zeros(3, dtype=torch.float64))
    assert torch.equal(dx.grad[0, 1], torch.zeros(3, dtype=torch.float64))
    assert torch.equal(dx.grad[:, -1], torch.zeros(4, 3, dtype=torch.float64))  # unused column
    assert torch.equal(dy.grad[-1], torch.zeros(5, 3, dtype=torch.float64))  # unused row


def test_weighted_cg_gradient_matches_finite_differences():
    gen = torch.Generator().manual_seed(3)
    weights = {
        f"weights_{n}": torch.rand(3, 4, 1, generator=gen, dtype=torch.float64) + 0.1
        for n in ("primal", "dx", "dy")
    }
    assert torch.autograd.gradcheck(
        lambda p, dx, dy: poisson.solve_weighted_cg(p, dx, dy, **weights),
        _inputs(3, 4, 2, seed=4),
    )


def test_weights_that_require_gradients_are_refused_by_name():
    p, dx, dy = _inputs(3, 4, 3)
    w = torch.ones(3, 4, 1, dtype=torch.float64, requires_grad=True)
    with pytest.raises(ValueError, match="weights_dy require gradients"):
        poisson.solve_weighted_cg(p, dx, dy, weights_dy=w)


def test_l1_without_reweighting_round_is_differentiated_exactly():
    one_round = poisson.L1Preset(
        name="one", rounds=1, reg_init=0.05, reg_decay=0.5, cg_iters=50, exact_first_round=True
    )
    assert torch.autograd.gradcheck(
        lambda p, dx, dy: poisson.solve_l1(p, dx, dy, preset=one_round), _inputs(4, 5, 3)
    )


@pytest.mark.parametrize("preset", ["l1", "fast"])
def test_l1_gradient_ignores_a_gross_outlier_as_its_solution_does(preset):
    """A +3 outlier in one ``dx``: the L1 solution barely depends on it (central differences
    of the solver), the L2 solution does; the L1 gradient (last IRLS weights) follows L1."""
    gen = torch.Generator().manual_seed(1)
    image = torch.rand(10, 10, 3, generator=gen, dtype=torch.float64)
    dx, dy = torch.zeros_like(image), torch.zeros_like(image)
    dx[:, :-1] = image[:, 1:] - image[:, :-1]
    dy[:-1] = image[1:] - image[:-1]
    dx[4, 4] += 3.0
    p = image + 0.05 * torch.randn(image.shape, generator=gen, dtype=torch.float64)
    target = torch.rand(image.shape, generator=gen, dtype=torch.float64)

    def loss(solve, dx_):
        return (solve(p, dx_, dy) * target).sum()

    def gradient(solve):
        d = dx.clone().requires_grad_(True)
        loss(solve, d).backward()
        return float(d.grad[4, 4, 0])

    l1 = lambda *a: poisson.solve_l1(*a, preset=preset)  # noqa: E731
    step = torch.zeros_like(dx)
    step[4, 4, 0] = 1e-3
    finite = float(loss(l1, dx + step) - loss(l1, dx - step)) / 2e-3
    l2 = gradient(poisson.solve_l2)
    assert abs(finite) < 0.05 * abs(l2)
    assert abs(gradient(l1)) < 0.01 * abs(l2)


@pytest.mark.parametrize("method", list(poisson.SOLVERS))
def test_every_method_passes_gradients_to_all_three_buffers(method):
    p, dx, dy = _inputs(6, 7, 3, seed=5)
    out = poisson.solve(p.float(), dx.float(), dy.float(), solver=method)
    out.square().sum().backward()
    for t in (p, dx, dy):
        assert t.grad is not None and t.grad.dtype == torch.float64
        assert torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0


def test_no_graph_without_inputs_that_require_gradients():
    p, dx, dy = (t.detach() for t in _inputs(4, 5, 3))
    assert not poisson.solve_l2(p, dx, dy).requires_grad
    p.requires_grad_(True)
    with torch.no_grad():
        assert not poisson.solve_l1(p, dx, dy, preset="fast").requires_grad
