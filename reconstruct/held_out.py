"""Choosing between two reconstructions without a reference, from held-out half renders.

Let ``A`` and ``B`` be the two independent halves of a render, ``C_a`` and ``R_a`` a candidate
and a baseline reconstruction computed from ``A`` alone, ``P_b`` the noisy primal of ``B``.
Because ``P_b`` is unbiased and independent of ``A``, per pixel::

    E[(C_a - P_b)^2 - (R_a - P_b)^2] = MSE(C_a) - MSE(R_a)

whatever ``B``'s noise (its variance cancels). Weighted by ``w = 1 / (eps + L^2)`` (the
denominator of relative MSE, ``L`` the baseline's luminance) and averaged with the swapped pair
(``C_b``, ``R_b`` against ``P_a``), the per-pixel terms summed over a region are an unbiased
estimate of the candidate's relMSE difference there (the held-out selection of SURE- and
cross-validation-based denoisers: Li, Wu and Chuang 2012; NFOR, Bitterli et al. 2016, sec. 5).
The candidate of the *whole* render is kept only where that sum is below ``-margin`` standard
errors of itself, else the baseline: unsure means the baseline.

:func:`choose` decides per image (``tile == 0``) or per square tile; the standard error of a
region's sum is taken from the spread of its sub-blocks' sums (``BLOCK`` px), which keeps the
spatial correlation of reconstructed images inside each block.

Layout: images ``(H, W, C)`` float tensors on one device; per-pixel maps ``(H, W, 1)``. Only
``torch`` is imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch.nn import functional as F

__all__ = ["BLOCK", "EPS", "HeldOutChoice", "apply", "choose", "held_out_terms", "region_sums"]

#: Side of the blocks whose sums give a region's standard error, in pixels.
BLOCK = 8

#: ``eps`` of the relMSE weights (that of :func:`gdpt.metrics.relmse`).
EPS = 1e-3


@dataclass
class HeldOutChoice:
    """What :func:`choose` decided.

    Attributes:
        keep: ``(H, W, 1)`` float weight of the candidate per pixel (1: candidate, 0: baseline).
        kept: share of the image's pixels where the candidate is kept.
        tile: region side in pixels (0: the whole image).
        margin: standard errors the held-out sum must fall below zero to keep the candidate.
        image_margin: the same for the whole image before tiles are decided (``None``: none).
        statistic: the whole image's held-out sum over its standard error (< 0: the candidate
            looks better; ``nan`` when the standard error is 0).
        difference: the whole image's estimated relMSE of the candidate minus the baseline's
            (a half render's), per pixel.
        nonfinite: pixels whose held-out term was not finite (counted as 0).
    """

    keep: torch.Tensor
    kept: float
    tile: int
    margin: float
    image_margin: float | None
    statistic: float
    difference: float
    nonfinite: int


def held_out_terms(
    candidate_a: torch.Tensor,
    baseline_a: torch.Tensor,
    candidate_b: torch.Tensor,
    baseline_b: torch.Tensor,
    primal_a: torch.Tensor,
    primal_b: torch.Tensor,
    luminance: torch.Tensor,
    *,
    eps: float = EPS,
) -> tuple[torch.Tensor, int]:
    """Per-pixel held-out estimate of the candidate's relMSE minus the baseline's.

    Args:
        candidate_a, baseline_a: ``(H, W, C)`` reconstructions from half ``a`` only.
        candidate_b, baseline_b: ``(H, W, C)`` the same from half ``b`` only.
        primal_a, primal_b: ``(H, W, C)`` the halves' noisy primals.
        luminance: ``(H, W, 1)`` the luminance in the relMSE weights ``1 / (eps + L^2)``.
        eps: see :data:`EPS`.

    Returns:
        ``(terms, nonfinite)``: ``(H, W, 1)`` terms (channel mean, the two directions averaged;
        non-finite ones set to 0) and how many were not finite.
    """

    def difference(c: torch.Tensor, r: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        # (c - p)^2 - (r - p)^2, without cancelling two large squares
        return ((c - r) * (c + r - 2.0 * p)).mean(-1, keepdim=True)

    raw = 0.5 * (
        difference(candidate_a, baseline_a, primal_b)
        + difference(candidate_b, baseline_b, primal_a)
    )
    terms = raw / (eps + luminance.square())
    finite = torch.isfinite(terms)
    return torch.where(finite, terms, 0.0), int((~finite).sum())


def region_sums(terms: torch.Tensor, size: int) -> torch.Tensor:
    """Sums of ``terms`` ``(H, W, 1)`` over ``size`` px squares (the last ones clipped):
    ``(ceil(H / size), ceil(W / size))``."""
    h, w = terms.shape[:2]
    padded = F.pad(terms[..., 0], (0, -w % size, 0, -h % size))
    return padded.unfold(0, size, size).unfold(1, size, size).sum((-1, -2))


def _sum_and_error(blocks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Sum of block sums ``(..., n)`` and its standard error ``sqrt(n var)`` (0 for n < 2)."""
    n = blocks.shape[-1]
    total = blocks.sum(-1)
    if n < 2:
        return total, torch.zeros_like(total)
    return total, (n * blocks.var(-1)).sqrt()


def choose(
    terms: torch.Tensor,
    *,
    tile: int = 0,
    margin: float = 2.0,
    block: int = BLOCK,
    image_margin: float | None = None,
    nonfinite: int = 0,
) -> HeldOutChoice:
    """Where the candidate's held-out sum is below ``-margin`` standard errors: per image
    (``tile == 0``) or per ``tile`` px square (a multiple of ``block``).

    Args:
        terms: ``(H, W, 1)`` finite per-pixel terms (:func:`held_out_terms`).
        tile: region side (0: the whole image).
        margin: standard errors (>= 0).
        block: side of the blocks whose sums give the standard errors.
        image_margin: with a ``tile``, keep the candidate in the whole image where the image's
            sum is below ``-image_margin`` standard errors, and decide per tile only otherwise
            (``None``: per tile always).
        nonfinite: the non-finite terms' count (:func:`held_out_terms`), recorded.

    Returns:
        The :class:`HeldOutChoice` (its ``keep`` on the device of ``terms``).

    Raises:
        ValueError: ``margin < 0``, ``block < 1`` or ``tile`` not a multiple of ``block``.
    """
    if not margin >= 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    if block < 1 or tile < 0 or tile % block:
        raise ValueError(f"tile must be 0 or a multiple of block {block}, got {tile}")
    h, w = terms.shape[:2]
    blocks = region_sums(terms, block)  # (nby, nbx)
    total, error = _sum_and_error(blocks.reshape(-1))
    statistic = float(total / error) if float(error) > 0 else math.nan
    if tile == 0:
        keep_blocks = torch.full_like(blocks, float(bool(total < -margin * error)))
    elif image_margin is not None and bool(total < -image_margin * error):
        keep_blocks = torch.ones_like(blocks)
    else:
        k = tile // block
        nby, nbx = blocks.shape
        grid = F.pad(blocks, (0, -nbx % k, 0, -nby % k), value=math.nan)
        per_tile = grid.unfold(0, k, k).unfold(1, k, k)
        flat = per_tile.reshape(per_tile.shape[0], per_tile.shape[1], k * k)
        present = ~torch.isnan(flat)
        n = present.sum(-1).clamp_min(1)
        values = torch.where(present, flat, 0.0)
        tile_total = values.sum(-1)
        mean = tile_total / n
        spread = torch.where(present, values - mean.unsqueeze(-1), 0.0).square().sum(-1)
        tile_error = (n / (n - 1).clamp_min(1) * spread).sqrt()
        keep_tiles = (tile_total < -margin * tile_error) & (n > 1)
        keep_blocks = keep_tiles.to(blocks.dtype).repeat_interleave(k, 0).repeat_interleave(k, 1)
    keep = keep_blocks.repeat_interleave(block, 0).repeat_interleave(block, 1)[:h, :w, None]
    return HeldOutChoice(
        keep=keep,
        kept=float(keep.mean()),
        tile=tile,
        margin=margin,
        image_margin=image_margin if tile else None,
        statistic=statistic,
        difference=float(total) / (h * w),
        nonfinite=nonfinite,
    )


def apply(candidate: torch.Tensor, baseline: torch.Tensor, choice: HeldOutChoice) -> torch.Tensor:
    """``candidate`` ``(H, W, C)`` where ``choice`` keeps it, else ``baseline``."""
    return baseline + choice.keep.to(candidate.dtype) * (candidate - baseline)
