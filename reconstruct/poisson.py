"""Screened-Poisson reconstruction of gradient-domain renders (L2 closed form, weighted CG, L1).

Given a noisy primal image ``p`` and noisy forward-difference gradients ``dx``, ``dy`` (the G-PT
buffers), find the image ``x`` that best agrees with all three. With the constraint operator
``P x = [alpha * x ; Dx x ; Dy x]`` and data ``b = [alpha * p ; dx ; dy]`` the energies are::

    L2:  E2(x) = alpha^2 ||x - p||^2 + ||Dx x - dx||^2 + ||Dy x - dy||^2
    L1:  E1(x) = sum_i alpha |x_i - p_i| + sum_i |(Dx x - dx)_i| + sum_i |(Dy x - dy)_i|

where in ``E1`` every ``|.|`` is the Euclidean norm of one constraint's channel vector (RGB),
as in the reference solver of Kettunen et al. 2015 / Manzi et al. (``poisson/src`` of
``mkettune/ngpt``). Default ``alpha = 0.2``.

Conventions shared with the rest of gdpt (``gdpt.buffers``)::

    dx[y, x] = I[y, x + 1] - I[y, x]      (last column unused)
    dy[y, x] = I[y + 1, x] - I[y, x]      (last row unused, y grows downward)

The forward-difference rows at the last column / last row do not exist (Neumann boundary), so
the supplied ``dx[:, W-1]`` and ``dy[H-1, :]`` have no effect on any result or energy here.
``Dx^T Dx + Dy^T Dy`` is then the reflecting-boundary graph Laplacian ``L``, which the
orthonormal 2-D DCT-II diagonalises with eigenvalues ``(2 - 2cos(pi k/W)) + (2 - 2cos(pi l/H))``.

Solvers:

* :func:`solve_l2`: exact L2 minimiser, ``x = IDCT(DCT(rhs) / lambda)`` (FFT based).
* :func:`solve_weighted_cg`: (preconditioned) conjugate gradients on
  ``P^T W P x = P^T W b`` with per-constraint weights ``W``.
* :func:`solve_l1`: IRLS for ``E1``. Presets are registered by name in :data:`L1_PRESETS`:
  ``"l1"`` reproduces the reference ``L1D`` schedule, ``"fast"`` is a DCT-preconditioned
  variant that reaches an equal or lower ``E1`` several times faster.
* :func:`reconstruct`: single name-based dispatcher (:data:`METHODS`).

Layout, dtype, device: images are ``(..., H, W, C)`` tensors (the project's HWC layout, any
leading batch dimensions, any channel count) or ``(H, W)`` single-channel images. All inputs must
be on one device; computation happens on that device. The compute and output dtype is
``torch.float64`` if any input is float64, else ``torch.float32`` (half/bfloat16/integer inputs
are promoted to float32). Leading batch entries are solved independently.

Non-finite inputs: a constraint (the channel vector of one primal pixel or one gradient) with any
NaN/Inf channel is treated as *missing*: it gets weight zero (a missing primal sample keeps a tiny
weight ``MISSING_PRIMAL_WEIGHT`` towards 0 so that the system stays non-singular). The number of
dropped constraints is reported through a :class:`NonFiniteInputWarning` and in
:class:`SolveInfo` (``return_info=True``). Results are always finite: values beyond the dtype's
range are clamped to its largest finite value.

Gradients: the solvers are differentiable w.r.t. ``primal``, ``dx`` and ``dy`` in torch
autograd. The result solves ``A x = P^T W b`` with ``A = P^T W P`` symmetric positive definite,
so the backward pass solves the adjoint system ``A lam = g`` for the incoming gradient ``g``
(the same solver: the DCT closed form for uniform weights, else preconditioned CG; the forward
iterations are not unrolled) and returns ``alpha^2 Wp lam``, ``Wx Dx lam`` and ``Wy Dy lam``
(zero at the unused last column / row and at missing constraints); the adjoint method of
e.g. Giles and Pierce 2000, *An introduction to the adjoint approach to design*. This is
exact for :func:`solve_l2` and for :func:`solve_weighted_cg` (its weights are constants and get
no gradient). For :func:`solve_l1` it is an approximation: the last IRLS weights are held
fixed, i.e. it is the derivative of the weighted least-squares problem the last round solved,
not of the reweighting itself.

Only ``torch`` and ``numpy`` are imported here (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal, overload

import torch

from .autograd import records

__all__ = [
    "DEFAULT_ALPHA",
    "L1_PRESETS",
    "METHODS",
    "MISSING_PRIMAL_WEIGHT",
    "L1Preset",
    "NonFiniteInputWarning",
    "SolveInfo",
    "dct2",
    "ADJOINT_MAX_ITER",
    "default_tol",
    "get_l1_preset",
    "idct2",
    "l1_energy",
    "l2_energy",
    "reconstruct",
    "solve_l1",
    "solve_l2",
    "solve_weighted_cg",
]

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
        method: Solver name (``"l2"``, ``"cg"``, ``"l1"``...).
        preset: L1 preset name, or ``None``.
        irls_rounds: Number of IRLS reweighting rounds run (0 for linear solves).
        cg_iterations: Total number of (P)CG iterations run.
        relative_residual: ``||b - A x|| / ||b||`` of the last linear system (max over systems),
            ``nan`` if not computed.
        n_missing: Number of dropped (non-finite) constraints per buffer
            (``"primal"``, ``"dx"``, ``"dy"``).
        energy: Final energy of the solved objective (E2 for L2 methods, E1 for L1), or ``None``.
        seconds: Wall-clock time of the solve.
    """

    method: str
    preset: str | None = None
    irls_rounds: int = 0
    cg_iterations: int = 0
    relative_residual: float = math.nan
    n_missing: dict[str, int] = field(default_factory=lambda: {"primal": 0, "dx": 0, "dy": 0})
    energy: float | None = None
    seconds: float = 0.0


