"""The fusion solve: the weighted screened Poisson energy of :mod:`gdpt.reconstruct.fuse`, its
weights in ratio form, its trust region, and the gain it predicts.

Layout: images ``(H, W, C)`` float32 tensors on one device (any torch device); variances and
errors ``(H, W, 1)``. Only ``torch`` is imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch.nn import functional as F

from ..poisson import solve_weighted_cg
from .statistics import ERROR_SCALE, FusionStatistics, fusion_statistics

__all__ = [
    "CORRECTION_BOUND",
    "MAX_WEIGHT_RATIO",
    "SOLVE_ITERATIONS",
    "TRUST_RATIO",
    "FuseInfo",
    "fuse",
    "fuse_halves",
    "fuse_statistics",
    "fusion_weights",
    "predicted_gain",
]

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
