"""L1 reconstruction by iteratively reweighted least squares (IRLS) and its named schedules
(:data:`L1_PRESETS`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .cg import (
    Operator,
    Weights,
    l2_exact,
    mask_weights,
    pcg,
    rhs,
)
from .dct import LaplaceDCT
from .energy import channel_norm, residuals
from .precond import PRECONDITIONERS, Precondition, make_precond
from .problem import MISSING_PRIMAL_WEIGHT, Problem, ProgressFn


@dataclass(frozen=True)
class L1Preset:
    """Schedule of the IRLS L1 solver (:func:`solve_l1`).

    Round ``k = 0 .. rounds-1``. Round 0 uses uniform weights (with ``exact_first_round`` it is
    the exact DCT L2 solve instead of CG). Round ``k >= 1`` sets
    ``reg = reg_init * reg_decay**(k-1)`` and gives each constraint ``w = 1 / (|e| + reg)``
    (``|e|`` = channel norm of its current residual), renormalised to mean 1 per image; then
    runs up to ``cg_iters`` (P)CG iterations on ``P^T W P x = P^T W b`` warm-started from
    ``x`` (fewer if ``cg_rtol`` is reached; exactly ``late_cg_iters`` from ``late_round`` on).
    Round 0 starts from the primal. The regulariser is absolute (image units), as in the
    reference, so L1 results depend on the radiance scale.
    """

    name: str
    """Registry name."""
    rounds: int
    """Number of reweighting rounds, including the uniform first round."""
    reg_init: float
    """Weight regulariser of round 1, in image units (the reference uses absolute values)."""
    reg_decay: float
    """Geometric decay of the regulariser per round."""
    cg_iters: int
    """Maximum (P)CG iterations per round."""
    cg_rtol: float = 0.0
    """Stop a round's CG early once every residual norm dropped by this factor (0: never)."""
    late_round: int | None = None
    """From this round on, run exactly ``late_cg_iters`` iterations (no early stop)."""
    late_cg_iters: int = 0
    """Iterations per round from ``late_round`` on."""
    precondition: Precondition = "none"
    """CG preconditioner: ``"none"``, ``"jacobi"`` (diagonal of ``P^T W P``), ``"dct"``
    (DCT solve of the Laplacian with mean weights) or ``"multigrid"`` (a V-cycle on
    ``P^T W P``)."""
    exact_first_round: bool = False
    """Replace the uniform first round by the exact DCT L2 solution."""
    description: str = ""
    """One line for listings."""

    def __post_init__(self) -> None:
        if self.rounds < 1 or self.cg_iters < 0:
            raise ValueError(f"L1Preset {self.name!r}: rounds must be >= 1 and cg_iters >= 0")
        if self.late_round is not None and self.late_cg_iters < 0:
            raise ValueError(f"L1Preset {self.name!r}: late_cg_iters must be >= 0")
        if not (self.reg_init > 0 and 0 < self.reg_decay <= 1):
            raise ValueError(f"L1Preset {self.name!r}: need reg_init > 0, 0 < reg_decay <= 1")
        if self.precondition not in PRECONDITIONERS:
            valid = ", ".join(repr(k) for k in PRECONDITIONERS)
            raise ValueError(
                f"L1Preset {self.name!r}: unknown precondition {self.precondition!r}; "
                f"valid: {valid}"
            )

    def reg(self, k: int) -> float:
        """Regulariser of round ``k >= 1``."""
        return self.reg_init * self.reg_decay ** (k - 1)


#: Named L1 presets (:class:`L1Preset`); what each is for and its measured cost (1280x720,
#: ``benchmarks/poisson.py``): docs/performance.md, "Screened Poisson".
L1_PRESETS: dict[str, L1Preset] = {
    "l1": L1Preset(
        name="l1",
        rounds=20,
        reg_init=0.05,
        reg_decay=0.5,
        cg_iters=50,
        description="reference L1D: 20 IRLS rounds x 50 plain CG iterations",
    ),
    "fast": L1Preset(
        name="fast",
        rounds=20,
        reg_init=0.05,
        reg_decay=0.5,
        cg_iters=50,
        cg_rtol=0.1,
        late_round=10,
        late_cg_iters=12,
        precondition="jacobi",
        exact_first_round=True,
        description="exact L2 start, then 19 rounds of Jacobi-PCG (adaptive, then 12 its)",
    ),
    "refine": L1Preset(
        name="refine",
        rounds=10,
        reg_init=0.05,
        reg_decay=0.5,
        cg_iters=30,
        cg_rtol=0.1,
        late_round=6,
        late_cg_iters=8,
        precondition="jacobi",
        exact_first_round=True,
        description="exact L2 start, then 9 rounds of Jacobi-PCG (adaptive, then 8 its)",
    ),
}


