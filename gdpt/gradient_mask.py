"""A gradient mask from a pilot render: offsets only in the tiles where the gradients are
predicted to pay, and the masked render of ``fuse`` that uses it.

:func:`render_masked` renders a small gradient pilot (``fuse``'s sampling: pooled primal,
variances, halves), turns it into a per-tile mask (:func:`pilot_mask`), renders the rest of the
gradient samples with offsets only inside the mask (``gdpt.render(..., gradient_mask=M)``) and
merges both renders, the pilot's gradients outside the mask marked untraced, so every sample
the pilot traced goes into the image except those gradients.

Two designs predict where gradients pay, both on :data:`TILE` px tiles (a partial tile at the
right or bottom edge counts its pixels only):

* ``"trust"``: the share of a tile's gradients (``dx``, ``dy`` of its pixels) that ``fuse``'s
  trust rule (:func:`gdpt.reconstruct.fuse.fusion_weights`: a gradient's variance at most
  ``trust_ratio`` times the denoiser's estimated error at both its pixels) keeps, from the
  pilot's fusion statistics (three primal-only denoises); the tile is masked when the share is
  at least ``min_share`` (the per-gradient decision is rounded to tiles by this vote;
  ``min_share`` -> 0 rounds up: any kept gradient sets its tile).
* ``"variance"``: the ratio of the tile's per-sample gradient variance (the mean of its finite
  ``var_dx``, ``var_dy`` times the gradient count) to its per-sample primal variance
  (``var_primal`` times the primal count); the tile is masked where the ratio is at most
  ``max_ratio``. No denoise: Kettunen et al. 2019, Fig. 5 (gradients hurt where their variance
  is high relative to the primal's) as a rule.

Tensors: masks ``(H, W)`` bool on the buffers' device; buffers as :class:`gdpt.GradientBuffers`.
Measurements: ``docs/gradients.md`` ("Offsets where they pay: a mask from the pilot").
"""

from __future__ import annotations

import math
import time
from typing import Any

import torch
from torch.nn import functional as F

from gdpt import methods, rendering
from gdpt.adapters import fusion_statistics_of
from gdpt.buffers import GradientBuffers, fill_untraced, merge_renders, primal_count

#: Side of the mask's tiles (pixels).
TILE = 16

#: Share of gradient samples rendered first as the pilot (at least :data:`PILOT_SPP`).
PILOT_FRACTION = 0.25

#: Fewest gradient samples per pixel of the pilot (its halves need two).
PILOT_SPP = 2

#: ``"trust"``: least share of a tile's gradients that ``fuse`` keeps for the tile to be masked.
MIN_SHARE = 0.5

#: ``"variance"``: largest per-sample gradient/primal variance ratio of a masked tile.
MAX_RATIO = 0.5

#: The designs of :func:`pilot_mask`.
DESIGNS = ("trust", "variance")

#: Mixed into the seed of the pilot render.
PILOT_SEED_SALT = 0x2F6B1C3D


def tile_sums(values: torch.Tensor, tile: int) -> torch.Tensor:
    """Sums of ``values`` ``(H, W)`` over ``tile`` px tiles: ``(ceil(H / tile), ceil(W /
    tile))`` (the edge tiles sum the pixels they have)."""
    h, w = values.shape
    padded = F.pad(values, (0, -w % tile, 0, -h % tile))
    th, tw = padded.shape[0] // tile, padded.shape[1] // tile
    return padded.reshape(th, tile, tw, tile).sum((1, 3))


def expand_tiles(tiles: torch.Tensor, shape: tuple[int, int], tile: int) -> torch.Tensor:
    """The per-tile values ``tiles`` ``(ceil(H / tile), ceil(W / tile))`` as ``(H, W)``."""
    full = tiles.repeat_interleave(tile, 0).repeat_interleave(tile, 1)
    return full[: shape[0], : shape[1]]


def _check_tile(tile: int, shape: tuple[int, int]) -> None:
    if not isinstance(tile, int) or isinstance(tile, bool) or tile < 1:
        raise ValueError(f"tile must be a positive int (pixels), got {tile!r}")
    if tile > max(shape):
        raise ValueError(f"tile {tile} px is larger than the {shape[1]}x{shape[0]} image")