# ------------------------------------------------------------------------------------------------
# Input handling
# ------------------------------------------------------------------------------------------------


@dataclass
class _Problem:
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


def _check_buffers(primal: object, dx: object, dy: object) -> None:
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


def _to_bchw(t: torch.Tensor, dtype: torch.dtype, squeeze_channel: bool) -> torch.Tensor:
    """``(..., H, W, C)`` (or ``(H, W)``) -> contiguous ``(B, C, H, W)`` in ``dtype``."""
    if squeeze_channel:
        t = t.unsqueeze(-1)
    h, w, c = t.shape[-3:]
    return t.reshape(-1, h, w, c).permute(0, 3, 1, 2).to(dtype).contiguous()


def _from_bchw(x: torch.Tensor, out_shape: torch.Size, squeeze_channel: bool) -> torch.Tensor:
    y = x.permute(0, 2, 3, 1)
    if squeeze_channel:
        y = y.squeeze(-1)
    return y.reshape(out_shape).contiguous()


def _finite_mask(t: torch.Tensor) -> torch.Tensor:
    """``(B, C, H, W)`` -> ``(B, 1, H, W)`` bool: all channels finite."""
    return torch.isfinite(t).all(dim=1, keepdim=True)


#: |b| range (as a power-of-two exponent) within which no rescaling is needed: squares and sums
#: over up to ~2^40 elements stay finite and normal.
_SAFE_EXP = {torch.float32: 40, torch.float64: 400}


def _pow2_scale(m: float) -> float:
    """Largest power of two ``<= m`` (1 if ``m`` is 0 or not finite); representable if ``m`` is."""
    if not math.isfinite(m) or m <= 0.0:
        return 1.0
    return math.ldexp(1.0, math.frexp(m)[1] - 1)