def get_l1_preset(preset: str | L1Preset) -> L1Preset:
    """Look up an L1 preset by name (an :class:`L1Preset` instance is returned unchanged).

    Args:
        preset: Preset name (a key of :data:`L1_PRESETS`) or an :class:`L1Preset`.

    Returns:
        The preset.

    Raises:
        ValueError: If the name is unknown; the message lists the valid names.
    """
    if isinstance(preset, L1Preset):
        return preset
    if isinstance(preset, str) and preset in L1_PRESETS:
        return L1_PRESETS[preset]
    valid = ", ".join(repr(k) for k in L1_PRESETS)
    raise ValueError(f"unknown L1 preset {preset!r}; valid presets: {valid}")


def _normalise_(ws: list[torch.Tensor], masks: list[torch.Tensor | None]) -> None:
    """Zero missing constraints, then scale each image's weights to mean 1 over the present ones."""
    total = count = None
    for w, m in zip(ws, masks, strict=True):
        if m is not None:
            w.mul_(m)
            n = m.sum(dim=(1, 2, 3), dtype=torch.float64)
        else:
            n = torch.full((w.shape[0],), float(w[0].numel()), dtype=torch.float64, device=w.device)
        s = w.sum(dim=(1, 2, 3), dtype=torch.float64)
        total = s if total is None else total + s
        count = n if count is None else count + n
    assert total is not None and count is not None
    coef = torch.where(total > 0, count / total.clamp_min(1e-300), torch.ones_like(total))
    for w in ws:
        w.mul_(coef.to(w.dtype).view(-1, 1, 1, 1))


def _irls_weights(prob: Problem, x: torch.Tensor, reg: float) -> Weights:
    """IRLS weights ``1 / (|e| + reg)`` of all constraints, renormalised to mean 1."""
    ep, ex, ey = residuals(prob, x)
    reg_s = reg / prob.scale
    ws = [(channel_norm(e) + reg_s).reciprocal_() for e in (ep, ex, ey)]
    _normalise_(ws, [prob.mp, prob.mx, prob.my])
    if prob.mp is not None:
        ws[0] += (1.0 - prob.mp) * MISSING_PRIMAL_WEIGHT
    return Weights(*ws)


def irls(
    prob: Problem, preset: L1Preset, dct: LaplaceDCT, progress: ProgressFn | None
) -> tuple[torch.Tensor, int, float, Weights]:
    """Run the IRLS schedule; returns ``(x, total CG iterations, last relative residual, the
    last round's weights)``."""
    cg_total = 0
    res = math.nan
    x = prob.p.clone()
    w = mask_weights(prob)
    for k in range(preset.rounds):
        if k == 0 and preset.exact_first_round:
            cap = max(preset.cg_iters, 50)
            x, its, res = l2_exact(prob, dct, tol=1e-5, max_iter=cap, refine=0)
            cg_total += its
        else:
            w = mask_weights(prob) if k == 0 else _irls_weights(prob, x, preset.reg(k))
            op = Operator(prob, w)
            late = preset.late_round is not None and k >= preset.late_round
            x, its, res = pcg(
                op,
                rhs(prob, w),
                x,
                max_iter=preset.late_cg_iters if late else preset.cg_iters,
                tol=0.0,
                precond=make_precond(preset.precondition, prob, w, dct, op),
                rtol0=0.0 if late else preset.cg_rtol,
            )
            cg_total += its
        if progress is not None:
            progress(k + 1, preset.rounds)
    return x, cg_total, res, w
