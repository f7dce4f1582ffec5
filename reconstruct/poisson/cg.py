"""The weighted normal equations ``P^T W P x = P^T W b`` and their solution by
(preconditioned) conjugate gradients.

:class:`Operator` applies ``A = alpha^2 Wp + Dx^T Wx Dx + Dy^T Wy Dy`` as a 5-point stencil,
:func:`rhs` builds ``P^T W b``, :func:`pcg` runs CG per ``(B, C)`` system,
:func:`l2_exact` solves the unweighted problem (DCT closed form, or DCT-preconditioned CG when
constraints are missing). Everything works on the internal ``(B, C, H, W)`` layout of
:class:`~.problem.Problem`.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from .dct import LaplaceDCT
from .problem import MISSING_PRIMAL_WEIGHT, Problem


def gradient(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Valid forward differences: ``(B,C,H,W-1)`` and ``(B,C,H-1,W)``."""
    return x[..., 1:] - x[..., :-1], x[..., 1:, :] - x[..., :-1, :]


def _grad_adj_(out: torch.Tensor, gx: torch.Tensor, gy: torch.Tensor) -> torch.Tensor:
    """``out += Dx^T gx + Dy^T gy`` in place."""
    if gx.shape[-1] > 0:
        out[..., :-1] -= gx
        out[..., 1:] += gx
    if gy.shape[-2] > 0:
        out[..., :-1, :] -= gy
        out[..., 1:, :] += gy
    return out


@dataclass
class Weights:
    """Per-constraint weights on the internal layout (``None`` = all ones).

    ``p``: ``(B, 1|C, H, W)``; ``x``: ``(B, 1|C, H, W-1)``; ``y``: ``(B, 1|C, H-1, W)``.
    """

    p: torch.Tensor | None = None
    x: torch.Tensor | None = None
    y: torch.Tensor | None = None


