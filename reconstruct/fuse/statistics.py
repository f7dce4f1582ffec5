"""The statistics :func:`~gdpt.reconstruct.fuse.fuse` weighs a denoise and gradients by.

The error of a denoise ``D`` comes from two independent half-buffers ``(p_a, D_a)``,
``(p_b, D_b)`` of the same render (:func:`cross_half_error`): ``D_a`` is independent of ``p_b``,
so ``(D_a - p_b)^2 - var(p_b)`` is an unbiased estimate of ``D_a``'s squared error, bias
included (the cross-validation idea of NFOR, Bitterli et al. 2016, sec. 5). The error and the
gradient variances are averaged over windows guided by ``D``'s log-luminance
(:func:`edge_aware_mean`, a joint bilateral filter) so that they do not mix across edges.

Layout: images ``(H, W, C)`` float32 tensors on one device (any torch device); variances and
errors ``(H, W, 1)``. Only ``torch`` is imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch.nn import functional as F

__all__ = [
    "ERROR_RADIUS",
    "ERROR_SCALE",
    "GUIDE_SIGMA",
    "VARIANCE_RADIUS",
    "FusionStatistics",
    "average_finite",
    "box_mean",
    "cross_half_error",
    "edge_aware_mean",
    "fusion_statistics",
    "half_statistics",
    "log_luminance",
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


@dataclass
class FusionStatistics:
    """The inputs of :func:`~gdpt.reconstruct.fuse.fuse` taken from one render and its half-buffers
    (:func:`fusion_statistics`).

    Attributes:
        denoised: ``(H, W, C)`` the primal-only denoise ``D`` of the whole render.
        error: ``(H, W, 1)`` estimated squared error of ``D`` (not floored; may be <= 0).
        error_floor: smallest error :func:`~gdpt.reconstruct.fuse.fuse` uses (``1e-4`` of the
            mean squared luminance of ``D``, at least ``1e-12``).
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
    where ``variance`` is not finite (NaN or inf: no information, zero weight in
    :func:`~gdpt.reconstruct.fuse.fuse` and :func:`~gdpt.reconstruct.fuse.predicted_gain`,
    counted there as ``variance_nonfinite``)."""
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
    """The three primal-only denoises of a render and the statistics
    :func:`~gdpt.reconstruct.fuse.fuse` weighs them by.

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
