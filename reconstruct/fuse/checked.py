"""The held-out safeguard of the fusion: :func:`fuse_checked` keeps the fused image only where
held-out half renders say it beats the denoise (:mod:`gdpt.reconstruct.held_out`).

Layout: images ``(H, W, C)`` float32 tensors on one device (any torch device); variances and
errors ``(H, W, 1)``. Only ``torch`` is imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

import torch

from ..held_out import apply, choose, held_out_terms
from .solve import SOLVE_ITERATIONS, TRUST_RATIO, FuseInfo, fuse_statistics
from .statistics import FusionStatistics, half_statistics

__all__ = [
    "CHECK_BLOCK",
    "CHECK_IMAGE_MARGIN",
    "CHECK_MARGIN",
    "CHECK_TILE",
    "fuse_checked",
    "held_out_fusion_terms",
]

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


def held_out_fusion_terms(
    statistics: FusionStatistics,
    gradient_halves: tuple[tuple[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
    primal_halves: tuple[torch.Tensor, torch.Tensor],
    variance_scales: tuple[float, float],
    *,
    trust_ratio: float = TRUST_RATIO,
    iterations: int = SOLVE_ITERATIONS,
) -> tuple[torch.Tensor, int]:
    """Per-pixel held-out estimate of the fusion's relMSE minus its denoise's: each half's
    fusion ``F_h`` (:func:`.statistics.half_statistics`, the half's gradients) and denoise
    ``D_h`` against the other half's primal (:func:`.held_out.held_out_terms`, relMSE weights
    from the luminance of ``statistics.denoised``).

    Args:
        statistics, gradient_halves, primal_halves, variance_scales, trust_ratio: as for
            :func:`fuse_checked`.
        iterations: CG iterations of each half's solve (at most).

    Returns:
        ``(terms, nonfinite)``: ``(H, W, 1)`` finite terms (< 0 where the fusion looks better)
        and the count of non-finite ones (set to 0).

    Raises:
        ValueError: ``statistics`` has no half denoises.
    """
    options = {"trust_ratio": trust_ratio, "iterations": iterations}
    fused_halves = [
        fuse_statistics(half_statistics(statistics, h, scale), gx, gy, **options)[0]
        for h, ((gx, gy), scale) in enumerate(zip(gradient_halves, variance_scales, strict=True))
    ]
    d_a, d_b = statistics.denoised_halves
    return held_out_terms(
        fused_halves[0],
        d_a,
        fused_halves[1],
        d_b,
        *primal_halves,
        statistics.denoised.mean(-1, keepdim=True),
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
    image, info = fuse_statistics(
        statistics, dx, dy, trust_ratio=trust_ratio, iterations=iterations
    )
    terms, nonfinite = held_out_fusion_terms(
        statistics,
        gradient_halves,
        primal_halves,
        variance_scales,
        trust_ratio=trust_ratio,
        iterations=iterations,
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
