"""The (P)CG preconditioners of the weighted system ``A = P^T W P`` by name
(:data:`PRECONDITIONERS`, :func:`make_precond`).

* ``"none"``: plain CG (the reference solver).
* ``"jacobi"``: the diagonal of ``A``.
* ``"dct"``: the DCT solve of the Laplacian with the mean weights (exact for uniform weights).
* ``"multigrid"``: one V-cycle of aggregation multigrid on ``A`` itself (:mod:`.multigrid`).

Layout, dtype, device: the internal ``(B, C, H, W)`` layout of :class:`~.problem.Problem`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import torch

from .cg import Operator, Weights
from .dct import LaplaceDCT
from .multigrid import Multigrid
from .problem import Problem

Precondition = Literal["none", "jacobi", "dct", "multigrid"]
PRECONDITIONERS = ("none", "jacobi", "dct", "multigrid")


def make_precond(
    kind: str, prob: Problem, w: Weights, dct: LaplaceDCT, op: Operator
) -> Callable[[torch.Tensor], torch.Tensor] | None:
    """The preconditioner ``kind`` of ``A = P^T W P`` (``op``), ``None`` for ``"none"``.

    Raises:
        ValueError: An unknown ``kind`` (the message lists the valid names).
    """
    if kind == "none":
        return None
    if kind == "jacobi":
        # Positive: the diagonal has alpha^2 * Wp > 0 (missing primals keep a tiny weight) unless
        # a caller passes zero primal weights; guard so the preconditioner stays finite.
        inv = op.diag.clamp_min(torch.finfo(prob.p.dtype).tiny).reciprocal()
        return lambda r, out=None: torch.mul(r, inv, out=out)
    if kind == "dct":
        a2 = prob.alpha**2
        cp = w.p.mean(dim=(2, 3), keepdim=True) * a2 if w.p is not None else a2
        mx = w.x.mean(dim=(2, 3), keepdim=True) if w.x is not None and w.x.numel() else 1.0
        my = w.y.mean(dim=(2, 3), keepdim=True) if w.y is not None and w.y.numel() else 1.0
        cg = 0.5 * (mx + my)
        return lambda r: dct.solve(r, cp, cg)
    if kind == "multigrid":
        return Multigrid(prob.alpha**2, w, prob.p[:, :1])
    valid = ", ".join(repr(k) for k in PRECONDITIONERS)
    raise ValueError(f"unknown preconditioner {kind!r}; valid: {valid}")