class Operator:
    """``A = P^T W P = alpha^2 Wp + Dx^T Wx Dx + Dy^T Wy Dy`` as a 5-point stencil.

    The diagonal is precomputed (it is also the Jacobi preconditioner), so one product costs
    one multiply and four shifted fused multiply-adds.
    """

    def __init__(self, prob: Problem, w: Weights) -> None:
        self.w = w
        self.diag = diag_of(prob.alpha**2, w, prob.p[:, :1])

    def __call__(self, x: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
        return apply_stencil(self.diag, self.w.x, self.w.y, x, out=out)


def apply_stencil(
    diag: torch.Tensor | None,
    wx: torch.Tensor | None,
    wy: torch.Tensor | None,
    x: torch.Tensor,
    *,
    out: torch.Tensor | None = None,
) -> torch.Tensor:
    """``diag * x - (off-diagonal couplings wx, wy)``: the product of a 5-point stencil whose
    off-diagonal entries are ``-wx`` (horizontal, ``(B, 1|C, H, W-1)``) and ``-wy`` (vertical,
    ``(B, 1|C, H-1, W)``), ``None`` meaning all ones (``diag`` ``None``: a unit diagonal, whose
    copy of ``x`` is folded into the first coupling's pass); ``x`` is ``(B, C, H, W)``.
    Written into ``out`` (a contiguous tensor of ``x``'s shape and dtype, not ``x``) when
    given, else into a new tensor."""
    if diag is None and wx is not None and x.shape[-1] > 1:
        out = torch.empty_like(x) if out is None else out
        torch.addcmul(x[..., :-1], wx, x[..., 1:], value=-1.0, out=out[..., :-1])
        out[..., -1:] = x[..., -1:]
        out[..., 1:].addcmul_(wx, x[..., :-1], value=-1.0)
    else:
        out = torch.mul(x, 1.0 if diag is None else diag, out=out)
        if x.shape[-1] > 1:
            _couple_(out, wx, x)
    if x.shape[-2] > 1:
        if wy is None:
            out[..., :-1, :].sub_(x[..., 1:, :])
            out[..., 1:, :].sub_(x[..., :-1, :])
        else:
            out[..., :-1, :].addcmul_(wy, x[..., 1:, :], value=-1.0)
            out[..., 1:, :].addcmul_(wy, x[..., :-1, :], value=-1.0)
    return out


def _couple_(out: torch.Tensor, wx: torch.Tensor | None, x: torch.Tensor) -> None:
    """``out -= `` the horizontal couplings ``wx`` (``None``: ones) of ``x``, in place."""
    if wx is None:
        out[..., :-1].sub_(x[..., 1:])
        out[..., 1:].sub_(x[..., :-1])
    else:
        out[..., :-1].addcmul_(wx, x[..., 1:], value=-1.0)
        out[..., 1:].addcmul_(wx, x[..., :-1], value=-1.0)


def rhs(prob: Problem, w: Weights) -> torch.Tensor:
    """``P^T W b = alpha^2 Wp p + Dx^T Wx dx + Dy^T Wy dy``."""
    a2 = prob.alpha**2
    out = prob.p * a2 if w.p is None else prob.p * (w.p * a2)
    gx = prob.gx if w.x is None else prob.gx * w.x
    gy = prob.gy if w.y is None else prob.gy * w.y
    return _grad_adj_(out, gx, gy)


def mask_weights(prob: Problem) -> Weights:
    """Weights of the plain problem: 1 for present constraints, 0 (primal: tiny) for missing."""
    if not prob.has_missing:
        return Weights()
    assert prob.mp is not None
    wp = prob.mp + (1.0 - prob.mp) * MISSING_PRIMAL_WEIGHT
    return Weights(wp, prob.mx, prob.my)


def default_tol(dtype: torch.dtype) -> float:
    """Default relative CG tolerance: ``1e-5`` for float32 compute, ``1e-10`` for float64."""
    return 1e-10 if dtype == torch.float64 else 1e-5


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-system inner products over ``(H, W)``: ``(B, C, 1, 1)``."""
    # einsum reduces through a batched matrix product: ~2x faster on the CPU than vecdot here.
    return torch.einsum("bchw,bchw->bc", a, b)[..., None, None]


def _safe_div(num: torch.Tensor, den: torch.Tensor) -> torch.Tensor:
    ok = den > 0
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))


def _writing(
    fn: Callable[..., torch.Tensor] | None,
) -> Callable[[torch.Tensor, torch.Tensor | None], torch.Tensor] | None:
    """``fn`` as ``f(v, buffer)``: ``fn(v, out=buffer)`` when ``fn`` takes an ``out`` keyword
    (``buffer`` ``None``: a new tensor), else ``fn(v)``."""
    if fn is None:
        return None
    try:
        writes = "out" in inspect.signature(fn).parameters
    except (TypeError, ValueError):  # a callable without an inspectable signature
        writes = False
    if writes:
        return lambda v, buffer: fn(v, out=buffer)
    return lambda v, buffer: fn(v)


def pcg(
    apply_a: Callable[[torch.Tensor], torch.Tensor],
    b: torch.Tensor,
    x: torch.Tensor,
    *,
    max_iter: int,
    tol: float,
    precond: Callable[[torch.Tensor], torch.Tensor] | None,
    rtol0: float = 0.0,
) -> tuple[torch.Tensor, int, float]:
    """(Preconditioned) CG on ``A x = b`` per ``(B, C)`` system, warm-started from ``x``.

    A system is done once ``||r|| <= tol ||b||`` or once ``||r||`` dropped below ``rtol0``
    times its initial value. Done systems are frozen (step 0), so every system gets the
    iterations it needs independently of the others. Stops when all are done or after
    ``max_iter`` iterations. ``apply_a`` and ``precond`` that take an ``out`` keyword
    (:class:`Operator`, the Jacobi preconditioner of :func:`.precond.make_precond`) write into
    buffers allocated once per solve: a fresh image-sized tensor per iteration costs as much as
    a pass over it (page faults on the CPU).

    Returns:
        ``(x, iterations, max relative residual ||r|| / ||b||)``.
    """
    apply_a, precond = _writing(apply_a), _writing(precond)
    x = x.clone()
    r = b - apply_a(x, None)
    tiny = torch.finfo(b.dtype).tiny
    bnorm = _dot(b, b).sqrt().clamp_min(tiny)
    rr = _dot(r, r)

    def relres(rr: torch.Tensor) -> float:
        return float((rr.sqrt() / bnorm).max())

    if max_iter <= 0 or (tol > 0 and bool((rr <= (tol * bnorm) ** 2).all())):
        return x, 0, relres(rr)
    z = precond(r, None) if precond is not None else r
    p = z.clone()
    ap = torch.empty_like(p)
    rz = _dot(r, z)
    thresh = torch.maximum((tol * bnorm) ** 2, rtol0**2 * rr)  # on ||r||^2, per system
    check = tol > 0 or rtol0 > 0  # a host sync per iteration only when stopping early
    active = torch.ones_like(rz, dtype=torch.bool)
    it = 0
    while True:
        ap = apply_a(p, ap)
        step = _safe_div(rz, _dot(p, ap))
        if check:
            step = torch.where(active, step, torch.zeros_like(step))
        x.addcmul_(step, p)
        r.addcmul_(step, ap, value=-1.0)
        it += 1
        if check:
            rr = _dot(r, r)
            active &= rr > thresh
            if not bool(active.any()):
                break
        if it >= max_iter:
            break
        # The preconditioner is applied only when another iteration follows.
        if precond is not None:
            z = precond(r, z)
            rz_new = _dot(r, z)
        else:
            z = r
            rz_new = rr if check else _dot(r, r)
        beta = _safe_div(rz_new, rz)
        p = torch.addcmul(z, p, beta, out=p)  # p = z + beta * p, in place
        rz = rz_new
    if not check:
        rr = _dot(r, r)
    return x, it, relres(rr)


def jacobi_scaled_cg(
    op: Operator, b: torch.Tensor, x: torch.Tensor, *, iterations: int, tol: float
) -> tuple[torch.Tensor, int, float]:
    """Exactly ``iterations`` iterations of Jacobi-preconditioned CG on ``op``'s system
    ``A x = b``, every ``(B, C)`` system on its own, warm-started from ``x`` (not modified);
    a system whose start already has ``||r|| <= tol ||b||`` is left at its start (iterating
    on a residual of rounding errors would only move it), no test after that. Run as plain CG
    on the symmetrically scaled system
    ``(S A S) (S^-1 x) = S b``, ``S = diag(A)^-1/2``, whose diagonal is one: in exact
    arithmetic the iterates of :func:`pcg` with the Jacobi preconditioner and ``tol = 0``
    (e.g. Saad 2003, *Iterative Methods for Sparse Linear Systems*, sec. 9.2), without the
    preconditioner's pass and one of the three dot products of each iteration.

    Returns:
        ``(x, iterations, max relative residual ||b - A x|| / ||b||)`` (of the recursion, as
        :func:`pcg`).
    """
    tiny = torch.finfo(b.dtype).tiny
    s = op.diag.clamp_min(tiny).rsqrt()
    couplings = []
    for w, here, there in (
        (op.w.x, s[..., :-1], s[..., 1:]),
        (op.w.y, s[..., :-1, :], s[..., 1:, :]),
    ):
        couplings.append(here * there if w is None else w * here * there)

    def apply_scaled(v: torch.Tensor, out: torch.Tensor | None) -> torch.Tensor:
        return apply_stencil(None, couplings[0], couplings[1], v, out=out)

    y = x / s
    r = b * s
    r -= apply_scaled(y, None)
    bnorm = _dot(b, b).sqrt().clamp_min(tiny)
    active = _dot(r / s, r / s) > (tol * bnorm) ** 2  # the unscaled residual at the start
    rr = _dot(r, r)
    p = r.clone()
    ap = torch.empty_like(p)
    for it in range(iterations):
        ap = apply_scaled(p, ap)
        step = torch.where(active, _safe_div(rr, _dot(p, ap)), 0.0)
        y.addcmul_(step, p)
        r.addcmul_(step, ap, value=-1.0)
        if it + 1 == iterations:
            break
        rr_new = _dot(r, r)
        p = torch.addcmul(r, p, _safe_div(rr_new, rr), out=p)  # p = r + beta * p, in place
        rr = rr_new
    r.div_(s)  # the residual of the unscaled system
    relres = _dot(r, r).sqrt() / bnorm
    return y.mul_(s), max(iterations, 0), float(relres.max())


def relative_residual_of(prob: Problem, x: torch.Tensor, w: Weights) -> float:
    b = rhs(prob, w)
    r = b - Operator(prob, w)(x)
    tiny = torch.finfo(b.dtype).tiny
    return float((_dot(r, r).sqrt() / _dot(b, b).sqrt().clamp_min(tiny)).max())


def l2_exact(
    prob: Problem, dct: LaplaceDCT, *, tol: float, max_iter: int, refine: int
) -> tuple[torch.Tensor, int, float]:
    """Exact L2 solve on the internal problem.

    Without missing constraints this is the DCT closed form plus ``refine`` steps of iterative
    refinement (each one more DCT solve on the residual). With missing constraints the closed
    form of the zero-filled problem warm-starts DCT-preconditioned CG.
    """
    a2 = prob.alpha**2
    x = dct.solve(rhs(prob, Weights()), a2)
    if not prob.has_missing:
        w = Weights()
        for _ in range(refine):
            x += dct.solve(rhs(prob, w) - Operator(prob, w)(x), a2)
        return x, 0, math.nan
    w = mask_weights(prob)
    return pcg(
        Operator(prob, w),
        rhs(prob, w),
        x,
        max_iter=max_iter,
        tol=tol,
        precond=lambda r: dct.solve(r, a2),
    )


def diag_of(a2: float, w: Weights, ref: torch.Tensor) -> torch.Tensor:
    """Diagonal of ``A = a2 Wp + Dx^T Wx Dx + Dy^T Wy Dy``: ``(B, 1|C, H, W)``; ``ref`` is a
    ``(B, 1, H, W)`` tensor giving shape, dtype and device."""
    d = torch.full_like(ref, a2) if w.p is None else (w.p * a2).expand_as(ref).clone()
    wx = torch.ones_like(ref[..., :-1]) if w.x is None else w.x
    wy = torch.ones_like(ref[..., :-1, :]) if w.y is None else w.y
    if wx.shape[1] != d.shape[1] or wy.shape[1] != d.shape[1]:
        c = max(wx.shape[1], wy.shape[1], d.shape[1])
        d = d.expand(-1, c, -1, -1).clone()
    if wx.shape[-1] > 0:
        d[..., :-1] += wx
        d[..., 1:] += wx
    if wy.shape[-2] > 0:
        d[..., :-1, :] += wy
        d[..., 1:, :] += wy
    return d