def trusted_share(pilot: GradientBuffers, denoise: Any, tile: int = TILE) -> torch.Tensor:
    """Per-tile share of the gradient constraints (``dx`` and ``dy`` of the tile's pixels that
    exist) that ``fuse``'s trust rule keeps in ``pilot`` (variances and halves needed):
    ``(ceil(H / tile), ceil(W / tile))`` float in ``[0, 1]``; ``denoise(buffers) -> image``
    is the primal-only denoiser."""
    from gdpt.reconstruct.fuse import TRUST_RATIO, fusion_weights

    statistics = fusion_statistics_of(pilot, denoise)
    _, w_x, w_y, _, _ = fusion_weights(
        statistics.error,
        statistics.var_dx,
        statistics.var_dy,
        trust_ratio=TRUST_RATIO,
        error_floor=statistics.error_floor,
    )
    used = (w_x[..., 0] > 0).float() + (w_y[..., 0] > 0).float()
    exists = torch.full_like(used, 2.0)
    exists[:, -1] -= 1.0  # (no dx in the last column, no dy in the last row)
    exists[-1] -= 1.0
    return tile_sums(used, tile) / tile_sums(exists, tile).clamp_min(1.0)


def variance_ratio(pilot: GradientBuffers, tile: int = TILE) -> torch.Tensor:
    """Per-tile ratio of the per-sample gradient variance to the per-sample primal variance of
    ``pilot`` (``var_primal``, ``var_dx``, ``var_dy`` needed): ``(ceil(H / tile), ceil(W /
    tile))`` float; ``inf`` in a tile without a finite gradient variance, ``nan`` in a black
    tile (no variance at all)."""
    if pilot.var_primal is None or pilot.var_dx is None or pilot.var_dy is None:
        raise ValueError("the variance design reads var_primal, var_dx, var_dy (variance=True)")
    gradient = torch.stack([pilot.var_dx[..., 0], pilot.var_dy[..., 0]])
    finite = torch.isfinite(gradient)
    g_sum = tile_sums(torch.where(finite, gradient, 0.0).sum(0), tile)
    g_count = tile_sums(finite.float().sum(0), tile)
    p_mean = tile_sums(pilot.var_primal[..., 0], tile) / tile_sums(
        torch.ones_like(pilot.var_primal[..., 0]), tile
    )
    g_mean = torch.where(g_count > 0, g_sum / g_count.clamp_min(1.0), torch.inf)
    return (g_mean * pilot.spp) / (p_mean * primal_count(pilot))


def pilot_mask(
    pilot: GradientBuffers,
    *,
    design: str = "trust",
    denoise: Any = None,
    tile: int = TILE,
    min_share: float = MIN_SHARE,
    max_ratio: float = MAX_RATIO,
) -> torch.Tensor:
    """``(H, W)`` bool mask of whole tiles where the gradients of ``pilot`` (a render with
    gradients, variances and halves) are predicted to pay (see the module docstring).

    Args:
        pilot: the pilot render.
        design: one of :data:`DESIGNS`.
        denoise: ``"trust"``: ``denoise(buffers) -> image``, default the primal-only denoiser of
            ``fuse`` (:func:`gdpt.methods.primal_only`).
        tile: tile side in pixels.
        min_share: ``"trust"``'s least share of kept constraints in a masked tile.
        max_ratio: ``"variance"``'s largest ratio.

    Raises:
        ValueError: an unknown ``design``, a bad ``tile``, or a pilot without gradients.
    """
    if design not in DESIGNS:
        raise ValueError(f"unknown mask design {design!r}; valid: {', '.join(DESIGNS)}")
    if not pilot.has_gradients:
        raise ValueError("pilot_mask reads the pilot's gradients; render it with gradients=True")
    shape = (pilot.height, pilot.width)
    _check_tile(tile, shape)
    if design == "variance":
        if not max_ratio > 0:
            raise ValueError(f"max_ratio must be > 0, got {max_ratio}")
        return expand_tiles(variance_ratio(pilot, tile) <= max_ratio, shape, tile)
    if not 0.0 < min_share <= 1.0:
        raise ValueError(f"min_share must be in (0, 1], got {min_share}")
    if denoise is None:
        denoise = methods.primal_only()[1]
    return expand_tiles(trusted_share(pilot, denoise, tile) >= min_share, shape, tile)