def _prepare(
    primal: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor, alpha: float, *, warn: bool = True
) -> _Problem:
    """Validate inputs and build the internal, scaled problem."""
    alpha = _check_alpha(alpha)
    _check_buffers(primal, dx, dy)
    dtype = _compute_dtype(primal, dx, dy)
    squeeze = primal.dim() == 2
    p = _to_bchw(primal, dtype, squeeze)
    gx = _to_bchw(dx, dtype, squeeze)[..., :-1]
    gy = _to_bchw(dy, dtype, squeeze)[..., :-1, :]

    fp, fx, fy = _finite_mask(p), _finite_mask(gx), _finite_mask(gy)
    n_missing = {
        "primal": int((~fp).sum()),
        "dx": int((~fx).sum()),
        "dy": int((~fy).sum()),
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
    else:
        gx = gx.contiguous()
        gy = gy.contiguous()

    # Rescale (by a power of two: exact) only when squares/dot products could overflow or
    # underflow; then 1 <= max|b| < 2. L1 regularisers are rescaled along, so results do not
    # change, but in float32 data more than ~1e38 below the maximum then become subnormal.
    amax = max(
        alpha * float(p.abs().max()),
        float(gx.abs().max()) if gx.numel() else 0.0,
        float(gy.abs().max()) if gy.numel() else 0.0,
    )
    lim = _SAFE_EXP[dtype]
    scale = _pow2_scale(amax) if not (2.0**-lim <= amax <= 2.0**lim) else 1.0
    if scale != 1.0:
        p, gx, gy = p / scale, gx / scale, gy / scale
    return _Problem(p, gx, gy, mp, mx, my, alpha, scale, primal.shape, squeeze, n_missing)


def _finish(x: torch.Tensor, prob: _Problem) -> torch.Tensor:
    """Undo scaling and layout; guarantee a finite result."""
    if prob.scale != 1.0:
        x = x * prob.scale
    big = torch.finfo(x.dtype).max
    x = torch.nan_to_num(x, nan=0.0, posinf=big, neginf=-big)
    return _from_bchw(x, prob.out_shape, prob.squeeze_channel)


# ------------------------------------------------------------------------------------------------
# DCT-II via FFT (Makhoul's reordering), along one dimension
# ------------------------------------------------------------------------------------------------


def _twiddle(n: int, like: torch.Tensor) -> torch.Tensor:
    """``exp(-i pi k / (2n))`` for ``k = 0 .. n//2``, complex, on ``like``'s device."""
    k = torch.arange(n // 2 + 1, dtype=torch.float64, device=like.device)
    ang = (-math.pi / (2 * n)) * k
    ctype = torch.complex128 if like.dtype == torch.float64 else torch.complex64
    return torch.polar(torch.ones_like(ang), ang).to(ctype)


def _dct_last(x: torch.Tensor, tw: torch.Tensor | None = None) -> torch.Tensor:
    """Unnormalised DCT-II along the last dim: ``y_k = sum_n x_n cos(pi k (2n+1) / (2N))``."""
    n = x.shape[-1]
    if n == 1:
        return x.clone()
    if tw is None:
        tw = _twiddle(n, x)
    v = torch.cat([x[..., ::2], x[..., 1::2].flip(-1)], dim=-1)
    z = torch.fft.rfft(v, dim=-1) * tw
    m = (n - 1) // 2
    return torch.cat([z.real, z.imag[..., 1 : m + 1].flip(-1).neg()], dim=-1)


def _idct_last(y: torch.Tensor, tw: torch.Tensor | None = None) -> torch.Tensor:
    """Exact inverse of :func:`_dct_last` (a scaled DCT-III) along the last dim."""
    n = y.shape[-1]
    if n == 1:
        return y.clone()
    if tw is None:
        tw = _twiddle(n, y)
    h = n // 2 + 1
    im = torch.zeros_like(y[..., :h])
    # Z_k = y_k - i y_{n-k} for k = 1 .. h-1 (y_n := 0).
    im[..., 1:h] = y[..., n - h + 1 :].flip(-1).neg()
    z = torch.complex(y[..., :h].contiguous(), im) * tw.conj()
    v = torch.fft.irfft(z, n=n, dim=-1)
    x = torch.empty_like(v)
    c = (n + 1) // 2
    x[..., ::2] = v[..., :c]
    x[..., 1::2] = v[..., c:].flip(-1)
    return x


def _ortho_scale(n: int, like: torch.Tensor) -> torch.Tensor:
    s = torch.full((n,), math.sqrt(2.0 / n), dtype=like.dtype, device=like.device)
    s[0] = math.sqrt(1.0 / n)
    return s


def dct2(x: torch.Tensor) -> torch.Tensor:
    """Orthonormal 2-D DCT-II over the last two dimensions (same as SciPy ``norm="ortho"``).

    Args:
        x: ``(..., H, W)`` real floating tensor, any device.

    Returns:
        ``(..., H, W)`` coefficients, same dtype and device; ``[..., l, k]`` is the coefficient
        of vertical frequency ``l`` and horizontal frequency ``k``.
    """
    h, w = x.shape[-2:]
    y = _dct_last(x) * _ortho_scale(w, x)
    y = _dct_last(y.transpose(-1, -2)) * _ortho_scale(h, x)
    return y.transpose(-1, -2)


def idct2(y: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`dct2` (orthonormal 2-D DCT-III over the last two dimensions).

    Args:
        y: ``(..., H, W)`` real floating tensor of DCT-II coefficients, any device.

    Returns:
        ``(..., H, W)`` image, same dtype and device.
    """
    h, w = y.shape[-2:]
    x = _idct_last(y.transpose(-1, -2) / _ortho_scale(h, y))
    return _idct_last(x.transpose(-1, -2) / _ortho_scale(w, y))


class _LaplaceDCT:
    """Solves ``(a * alpha^2 I + c * L) z = r`` for ``(B, C, H, W)`` tensors with the DCT.

    ``a`` and ``c`` are scalars or ``(B, 1, 1, 1)`` / ``(B, C, 1, 1)`` tensors.
    """

    def __init__(self, h: int, w: int, like: torch.Tensor) -> None:
        self.h, self.w = h, w
        self.tw_w = _twiddle(w, like) if w > 1 else None
        self.tw_h = _twiddle(h, like) if h > 1 else None
        dt, dev = like.dtype, like.device
        kx = torch.arange(w, dtype=torch.float64, device=dev)
        ky = torch.arange(h, dtype=torch.float64, device=dev)
        lx = 2.0 - 2.0 * torch.cos(math.pi * kx / w)
        ly = 2.0 - 2.0 * torch.cos(math.pi * ky / h)
        # Eigenvalues of L, laid out like the transformed tensor (B, C, W, H) -> here (H, W).
        self.lam = (ly[:, None] + lx[None, :]).to(dt)

    def forward(self, r: torch.Tensor) -> torch.Tensor:
        """Unnormalised 2-D DCT, returned in ``(B, C, W, H)`` (transposed) layout."""
        y = _dct_last(r, self.tw_w) if self.w > 1 else r
        y = y.transpose(-1, -2)
        return _dct_last(y, self.tw_h) if self.h > 1 else y.contiguous()

    def inverse(self, y: torch.Tensor) -> torch.Tensor:
        x = _idct_last(y, self.tw_h) if self.h > 1 else y
        x = x.transpose(-1, -2)
        return _idct_last(x, self.tw_w) if self.w > 1 else x.contiguous()

    def solve(
        self, r: torch.Tensor, a2: float | torch.Tensor, c: float | torch.Tensor = 1.0
    ) -> torch.Tensor:
        """``z = (a2 I + c L)^-1 r`` (``a2`` already includes ``alpha^2``)."""
        y = self.forward(r)
        denom = self.lam.transpose(0, 1) * c + a2  # (W, H) layout, broadcast over (B, C)
        return self.inverse(y / denom)


# ------------------------------------------------------------------------------------------------
# Operators on the internal layout
# ------------------------------------------------------------------------------------------------


def _grad(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
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
class _Weights:
    """Per-constraint weights on the internal layout (``None`` = all ones).

    ``p``: ``(B, 1|C, H, W)``; ``x``: ``(B, 1|C, H, W-1)``; ``y``: ``(B, 1|C, H-1, W)``.
    """

    p: torch.Tensor | None = None
    x: torch.Tensor | None = None
    y: torch.Tensor | None = None


class _Operator:
    """``A = P^T W P = alpha^2 Wp + Dx^T Wx Dx + Dy^T Wy Dy`` as a 5-point stencil.

    The diagonal is precomputed (it is also the Jacobi preconditioner), so one product costs
    one multiply and four shifted fused multiply-adds.
    """

    def __init__(self, prob: _Problem, w: _Weights) -> None:
        self.w = w
        self.diag = _diag_a(prob, w)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        out = x * self.diag
        wx, wy = self.w.x, self.w.y
        if x.shape[-1] > 1:
            if wx is None:
                out[..., :-1].sub_(x[..., 1:])
                out[..., 1:].sub_(x[..., :-1])
            else:
                out[..., :-1].addcmul_(wx, x[..., 1:], value=-1.0)
                out[..., 1:].addcmul_(wx, x[..., :-1], value=-1.0)
        if x.shape[-2] > 1:
            if wy is None:
                out[..., :-1, :].sub_(x[..., 1:, :])
                out[..., 1:, :].sub_(x[..., :-1, :])
            else:
                out[..., :-1, :].addcmul_(wy, x[..., 1:, :], value=-1.0)
                out[..., 1:, :].addcmul_(wy, x[..., :-1, :], value=-1.0)
        return out


def _rhs(prob: _Problem, w: _Weights) -> torch.Tensor:
    """``P^T W b = alpha^2 Wp p + Dx^T Wx dx + Dy^T Wy dy``."""
    a2 = prob.alpha**2
    out = prob.p * a2 if w.p is None else prob.p * (w.p * a2)
    gx = prob.gx if w.x is None else prob.gx * w.x
    gy = prob.gy if w.y is None else prob.gy * w.y
    return _grad_adj_(out, gx, gy)


def _mask_weights(prob: _Problem) -> _Weights:
    """Weights of the plain problem: 1 for present constraints, 0 (primal: tiny) for missing."""
    if not prob.has_missing:
        return _Weights()
    assert prob.mp is not None
    wp = prob.mp + (1.0 - prob.mp) * MISSING_PRIMAL_WEIGHT
    return _Weights(wp, prob.mx, prob.my)


def default_tol(dtype: torch.dtype) -> float:
    """Default relative CG tolerance: ``1e-5`` for float32 compute, ``1e-10`` for float64."""
    return 1e-10 if dtype == torch.float64 else 1e-5


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-system inner products over ``(H, W)``: ``(B, C, 1, 1)``."""
    return torch.linalg.vecdot(a.flatten(2), b.flatten(2)).unsqueeze(-1).unsqueeze(-1)


def _safe_div(num: torch.Tensor, den: torch.Tensor) -> torch.Tensor:
    ok = den > 0
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))


def _pcg(
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
    ``max_iter`` iterations.

    Returns:
        ``(x, iterations, max relative residual ||r|| / ||b||)``.
    """
    x = x.clone()
    r = b - apply_a(x)
    tiny = torch.finfo(b.dtype).tiny
    bnorm = _dot(b, b).sqrt().clamp_min(tiny)
    rr = _dot(r, r)

    def relres(rr: torch.Tensor) -> float:
        return float((rr.sqrt() / bnorm).max())

    if max_iter <= 0 or (tol > 0 and bool((rr <= (tol * bnorm) ** 2).all())):
        return x, 0, relres(rr)
    z = precond(r) if precond is not None else r
    p = z.clone()
    rz = _dot(r, z)
    thresh = torch.maximum((tol * bnorm) ** 2, rtol0**2 * rr)  # on ||r||^2, per system
    check = tol > 0 or rtol0 > 0  # a host sync per iteration only when stopping early
    active = torch.ones_like(rz, dtype=torch.bool)
    it = 0
    while True:
        ap = apply_a(p)
        step = _safe_div(rz, _dot(p, ap))
        if check:
            step = torch.where(active, step, torch.zeros_like(step))
        x.addcmul_(step, p)
        r.addcmul_(step, ap, value=-1.0)
        it += 1
        z = precond(r) if precond is not None else r
        rz_new = _dot(r, z)
        if check:
            rr = _dot(r, r) if precond is not None else rz_new
            active &= rr > thresh
            if not bool(active.any()):
                break
        if it >= max_iter:
            break
        beta = _safe_div(rz_new, rz)
        p = torch.addcmul(z, p, beta, out=p)  # p = z + beta * p, in place
        rz = rz_new
    if precond is not None or not check:
        rr = _dot(r, r)
    return x, it, relres(rr)


def _relres(prob: _Problem, x: torch.Tensor, w: _Weights) -> float:
    b = _rhs(prob, w)
    r = b - _Operator(prob, w)(x)
    tiny = torch.finfo(b.dtype).tiny
    return float((_dot(r, r).sqrt() / _dot(b, b).sqrt().clamp_min(tiny)).max())


def _l2_exact(
    prob: _Problem, dct: _LaplaceDCT, *, tol: float, max_iter: int, refine: int
) -> tuple[torch.Tensor, int, float]:
    """Exact L2 solve on the internal problem.

    Without missing constraints this is the DCT closed form plus ``refine`` steps of iterative
    refinement (each one more DCT solve on the residual). With missing constraints the closed
    form of the zero-filled problem warm-starts DCT-preconditioned CG.
    """
    a2 = prob.alpha**2
    x = dct.solve(_rhs(prob, _Weights()), a2)
    if not prob.has_missing:
        w = _Weights()
        for _ in range(refine):
            x += dct.solve(_rhs(prob, w) - _Operator(prob, w)(x), a2)
        return x, 0, math.nan
    w = _mask_weights(prob)
    return _pcg(
        _Operator(prob, w),
        _rhs(prob, w),
        x,
        max_iter=max_iter,
        tol=tol,
        precond=lambda r: dct.solve(r, a2),
    )


# ------------------------------------------------------------------------------------------------
# Energies
# ------------------------------------------------------------------------------------------------


def _residuals(prob: _Problem, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Constraint residuals ``P x - b`` (primal part includes the factor alpha)."""
    gx, gy = _grad(x)
    return (x - prob.p) * prob.alpha, gx - prob.gx, gy - prob.gy


def _cnorm(e: torch.Tensor) -> torch.Tensor:
    """Euclidean norm over channels: ``(B, C, h, w)`` -> ``(B, 1, h, w)``.

    Written out per channel: ``torch.linalg.vector_norm(dim=1)`` is ~50x slower on CPU here.
    """
    acc = e[:, :1].square()
    for c in range(1, e.shape[1]):
        acc.addcmul_(e[:, c : c + 1], e[:, c : c + 1])
    return acc.sqrt_()


def _masked_sum(v: torch.Tensor, m: torch.Tensor | None) -> float:
    if m is not None:
        v = v * m
    return float(v.sum(dtype=torch.float64))


def _energy_internal(prob: _Problem, x: torch.Tensor, kind: Literal["l1", "l2"]) -> float:
    ep, ex, ey = _residuals(prob, x)
    if kind == "l1":
        e = sum(_masked_sum(_cnorm(r), m) for r, m in ((ep, prob.mp), (ex, prob.mx), (ey, prob.my)))
        return e * prob.scale
    e = sum(_masked_sum(r * r, m) for r, m in ((ep, prob.mp), (ex, prob.mx), (ey, prob.my)))
    return e * prob.scale**2


def _energy(
    x: torch.Tensor,
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    alpha: float,
    kind: Literal["l1", "l2"],
) -> float:
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"x must be a torch.Tensor, got {type(x).__name__}")
    _check_buffers(primal, dx, dy)
    if x.shape != primal.shape:
        raise ValueError(
            f"x must have the shape of primal, got x {tuple(x.shape)}, primal {tuple(primal.shape)}"
        )
    prob = _prepare(primal, dx, dy, alpha, warn=False)
    xi = _to_bchw(x.to(primal.device), prob.p.dtype, prob.squeeze_channel) / prob.scale
    return _energy_internal(prob, xi, kind)


def l2_energy(
    x: torch.Tensor,
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    alpha: float = DEFAULT_ALPHA,
) -> float:
    """Screened-Poisson L2 energy ``alpha^2 ||x-p||^2 + ||Dx x - dx||^2 + ||Dy x - dy||^2``.

    Only valid constraints count (no ``dx`` at the last column, no ``dy`` at the last row);
    non-finite (missing) constraints are skipped. Accumulated in float64.

    Args:
        x: ``(..., H, W, C)`` or ``(H, W)`` candidate image.
        primal: Primal estimate, same shape as ``x``.
        dx: Horizontal forward differences, same shape.
        dy: Vertical forward differences, same shape.
        alpha: Primal weight (> 0); it enters squared.

    Returns:
        The energy as a Python float (summed over batch entries and channels).

    Raises:
        ValueError: On bad ``alpha`` or mismatched/empty shapes.
    """
    return _energy(x, primal, dx, dy, alpha, "l2")


def l1_energy(
    x: torch.Tensor,
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    alpha: float = DEFAULT_ALPHA,
) -> float:
    """L1 reconstruction energy minimised by :func:`solve_l1`.

    ``E1 = sum_i alpha ||x_i - p_i|| + sum ||(Dx x - dx)_i|| + sum ||(Dy x - dy)_i||`` where
    ``||.||`` is the Euclidean norm over channels of one constraint. Only valid constraints
    count; non-finite (missing) ones are skipped. Accumulated in float64.

    Args:
        x: ``(..., H, W, C)`` or ``(H, W)`` candidate image.
        primal: Primal estimate, same shape as ``x``.
        dx: Horizontal forward differences, same shape.
        dy: Vertical forward differences, same shape.
        alpha: Primal weight (> 0).

    Returns:
        The energy as a Python float (summed over batch entries).

    Raises:
        ValueError: On bad ``alpha`` or mismatched/empty shapes.
    """
    return _energy(x, primal, dx, dy, alpha, "l1")


# ------------------------------------------------------------------------------------------------
# Preconditioners
# ------------------------------------------------------------------------------------------------

Precondition = Literal["none", "jacobi", "dct"]
_PRECONDITIONERS = ("none", "jacobi", "dct")


def _diag_a(prob: _Problem, w: _Weights) -> torch.Tensor:
    """Diagonal of ``A = alpha^2 Wp + Dx^T Wx Dx + Dy^T Wy Dy``: ``(B, 1|C, H, W)``."""
    a2 = prob.alpha**2
    ref = prob.p[:, :1]
    d = torch.full_like(ref, a2) if w.p is None else (w.p * a2).expand_as(ref).clone()
    wx = torch.ones_like(prob.gx[:, :1]) if w.x is None else w.x
    wy = torch.ones_like(prob.gy[:, :1]) if w.y is None else w.y
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


def _make_precond(
    kind: str, prob: _Problem, w: _Weights, dct: _LaplaceDCT, op: _Operator
) -> Callable[[torch.Tensor], torch.Tensor] | None:
    if kind == "none":
        return None
    if kind == "jacobi":
        # Positive: the diagonal has alpha^2 * Wp > 0 (missing primals keep a tiny weight) unless
        # a caller passes zero primal weights; guard so the preconditioner stays finite.
        inv = op.diag.clamp_min(torch.finfo(prob.p.dtype).tiny).reciprocal()
        return lambda r: r * inv
    if kind == "dct":
        a2 = prob.alpha**2
        cp = w.p.mean(dim=(2, 3), keepdim=True) * a2 if w.p is not None else a2
        mx = w.x.mean(dim=(2, 3), keepdim=True) if w.x is not None and w.x.numel() else 1.0
        my = w.y.mean(dim=(2, 3), keepdim=True) if w.y is not None and w.y.numel() else 1.0
        cg = 0.5 * (mx + my)
        return lambda r: dct.solve(r, cp, cg)
    valid = ", ".join(repr(k) for k in _PRECONDITIONERS)
    raise ValueError(f"unknown preconditioner {kind!r}; valid: {valid}")


# ------------------------------------------------------------------------------------------------
# L1 via IRLS
# ------------------------------------------------------------------------------------------------


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
    """CG preconditioner: ``"none"``, ``"jacobi"`` (diagonal of ``P^T W P``) or ``"dct"``
    (DCT solve of the Laplacian with mean weights)."""
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
        if self.precondition not in _PRECONDITIONERS:
            valid = ", ".join(repr(k) for k in _PRECONDITIONERS)
            raise ValueError(
                f"L1Preset {self.name!r}: unknown precondition {self.precondition!r}; "
                f"valid: {valid}"
            )

    def reg(self, k: int) -> float:
        """Regulariser of round ``k >= 1``."""
        return self.reg_init * self.reg_decay ** (k - 1)


#: Named L1 presets (see :class:`L1Preset`).
#:
#: * ``"l1"``: the reference ``L1D`` configuration of the NVIDIA / Kettunen solver: 20 rounds,
#:   reg ``0.05 * 0.5^(k-1)``, 50 plain CG iterations per round, warm start from the primal,
#:   first round unweighted (1000 CG iterations in total).
#: * ``"fast"``: same reweighting schedule, but the first round is the exact DCT L2 solve and the
#:   later rounds use Jacobi-preconditioned CG: rounds 1-9 iterate until each residual dropped
#:   10x (at most 50 iterations; these rounds undo the spread of large outliers), rounds 10-19 run
#:   12 iterations each. The reweighted systems are badly scaled (weights span ~7 orders of
#:   magnitude), which the diagonal preconditioner removes. On G-PT-like inputs it ends at an
#:   equal or lower L1 energy than ``"l1"`` with ~4.5x fewer iterations (see
#:   ``benchmarks/poisson.py``), and it is more robust to huge outliers.
#: * ``"refine"``: ``"fast"`` cut to 10 rounds (adaptive PCG of at most 30 iterations, 8 from
#:   round 6), for a data term that is already close to the solution: the denoised image of the
#:   gated refinement (:mod:`gdpt.reconstruct.refine`). There its gated result is within 0.1%
#:   of ``"fast"``'s relMSE (geometric mean over 180 procedural crops) at 2.3x less time.
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


def _irls_weights(prob: _Problem, x: torch.Tensor, reg: float) -> _Weights:
    """IRLS weights ``1 / (|e| + reg)`` of all constraints, renormalised to mean 1."""
    ep, ex, ey = _residuals(prob, x)
    reg_s = reg / prob.scale
    ws = [(_cnorm(e) + reg_s).reciprocal_() for e in (ep, ex, ey)]
    _normalise_(ws, [prob.mp, prob.mx, prob.my])
    if prob.mp is not None:
        ws[0] += (1.0 - prob.mp) * MISSING_PRIMAL_WEIGHT
    return _Weights(*ws)


def _irls(
    prob: _Problem, preset: L1Preset, dct: _LaplaceDCT, progress: ProgressFn | None
) -> tuple[torch.Tensor, int, float, _Weights]:
    """Run the IRLS schedule; returns ``(x, total CG iterations, last relative residual, the
    last round's weights)``."""
    cg_total = 0
    res = math.nan
    x = prob.p.clone()
    w = _mask_weights(prob)
    for k in range(preset.rounds):
        if k == 0 and preset.exact_first_round:
            cap = max(preset.cg_iters, 50)
            x, its, res = _l2_exact(prob, dct, tol=1e-5, max_iter=cap, refine=0)
            cg_total += its
        else:
            w = _mask_weights(prob) if k == 0 else _irls_weights(prob, x, preset.reg(k))
            op = _Operator(prob, w)
            late = preset.late_round is not None and k >= preset.late_round
            x, its, res = _pcg(
                op,
                _rhs(prob, w),
                x,
                max_iter=preset.late_cg_iters if late else preset.cg_iters,
                tol=0.0,
                precond=_make_precond(preset.precondition, prob, w, dct, op),
                rtol0=0.0 if late else preset.cg_rtol,
            )
            cg_total += its
        if progress is not None:
            progress(k + 1, preset.rounds)
    return x, cg_total, res, w


# ------------------------------------------------------------------------------------------------
# Gradients: the adjoint solve
# ------------------------------------------------------------------------------------------------

#: Iteration cap of an adjoint (P)CG solve with non-uniform weights.
ADJOINT_MAX_ITER = 1000


@dataclass
class _System:
    """The SPD system ``A = P^T W P`` a solve ended with, ``W`` held fixed.

    ``precond`` preconditions the adjoint CG; ``None`` with uniform weights, whose system the
    DCT solves in closed form. ``dtypes``: the dtypes of ``primal``, ``dx``, ``dy``.
    """

    prob: _Problem
    w: _Weights
    dct: _LaplaceDCT
    precond: Callable[[torch.Tensor], torch.Tensor] | None
    max_iter: int
    dtypes: tuple[torch.dtype, torch.dtype, torch.dtype]

    def solve(self, r: torch.Tensor) -> torch.Tensor:
        """``A^-1 r`` on the internal layout."""
        a2 = self.prob.alpha**2
        if self.precond is None:
            return self.dct.solve(r, a2)
        x, _, _ = _pcg(
            _Operator(self.prob, self.w),
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
        lam = self.solve(_to_bchw(grad, prob.p.dtype, prob.squeeze_channel))
        gp = lam * prob.alpha**2
        lx, ly = _grad(lam)
        gx = lx if w.x is None else lx * w.x
        gy = ly if w.y is None else ly * w.y
        if w.p is not None:
            gp = gp * w.p
        if prob.has_missing:
            gp, gx, gy = gp * prob.mp, gx * prob.mx, gy * prob.my
        gx = torch.nn.functional.pad(gx, (0, 1))
        gy = torch.nn.functional.pad(gy, (0, 0, 0, 1))
        return tuple(
            _from_bchw(g, prob.out_shape, prob.squeeze_channel).to(dtype)
            for g, dtype in zip((gp, gx, gy), self.dtypes, strict=True)
        )


_Core = Callable[
    [torch.Tensor, torch.Tensor, torch.Tensor], tuple[torch.Tensor, "SolveInfo | None", _System]
]


class _Solve(torch.autograd.Function):
    """A solver ``core(primal, dx, dy) -> (image, info, system)`` whose backward pass solves
    the adjoint system of ``system``."""

    @staticmethod
    def forward(ctx, core: _Core, primal, dx, dy):
        out, info, system = core(primal, dx, dy)
        ctx.system = system
        return out, info

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad, _info):
        return None, *ctx.system.adjoint(grad)


def _run(
    core: _Core, primal: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor
) -> tuple[torch.Tensor, SolveInfo | None]:
    """``core`` on the buffers, through :class:`_Solve` when autograd records a buffer."""
    if records((primal, dx, dy)):
        return _Solve.apply(core, primal, dx, dy)
    out, info, _ = core(primal, dx, dy)
    return out, info


def _dtypes(*ts: torch.Tensor) -> tuple[torch.dtype, torch.dtype, torch.dtype]:
    return tuple(t.dtype for t in ts)  # type: ignore[return-value]


# ------------------------------------------------------------------------------------------------
# Public solvers
# ------------------------------------------------------------------------------------------------


def _info_energy(prob: _Problem, x: torch.Tensor, kind: Literal["l1", "l2"]) -> float:
    return _energy_internal(prob, x, kind)


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
    ) -> tuple[torch.Tensor, SolveInfo | None, _System]:
        t0 = time.perf_counter()
        prob = _prepare(primal, dx, dy, alpha)
        h, w = prob.p.shape[-2:]
        dct = _LaplaceDCT(h, w, prob.p)
        cg_tol = default_tol(prob.p.dtype) if tol is None else tol
        x, its, res = _l2_exact(prob, dct, tol=cg_tol, max_iter=max_iter, refine=refine)
        a2 = prob.alpha**2
        precond = (lambda r: dct.solve(r, a2)) if prob.has_missing else None
        system = _System(prob, _mask_weights(prob), dct, precond, max_iter, _dtypes(primal, dx, dy))
        if not return_info:
            return _finish(x, prob), None, system
        info = SolveInfo(
            method="l2",
            cg_iterations=its,
            relative_residual=res if prob.has_missing else _relres(prob, x, _Weights()),
            n_missing=prob.n_missing,
            energy=_info_energy(prob, x, "l2"),
            seconds=time.perf_counter() - t0,
        )
        return _finish(x, prob), info, system

    out, info = _run(core, primal, dx, dy)
    return (out, info) if return_info else out


