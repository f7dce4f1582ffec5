"""Nonlinearly weighted first-order regression (NFOR) denoising in PyTorch.

Bitterli, Rousselle, Moon, Iglesias-Guitián, Adler, Mitchell, Jarosz and Novák 2016, *Nonlinearly
Weighted First-order Regression for Denoising Monte Carlo Renderings*, following the steps of
the public re-implementation in the Tungsten renderer (``src/denoiser``):

1. **Feature prefiltering** (sec. 5.1): each feature half-buffer is NL-means filtered with
   weights from the *other* half (cross-filtering keeps the filtered feature independent of the
   half it will be regressed against).
2. **Collaborative first-order regression** (sec. 5.2), for every bandwidth ``k``: half ``a``
   is regressed on the prefiltered features of half ``b`` with NL-means weights computed on
   colour half ``b``, and vice versa. In the window of pixel ``p`` the model is
   ``y(q) ~ beta_p . [1, dy, dx, f(q) - f(p)]`` (weighted least squares); every pixel's model
   is evaluated at every ``q`` of its window and the predictions are averaged with the same
   weights.
3. **Error estimates** (sec. 5.3): ``(b - a_hat)^2 - var(b)`` estimates the squared error of
   ``a_hat`` (the halves are independent), averaged over the two halves, minus the halves'
   disagreement ``(b_hat - a_hat)^2 / 4``, then NL-means smoothed.
4. **Bandwidth selection**: per pixel and channel the bandwidth of least estimated error; the
   indicator maps are NL-means smoothed and blend the candidates.
5. **Second pass** (sec. 5.4): the mean of the two filtered halves (variance from their
   difference) is regressed once more on the mean prefiltered features.

NL-means weights (Rousselle, Knaus and Zwicker 2012, eq. 7): per channel
``d = ((u_p - u_q)^2 - (v_p + min(v_p, v_q))) / (eps + k^2 (v_p + v_q))``, averaged over the
channels and a ``(2F+1)^2`` patch, ``w = exp(-max(d, 0))`` (Rousselle et al.'s channel mean;
the Tungsten code takes the largest channel distance instead, three times the filtering work).

Everything is batched over row bands of pixels with ``unfold``/``fold`` and a batched
``linalg.solve``; the same code runs on any torch device. Layout: images ``(H, W, C)`` float32
tensors on one device; the variance of the primal ``(H, W, 1)`` or ``(H, W, 3)``. Only
``torch`` is imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch
from torch.nn import functional as F

__all__ = [
    "NforConfig",
    "NforInfo",
    "nfor",
    "nlm_filter",
    "regress",
    "weighted_least_squares",
]

#: ``eps`` of the NL-means distance (Tungsten's value).
NLM_EPS = 1e-7

#: Largest patch distance kept (Tungsten's clamp; ``exp(-10^4)`` is 0 in float32 anyway).
MAX_DISTANCE = 1e4

#: Ridge of the regression, relative to the window's total weight, on the non-constant
#: columns (the Tungsten code solves by pivoted QR instead; a ridge keeps the batched
#: ``linalg.solve`` defined where a feature is constant in a window).
RIDGE = 1e-5

#: Pixels per band of the batched work (bounds memory: ``window^2 x 10`` floats per pixel).
BAND_PIXELS = 8192


@dataclass(frozen=True)
class NforConfig:
    """Parameters of :func:`nfor` (defaults: Tungsten's re-implementation).

    Attributes:
        radius: half-size ``R`` of the regression window (``(2R+1)^2`` pixels), >= 1.
        patch: half-size ``F`` of the NL-means patch of the regression weights, >= 0.
        bandwidths: the candidate NL-means bandwidths ``k`` of the first pass, each > 0.
        prefilter_radius, prefilter_patch, prefilter_k: NL-means of the feature prefilter.
        error_radius, error_patch: NL-means smoothing of the error estimates and selection
            maps (bandwidth 1).
        second_radius, second_patch, second_k: NL-means of the second pass's feature filter.
        final_k: bandwidth of the second-pass regression.
        variance_scale: factor on the variance of a half-buffer used as a guide (Tungsten: 2).
    """

    radius: int = 9
    patch: int = 3
    bandwidths: tuple[float, ...] = (0.5, 1.0)
    prefilter_radius: int = 5
    prefilter_patch: int = 3
    prefilter_k: float = 0.5
    error_radius: int = 9
    error_patch: int = 1
    second_radius: int = 2
    second_patch: int = 3
    second_k: float = 0.5
    final_k: float = 1.0
    variance_scale: float = 2.0

    def __post_init__(self) -> None:
        for name in ("radius", "prefilter_radius", "error_radius", "second_radius"):
            value = getattr(self, name)
            if not isinstance(value, int) or not 1 <= value <= 32:
                raise ValueError(f"NFOR {name} must be an integer in [1, 32], got {value!r}")
        for name in ("patch", "prefilter_patch", "error_patch", "second_patch"):
            value = getattr(self, name)
            if not isinstance(value, int) or not 0 <= value <= 16:
                raise ValueError(f"NFOR {name} must be an integer in [0, 16], got {value!r}")
        if not self.bandwidths:
            raise ValueError("NFOR bandwidths must name at least one bandwidth")
        for name, values in (
            ("bandwidths", self.bandwidths),
            ("prefilter_k", (self.prefilter_k,)),
            ("second_k", (self.second_k,)),
            ("final_k", (self.final_k,)),
            ("variance_scale", (self.variance_scale,)),
        ):
            if not all(isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in values):
                raise ValueError(f"NFOR {name} must be finite and > 0, got {values!r}")


@dataclass
class NforInfo:
    """What :func:`nfor` did.

    Attributes:
        nonfinite: input values that were NaN or infinite (replaced by 0 before filtering).
        bandwidth_share: per bandwidth of :attr:`NforConfig.bandwidths`, the mean weight the
            selection gave it (sums to 1).
    """

    nonfinite: int = 0
    bandwidth_share: list[float] = field(default_factory=list)


def _bands(height: int, width: int) -> list[tuple[int, int]]:
    rows = max(1, BAND_PIXELS // width)
    return [(r, min(height, r + rows)) for r in range(0, height, rows)]


class _Guide:
    """A guide image and its variance, padded once for the band-wise NL-means weights.

    Args:
        guide: ``(H, W, C)``; var: ``(H, W, C)`` or ``(H, W, 1)`` variances of ``guide``.
        radius, patch: window and patch half-sizes the weights are asked for.
    """

    def __init__(self, guide: torch.Tensor, var: torch.Tensor, radius: int, patch: int) -> None:
        self.height, self.width, self.channels = guide.shape
        self.radius, self.patch = radius, patch
        halo = radius + patch
        both = torch.cat([_chw(guide), _chw(var.expand_as(guide))])[None]
        # Replicated borders: patches may leave the image; neighbours outside get weight 0.
        self.padded = F.pad(both, (halo,) * 4, mode="replicate")[0]
        inside = torch.ones((1, 1, self.height, self.width), dtype=guide.dtype, device=guide.device)
        self.inside = F.pad(inside, (radius,) * 4)

    def weights(self, r0: int, r1: int, ks: Sequence[float]) -> list[torch.Tensor]:
        """Per bandwidth ``k``, the ``(n, K)`` NL-means weights of the pixels of rows
        ``[r0, r1)`` (``n = (r1 - r0) W``) to the ``K = (2R+1)^2`` offsets of their windows
        (row-major); 0 for offsets outside the image."""
        c, radius, patch = self.channels, self.radius, self.patch
        both = self.padded[:, r0 : r1 + 2 * (radius + patch)]
        size = (r1 - r0 + 2 * patch, self.width + 2 * patch)
        window = 2 * radius + 1
        neighbours = F.unfold(both[None], window).view(2 * c, window * window, *size)
        centre = both[:, radius : radius + size[0], radius : radius + size[1]].unsqueeze(1)
        u_q, v_q = neighbours[:c], neighbours[c:]
        u_p, v_p = centre[:c], centre[c:]
        excess = (u_p - u_q).square_().sub_(torch.minimum(v_q, v_p).add_(v_p))
        spread = v_p + v_q
        inside = F.unfold(self.inside[:, :, r0 : r1 + 2 * radius], window)[0]
        out = []
        for k in ks:
            distance = (excess / (spread * (k * k) + NLM_EPS)).mean(dim=0)
            distance = distance.nan_to_num_(nan=MAX_DISTANCE, posinf=MAX_DISTANCE)
            if patch:
                distance = _box_valid(distance, patch)
            weights = distance.clamp_(0.0, MAX_DISTANCE).neg_().exp_()  # (K, h, W)
            out.append((weights.reshape(window * window, -1) * inside).T)
        return out


def _box_valid(image: torch.Tensor, radius: int) -> torch.Tensor:
    """Mean over ``(2 radius + 1)^2`` boxes of ``image (..., h, w)``, valid part only:
    ``(..., h - 2 radius, w - 2 radius)`` (separable sums of shifted slices; faster on the
    CPU than ``avg_pool2d`` for hundreds of channels)."""
    size = 2 * radius + 1
    h, w = image.shape[-2] - 2 * radius, image.shape[-1] - 2 * radius
    rows = sum(image[..., i : i + h, :] for i in range(size))
    return sum(rows[..., j : j + w] for j in range(size)) / (size * size)


def _pad_hwc(image: torch.Tensor, radius: int) -> torch.Tensor:
    """``image (H, W, C)`` with ``radius`` replicated pixels on every side."""
    return _hwc(F.pad(_chw(image)[None], (radius,) * 4, mode="replicate")[0])


def _windows(padded: torch.Tensor, r0: int, r1: int, radius: int) -> torch.Tensor:
    """``(h, W, 2R+1, 2R+1, C)`` view: the window of every pixel of rows ``[r0, r1)`` of an
    image padded by :func:`_pad_hwc` (its borders get weight 0 from :class:`_Guide`)."""
    window = 2 * radius + 1
    band = padded[r0 : r1 + 2 * radius]
    return band.unfold(0, window, 1).unfold(1, window, 1).permute(0, 1, 3, 4, 2)


def _chw(image: torch.Tensor) -> torch.Tensor:
    return image.permute(2, 0, 1).contiguous()


def _hwc(image: torch.Tensor) -> torch.Tensor:
    return image.permute(1, 2, 0).contiguous()


def nlm_filter(
    image: torch.Tensor,
    guide: torch.Tensor,
    guide_var: torch.Tensor,
    *,
    radius: int,
    patch: int,
    k: float,
) -> torch.Tensor:
    """NL-means filter of ``image`` with weights from ``guide`` and its variance.

    Args:
        image: ``(H, W, C)`` float32.
        guide: ``(H, W, G)`` float32, same device; guide_var: ``(H, W, G)`` or ``(H, W, 1)``.
        radius, patch, k: window half-size, patch half-size, bandwidth.

    Returns:
        ``(H, W, C)``: per pixel the weighted mean of ``image`` over its window.
    """
    height, width, channels = image.shape
    weights_of = _Guide(guide, guide_var, radius, patch)
    padded = _pad_hwc(image, radius)
    out = torch.empty_like(image).view(-1, channels)
    for r0, r1 in _bands(height, width):
        (weights,) = weights_of.weights(r0, r1, (k,))
        values = _windows(padded, r0, r1, radius).reshape(weights.shape[0], -1, channels)
        mean = (weights[:, :, None] * values).sum(1) / weights.sum(1, keepdim=True)
        out[r0 * width : r1 * width] = mean
    return out.view_as(image)


def regress(
    image: torch.Tensor,
    features: torch.Tensor,
    guide: torch.Tensor,
    guide_var: torch.Tensor,
    *,
    radius: int,
    patch: int,
    ks: Sequence[float],
) -> list[torch.Tensor]:
    """Collaborative first-order weighted regression of ``image`` on ``features``
    (Bitterli et al. 2016, sec. 4-5.2), once per NL-means bandwidth of ``ks``.

    Per pixel ``p`` the weighted least-squares fit over its window of
    ``image(q) ~ beta_p . [1, dy/R, dx/R, (f(q) - f(p)) / s]`` (``s``: each feature's standard
    deviation over the image, so the ridge :data:`RIDGE` treats features alike), weights
    :func:`nlm_filter`'s; the output at ``q`` is the weight-averaged prediction of every model
    whose window holds ``q``. The bandwidths share the windows and distances.

    Args:
        image: ``(H, W, C)`` float32; features: ``(H, W, D)``; guide, guide_var as in
            :func:`nlm_filter`; all on one device.

    Returns:
        Per bandwidth, ``(H, W, C)`` float32.
    """
    height, width, channels = image.shape
    window = 2 * radius + 1
    scale = features.reshape(-1, features.shape[-1]).std(dim=0, correction=0).clamp(min=1e-4)
    scaled = features / scale
    weights_of = _Guide(guide, guide_var, radius, patch)
    padded = _pad_hwc(torch.cat([scaled, image], dim=-1), radius)
    offsets = torch.arange(-radius, radius + 1, dtype=image.dtype, device=image.device) / radius
    dy, dx = torch.meshgrid(offsets, offsets, indexing="ij")
    columns = 3 + features.shape[-1]
    full = (height + 2 * radius, width + 2 * radius)
    totals = [image.new_zeros((channels, *full)) for _ in ks]
    norms = [image.new_zeros((1, *full)) for _ in ks]
    for r0, r1 in _bands(height, width):
        n = (r1 - r0) * width
        # One window tensor [1, dy, dx, f(q) - f(p), y(q)]: one product gives both sides.
        stacked = image.new_empty((n, window * window, columns + channels))
        stacked[..., 0] = 1.0
        stacked[..., 1] = dy.reshape(1, -1)
        stacked[..., 2] = dx.reshape(1, -1)
        stacked.view(r1 - r0, width, window, window, -1)[..., 3:] = _windows(padded, r0, r1, radius)
        stacked[..., 3:columns] -= scaled[r0:r1].reshape(n, 1, -1)
        design = stacked[..., :columns]
        out_size = (r1 - r0 + 2 * radius, full[1])
        for weights, total, norm in zip(weights_of.weights(r0, r1, ks), totals, norms, strict=True):
            beta = weighted_least_squares(stacked, weights, columns)
            prediction = (design @ beta) * weights[:, :, None]  # (n, K, C)
            folded = F.fold(prediction.permute(2, 1, 0).reshape(1, -1, n), out_size, window)
            total[:, r0 : r1 + 2 * radius] += folded[0]
            norm[:, r0 : r1 + 2 * radius] += F.fold(weights.T.reshape(1, -1, n), out_size, window)[
                0
            ]
    crop = (slice(None), slice(radius, radius + height), slice(radius, radius + width))
    return [_hwc(total[crop] / norm[crop]) for total, norm in zip(totals, norms, strict=True)]


def weighted_least_squares(
    windows: torch.Tensor, weights: torch.Tensor, columns: int
) -> torch.Tensor:
    """Per window, ``argmin_beta sum_q w_q |y_q - x_q beta|^2 + RIDGE (sum_q w_q) |beta'|^2``
    (``beta'``: all but the first coefficient, the intercept).

    Args:
        windows: ``(n, K, columns + C)`` float32: per window and sample the design row
            ``x_q`` (first column the constant 1) followed by the targets ``y_q``.
        weights: ``(n, K)`` float32 sample weights >= 0, each window's sum > 0.
        columns: length of the design rows.

    Returns:
        ``(n, columns, C)`` coefficients, ``windows``' dtype (normal equations formed in
        ``windows``' dtype, solved in float64).
    """
    products = ((windows * weights[:, :, None]).transpose(1, 2) @ windows).double()
    normal = products[:, :columns, :columns]
    ridge = torch.full((columns,), RIDGE, dtype=torch.float64, device=windows.device)
    ridge[0] = 0.0
    normal += torch.diag_embed(ridge * weights.sum(1, keepdim=True).double())
    return torch.linalg.solve(normal, products[:, :columns, columns:]).to(windows.dtype)


def _finite(image: torch.Tensor) -> tuple[torch.Tensor, int]:
    bad = ~torch.isfinite(image)
    return torch.where(bad, 0.0, image), int(bad.sum())


def nfor(
    primal_a: torch.Tensor,
    primal_b: torch.Tensor,
    var_primal: torch.Tensor,
    features_a: Sequence[torch.Tensor],
    features_b: Sequence[torch.Tensor],
    config: NforConfig | None = None,
) -> tuple[torch.Tensor, NforInfo]:
    """Denoise a render from its two independent half-buffers (Bitterli et al. 2016).

    Args:
        primal_a, primal_b: ``(H, W, 3)`` float32 means of two disjoint halves of the samples,
            on one device.
        var_primal: ``(H, W, 1)`` or ``(H, W, 3)`` variance of the mean of *all* samples
            (a half's is ``config.variance_scale`` times it; 2 for equal halves).
        features_a, features_b: the feature groups of the two halves (e.g. albedo, normal,
            depth), each ``(H, W, c)``; a group is prefiltered with its own guide. Their
            variances are the two-buffer estimate ``(a - b)^2 / 2`` per half, box-averaged
            over 3x3 pixels.
        config: parameters (:class:`NforConfig`).

    Returns:
        ``(H, W, 3)`` float32 denoised image (finite), and :class:`NforInfo`.

    Raises:
        ValueError: shapes disagree or no feature group is given.
    """
    cfg = config or NforConfig()
    if primal_a.shape != primal_b.shape or primal_a.ndim != 3:
        raise ValueError(
            f"primal halves must both be (H, W, C), got {tuple(primal_a.shape)} and "
            f"{tuple(primal_b.shape)}"
        )
    if len(features_a) != len(features_b) or not features_a:
        raise ValueError("NFOR needs the same non-empty list of feature groups for both halves")
    hw = primal_a.shape[:2]
    for t in (var_primal, *features_a, *features_b):
        if t.shape[:2] != hw:
            raise ValueError(f"NFOR buffers must share (H, W) = {tuple(hw)}, got {tuple(t.shape)}")
    info = NforInfo()
    (a, bad_a), (b, bad_b) = _finite(primal_a.float()), _finite(primal_b.float())
    var, bad_v = _finite(var_primal.float().clamp(min=0.0))
    info.nonfinite = bad_a + bad_b + bad_v
    groups = []
    for fa, fb in zip(features_a, features_b, strict=True):
        (fa, nan_a), (fb, nan_b) = _finite(fa.float()), _finite(fb.float())
        info.nonfinite += nan_a + nan_b
        groups.append((fa, fb))
    var_half = cfg.variance_scale * var

    # 1. Feature prefiltering, cross-guided by the other half.
    pre_a, pre_b = [], []
    for fa, fb in groups:
        fvar = _box3((fa - fb).square() / 2)
        nlm = dict(radius=cfg.prefilter_radius, patch=cfg.prefilter_patch, k=cfg.prefilter_k)
        pre_a.append(nlm_filter(fa, fb, fvar, **nlm))
        pre_b.append(nlm_filter(fb, fa, fvar, **nlm))
    feat_a, feat_b = torch.cat(pre_a, dim=-1), torch.cat(pre_b, dim=-1)

    # 2.-3. Cross-filtered regressions per bandwidth and their estimated errors.
    mean = (a + b) / 2
    candidates, errors = [], []
    first = dict(radius=cfg.radius, patch=cfg.patch, ks=cfg.bandwidths)
    a_hats = regress(a, feat_b, b, var_half, **first)
    b_hats = regress(b, feat_a, a, var_half, **first)
    for a_hat, b_hat in zip(a_hats, b_hats, strict=True):
        error = ((b - a_hat).square() + (a - b_hat).square()) / 2 - var_half
        error = error - (b_hat - a_hat).square() / 4
        errors.append(
            nlm_filter(error, mean, var, radius=cfg.error_radius, patch=cfg.error_patch, k=1.0)
        )
        candidates.append((a_hat, b_hat))

    # 4. Selection: smoothed indicator of the least estimated error, per pixel and channel.
    best = torch.stack(errors).argmin(dim=0)
    share = torch.stack(
        [
            nlm_filter(
                (best == i).float(),
                mean,
                var,
                radius=cfg.error_radius,
                patch=cfg.error_patch,
                k=1.0,
            )
            for i in range(len(cfg.bandwidths))
        ]
    )
    share = share / share.sum(0).clamp(min=1e-12)
    info.bandwidth_share = [float(s.mean()) for s in share]
    a_sel = sum(s * c[0] for s, c in zip(share, candidates, strict=True))
    b_sel = sum(s * c[1] for s, c in zip(share, candidates, strict=True))

    # 5. Second pass on the mean of the filtered halves.
    second = []
    for fa, fb in zip(pre_a, pre_b, strict=True):
        f_mean, f_var = (fa + fb) / 2, (fb - fa).square() / 4
        second.append(
            nlm_filter(
                f_mean,
                f_mean,
                f_var,
                radius=cfg.second_radius,
                patch=cfg.second_patch,
                k=cfg.second_k,
            )
        )
    colour, colour_var = (a_sel + b_sel) / 2, (b_sel - a_sel).square() / 4
    (out,) = regress(
        colour,
        torch.cat(second, dim=-1),
        colour,
        colour_var,
        radius=cfg.radius,
        patch=cfg.patch,
        ks=(cfg.final_k,),
    )
    out, bad_out = _finite(out)
    info.nonfinite += bad_out
    return out, info


def _box3(image: torch.Tensor) -> torch.Tensor:
    """``(H, W, C)`` mean over each pixel's 3x3 neighbourhood (replicated borders)."""
    padded = F.pad(_chw(image)[None], (1, 1, 1, 1), mode="replicate")
    return _hwc(F.avg_pool2d(padded, 3, stride=1)[0])