def pilot_spp(spp: int, fraction: float = PILOT_FRACTION) -> int:
    """Gradient samples per pixel of the pilot of a render of ``spp``: ``fraction`` of them, at
    least :data:`PILOT_SPP`; ``spp`` itself when no sample would be left for the main render."""
    g = max(PILOT_SPP, math.ceil(fraction * spp))
    return spp if g >= spp else g


def traced_of(mask: torch.Tensor) -> torch.Tensor:
    """``(H, W, 2)`` bool: the gradients a render with the pixel mask ``mask`` traces (``dx``
    where both pixels of the pair are masked, ``dy`` likewise), as
    ``gdpt.integrators.common.traced_gradients``."""
    out = torch.zeros((*mask.shape, 2), dtype=torch.bool, device=mask.device)
    out[:, :-1, 0] = mask[:, :-1] & mask[:, 1:]
    out[:-1, :, 1] = mask[:-1] & mask[1:]
    return out


def render_masked(
    scene: Any,
    *,
    spp: int,
    seed: int = 0,
    design: str = "trust",
    tile: int = TILE,
    fraction: float = PILOT_FRACTION,
    **props: Any,
) -> GradientBuffers:
    """``fuse``'s input with offsets only where a pilot predicts they pay.

    Renders :func:`pilot_spp` gradient samples everywhere (the pilot, ``fuse``'s sampling),
    :func:`pilot_mask` of it, then ``spp`` minus the pilot's gradient samples with offsets
    inside the mask only, and merges both (:func:`gdpt.buffers.merge_renders`; the pilot's
    gradients outside the mask are marked untraced). Below ``PILOT_SPP + 1`` gradient spp the
    pilot is the whole render (mask all set).

    Args:
        scene: an ``mi.Scene`` (or anything :func:`gdpt.render` accepts).
        spp: gradient samples per pixel in the mask (pooled plain ones added as ``fuse`` does).
        seed: the main render's seed (the pilot's is derived from it).
        design, tile: see :func:`pilot_mask`.
        fraction: see :func:`pilot_spp`.
        **props: integrator properties (``max_depth``, ...).

    Returns:
        The merged buffers; ``metadata["pilot_mask"]``: ``design``, ``tile``, ``share`` (of
        masked pixels), ``pilot_spp``, ``mask_seconds`` (the mask's statistics).

    Raises:
        ValueError: ``spp < 1``, an unknown ``design`` or a bad ``tile`` (before rendering).
    """
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    if design not in DESIGNS:
        raise ValueError(f"unknown mask design {design!r}; valid: {', '.join(DESIGNS)}")
    if not isinstance(tile, int) or isinstance(tile, bool) or tile < 1:
        raise ValueError(f"tile must be a positive int (pixels), got {tile!r}")
    fuse = methods.METHODS["fuse"]
    g = pilot_spp(spp, fraction)
    pilot = rendering.render(
        scene,
        spp=g,
        seed=(seed ^ PILOT_SEED_SALT) & 0xFFFFFFFF,
        **{**props, **fuse.sampling(g)},
    )
    info: dict[str, Any] = {"design": design, "tile": tile, "pilot_spp": g}
    if g == spp:
        pilot.metadata["pilot_mask"] = {**info, "share": 1.0, "mask_seconds": 0.0}
        return pilot
    start = time.perf_counter()
    mask = pilot_mask(pilot, design=design, tile=tile)
    mask_seconds = time.perf_counter() - start
    main = rendering.render(
        scene,
        spp=spp - g,
        seed=seed,
        gradient_mask=mask,
        **{**props, **fuse.sampling(spp - g)},
    )
    # the gradients the main render traced (None: every one); the pilot's others are dropped
    traced = main.gradient_mask if main.has_gradients else traced_of(mask)
    if traced is not None:
        pilot = fill_untraced(pilot.replace(gradient_mask=traced), 0.0, 0.0)
        pilot = pilot.replace(gradient_mask=traced)
    merged = merge_renders([pilot, main])
    merged.metadata["pilot_mask"] = {
        **info,
        "share": float(mask.float().mean()),
        "mask_seconds": mask_seconds,
    }
    return merged
