"""Variance-aware fusion of a denoised image with sampled gradients (screened Poisson).

Given a denoised image ``D`` (any primal-only denoiser), an estimate ``e`` of its per-pixel
squared error, and the gradient-domain render's forward differences ``dx``, ``dy`` with the
variances of their means ``v_x``, ``v_y``, the fused image minimises, per colour channel::

    E(I) = sum_p (I_p - D_p)^2 / e_p
         + sum_p t^x_p (I_{p+x} - I_p - dx_p)^2 / v^x_p + sum_p t^y_p (...)^2 / v^y_p

the generalised-least-squares combination of two independent estimates (Rousselle, Jarosz and
Novak 2016, *Image-space control variate rendering*, sec. 4: the screened Poisson solve as a
control variate weighted by the inverse variances). ``t`` is the trust mask: a gradient enters
only where its variance is at most ``trust_ratio`` times the denoised image's error at both of
its pixels (the regime where the paper's Fig. 5 shows gradients help); elsewhere the result
follows ``D``. With ``v -> 0`` and exact gradients the solve recovers the image up to the
``1/e``-weighted mean error of ``D``; with ``v -> inf`` it returns ``D`` exactly. The result
differs from ``D`` by at most :data:`CORRECTION_BOUND` ``sqrt(e)`` per pixel (a trust region
against wrong statistics).

The error of ``D`` comes from two independent half-buffers ``(p_a, D_a)``, ``(p_b, D_b)`` of
the same render (:func:`cross_half_error`): ``D_a`` is independent of ``p_b``, so
``(D_a - p_b)^2 - var(p_b)`` is an unbiased estimate of ``D_a``'s squared error, bias
included (the cross-validation idea of NFOR, Bitterli et al. 2016, sec. 5).

Layout: images ``(H, W, C)`` float32 tensors on one device (any torch device); variances and
errors ``(H, W, 1)``. Only ``torch`` is imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch.nn import functional as F

from .held_out import apply, choose, held_out_terms
from .poisson import solve_weighted_cg

__all__ = [
    "FuseInfo",
    "FusionStatistics",
    "average_finite",
    "box_mean",
    "cross_half_error",
    "edge_aware_mean",
    "fuse",
    "fuse_checked",
    "fuse_halves",
    "fuse_statistics",
    "fusion_statistics",
    "fusion_weights",
    "half_statistics",
    "log_luminance",
    "predicted_gain",
]

#: Error of a whole-render denoise over a half-render one (0.47-0.87 measured on ``random:5`` and
#: ``cbox-demo``, 128 px, 8 and 32 gradient spp, against 4096-spp references).
ERROR_SCALE = 0.5

#: Window radius of the cross-half error's average (log-correlation with the true error
#: 0.88-0.95 on the scenes of :data:`ERROR_SCALE`).
ERROR_RADIUS = 4

#: Window radius of the gradient variances' average (radius 2 turned cbox-demo's 0.87x relMSE
#: into 1.11x).
VARIANCE_RADIUS = 1

#: Width, in log-luminance, of the edge-aware weights of :func:`edge_aware_mean`.
GUIDE_SIGMA = 0.3

#: Default ``trust_ratio`` of the statistics-driven fusion (:func:`fuse_statistics`).
TRUST_RATIO = 4.0

#: Largest change of a pixel of ``D``, in estimated standard errors ``sqrt(e)`` (a trust region).
CORRECTION_BOUND = 3.0

#: Largest ratio of a gradient weight to the data weight of its pixels (keeps CG conditioned).
MAX_WEIGHT_RATIO = 1e3

#: Conjugate-gradient iterations of a fusion solve (Jacobi-preconditioned, from ``D``). CG
#: stopped early makes the local part of the correction and leaves the long-range part, where
#: integrated gradient noise piles up (early stopping as regularisation): 30 iterations, not 100
#: (which most 128 px solves of cornell-box and veach-mis reached), gave 0.87-0.97x the relMSE
#: on those; 20 gave 0.98-1.02x that of 30 on the 48 renders of the safety table, no render
#: worse than its ``D`` by more than the bar, at 2/3 of the solves' cost (docs/gradients.md).
SOLVE_ITERATIONS = 20

#: :func:`fuse_checked`'s held-out choice (:func:`.held_out.choose`): the fusion is kept in the
#: whole image where the image's held-out sum favours it by :data:`CHECK_IMAGE_MARGIN` standard
#: errors, else in each :data:`CHECK_TILE` px tile whose sum favours it by :data:`CHECK_MARGIN`
#: (standard errors from :data:`CHECK_BLOCK` px blocks). Chosen over per-image choices (margin 1
#: or 2), ungated tiles and 16 px tiles (margin 1 or 2: up to 1.3x ``D`` where the halves are
#: far noisier than ``D``'s error) on 8 scenes x 16-256 gradient spp (docs/gradients.md).
CHECK_TILE = 32
CHECK_MARGIN = 2.0
CHECK_BLOCK = 8
CHECK_IMAGE_MARGIN = 2.0


@dataclass
class FuseInfo:
    """What :func:`fuse` did.

    Attributes:
        trusted: fraction of the gradient constraints used (``t = 1``).
        cg_iterations: conjugate-gradient iterations of the solve.
        relative_residual: final relative residual of the normal equations.
        guards: how often each guard replaced a value: ``error_floor`` (error estimates raised
            to the floor), ``variance_nonfinite`` (non-finite gradient variances, dropped),
            ``weight_ratio_cap`` (gradient weights capped at :data:`MAX_WEIGHT_RATIO`),
            ``correction_bound`` (pixel-channels whose change was limited to
            :data:`CORRECTION_BOUND` standard errors).
        held_out: the held-out choice between the fusion and ``D`` (:func:`fuse_checked`):
            ``kept`` (share of the pixels where the fusion is kept), ``tile``, ``margin``,
            ``image_margin``, ``statistic`` (the image's held-out sum in standard errors, < 0:
            the fusion looks better), ``difference`` (its estimated relMSE difference per
            pixel), ``nonfinite`` (held-out terms that were not finite, counted as 0); empty
            when not checked.
    """

    trusted: float
    cg_iterations: int
    relative_residual: float
    guards: dict[str, int] = field(default_factory=dict)
    held_out: dict[str, float] = field(default_factory=dict)


def box_mean(x: torch.Tensor, radius: int) -> torch.Tensor:
    """Mean of ``x`` ``(H, W, C)`` over a ``(2 radius + 1)^2`` window, the window clipped at
    the border (no padding values); same shape, dtype and device."""
    if radius <= 0:
        return x
    k = 2 * radius + 1
    out = F.avg_pool2d(
        x.permute(2, 0, 1).unsqueeze(0), k, stride=1, padding=radius, count_include_pad=False
    )
    return out.squeeze(0).permute(1, 2, 0)


def edge_aware_mean(
    x: torch.Tensor, guide: torch.Tensor, radius: int, sigma: float
) -> torch.Tensor:
    """Mean of ``x`` ``(H, W, C)`` over a ``(2 radius + 1)^2`` window, each neighbour weighted
    by ``exp(-(g_q - g_p)^2 / (2 sigma^2))`` of the guide ``(H, W, 1)`` (a joint bilateral
    filter, Petschnigg et al. 2004): statistics do not mix across edges of the guide (a light
    next to a black background). Window clipped at the border; same shape, dtype and device.
    """
    if radius <= 0:
        return x
    h, w = x.shape[:2]
    total = x.clone()
    weight = torch.ones_like(guide)
    scale = -0.5 / (sigma * sigma)
    # Each pair of pixels p, q = p + (oy, ox) once: the weight is symmetric, so it is added
    # at both ends (one pass per offset over the image, no (k^2, H, W) window tensor).
    for oy in range(min(radius, h - 1) + 1):
        for ox in range(-min(radius, w - 1), min(radius, w - 1) + 1):
            if oy == 0 and ox <= 0:
                continue
            p = (slice(0, h - oy), slice(max(0, -ox), w - max(0, ox)))
            q = (slice(oy, h), slice(max(0, ox), w - max(0, -ox)))
            pair = (guide[q] - guide[p]).square_().mul_(scale).exp_()
            weight[p] += pair
            weight[q] += pair
            total[p].addcmul_(pair, x[q])
            total[q].addcmul_(pair, x[p])
    return total.div_(weight)


def log_luminance(image: torch.Tensor, eps: float = 1e-2) -> torch.Tensor:
    """``log(eps + mean_c(image))`` ``(H, W, 1)``: the guide of :func:`edge_aware_mean`."""
    return torch.log(eps + image.clamp_min(0).mean(-1, keepdim=True))


def cross_half_error(
    denoised_a: torch.Tensor,
    denoised_b: torch.Tensor,
    primal_a: torch.Tensor,
    primal_b: torch.Tensor,
    *,
    radius: int = 3,
) -> torch.Tensor:
    """Per-pixel squared error of a half-buffer denoise, bias included, from cross-validation.

    ``(D_a - p_b)^2`` has expectation ``err(D_a) + var(p_b)`` because ``D_a`` depends only on
    half ``a``; ``var(p_b)`` is estimated from ``(p_a - p_b)^2 / 2`` (equal halves). Both are
    averaged over the two halves, the channels and a box window of ``radius``.

    Args:
        denoised_a, denoised_b: ``(H, W, C)`` denoiser outputs on halves ``a`` and ``b``.
        primal_a, primal_b: ``(H, W, C)`` the noisy half primals.
        radius: box-window radius of the local average (>= 0).

    Returns:
        ``(H, W, 1)`` estimate of the squared error of one half's denoise (may be <= 0 where
        the estimate is noise-dominated: callers floor it).
    """
    cross = (denoised_a - primal_b).square() + (denoised_b - primal_a).square()
    noise = (primal_a - primal_b).square()
    raw = (0.5 * cross - 0.5 * noise).mean(-1, keepdim=True)
    return box_mean(raw, radius)


def fusion_weights(
    error: torch.Tensor,
    var_dx: torch.Tensor,
    var_dy: torch.Tensor,
    *,
    trust_ratio: float,
    error_floor: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float, dict[str, int]]:
    """Data and gradient weights of :func:`fuse`, in ratio form.

    The energy is scaled by ``s = median(e)`` so that weights are ``s / e`` and ``s / v``
    (float32 stays far from its range even for ``e`` near the floor).

    Args:
        error: ``(H, W, 1)`` squared-error estimate of the denoised image.
        var_dx, var_dy: ``(H, W, 1)`` variances of the means of ``dx``/``dy``.
        trust_ratio: use a gradient only where ``v <= trust_ratio * min(e_p, e_q)`` over its
            two pixels ``p``, ``q``.
        error_floor: smallest error (errors below it are raised to it, counted).

    Returns:
        ``(w_d, w_x, w_y, trusted_fraction, guards)``: ``(H, W, 1)`` weights (``w_x`` zero in
        the last column, ``w_y`` in the last row) and the guard counts of :class:`FuseInfo`.
    """
    guards = {
        "error_floor": int((~(error >= error_floor)).sum()),
        "variance_nonfinite": int(
            (~torch.isfinite(var_dx)).sum() + (~torch.isfinite(var_dy)).sum()
        ),
    }
    e = torch.nan_to_num(error, nan=error_floor).clamp_min(error_floor)
    scale = e.median()
    w_d = scale / e
    # the error a gradient between p and q must beat: the smaller of its two pixels'
    e_x = torch.minimum(e[:, :-1], e[:, 1:])
    e_y = torch.minimum(e[:-1], e[1:])
    weights, capped, used = [], 0, 0
    # (variances of the existing constraints, their pair errors, padding back to (H, W, 1))
    pairs = ((var_dx[:, :-1], e_x, (0, 0, 0, 1)), (var_dy[:-1], e_y, (0, 0, 0, 0, 0, 1)))
    for var, e_pair, pad in pairs:
        v = torch.nan_to_num(var, nan=float("inf"), posinf=float("inf"))
        trust = v <= trust_ratio * e_pair
        ratio = e_pair / v.clamp_min(torch.finfo(v.dtype).tiny)
        capped += int((trust & (ratio > MAX_WEIGHT_RATIO)).sum())
        w = torch.where(trust, scale / e_pair * ratio.clamp_max(MAX_WEIGHT_RATIO), 0.0)
        used += int(trust.sum())
        weights.append(F.pad(w, pad))
    guards["weight_ratio_cap"] = capped
    n_constraints = var_dx[:, :-1].numel() + var_dy[:-1].numel()
    return w_d, weights[0], weights[1], used / max(n_constraints, 1), guards


def fuse(
    denoised: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    var_dx: torch.Tensor,
    var_dy: torch.Tensor,
    error: torch.Tensor,
    *,
    trust_ratio: float = 1.0,
    error_floor: float = 1e-8,
    max_iter: int = SOLVE_ITERATIONS,
    tol: float = 1e-3,
) -> tuple[torch.Tensor, FuseInfo]:
    """Fuse a denoised image with sampled gradients (the energy of the module docstring).

    Args:
        denoised: ``(H, W, C)`` float32 primal-only denoiser output ``D``.
        dx, dy: ``(H, W, C)`` forward-difference estimates (last column / row unused).
        var_dx, var_dy: ``(H, W, 1)`` variances of their means (``inf``: unusable; such a
            gradient, like any of zero weight, is not read).
        error: ``(H, W, 1)`` squared-error estimate of ``D`` (e.g. :func:`cross_half_error`).
        trust_ratio: see :func:`fusion_weights` (``0``: return ``D``).
        error_floor: see :func:`fusion_weights`; > 0.
        max_iter, tol: exactly ``max_iter`` Jacobi-preconditioned CG iterations from ``D``,
            none for a channel whose start already has a relative residual <= ``tol``.

    Returns:
        ``(image, info)``: the fused ``(H, W, C)`` image (dtype and device of ``denoised``)
        and a :class:`FuseInfo`.

    Raises:
        ValueError: shapes or devices disagree, ``error_floor <= 0`` or ``trust_ratio < 0``.
    """
    if not error_floor > 0:
        raise ValueError(f"error_floor must be > 0, got {error_floor}")
    if not trust_ratio >= 0:
        raise ValueError(f"trust_ratio must be >= 0, got {trust_ratio}")
    h, w = denoised.shape[:2]
    for name, t, c in (
        ("dx", dx, denoised.shape[2]),
        ("dy", dy, denoised.shape[2]),
        ("var_dx", var_dx, 1),
        ("var_dy", var_dy, 1),
        ("error", error, 1),
    ):
        if tuple(t.shape) != (h, w, c):
            raise ValueError(f"fuse: {name} has shape {tuple(t.shape)}, expected {(h, w, c)}")
        if t.device != denoised.device:
            raise ValueError(f"fuse: {name} is on {t.device}, denoised on {denoised.device}")
    w_d, w_x, w_y, trusted, guards = fusion_weights(
        error, var_dx, var_dy, trust_ratio=trust_ratio, error_floor=error_floor
    )
    if trusted == 0.0:
        return denoised.clone(), FuseInfo(0.0, 0, 0.0, guards)
    # a gradient of zero weight (untrusted, infinite variance: not traced) is not read
    dx, dy = torch.where(w_x > 0, dx, 0.0), torch.where(w_y > 0, dy, 0.0)
    image, info = solve_weighted_cg(
        denoised,
        dx,
        dy,
        alpha=1.0,
        weights_primal=w_d,
        weights_dx=w_x,
        weights_dy=w_y,
        x0=denoised,
        max_iter=max_iter,
        tol=tol,
        precondition="jacobi",
        return_info=True,
        fixed_iterations=True,
    )
    bound = CORRECTION_BOUND * torch.sqrt(error.nan_to_num(0.0).clamp_min(error_floor))
    change = image.to(denoised.dtype) - denoised
    guards["correction_bound"] = int((change.abs() > bound).sum())
    image = denoised + torch.maximum(torch.minimum(change, bound), -bound)
    return image, FuseInfo(trusted, info.cg_iterations, info.relative_residual, guards)


def predicted_gain(
    denoised: torch.Tensor,
    error: torch.Tensor,
    var_dx: torch.Tensor,
    var_dy: torch.Tensor,
    *,
    trust_ratio: float = TRUST_RATIO,
    eps: float = 1e-3,
) -> float:
    """Predicted relative MSE of :func:`fuse` over that of ``D`` (< 1: the gradients help).

    Per pixel, the trusted gradients at it (as in :func:`fusion_weights`) act as one more
    estimate with variance ``v = 1 / sum(1 / v_k)``, combined with ``D`` as independent
    estimates: ``e v / (e + v)``; the ratio of the sums is weighted as relative MSE
    (``1 / (eps + L_D^2)``, the denominator of the metric with ``D`` for the reference). It
    ignores that gradients fix differences only, so it is optimistic: a route choice compares
    it with a margin.

    Args:
        denoised: ``(H, W, C)``; error, var_dx, var_dy: ``(H, W, 1)`` as for :func:`fuse`.

    Returns:
        The ratio in ``(0, 1]`` (1 when no gradient is trusted).
    """
    e = error.clamp_min(torch.finfo(error.dtype).tiny)
    precision = torch.zeros_like(e)
    for var, axis in ((var_dx, 1), (var_dy, 0)):
        v = torch.nan_to_num(var, nan=float("inf"), posinf=float("inf"))
        n = v.shape[axis] - 1
        v, here, there = v.narrow(axis, 0, n), e.narrow(axis, 0, n), e.narrow(axis, 1, n)
        p = torch.where(v <= trust_ratio * torch.minimum(here, there), 1.0 / v, 0.0)
        p = torch.nan_to_num(p, posinf=torch.finfo(p.dtype).max)
        precision.narrow(axis, 0, n).add_(p)
        precision.narrow(axis, 1, n).add_(p)
    fused = e / (1.0 + e * precision)
    weight = 1.0 / (eps + denoised.mean(-1, keepdim=True).square())
    return float((weight * fused).sum() / (weight * e).sum())


@dataclass
class FusionStatistics:
    """The inputs of :func:`fuse` taken from one render and its half-buffers
    (:func:`fusion_statistics`).

    Attributes:
        denoised: ``(H, W, C)`` the primal-only denoise ``D`` of the whole render.
        error: ``(H, W, 1)`` estimated squared error of ``D`` (not floored; may be <= 0).
        error_floor: smallest error :func:`fuse` uses (``1e-4`` of the mean squared luminance
            of ``D``, at least ``1e-12``).
        var_dx, var_dy: ``(H, W, 1)`` locally averaged gradient variances; ``inf`` where the
            render's variance is not finite (no information: the gradient gets zero weight).
        denoised_halves: ``(D_a, D_b)``, the ``(H, W, C)`` denoises of the two halves, or
            ``None``.
        error_scale: :attr:`error` over the estimated error of a half's denoise.
    """

    denoised: torch.Tensor
    error: torch.Tensor
    error_floor: float
    var_dx: torch.Tensor
    var_dy: torch.Tensor
    denoised_halves: tuple[torch.Tensor, torch.Tensor] | None = None
    error_scale: float = ERROR_SCALE

    def floored_error(self) -> torch.Tensor:
        """:attr:`error` raised to :attr:`error_floor`."""
        return self.error.clamp_min(self.error_floor)


def average_finite(
    variance: torch.Tensor, guide: torch.Tensor, radius: int, sigma: float
) -> torch.Tensor:
    """:func:`edge_aware_mean` of ``variance`` ``(H, W, 1)`` over its finite values only; ``inf``
    where ``variance`` is not finite (NaN or inf: no information, zero weight in :func:`fuse`
    and :func:`predicted_gain`, counted there as ``variance_nonfinite``)."""
    finite = torch.isfinite(variance)
    if bool(finite.all()):
        return edge_aware_mean(variance, guide, radius, sigma)
    total = edge_aware_mean(torch.where(finite, variance, 0.0), guide, radius, sigma)
    share = edge_aware_mean(finite.to(variance.dtype), guide, radius, sigma)
    return torch.where(finite, total / share.clamp_min(torch.finfo(share.dtype).tiny), torch.inf)


def fusion_statistics(
    denoise: Callable[[str], torch.Tensor],
    primal_a: torch.Tensor,
    primal_b: torch.Tensor,
    var_dx: torch.Tensor,
    var_dy: torch.Tensor,
    *,
    error_scale: float = ERROR_SCALE,
) -> FusionStatistics:
    """The three primal-only denoises of a render and the statistics :func:`fuse` weighs them by.

    The error of ``D`` is ``error_scale`` times the :func:`cross_half_error` of the half
    denoises; it and the gradient variances (:func:`average_finite`) are averaged by
    :func:`edge_aware_mean` guided by the :func:`log_luminance` of ``D``.

    Args:
        denoise: ``denoise(part) -> (H, W, C)`` the primal-only denoise of the whole render
            (``part == "full"``, gradients left out) or of its half ``"a"`` or ``"b"``.
        primal_a, primal_b: ``(H, W, C)`` the noisy half primals.
        var_dx, var_dy: ``(H, W, 1)`` variances of the gradients' means.
        error_scale: error of the whole render's denoise over that of a half's.

    Returns:
        The :class:`FusionStatistics` (tensors on the device of the denoises).
    """
    denoised, denoised_a, denoised_b = (denoise(part) for part in ("full", "a", "b"))
    guide = log_luminance(denoised)
    raw = cross_half_error(denoised_a, denoised_b, primal_a, primal_b, radius=0)
    error = error_scale * edge_aware_mean(raw, guide, ERROR_RADIUS, GUIDE_SIGMA)
    v_x, v_y = (average_finite(v, guide, VARIANCE_RADIUS, GUIDE_SIGMA) for v in (var_dx, var_dy))
    floor = max(1e-4 * float(denoised.mean(-1).square().mean()), 1e-12)
    return FusionStatistics(denoised, error, floor, v_x, v_y, (denoised_a, denoised_b), error_scale)


def fuse_statistics(
    statistics: FusionStatistics,
    dx: torch.Tensor,
    dy: torch.Tensor,
    *,
    trust_ratio: float = TRUST_RATIO,
    iterations: int = SOLVE_ITERATIONS,
) -> tuple[torch.Tensor, FuseInfo]:
    """:func:`fuse` of ``dx``, ``dy`` ``(H, W, C)`` with the denoise and weights of
    ``statistics``, at most ``iterations`` CG iterations; returns as :func:`fuse`."""
    s = statistics
    return fuse(
        s.denoised,
        dx,
        dy,
        s.var_dx,
        s.var_dy,
        s.error,
        trust_ratio=trust_ratio,
        error_floor=s.error_floor,
        max_iter=iterations,
    )


def fuse_halves(
    denoised: torch.Tensor,
    denoised_a: torch.Tensor,
    denoised_b: torch.Tensor,
    primal_a: torch.Tensor,
    primal_b: torch.Tensor,
    dx: torch.Tensor,
    dy: torch.Tensor,
    var_dx: torch.Tensor,
    var_dy: torch.Tensor,
    *,
    trust_ratio: float = TRUST_RATIO,
    error_scale: float = ERROR_SCALE,
) -> tuple[torch.Tensor, FuseInfo]:
    """:func:`fuse` with every statistic taken from denoises already computed
    (:func:`fusion_statistics` with ``denoise`` returning them).

    Args:
        denoised, denoised_a, denoised_b: ``(H, W, C)`` denoiser outputs on the full render and
            on its halves ``a`` and ``b``.
        primal_a, primal_b: ``(H, W, C)`` the noisy half primals.
        dx, dy: ``(H, W, C)`` gradients; var_dx, var_dy: ``(H, W, 1)`` their variances.
        trust_ratio, error_scale: see :func:`fusion_weights` and :func:`fusion_statistics`.

    Returns:
        As :func:`fuse`.
    """
    parts = {"full": denoised, "a": denoised_a, "b": denoised_b}
    statistics = fusion_statistics(
        parts.__getitem__, primal_a, primal_b, var_dx, var_dy, error_scale=error_scale
    )
    return fuse_statistics(statistics, dx, dy, trust_ratio=trust_ratio)


def half_statistics(
    statistics: FusionStatistics, which: int, variance_scale: float
) -> FusionStatistics:
    """The statistics of a fusion of half ``which`` (0: ``a``, 1: ``b``) alone: its denoise,
    the error of a half's denoise, the gradient variances times ``variance_scale`` (the whole
    render's gradient samples over the half's).

    Raises:
        ValueError: ``statistics`` has no :attr:`~FusionStatistics.denoised_halves`.
    """
    s = statistics
    if s.denoised_halves is None:
        raise ValueError("half_statistics: these statistics have no half denoises")
    return FusionStatistics(
        s.denoised_halves[which],
        s.error / s.error_scale,
        s.error_floor,
        s.var_dx * variance_scale,
        s.var_dy * variance_scale,
    )


def fuse_checked(
    statistics: FusionStatistics,
    dx: torch.Tensor,
    dy: torch.Tensor,
    gradient_halves: tuple[tuple[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
    primal_halves: tuple[torch.Tensor, torch.Tensor],
    variance_scales: tuple[float, float],
    *,
    trust_ratio: float = TRUST_RATIO,
    tile: int = CHECK_TILE,
    margin: float = CHECK_MARGIN,
    block: int = CHECK_BLOCK,
    image_margin: float | None = CHECK_IMAGE_MARGIN,
    iterations: int = SOLVE_ITERATIONS,
) -> tuple[torch.Tensor, FuseInfo]:
    """:func:`fuse_statistics`, kept only where held-out data say it beats ``D``.

    Each half's fusion ``F_h`` (:func:`half_statistics`, the half's gradients) and denoise
    ``D_h`` are compared against the other half's primal (:func:`.held_out.held_out_terms`,
    relMSE weights from ``D``); the whole render's fusion is kept where the sum is below
    ``-margin`` standard errors (:func:`.held_out.choose`: per ``tile``, or the whole image
    where it passes ``image_margin``), else ``D``. Assumes the choice between the half fusions
    carries over to the whole render's (both have the same statistics, at twice the samples).
    The half fusions' weights use statistics of the whole render (smoothed over windows): a
    second-order dependence on the held-out half.

    Args:
        statistics: :func:`fusion_statistics` of the render (with its half denoises).
        dx, dy: ``(H, W, C)`` the render's gradients.
        gradient_halves: ``((dx_a, dy_a), (dx_b, dy_b))`` the halves' gradients.
        primal_halves: ``(p_a, p_b)`` the halves' noisy primals ``(H, W, C)``.
        variance_scales: per half, the render's gradient samples over the half's (``inf``: a
            half without samples; its fusion is its denoise and ``D`` is kept).
        trust_ratio: see :func:`fusion_weights`.
        tile, margin, block, image_margin: see :func:`.held_out.choose`.
        iterations: CG iterations of each of the three solves (at most).

    Returns:
        As :func:`fuse`; :attr:`FuseInfo.held_out` says what was kept.
    """
    options = {"trust_ratio": trust_ratio, "iterations": iterations}
    image, info = fuse_statistics(statistics, dx, dy, **options)
    fused_halves = [
        fuse_statistics(half_statistics(statistics, h, scale), gx, gy, **options)[0]
        for h, ((gx, gy), scale) in enumerate(zip(gradient_halves, variance_scales, strict=True))
    ]
    d_a, d_b = statistics.denoised_halves
    terms, nonfinite = held_out_terms(
        fused_halves[0],
        d_a,
        fused_halves[1],
        d_b,
        *primal_halves,
        statistics.denoised.mean(-1, keepdim=True),
    )
    choice = choose(
        terms,
        tile=tile,
        margin=margin,
        block=block,
        image_margin=image_margin,
        nonfinite=nonfinite,
    )
    info.held_out = {
        name: getattr(choice, name)
        for name in ("kept", "tile", "margin", "image_margin", "statistic", "difference")
    } | {"nonfinite": choice.nonfinite}
    return apply(image, statistics.denoised, choice), info
