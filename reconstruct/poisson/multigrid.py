"""A geometric multigrid V-cycle for the weighted screened-Poisson system, used as a CG
preconditioner.

The system ``A = a2 Wp + Dx^T Wx Dx + Dy^T Wy Dy`` (:class:`~.cg.Operator`) is coarsened by
aggregating 2x2 pixel blocks with piecewise-constant interpolation ``P`` and the Galerkin
product ``P^T A P``: the coarse system is again a 5-point stencil whose mass term is the sum of
the block's ``a2 Wp`` and whose coupling between two blocks is the sum of the fine couplings
across their common edge, so strong and weak weights (IRLS weights span many orders of
magnitude) carry over exactly (aggregation multigrid, e.g. Braess 1995, *Towards algebraic
multigrid for elliptic problems of second order*, Computing 55). Smoothing is damped Jacobi,
the same number of sweeps before and after the coarse correction, so the V-cycle is a
symmetric positive-definite preconditioner.

Layout, dtype, device: ``(B, C, H, W)`` tensors on any device; the hierarchy has the dtype and
device of the weights it is built from.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .cg import Weights, apply_stencil, diag_of

#: Damping of the Jacobi smoother (4/5 is the classic choice for the 5-point Laplacian).
JACOBI_DAMPING = 0.8

#: Jacobi sweeps before and after each coarse correction.
SWEEPS = 1

#: Coarsening stops once a level has at most this many pixels on its long side.
COARSEST_SIDE = 4

#: Jacobi sweeps on the coarsest level.
COARSEST_SWEEPS = 16


@dataclass
class Level:
    """One grid: the stencil's diagonal ``diag`` (``(B, 1|C, H, W)``), its couplings ``wx``
    (``(B, 1|C, H, W-1)``) and ``wy`` (``(B, 1|C, H-1, W)``), and ``omega / diag``."""

    diag: torch.Tensor
    wx: torch.Tensor
    wy: torch.Tensor
    mass: torch.Tensor
    inv: torch.Tensor

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return apply_stencil(self.diag, self.wx, self.wy, x)


def _sum_pairs(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sum neighbouring pairs along ``dim`` (-1 or -2); an odd last element stays alone."""
    if dim == -1:
        out = t[..., 0::2].clone()
        odd = t[..., 1::2]
        out[..., : odd.shape[-1]] += odd
    else:
        out = t[..., 0::2, :].clone()
        odd = t[..., 1::2, :]
        out[..., : odd.shape[-2], :] += odd
    return out


def _level(mass: torch.Tensor, wx: torch.Tensor, wy: torch.Tensor) -> Level:
    diag = diag_of(1.0, Weights(mass, wx, wy), mass[:, :1])
    inv = JACOBI_DAMPING / diag.clamp_min(torch.finfo(diag.dtype).tiny)
    return Level(diag, wx, wy, mass, inv)


def _coarsen(lv: Level) -> Level:
    """Galerkin coarse level of 2x2 aggregates."""
    mass = _sum_pairs(_sum_pairs(lv.mass, -1), -2)
    # Couplings across a block boundary: fine edges 1, 3, 5, ... (between pixel 2J+1 and 2J+2).
    wx = _sum_pairs(lv.wx[..., 1::2], -2)
    wy = _sum_pairs(lv.wy[..., 1::2, :], -1)
    return _level(mass, wx, wy)


def restrict(r: torch.Tensor) -> torch.Tensor:
    """``P^T r``: sums of 2x2 blocks, ``(B, C, H, W)`` -> ``(B, C, ceil(H/2), ceil(W/2))``."""
    return _sum_pairs(_sum_pairs(r, -1), -2)


def prolong_add_(x: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
    """``x += P e`` in place: each coarse value added to its 2x2 block of ``x``."""
    for i in (0, 1):
        for j in (0, 1):
            xs = x[..., i::2, j::2]
            xs += e[..., : xs.shape[-2], : xs.shape[-1]]
    return x


class Multigrid:
    """V-cycle preconditioner for ``A = a2 Wp + Dx^T Wx Dx + Dy^T Wy Dy``.

    Args:
        a2: ``alpha^2``.
        w: Weights on the internal layout (``None`` entries mean ones).
        ref: ``(B, 1, H, W)`` tensor giving the fine grid's shape, dtype and device.
    """

    def __init__(self, a2: float, w: Weights, ref: torch.Tensor) -> None:
        mass = torch.full_like(ref, a2) if w.p is None else w.p * a2
        wx = torch.ones_like(ref[..., :-1]) if w.x is None else w.x
        wy = torch.ones_like(ref[..., :-1, :]) if w.y is None else w.y
        self.levels = [_level(mass, wx, wy)]
        while max(self.levels[-1].diag.shape[-2:]) > COARSEST_SIDE:
            self.levels.append(_coarsen(self.levels[-1]))

    def __call__(self, r: torch.Tensor) -> torch.Tensor:
        """``B r`` with ``B`` one V-cycle from a zero initial guess (SPD, ``~A^-1``)."""
        return self._cycle(0, r)

    def _cycle(self, k: int, b: torch.Tensor) -> torch.Tensor:
        lv = self.levels[k]
        coarsest = k == len(self.levels) - 1
        n = COARSEST_SWEEPS if coarsest else SWEEPS
        x = b * lv.inv
        for _ in range(n - 1):
            x.addcmul_(b - lv.apply(x), lv.inv)
        if coarsest:
            return x
        prolong_add_(x, self._cycle(k + 1, restrict(b - lv.apply(x))))
        for _ in range(n):
            x.addcmul_(b - lv.apply(x), lv.inv)
        return x