def _user_weight(
    w: torch.Tensor | None, name: str, like: torch.Tensor, prob: _Problem
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
    return _to_bchw(w, like.dtype, squeeze_channel=False)


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
            uniform weights) or ``"none"`` (plain CG, as the reference solver).
        return_info: Also return a :class:`SolveInfo`.

    Returns:
        The reconstruction, same shape/device as ``primal`` (dtype as in :func:`solve_l2`);
        with ``return_info`` a tuple ``(image, info)``.

    Raises:
        ValueError: Bad ``alpha``, shapes, weights or preconditioner name.
        TypeError: Non-tensor inputs.
    """
    if precondition not in _PRECONDITIONERS:
        valid = ", ".join(repr(k) for k in _PRECONDITIONERS)
        raise ValueError(f"unknown preconditioner {precondition!r}; valid: {valid}")
    if max_iter < 0:
        raise ValueError(f"max_iter must be >= 0, got {max_iter}")
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
    ) -> tuple[torch.Tensor, SolveInfo | None, _System]:
        t0 = time.perf_counter()
        prob = _prepare(primal, dx, dy, alpha)
        wu = [_user_weight(t, n, prob.p, prob) for t, n in named]
        base = _mask_weights(prob)
        wp = _mul_opt(base.p, wu[0])
        wx = _mul_opt(base.x, wu[1][..., :-1] if wu[1] is not None else None)
        wy = _mul_opt(base.y, wu[2][..., :-1, :] if wu[2] is not None else None)
        w = _Weights(wp, wx, wy)
        if x0 is None:
            x = prob.p.clone()
        else:
            if not isinstance(x0, torch.Tensor) or x0.shape != primal.shape:
                got = tuple(x0.shape) if isinstance(x0, torch.Tensor) else type(x0).__name__
                raise ValueError(
                    f"x0 must have the shape of primal {tuple(primal.shape)}, got {got}"
                )
            x = _to_bchw(x0.detach().to(prob.p.device), prob.p.dtype, prob.squeeze_channel)
            x = torch.nan_to_num(x / prob.scale, nan=0.0, posinf=0.0, neginf=0.0)
        h, wd = prob.p.shape[-2:]
        dct = _LaplaceDCT(h, wd, prob.p)
        op = _Operator(prob, w)
        cg_tol = default_tol(prob.p.dtype) if tol is None else tol
        x, its, res = _pcg(
            op,
            _rhs(prob, w),
            x,
            max_iter=max_iter,
            tol=cg_tol,
            precond=_make_precond(precondition, prob, w, dct, op),
        )
        jacobi = _make_precond("jacobi", prob, w, dct, op)
        system = _System(prob, w, dct, jacobi, max(max_iter, 1), _dtypes(primal, dx, dy))
        info = None
        if return_info:
            info = SolveInfo(
                method="cg",
                cg_iterations=its,
                relative_residual=res,
                n_missing=prob.n_missing,
                seconds=time.perf_counter() - t0,
            )
        return _finish(x, prob), info, system

    out, info = _run(core, primal, dx, dy)
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
    ) -> tuple[torch.Tensor, SolveInfo | None, _System]:
        t0 = time.perf_counter()
        prob = _prepare(primal, dx, dy, alpha)
        h, w = prob.p.shape[-2:]
        dct = _LaplaceDCT(h, w, prob.p)
        x, its, res, weights = _irls(prob, pr, dct, progress)
        uniform = weights.p is None and weights.x is None and weights.y is None
        op = _Operator(prob, weights)
        precond = None if uniform else _make_precond("jacobi", prob, weights, dct, op)
        system = _System(prob, weights, dct, precond, ADJOINT_MAX_ITER, _dtypes(primal, dx, dy))
        info = None
        if return_info:
            info = SolveInfo(
                method="l1",
                preset=pr.name,
                irls_rounds=pr.rounds,
                cg_iterations=its,
                relative_residual=res,
                n_missing=prob.n_missing,
                energy=_info_energy(prob, x, "l1"),
                seconds=time.perf_counter() - t0,
            )
        return _finish(x, prob), info, system

    out, info = _run(core, primal, dx, dy)
    return (out, info) if return_info else out


# ------------------------------------------------------------------------------------------------
# Dispatcher
# ------------------------------------------------------------------------------------------------


def _m_l2(
    p: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor, alpha: float, progress: ProgressFn | None
) -> tuple[torch.Tensor, SolveInfo]:
    out = solve_l2(p, dx, dy, alpha=alpha, return_info=True)
    if progress is not None:
        progress(1, 1)
    return out


def _m_cg(
    p: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor, alpha: float, progress: ProgressFn | None
) -> tuple[torch.Tensor, SolveInfo]:
    out = solve_weighted_cg(p, dx, dy, alpha=alpha, precondition="dct", return_info=True)
    if progress is not None:
        progress(1, 1)
    return out


def _m_l1(
    p: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor, alpha: float, progress: ProgressFn | None
) -> tuple[torch.Tensor, SolveInfo]:
    return solve_l1(p, dx, dy, alpha=alpha, preset="l1", progress=progress, return_info=True)


def _m_l1_fast(
    p: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor, alpha: float, progress: ProgressFn | None
) -> tuple[torch.Tensor, SolveInfo]:
    return solve_l1(p, dx, dy, alpha=alpha, preset="fast", progress=progress, return_info=True)


_MethodFn = Callable[
    [torch.Tensor, torch.Tensor, torch.Tensor, float, ProgressFn | None],
    tuple[torch.Tensor, SolveInfo],
]

#: Reconstruction methods by name, for :func:`reconstruct`:
#: ``"l2"`` exact DCT L2; ``"l2-cg"`` L2 by DCT-preconditioned CG (cross-check);
#: ``"l1"`` reference L1D IRLS; ``"l1-fast"`` accelerated IRLS (preset ``"fast"``).
METHODS: dict[str, _MethodFn] = {
    "l2": _m_l2,
    "l2-cg": _m_cg,
    "l1": _m_l1,
    "l1-fast": _m_l1_fast,
}


@overload
def reconstruct(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    method: str = ...,
    alpha: float = ...,
    progress: ProgressFn | None = ...,
    return_info: Literal[False] = ...,
) -> torch.Tensor: ...
@overload
def reconstruct(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    method: str = ...,
    alpha: float = ...,
    progress: ProgressFn | None = ...,
    return_info: Literal[True],
) -> tuple[torch.Tensor, SolveInfo]: ...
def reconstruct(
    primal: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    method: str = "l1",
    alpha: float = DEFAULT_ALPHA,
    progress: ProgressFn | None = None,
    return_info: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, SolveInfo]:
    """Screened-Poisson reconstruction by method name (see :data:`METHODS`).

    Args:
        primal: ``(..., H, W, C)`` (or ``(H, W)``) primal estimate; float tensor, any device.
        dx: Horizontal forward differences, same shape/device (last column ignored).
        dy: Vertical forward differences, same shape/device (last row ignored).
        method: ``"l1"`` (default; reference L1D schedule), ``"l1-fast"``, ``"l2"`` or
            ``"l2-cg"``.
        alpha: Primal weight, > 0.
        progress: Optional ``progress(done, total)`` callback.
        return_info: Also return a :class:`SolveInfo`.

    Returns:
        The reconstruction (same shape/device as ``primal``), or ``(image, info)``.

    Raises:
        ValueError: Unknown method (message lists the valid names) or bad inputs.
    """
    fn = METHODS.get(method) if isinstance(method, str) else None
    if fn is None:
        valid = ", ".join(repr(k) for k in METHODS)
        raise ValueError(f"unknown reconstruction method {method!r}; valid methods: {valid}")
    out, info = fn(primal, dx, dy, alpha, progress)
    info.method = method
    return (out, info) if return_info else out
