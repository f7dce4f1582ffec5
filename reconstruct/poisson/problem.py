"""The screened-Poisson problem: input checks, the internal layout, missing constraints.

:func:`prepare` validates ``primal``, ``dx``, ``dy`` (``(..., H, W, C)`` or ``(H, W)``, one
device) and returns a :class:`Problem` in the internal ``(B, C, H, W)`` layout in the compute
dtype (float64 if any input is, else float32), with non-finite constraints zeroed and masked and
extreme magnitudes rescaled by a power of two; :func:`finish` maps a solution back to the
user's shape. :class:`SolveInfo` is what a solve reports.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

#: Default weight of the primal (data) term; it enters the L2 energy squared.
DEFAULT_ALPHA = 0.2

#: Relative weight (w.r.t. a present sample) that keeps a missing primal sample in the system.
MISSING_PRIMAL_WEIGHT = 1e-6

#: ``progress(done, total)`` callback type used by the iterative solvers.
ProgressFn = Callable[[int, int], None]


class NonFiniteInputWarning(RuntimeWarning):
    """Some input constraints were NaN/Inf and were dropped (treated as missing)."""


@dataclass
class SolveInfo:
    """What a solve did; returned next to the image when ``return_info=True``.

    Attributes:
        solver: Solver name (``"l2"``, ``"cg"``, ``"l1"``...; under :func:`solve` its name there).
        preset: L1 preset name, or ``None``.
        irls_rounds: Number of IRLS reweighting rounds run (0 for linear solves).
        cg_iterations: Total number of (P)CG iterations run.
        relative_residual: ``||b - A x|| / ||b||`` of the last linear system (max over systems),
            ``nan`` if not computed.
        n_missing: Number of dropped (non-finite) constraints per buffer
            (``"primal"``, ``"dx"``, ``"dy"``).
        energy: Final energy of the solved objective (E2 for L2 solvers, E1 for L1), or ``None``.
        seconds: Wall-clock time of the solve.
    """

    solver: str
    preset: str | None = None
    irls_rounds: int = 0
    cg_iterations: int = 0
    relative_residual: float = math.nan
    n_missing: dict[str, int] = field(default_factory=lambda: {"primal": 0, "dx": 0, "dy": 0})
    energy: float | None = None
    seconds: float = 0.0


@dataclass
class Problem:
    """Validated problem in the internal ``(B, C, H, W)`` layout (rescaled if extreme).

    ``p``, ``gx`` (``(B, C, H, W-1)``), ``gy`` (``(B, C, H-1, W)``) hold the data with missing
    samples zeroed; ``mp``, ``mx``, ``my`` are ``(B, 1, ., .)`` 0/1 masks of present constraints
    or ``None`` when everything is present. ``scale`` is 1 or a power of two with
    ``original = scaled * scale`` (exact in floating point), used only for extreme magnitudes.
    """

    p: torch.Tensor
    gx: torch.Tensor
    gy: torch.Tensor
    mp: torch.Tensor | None
    mx: torch.Tensor | None
    my: torch.Tensor | None
    alpha: float
    scale: float
    out_shape: torch.Size
    squeeze_channel: bool
    n_missing: dict[str, int]

    @property
    def has_missing(self) -> bool:
        return self.mp is not None


def _check_alpha(alpha: float) -> float:
    try:
        a = float(alpha)
    except (TypeError, ValueError):
        raise TypeError(f"alpha must be a real number, got {alpha!r}") from None
    if not math.isfinite(a) or a <= 0.0:
        raise ValueError(f"alpha must be finite and > 0, got alpha={alpha!r}")
    return a


def _compute_dtype(*ts: torch.Tensor) -> torch.dtype:
    return torch.float64 if any(t.dtype == torch.float64 for t in ts) else torch.float32


def check_buffers(primal: object, dx: object, dy: object) -> None:
    for name, t in (("primal", primal), ("dx", dx), ("dy", dy)):
        if not isinstance(t, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
        if t.is_complex():
            raise TypeError(f"{name} must be real, got dtype {t.dtype}")
    assert isinstance(primal, torch.Tensor)
    assert isinstance(dx, torch.Tensor)
    assert isinstance(dy, torch.Tensor)
    if not (primal.shape == dx.shape == dy.shape):
        raise ValueError(
            "primal, dx and dy must have the same shape, got "
            f"primal {tuple(primal.shape)}, dx {tuple(dx.shape)}, dy {tuple(dy.shape)}"
        )
    if not (primal.device == dx.device == dy.device):
        raise ValueError(
            "primal, dx and dy must be on the same device, got "
            f"primal {primal.device}, dx {dx.device}, dy {dy.device}"
        )
    if primal.dim() < 2:
        raise ValueError(
            f"primal must be (H, W) or (..., H, W, C), got shape {tuple(primal.shape)}"
        )
    if primal.numel() == 0:
        raise ValueError(f"empty image: primal/dx/dy have shape {tuple(primal.shape)}")


def to_bchw(t: torch.Tensor, dtype: torch.dtype, squeeze_channel: bool) -> torch.Tensor:
    """``(..., H, W, C)`` (or ``(H, W)``) -> contiguous ``(B, C, H, W)`` in ``dtype``."""
    if squeeze_channel:
        t = t.unsqueeze(-1)
    h, w, c = t.shape[-3:]
    return t.reshape(math.prod(t.shape[:-3]), h, w, c).permute(0, 3, 1, 2).to(dtype).contiguous()


def from_bchw(x: torch.Tensor, out_shape: torch.Size, squeeze_channel: bool) -> torch.Tensor:
    y = x.permute(0, 2, 3, 1)
    if squeeze_channel:
        y = y.squeeze(-1)
    return y.reshape(out_shape).contiguous()


def _finite_mask(t: torch.Tensor) -> torch.Tensor:
    """``(B, C, H, W)`` -> ``(B, 1, H, W)`` bool: all channels finite."""
    return torch.isfinite(t).all(dim=1, keepdim=True)


#: Power-of-two exponent of the largest ``|b|`` solved unscaled (sums of 2^40 squares stay normal).
_SAFE_EXP = {torch.float32: 40, torch.float64: 400}


def _pow2_scale(m: float) -> float:
    """Largest power of two ``<= m`` (1 if ``m`` is 0 or not finite); representable if ``m`` is."""
    if not math.isfinite(m) or m <= 0.0:
        return 1.0
    return math.ldexp(1.0, math.frexp(m)[1] - 1)


def _abs_max(t: torch.Tensor) -> float:
    """``max |t|`` in one pass, without an ``|t|`` tensor."""
    low, high = torch.aminmax(t)
    return max(-float(low), float(high))


def prepare(
    primal: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor, alpha: float, *, warn: bool = True
) -> Problem:
    """Validate inputs and build the internal, scaled problem."""
    alpha = _check_alpha(alpha)
    check_buffers(primal, dx, dy)
    dtype = _compute_dtype(primal, dx, dy)
    squeeze = primal.dim() == 2
    p = to_bchw(primal, dtype, squeeze)
    # the last column of dx and row of dy are not constraints: left out before the copy
    gx = to_bchw(dx[..., :-1] if squeeze else dx[..., :-1, :], dtype, squeeze)
    gy = to_bchw(dy[..., :-1, :] if squeeze else dy[..., :-1, :, :], dtype, squeeze)

    # one pass per buffer where all is finite (a NaN or inf makes the sum non-finite)
    finite = all(bool(torch.isfinite(t.sum())) for t in (p, gx, gy))
    fp, fx, fy = (None, None, None) if finite else (_finite_mask(t) for t in (p, gx, gy))
    n_missing = {
        name: 0 if m is None else int((~m).sum())
        for name, m in (("primal", fp), ("dx", fx), ("dy", fy))
    }
    mp = mx = my = None
    if any(n_missing.values()):
        if warn:
            warnings.warn(
                f"non-finite inputs treated as missing constraints: {n_missing['primal']} primal, "
                f"{n_missing['dx']} dx, {n_missing['dy']} dy samples",
                NonFiniteInputWarning,
                stacklevel=3,
            )
        zero = torch.zeros((), dtype=dtype, device=p.device)
        p = torch.where(fp, p, zero)
        gx = torch.where(fx, gx, zero)
        gy = torch.where(fy, gy, zero)
        mp, mx, my = (m.to(dtype) for m in (fp, fx, fy))

    # Rescale (by a power of two: exact) only when squares/dot products could overflow or
    # underflow; then 1 <= max|b| < 2. L1 regularisers are rescaled along, so results do not
    # change, but in float32 data more than ~1e38 below the maximum then become subnormal.
    amax = max(
        alpha * _abs_max(p),
        _abs_max(gx) if gx.numel() else 0.0,
        _abs_max(gy) if gy.numel() else 0.0,
    )
    lim = _SAFE_EXP[dtype]
    scale = _pow2_scale(amax) if not (2.0**-lim <= amax <= 2.0**lim) else 1.0
    if scale != 1.0:
        p, gx, gy = p / scale, gx / scale, gy / scale
    return Problem(p, gx, gy, mp, mx, my, alpha, scale, primal.shape, squeeze, n_missing)


def finish(x: torch.Tensor, prob: Problem) -> torch.Tensor:
    """Undo scaling and layout; guarantee a finite result."""
    if prob.scale != 1.0:
        x = x * prob.scale
    big = torch.finfo(x.dtype).max
    x = torch.nan_to_num(x, nan=0.0, posinf=big, neginf=-big)
    return from_bchw(x, prob.out_shape, prob.squeeze_channel)
