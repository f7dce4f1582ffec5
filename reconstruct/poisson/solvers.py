"""The public screened-Poisson solvers and their registry by name (:data:`SOLVERS`,
:func:`solve`); the problem and conventions are those of :mod:`gdpt.reconstruct.poisson`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Literal, overload

import torch

from .adjoint import ADJOINT_MAX_ITER, System, dtypes_of, run_solver
from .cg import (
    Operator,
    Weights,
    default_tol,
    jacobi_scaled_cg,
    l2_exact,
    mask_weights,
    pcg,
    relative_residual_of,
    rhs,
)
from .dct import LaplaceDCT
from .energy import energy_of
from .l1 import L1Preset, get_l1_preset, irls
from .precond import PRECONDITIONERS, Precondition, make_precond
from .problem import (
    DEFAULT_ALPHA,
    Problem,
    ProgressFn,
    SolveInfo,
    finish,
    prepare,
    to_bchw,
)


@overload
def solve_l2(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    alpha: float = ...,
    refine: int = ...,
    tol: float | None = ...,
    max_iter: int = ...,
    return_info: Literal[False] = ...,
) -> torch.Tensor: ...
@overload
def solve_l2(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    alpha: float = ...,
    refine: int = ...,
    tol: float | None = ...,
    max_iter: int = ...,
    return_info: Literal[True],
) -> tuple[torch.Tensor, SolveInfo]: ...
def solve_l2(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    alpha: float = DEFAULT_ALPHA,
    refine: int = 0,
    tol: float | None = None,
    max_iter: int = 500,
    return_info: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, SolveInfo]:
    """Exact screened-Poisson L2 reconstruction (DCT closed form).

    Solves ``(alpha^2 I + Dx^T Dx + Dy^T Dy) x = alpha^2 p + Dx^T dx + Dy^T dy`` with an
    orthonormal 2-D DCT-II computed by FFT (eigenvalues
    ``alpha^2 + (2 - 2cos(pi k/W)) + (2 - 2cos(pi l/H))``). This is the converged answer that
    the reference ``L2D`` preset (50 CG iterations) only approximates.

    Args:
        primal: ``(..., H, W, C)`` (or ``(H, W)``) primal estimate; float tensor, any device.
        dx: Horizontal forward differences, same shape/device (last column ignored).
        dy: Vertical forward differences, same shape/device (last row ignored).
        alpha: Primal weight, > 0 (enters the energy squared). Default 0.2.
        refine: Iterative-refinement steps after the closed form (each one more DCT solve on
            the residual). The closed form alone is accurate to float32 round-off (~3e-7
            relative at 1280x720), so the default is 0.
        tol: Relative residual for the CG solve used only when some inputs are non-finite
            (default :func:`default_tol` of the compute dtype).
        max_iter: Iteration cap of that CG solve.
        return_info: Also return a :class:`SolveInfo`.

    Returns:
        The reconstruction, same shape and device as ``primal``; float64 if any input is
        float64, else float32. With ``return_info`` a tuple ``(image, info)``.

    Raises:
        ValueError: ``alpha <= 0``, mismatched shapes/devices, or an empty image.
        TypeError: Non-tensor or complex inputs.
    """

    def core(
        primal: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor
    ) -> tuple[torch.Tensor, SolveInfo | None, System]:
        t0 = time.perf_counter()
        prob = prepare(primal, dx, dy, alpha)
        h, w = prob.p.shape[-2:]
        dct = LaplaceDCT(h, w, prob.p)
        cg_tol = default_tol(prob.p.dtype) if tol is None else tol
        x, its, res = l2_exact(prob, dct, tol=cg_tol, max_iter=max_iter, refine=refine)
        a2 = prob.alpha**2
        precond = (lambda r: dct.solve(r, a2)) if prob.has_missing else None
        system = System(prob, mask_weights(prob), dct, precond, max_iter, dtypes_of(primal, dx, dy))
        if not return_info:
            return finish(x, prob), None, system
        info = SolveInfo(
            solver="l2",
            cg_iterations=its,
            relative_residual=res if prob.has_missing else relative_residual_of(prob, x, Weights()),
            n_missing=prob.n_missing,
            energy=energy_of(prob, x, "l2"),
            seconds=time.perf_counter() - t0,
        )
        return finish(x, prob), info, system

    out, info = run_solver(core, primal, dx, dy)
    return (out, info) if return_info else out


def _user_weight(
    w: torch.Tensor | None, name: str, like: torch.Tensor, prob: Problem
) -> torch.Tensor | None:
    """User weight (broadcastable to the buffer shape) -> ``(B, 1|C, H, W)`` internal layout."""
    if w is None:
        return None
    if not isinstance(w, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor or None, got {type(w).__name__}")
    shape = prob.out_shape
    if prob.squeeze_channel:
        shape = torch.Size((*shape, 1))
        w = w.unsqueeze(-1)
    keep_c = w.dim() >= 1 and w.shape[-1] == 1
    target = torch.Size((*shape[:-1], 1)) if keep_c else shape
    try:
        w = torch.broadcast_to(w, target)
    except RuntimeError:
        raise ValueError(
            f"{name} of shape {tuple(w.shape)} does not broadcast to the buffer shape "
            f"{tuple(prob.out_shape)}"
        ) from None
    w = w.to(device=like.device)
    if not torch.isfinite(w).all() or (w < 0).any():
        raise ValueError(f"{name} must be finite and >= 0")
    return to_bchw(w, like.dtype, squeeze_channel=False)


@overload
def solve_weighted_cg(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    alpha: float = ...,
    weights_primal: torch.Tensor | None = ...,
    weights_dx: torch.Tensor | None = ...,
    weights_dy: torch.Tensor | None = ...,
    x0: torch.Tensor | None = ...,
    max_iter: int = ...,
    tol: float | None = ...,
    precondition: Precondition = ...,
    return_info: Literal[False] = ...,
    fixed_iterations: bool = ...,
) -> torch.Tensor: ...
@overload
def solve_weighted_cg(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    alpha: float = ...,
    weights_primal: torch.Tensor | None = ...,
    weights_dx: torch.Tensor | None = ...,
    weights_dy: torch.Tensor | None = ...,
    x0: torch.Tensor | None = ...,
    max_iter: int = ...,
    tol: float | None = ...,
    precondition: Precondition = ...,
    return_info: Literal[True],
    fixed_iterations: bool = ...,
) -> tuple[torch.Tensor, SolveInfo]: ...
def solve_weighted_cg(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    alpha: float = DEFAULT_ALPHA,
    weights_primal: torch.Tensor | None = None,
    weights_dx: torch.Tensor | None = None,
    weights_dy: torch.Tensor | None = None,
    x0: torch.Tensor | None = None,
    max_iter: int = 500,
    tol: float | None = None,
    precondition: Precondition = "jacobi",
    return_info: bool = False,
    fixed_iterations: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, SolveInfo]:
    """Weighted least squares by (preconditioned) conjugate gradients.

    Minimises ``sum Wp alpha^2 |x - p|^2 + sum Wx |Dx x - dx|^2 + sum Wy |Dy x - dy|^2`` by
    solving the normal equations ``P^T W P x = P^T W b`` independently per image and channel.
    With all weights ``None`` this is the L2 problem of :func:`solve_l2`.

    Args:
        primal: ``(..., H, W, C)`` (or ``(H, W)``) primal estimate; float tensor, any device.
        dx: Horizontal forward differences, same shape/device (last column ignored).
        dy: Vertical forward differences, same shape/device (last row ignored).
        alpha: Primal weight, > 0.
        weights_primal: Non-negative weights of the primal constraints, broadcastable to the
            buffer shape (e.g. ``(H, W, 1)`` per pixel or ``(H, W, C)`` per channel), or
            ``None`` for ones.
        weights_dx: Same for the ``dx`` constraints (last column ignored).
        weights_dy: Same for the ``dy`` constraints (last row ignored).
        x0: Initial guess, same shape as ``primal``; default the primal (as the reference).
        max_iter: Maximum CG iterations.
        tol: Stop when ``||P^T W b - P^T W P x|| <= tol ||P^T W b||`` for every system
            (default :func:`default_tol` of the compute dtype; 0 runs exactly ``max_iter``
            iterations).
        precondition: ``"jacobi"`` (diagonal), ``"dct"`` (mean-weight Laplacian, exact for
            uniform weights), ``"multigrid"`` (a V-cycle of aggregation multigrid on the
            weighted system; fewest iterations for spatially coherent weights) or ``"none"``
            (plain CG, as the reference solver).
        return_info: Also return a :class:`SolveInfo`.
        fixed_iterations: Run exactly ``max_iter`` Jacobi-preconditioned iterations on every
            system whose start does not already meet ``tol`` (no test after the start;
            ``precondition`` must be ``"jacobi"``), as CG on the Jacobi-scaled system
            (:func:`.cg.jacobi_scaled_cg`: fewer passes per iteration than a tested PCG).

    Returns:
        The reconstruction, same shape/device as ``primal`` (dtype as in :func:`solve_l2`);
        with ``return_info`` a tuple ``(image, info)``.

    Raises:
        ValueError: Bad ``alpha``, shapes, weights or preconditioner name.
        TypeError: Non-tensor inputs.
    """
    if precondition not in PRECONDITIONERS:
        valid = ", ".join(repr(k) for k in PRECONDITIONERS)
        raise ValueError(f"unknown preconditioner {precondition!r}; valid: {valid}")
    if max_iter < 0:
        raise ValueError(f"max_iter must be >= 0, got {max_iter}")
    if fixed_iterations and precondition != "jacobi":
        raise ValueError(f"fixed_iterations runs Jacobi-PCG, got precondition={precondition!r}")
    named = (
        (weights_primal, "weights_primal"),
        (weights_dx, "weights_dx"),
        (weights_dy, "weights_dy"),
    )
    if torch.is_grad_enabled():
        if held := [n for t, n in named if isinstance(t, torch.Tensor) and t.requires_grad]:
            raise ValueError(
                f"{', '.join(held)} require gradients, but the weights are constants of the "
                "solve (only primal, dx and dy get gradients): pass them detached"
            )

    def core(
        primal: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor
    ) -> tuple[torch.Tensor, SolveInfo | None, System]:
        t0 = time.perf_counter()
        prob = prepare(primal, dx, dy, alpha)
        wu = [_user_weight(t, n, prob.p, prob) for t, n in named]
        base = mask_weights(prob)
        wp = _mul_opt(base.p, wu[0])
        wx = _mul_opt(base.x, wu[1][..., :-1] if wu[1] is not None else None)
        wy = _mul_opt(base.y, wu[2][..., :-1, :] if wu[2] is not None else None)
        w = Weights(wp, wx, wy)
        if x0 is None or (x0 is primal and not prob.has_missing):
            x = prob.p  # (pcg starts from a copy)
        else:
            if not isinstance(x0, torch.Tensor) or x0.shape != primal.shape:
                got = tuple(x0.shape) if isinstance(x0, torch.Tensor) else type(x0).__name__
                raise ValueError(
                    f"x0 must have the shape of primal {tuple(primal.shape)}, got {got}"
                )
            x = to_bchw(x0.detach().to(prob.p.device), prob.p.dtype, prob.squeeze_channel)
            x = torch.nan_to_num(x / prob.scale, nan=0.0, posinf=0.0, neginf=0.0)
        h, wd = prob.p.shape[-2:]
        dct = LaplaceDCT(h, wd, prob.p)
        op = Operator(prob, w)
        cg_tol = default_tol(prob.p.dtype) if tol is None else tol
        if fixed_iterations:
            x, its, res = jacobi_scaled_cg(op, rhs(prob, w), x, iterations=max_iter, tol=cg_tol)
        else:
            x, its, res = pcg(
                op,
                rhs(prob, w),
                x,
                max_iter=max_iter,
                tol=cg_tol,
                precond=make_precond(precondition, prob, w, dct, op),
            )
        jacobi = make_precond("jacobi", prob, w, dct, op)
        system = System(prob, w, dct, jacobi, max(max_iter, 1), dtypes_of(primal, dx, dy))
        info = None
        if return_info:
            info = SolveInfo(
                solver="cg",
                cg_iterations=its,
                relative_residual=res,
                n_missing=prob.n_missing,
                seconds=time.perf_counter() - t0,
            )
        return finish(x, prob), info, system

    out, info = run_solver(core, primal, dx, dy)
    return (out, info) if return_info else out


def _mul_opt(a: torch.Tensor | None, b: torch.Tensor | None) -> torch.Tensor | None:
    if a is None:
        return b
    if b is None:
        return a
    return a * b


@overload
def solve_l1(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    alpha: float = ...,
    preset: str | L1Preset = ...,
    progress: ProgressFn | None = ...,
    return_info: Literal[False] = ...,
) -> torch.Tensor: ...
@overload
def solve_l1(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    alpha: float = ...,
    preset: str | L1Preset = ...,
    progress: ProgressFn | None = ...,
    return_info: Literal[True],
) -> tuple[torch.Tensor, SolveInfo]: ...
def solve_l1(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    alpha: float = DEFAULT_ALPHA,
    preset: str | L1Preset = "l1",
    progress: ProgressFn | None = None,
    return_info: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, SolveInfo]:
    """L1 screened-Poisson reconstruction by iteratively reweighted least squares.

    Approximately minimises :func:`l1_energy` (per-constraint Euclidean norms over channels).
    L1 is robust to outliers in the gradients/primal (e.g. failed shifts, fireflies) that L2
    smears into dipoles. IRLS with a finite schedule is an approximation; the presets differ in
    cost and in how close they get to the minimum.

    Args:
        primal: ``(..., H, W, C)`` (or ``(H, W)``) primal estimate; float tensor, any device.
        dx: Horizontal forward differences, same shape/device (last column ignored).
        dy: Vertical forward differences, same shape/device (last row ignored).
        alpha: Primal weight, > 0.
        preset: Name in :data:`L1_PRESETS` (``"l1"``: reference L1D schedule, ``"fast"``:
            accelerated, equal or lower energy in a fraction of the time) or an
            :class:`L1Preset`.
        progress: Optional ``progress(done_rounds, total_rounds)`` callback.
        return_info: Also return a :class:`SolveInfo` (includes the final L1 energy).

    Returns:
        The reconstruction, same shape/device as ``primal`` (dtype as in :func:`solve_l2`);
        with ``return_info`` a tuple ``(image, info)``.

    Raises:
        ValueError: Bad ``alpha``, shapes, empty image or unknown preset (message lists the
            valid names).
        TypeError: Non-tensor inputs.
    """
    pr = get_l1_preset(preset)

    def core(
        primal: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor
    ) -> tuple[torch.Tensor, SolveInfo | None, System]:
        t0 = time.perf_counter()
        prob = prepare(primal, dx, dy, alpha)
        h, w = prob.p.shape[-2:]
        dct = LaplaceDCT(h, w, prob.p)
        x, its, res, weights = irls(prob, pr, dct, progress)
        uniform = weights.p is None and weights.x is None and weights.y is None
        op = Operator(prob, weights)
        precond = None if uniform else make_precond("jacobi", prob, weights, dct, op)
        system = System(prob, weights, dct, precond, ADJOINT_MAX_ITER, dtypes_of(primal, dx, dy))
        info = None
        if return_info:
            info = SolveInfo(
                solver="l1",
                preset=pr.name,
                irls_rounds=pr.rounds,
                cg_iterations=its,
                relative_residual=res,
                n_missing=prob.n_missing,
                energy=energy_of(prob, x, "l1"),
                seconds=time.perf_counter() - t0,
            )
        return finish(x, prob), info, system

    out, info = run_solver(core, primal, dx, dy)
    return (out, info) if return_info else out


def _solver_l2(
    p: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor, alpha: float, progress: ProgressFn | None
) -> tuple[torch.Tensor, SolveInfo]:
    out = solve_l2(p, dx, dy, alpha=alpha, return_info=True)
    if progress is not None:
        progress(1, 1)
    return out


def _solver_l2_cg(
    p: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor, alpha: float, progress: ProgressFn | None
) -> tuple[torch.Tensor, SolveInfo]:
    out = solve_weighted_cg(p, dx, dy, alpha=alpha, precondition="dct", return_info=True)
    if progress is not None:
        progress(1, 1)
    return out


def _solver_l1(
    p: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor, alpha: float, progress: ProgressFn | None
) -> tuple[torch.Tensor, SolveInfo]:
    return solve_l1(p, dx, dy, alpha=alpha, preset="l1", progress=progress, return_info=True)


def _solver_l1_fast(
    p: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor, alpha: float, progress: ProgressFn | None
) -> tuple[torch.Tensor, SolveInfo]:
    return solve_l1(p, dx, dy, alpha=alpha, preset="fast", progress=progress, return_info=True)


_SolverFn = Callable[
    [torch.Tensor, torch.Tensor, torch.Tensor, float, ProgressFn | None],
    tuple[torch.Tensor, SolveInfo],
]

#: Solvers by name, for :func:`solve` (the gdpt methods of the same names):
#: ``"l2"`` exact DCT L2; ``"l2-cg"`` L2 by DCT-preconditioned CG (cross-check);
#: ``"l1"`` reference L1D IRLS; ``"l1-fast"`` accelerated IRLS (preset ``"fast"``).
SOLVERS: dict[str, _SolverFn] = {
    "l2": _solver_l2,
    "l2-cg": _solver_l2_cg,
    "l1": _solver_l1,
    "l1-fast": _solver_l1_fast,
}


@overload
def solve(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    solver: str = ...,
    alpha: float = ...,
    progress: ProgressFn | None = ...,
    return_info: Literal[False] = ...,
) -> torch.Tensor: ...
@overload
def solve(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    solver: str = ...,
    alpha: float = ...,
    progress: ProgressFn | None = ...,
    return_info: Literal[True],
) -> tuple[torch.Tensor, SolveInfo]: ...
def solve(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    solver: str = "l1",
    alpha: float = DEFAULT_ALPHA,
    progress: ProgressFn | None = None,
    return_info: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, SolveInfo]:
    """Screened-Poisson reconstruction by solver name (see :data:`SOLVERS`).

    Args:
        primal: ``(..., H, W, C)`` (or ``(H, W)``) primal estimate; float tensor, any device.
        dx: Horizontal forward differences, same shape/device (last column ignored).
        dy: Vertical forward differences, same shape/device (last row ignored).
        solver: ``"l1"`` (default; reference L1D schedule), ``"l1-fast"``, ``"l2"`` or
            ``"l2-cg"``.
        alpha: Primal weight, > 0.
        progress: Optional ``progress(done, total)`` callback.
        return_info: Also return a :class:`SolveInfo`.

    Returns:
        The reconstruction (same shape/device as ``primal``), or ``(image, info)``.

    Raises:
        ValueError: Unknown solver (message lists the valid names) or bad inputs.
    """
    fn = SOLVERS.get(solver) if isinstance(solver, str) else None
    if fn is None:
        valid = ", ".join(repr(k) for k in SOLVERS)
        raise ValueError(
            f"unknown reconstruction method {solver!r} of the screened-Poisson solvers; "
            f"valid solvers: {valid}"
        )
    out, info = fn(primal, dx, dy, alpha, progress)
    info.solver = solver
    return (out, info) if return_info else out
