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

The error of ``D`` comes from two independent half-buffers of the same render
(:func:`cross_half_error`, the cross-validation idea of NFOR, Bitterli et al. 2016, sec. 5).

Modules: the statistics (:mod:`.statistics`: ``D``'s error, the windowed averages), the
weighted solve (:mod:`.solve`: :func:`fuse`, its weights, :func:`predicted_gain`) and the
held-out safeguard (:mod:`.checked`: :func:`fuse_checked`); every public name is re-exported
here.

Layout: images ``(H, W, C)`` float32 tensors on one device (any torch device); variances and
errors ``(H, W, 1)``. Only ``torch`` is imported (layering rule of ``gdpt.reconstruct``).
"""

from .checked import (
    CHECK_BLOCK,
    CHECK_IMAGE_MARGIN,
    CHECK_MARGIN,
    CHECK_TILE,
    fuse_checked,
    held_out_fusion_terms,
)
from .solve import (
    CORRECTION_BOUND,
    MAX_WEIGHT_RATIO,
    SOLVE_ITERATIONS,
    TRUST_RATIO,
    FuseInfo,
    fuse,
    fuse_halves,
    fuse_statistics,
    fusion_weights,
    predicted_gain,
)
from .statistics import (
    ERROR_RADIUS,
    ERROR_SCALE,
    GUIDE_SIGMA,
    VARIANCE_RADIUS,
    FusionStatistics,
    average_finite,
    box_mean,
    cross_half_error,
    edge_aware_mean,
    fusion_statistics,
    half_statistics,
    log_luminance,
)

__all__ = [
    "CHECK_BLOCK",
    "CHECK_IMAGE_MARGIN",
    "CHECK_MARGIN",
    "CHECK_TILE",
    "CORRECTION_BOUND",
    "ERROR_RADIUS",
    "ERROR_SCALE",
    "GUIDE_SIGMA",
    "MAX_WEIGHT_RATIO",
    "SOLVE_ITERATIONS",
    "TRUST_RATIO",
    "VARIANCE_RADIUS",
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
    "held_out_fusion_terms",
    "log_luminance",
    "predicted_gain",
]
