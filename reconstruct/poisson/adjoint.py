"""Gradients of a solve: the adjoint system, solved in the backward pass.

A solve ends with ``A x = P^T W b``, ``A = P^T W P`` symmetric positive definite. For an
incoming gradient ``g`` of the result, :meth:`System.adjoint` solves ``A lam = g`` (the DCT
closed form for uniform weights, else preconditioned CG; the forward iterations are not
unrolled) and returns ``alpha^2 Wp lam``, ``Wx Dx lam`` and ``Wy Dy lam``: the adjoint method
(e.g. Giles and Pierce 2000, *An introduction to the adjoint approach to design*), with ``W``
held fixed. :func:`run_solver` runs a solver through :class:`torch.autograd.Function` when
autograd records an input buffer.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from ..autograd import records
from .cg import Operator, Weights, default_tol, gradient, pcg
from .dct import LaplaceDCT
from .problem import Problem, SolveInfo, from_bchw, to_bchw

#: Iteration cap of an adjoint (P)CG solve with non-uniform weights.
ADJOINT_MAX_ITER = 1000


@dataclass
class System:
    """The SPD system ``A = P^T W P`` a solve ended with, ``W`` held fixed.

    ``precond`` preconditions the adjoint CG; ``None`` with uniform weights, whose system the
    DCT solves in closed form. ``dtypes``: the dtypes of ``primal``, ``dx``, ``dy``.
    """

    prob: Problem
    w: Weights
    dct: LaplaceDCT
    precond: Callable[[torch.Tensor], torch.Tensor] | None
    max_iter: int
    dtypes: tuple[torch.dtype, torch.dtype, torch.dtype]

    def solve(self, r: torch.Tensor) -> torch.Tensor:
        """``A^-1 r`` on the internal layout."""
        a2 = self.prob.alpha**2
        if self.precond is None:
            return self.dct.solve(r, a2)
        x, _, _ = pcg(
            Operator(self.prob, self.w),
            r,
            torch.zeros_like(r),
            max_iter=self.max_iter,
            tol=default_tol(r.dtype),
            precond=self.precond,
        )
        return x

    def adjoint(self, grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Gradients w.r.t. ``primal``, ``dx``, ``dy`` (user layout and dtypes) of a scalar
        whose gradient w.r.t. the result is ``grad``."""
        prob, w = self.prob, self.w
        lam = self.solve(to_bchw(grad, prob.p.dtype, prob.squeeze_channel))
        gp = lam * prob.alpha**2
        lx, ly = gradient(lam)
        gx = lx if w.x is None else lx * w.x
        gy = ly if w.y is None else ly * w.y
        if w.p is not None:
            gp = gp * w.p
        if prob.has_missing:
            gp, gx, gy = gp * prob.mp, gx * prob.mx, gy * prob.my
        gx = torch.nn.functional.pad(gx, (0, 1))
        gy = torch.nn.functional.pad(gy, (0, 0, 0, 1))
        return tuple(
            from_bchw(g, prob.out_shape, prob.squeeze_channel).to(dtype)
            for g, dtype in zip((gp, gx, gy), self.dtypes, strict=True)
        )


Core = Callable[
    [torch.Tensor, torch.Tensor, torch.Tensor], tuple[torch.Tensor, "SolveInfo | None", System]
]


class _Solve(torch.autograd.Function):
    """A solver ``core(primal, dx, dy) -> (image, info, system)`` whose backward pass solves
    the adjoint system of ``system``."""

    @staticmethod
    def forward(ctx, core: Core, primal, dx, dy):
        out, info, system = core(primal, dx, dy)
        ctx.system = system
        return out, info

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad, _info):
        return None, *ctx.system.adjoint(grad)


def run_solver(
    core: Core, primal: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor
) -> tuple[torch.Tensor, SolveInfo | None]:
    """``core`` on the buffers, through :class:`_Solve` when autograd records a buffer."""
    if records((primal, dx, dy)):
        return _Solve.apply(core, primal, dx, dy)
    out, info, _ = core(primal, dx, dy)
    return out, info


def dtypes_of(*ts: torch.Tensor) -> tuple[torch.dtype, torch.dtype, torch.dtype]:
    return tuple(t.dtype for t in ts)  # type: ignore[return-value]
