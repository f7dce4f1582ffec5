"""Training losses for the neural (NGPT) reconstruction: tone mapping, FLIP, E-LPIPS, registry.

Every loss takes ``(pred, target)``: ``(N, 3, H, W)`` float tensors of *linear HDR* radiance on
any one device, and returns a scalar tensor on that device. The perceptual terms see tone-mapped
images, as in NGPT [Kettunen et al. 2019, Eq. 6-8]:

* ``R(x) = x / (1 + mean_c |x|)`` (per-pixel Reinhard; it is odd, so the same formula is the
  "odd reflection" the paper applies to gradients),
* ``sRGB(R(x))`` (IEC 61966-2-1 encoding) for E-LPIPS,
* ``clamp(R(x), 0, 1)`` (linear) for LDR-FLIP.

FLIP is a re-implementation of NVIDIA's FLIP v1.7 (Andersson et al. 2020, HDR-FLIP 2021) that
follows the separable C++ evaluator shipped as ``flip_evaluator``, so mean errors agree with it to
well under 1 %. E-LPIPS follows ``mkettune/elpips`` (Kettunen et al. 2019): the same random
ensemble of input transformations, backbone dropout and linear heads; the weights are read from a
local file (see :func:`load_elpips_weights`); nothing is ever downloaded.

Argument order: the test/predicted image always comes first and the reference second. FLIP is
not symmetric (HDR exposures are computed from the reference).
"""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .registry import Registry

__all__ = [
    "Dropout",
    "ELPIPS",
    "ELPIPS_WEIGHTS_ENV",
    "ELPIPSConfig",
    "ELPIPSLoss",
    "ELPIPSWeightsError",
    "EnsembleSample",
    "FLIPLoss",
    "FLIP_DEFAULT_PPD",
    "LOSSES",
    "NGPTLoss",
    "SqueezeNetFeatures",
    "VGG16Features",
    "apply_ensemble",
    "flip_exposures",
    "forward_differences",
    "get_loss",
    "gradient_l1_tonemapped",
    "hdr_flip",
    "l1_log",
    "l1_relative",
    "l1_tonemapped",
    "ldr_flip",
    "load_elpips_weights",
    "reinhard",
    "sample_ensemble",
    "srgb_decode",
    "srgb_encode",
]


# ---------------------------------------------------------------------------------------------
# Tone mapping and transfer functions
# ---------------------------------------------------------------------------------------------


def reinhard(x: Tensor, *, channel_dim: int = -3) -> Tensor:
    """NGPT per-pixel Reinhard tone map ``R(x) = x / (1 + mean_c |x|)``.

    The map is odd (``R(-x) = -R(x)``), so it is also the sign-preserving version NGPT applies to
    image gradients. It is differentiable everywhere except where all channels are 0.

    Args:
        x: float tensor of any shape with channels along ``channel_dim`` (``-3`` for NCHW/CHW,
            ``-1`` for HWC); any device.
        channel_dim: dimension holding the colour channels.

    Returns:
        Tensor of the same shape, dtype and device; ``|R(x)| < 1`` for each channel mean.
    """
    return x / (1.0 + x.abs().mean(dim=channel_dim, keepdim=True))


def _where_pow(x: Tensor, exponent: float, threshold: float) -> Tensor:
    """``x ** exponent`` evaluated only on ``x > threshold`` (finite gradients elsewhere)."""
    return x.clamp_min(threshold) ** exponent


def srgb_encode(x: Tensor) -> Tensor:
    """sRGB encoding (IEC 61966-2-1): linear -> non-linear, element-wise and differentiable.

    ``12.92 x`` for ``x <= 0.0031308``, else ``1.055 x^(1/2.4) - 0.055`` (negative values use the
    linear branch, as ``colour.cctf_encoding(x, function="sRGB")`` does).

    Args:
        x: float tensor of linear values, any shape and device.

    Returns:
        Encoded tensor of the same shape, dtype and device.
    """
    high = 1.055 * _where_pow(x, 1.0 / 2.4, 0.0031308) - 0.055
    return torch.where(x <= 0.0031308, 12.92 * x, high)


def srgb_decode(x: Tensor) -> Tensor:
    """sRGB decoding (IEC 61966-2-1): non-linear -> linear, inverse of :func:`srgb_encode`.

    Args:
        x: float tensor of sRGB-encoded values, any shape and device.

    Returns:
        Linear tensor of the same shape, dtype and device.
    """
    high = _where_pow((x + 0.055) / 1.055, 2.4, (0.04045 + 0.055) / 1.055)
    return torch.where(x <= 0.04045, x / 12.92, high)


def forward_differences(x: Tensor) -> tuple[Tensor, Tensor]:
    """Forward differences with the gdpt convention (zero last column / row).

    ``dx[..., y, x] = I[..., y, x + 1] - I[..., y, x]``, ``dy[..., y, x] = I[..., y + 1, x] -
    I[..., y, x]``.

    Args:
        x: ``(..., H, W)`` float tensor (e.g. NCHW), any device.

    Returns:
        ``(dx, dy)``, each shaped like ``x``.
    """
    dx = F.pad(x[..., :, 1:] - x[..., :, :-1], (0, 1, 0, 0))
    dy = F.pad(x[..., 1:, :] - x[..., :-1, :], (0, 0, 0, 1))
    return dx, dy


def _check_pair(pred: Tensor, target: Tensor) -> None:
    """Raise ``ValueError`` unless both are ``(N, 3, H, W)`` tensors of equal shape."""
    if pred.ndim != 4 or pred.shape[1] != 3 or pred.shape != target.shape:
        raise ValueError(
            "expected pred and target of equal shape (N, 3, H, W), got "
            f"pred {tuple(pred.shape)} and target {tuple(target.shape)}"
        )


def l1_tonemapped(pred: Tensor, target: Tensor) -> Tensor:
    """NGPT tone-mapped L1: ``mean |R(target) - R(pred)|``.

    Args:
        pred: ``(N, 3, H, W)`` float linear HDR prediction, any device.
        target: ``(N, 3, H, W)`` float linear HDR reference, same device.

    Returns:
        Scalar tensor.
    """
    _check_pair(pred, target)
    return (reinhard(pred) - reinhard(target)).abs().mean()


def gradient_l1_tonemapped(pred: Tensor, target: Tensor) -> Tensor:
    """NGPT gradient term: ``mean|R(dx_t) - R(dx_p)| + mean|R(dy_t) - R(dy_p)|``.

    The forward differences (:func:`forward_differences`) are taken on the *linear* images and
    then tone-mapped with the odd Reinhard map :func:`reinhard`.

    Args:
        pred: ``(N, 3, H, W)`` float linear HDR prediction, any device.
        target: ``(N, 3, H, W)`` float linear HDR reference, same device.

    Returns:
        Scalar tensor.
    """
    _check_pair(pred, target)
    loss = pred.new_zeros(())
    for d_pred, d_target in zip(
        forward_differences(pred), forward_differences(target), strict=False
    ):
        loss = loss + (reinhard(d_pred) - reinhard(d_target)).abs().mean()
    return loss


def l1_log(pred: Tensor, target: Tensor) -> Tensor:
    """L1 in the network's output domain: ``mean |log1p(pred) - log1p(target)|``.

    Unlike the Reinhard-mapped terms this does not saturate on bright pixels, so it pins HDR
    magnitudes (emitters, highlights) that the tone-mapped losses cannot tell apart.
    ``pred`` is clamped to ``> -1`` (the output transform's range).

    Args:
        pred: ``(N, 3, H, W)`` float linear HDR prediction, any device.
        target: ``(N, 3, H, W)`` float linear HDR reference (``>= 0``), same device.

    Returns:
        Scalar tensor.
    """
    _check_pair(pred, target)
    return (torch.log1p(pred.clamp_min(-0.999)) - torch.log1p(target.clamp_min(0.0))).abs().mean()


def l1_relative(pred: Tensor, target: Tensor, *, eps: float = 1e-2) -> Tensor:
    """Relative L1 with the relMSE convention: ``mean |pred - target| / (eps + mean_c target)``.

    The robust (L1) counterpart of the relMSE metric (:func:`gdpt.metrics.relmse` divides by the
    channel mean of the reference too): it weighs colour errors in dark regions and fireflies as
    the metric does, which tone-mapped and perceptual terms barely see.

    Args:
        pred: ``(N, 3, H, W)`` float linear HDR prediction, any device.
        target: ``(N, 3, H, W)`` float linear HDR reference, same device.
        eps: added to the denominator (the metric uses 1e-3 on squared values).

    Returns:
        Scalar tensor.
    """
    _check_pair(pred, target)
    scale = eps + target.mean(dim=1, keepdim=True).clamp_min(0.0)
    return ((pred - target).abs() / scale).mean()


# ---------------------------------------------------------------------------------------------
# FLIP (LDR and HDR), after NVlabs/flip v1.7 (separable C++ evaluator)
# ---------------------------------------------------------------------------------------------

#: Pixels per degree of the FLIP tool's default viewing conditions (0.7 m from a 0.7 m wide,
#: 3840 px monitor): 67.0206.
FLIP_DEFAULT_PPD = 0.7 * (3840.0 / 0.7) * (3.14159265358979 / 180.0)

_FLIP_QC, _FLIP_PC, _FLIP_PT, _FLIP_W, _FLIP_QF = 0.7, 0.4, 0.95, 0.082, 0.5
_EPS32 = float(np.finfo(np.float32).eps)  # FLIP clamps the median luminance to FLT_EPSILON
_D65 = (0.950428545, 1.0, 1.088900371)
_LIN_TO_XYZ = (
    (10135552.0 / 24577794.0, 8788810.0 / 24577794.0, 4435075.0 / 24577794.0),
    (2613072.0 / 12288897.0, 8788810.0 / 12288897.0, 887015.0 / 12288897.0),
    (1425312.0 / 73733382.0, 8788810.0 / 73733382.0, 70074185.0 / 73733382.0),
)
_XYZ_TO_LIN = (
    (3.241003275, -1.537398934, -0.498615861),
    (-0.969224334, 1.875930071, 0.041554224),
    (0.055639423, -0.204011202, 1.057148933),
)
#: Rational tone curves ``(a x^2 + b x + c) / (d x^2 + e x + f)`` used by HDR-FLIP.
_TONE_CURVES = {
    "reinhard": (0.0, 1.0, 0.0, 0.0, 1.0, 1.0),  # only for the exposure range; see _tonemap
    "aces": (0.6 * 0.6 * 2.51, 0.6 * 0.03, 0.0, 0.6 * 0.6 * 2.43, 0.6 * 0.59, 0.14),
    "hable": (0.231683, 0.013791, 0.0, 0.18, 0.3, 0.018),
}


def _safe_sqrt(x: Tensor) -> Tensor:
    """``sqrt(x)`` for ``x >= 0`` with a zero (not infinite) gradient at 0."""
    positive = x > 0
    return torch.where(positive, torch.where(positive, x, 1.0).sqrt(), 0.0)


def _safe_pow(base: Tensor, exponent: Tensor | float) -> Tensor:
    """``base ** exponent`` for ``base >= 0``, ``exponent > 0``; 0 (zero gradient) at base 0."""
    positive = base > 0
    return torch.where(positive, torch.where(positive, base, 1.0) ** exponent, 0.0)


def _mix(matrix: Sequence[Sequence[float]], x: Tensor) -> Tensor:
    """Apply a 3x3 colour matrix to ``(B, 3, H, W)`` ``x``."""
    m = torch.tensor(matrix, dtype=x.dtype, device=x.device)
    return torch.einsum("ij,bjhw->bihw", m, x)


def _lab_f(t: Tensor) -> Tensor:
    """CIELAB companding function ``f(t)``."""
    delta = 6.0 / 29.0
    return torch.where(
        t > delta**3, _where_pow(t, 1.0 / 3.0, delta**3), t / (3.0 * delta**2) + 4.0 / 29.0
    )


def _linear_to_lab(rgb: Tensor, *, hunt: bool) -> Tensor:
    """Linear sRGB ``(B, 3, H, W)`` to CIELAB (D65), optionally with FLIP's Hunt adjustment."""
    xyz = _mix(_LIN_TO_XYZ, rgb) / rgb.new_tensor(_D65).view(1, 3, 1, 1)
    fx, fy, fz = _lab_f(xyz).unbind(1)
    lightness = 116.0 * fy - 16.0
    a, b = 500.0 * (fx - fy), 200.0 * (fy - fz)
    if hunt:
        a, b = 0.01 * lightness * a, 0.01 * lightness * b
    return torch.stack([lightness, a, b], 1)


def _linear_to_ycxcz(rgb: Tensor) -> Tensor:
    """Linear sRGB ``(B, 3, H, W)`` to YCxCz (linearised CIELAB, D65)."""
    x, y, z = (_mix(_LIN_TO_XYZ, rgb) / rgb.new_tensor(_D65).view(1, 3, 1, 1)).unbind(1)
    return torch.stack([116.0 * y - 16.0, 500.0 * (x - y), 200.0 * (y - z)], 1)


def _ycxcz_to_linear(ycxcz: Tensor) -> Tensor:
    """Inverse of :func:`_linear_to_ycxcz`."""
    y_, cx, cz = ycxcz.unbind(1)
    y = (y_ + 16.0) / 116.0
    xyz = torch.stack([y + cx / 500.0, y, y - cz / 200.0], 1)
    return _mix(_XYZ_TO_LIN, xyz * ycxcz.new_tensor(_D65).view(1, 3, 1, 1))


def _hyab(lab_a: Tensor, lab_b: Tensor) -> Tensor:
    """HyAB distance ``|dL| + ||d(a, b)||`` of ``(B, 3, H, W)`` Lab images -> ``(B, H, W)``."""
    diff = lab_a - lab_b
    return diff[:, 0].abs() + _safe_sqrt(diff[:, 1] ** 2 + diff[:, 2] ** 2)


def _flip_cmax() -> float:
    """FLIP's maximal colour distance (green vs blue, Hunt-adjusted HyAB) to the power ``qc``."""
    lab = _linear_to_lab(torch.eye(3, dtype=torch.float64)[1:].view(2, 3, 1, 1), hunt=True)
    return float(_hyab(lab[:1], lab[1:]).item() ** _FLIP_QC)


_FLIP_CMAX = _flip_cmax()


def _flip_filters(ppd: float, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """1-D filters of the separable FLIP evaluator.

    Returns:
        ``(spatial, feature)``: ``spatial`` is ``(4, 2r+1)`` with the Y, Cx and the two Cz
        component filters (CSF; the Cz filter is a sum of two Gaussians, each separated into two
        equal 1-D factors, see FLIP's ``misc/separatedConvolutions.pdf``); ``feature`` is
        ``(3, 2s+1)`` with the Gaussian, its 1st and its 2nd derivative, normalised as in FLIP.
    """
    a1, b1 = (1.0, 1.0, 34.1), (0.0047, 0.0053, 0.04)
    a2, b2 = (0.0, 0.0, 13.5), (1.0e-5, 1.0e-5, 0.025)
    radius = math.ceil(3.0 * math.sqrt(max(b1 + b2) / (2.0 * math.pi**2)) * ppd)
    x2 = (torch.arange(-radius, radius + 1, dtype=torch.float64) / ppd) ** 2

    def gauss(a: float, b: float) -> Tensor:
        return a * torch.exp(-(math.pi**2) * x2 / b)

    g_y, g_cx = gauss(1.0, b1[0]), gauss(1.0, b1[1])
    g_cz1 = gauss(math.sqrt(a1[2] * math.sqrt(math.pi / b1[2])), b1[2])
    g_cz2 = gauss(math.sqrt(a2[2] * math.sqrt(math.pi / b2[2])), b2[2])
    cz_norm = math.hypot(g_cz1.sum().item(), g_cz2.sum().item())
    spatial = torch.stack([g_y / g_y.sum(), g_cx / g_cx.sum(), g_cz1 / cz_norm, g_cz2 / cz_norm])

    sigma = 0.5 * _FLIP_W * ppd
    s_radius = math.ceil(3.0 * sigma)
    xs = torch.arange(-s_radius, s_radius + 1, dtype=torch.float64)
    g = torch.exp(-(xs**2) / (2.0 * sigma**2))
    dg, ddg = -xs * g, (xs**2 / sigma**2 - 1.0) * g

    def signed_normalise(k: Tensor) -> Tensor:
        return torch.where(k > 0, k / k.clamp_min(0).sum(), k / (-k).clamp_min(0).sum())

    feature = torch.stack([g / g.sum(), signed_normalise(dg), signed_normalise(ddg)])
    return spatial.to(dtype=dtype, device=device), feature.to(dtype=dtype, device=device)


def _conv_x(x: Tensor, kernels: Tensor) -> Tensor:
    """Depthwise horizontal correlation of ``(B, C, H, W)`` with ``(C, K)`` kernels (edge clamp)."""
    c, k = kernels.shape
    x = F.pad(x, (k // 2, k // 2, 0, 0), mode="replicate")
    return F.conv2d(x, kernels.view(c, 1, 1, k), groups=c)


def _conv_y(x: Tensor, kernels: Tensor) -> Tensor:
    """Depthwise vertical correlation of ``(B, C, H, W)`` with ``(C, K)`` kernels (edge clamp)."""
    c, k = kernels.shape
    x = F.pad(x, (0, 0, k // 2, k // 2), mode="replicate")
    return F.conv2d(x, kernels.view(c, 1, k, 1), groups=c)


def _ldr_flip_map(test: Tensor, reference: Tensor, ppd: float) -> Tensor:
    """Per-pixel LDR-FLIP of linear-RGB ``(B, 3, H, W)`` images (clamped to [0, 1]) -> (B, H, W)."""
    n = test.shape[0]
    spatial, feature = _flip_filters(ppd, test.dtype, test.device)
    ycxcz = _linear_to_ycxcz(torch.cat([reference, test]).clamp(0.0, 1.0))

    # Colour pipeline: CSF filtering, clamp to the RGB cube, Hunt-adjusted HyAB, re-mapping.
    filtered = _conv_y(_conv_x(torch.cat([ycxcz, ycxcz[:, 2:]], 1), spatial), spatial)
    filtered = torch.cat([filtered[:, :2], filtered[:, 2:3] + filtered[:, 3:]], 1)
    lab = _linear_to_lab(_ycxcz_to_linear(filtered).clamp(0.0, 1.0), hunt=True)
    colour = _safe_pow(_hyab(lab[:n], lab[n:]), _FLIP_QC)
    pccmax = _FLIP_PC * _FLIP_CMAX
    colour = torch.where(
        colour < pccmax,
        colour * (_FLIP_PT / pccmax),
        _FLIP_PT + (colour - pccmax) / (_FLIP_CMAX - pccmax) * (1.0 - _FLIP_PT),
    )

    # Feature pipeline: edges and points on the achromatic channel, normalised to [0, 1].
    lum = ((ycxcz[:, :1] + 16.0) / 116.0).expand(-1, 3, -1, -1)
    g, dg, ddg = feature
    first = _conv_x(lum, torch.stack([dg, ddg, g]))
    d_x, dd_x, d_y, dd_y = _conv_y(first[:, [0, 1, 2, 2]], torch.stack([g, g, dg, ddg])).unbind(1)
    edges, points = _safe_sqrt(d_x**2 + d_y**2), _safe_sqrt(dd_x**2 + dd_y**2)
    feat_diff = torch.maximum((edges[:n] - edges[n:]).abs(), (points[:n] - points[n:]).abs())
    feat_diff = _safe_pow(feat_diff / math.sqrt(2.0), _FLIP_QF)

    return _safe_pow(colour, 1.0 - feat_diff)


def _reduce(error_map: Tensor, reduction: str) -> Tensor:
    """Apply ``reduction`` (``"mean"`` or ``"none"``) to a ``(N, H, W)`` error map."""
    if reduction == "mean":
        return error_map.mean()
    if reduction == "none":
        return error_map
    raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")


def ldr_flip(
    test: Tensor,
    reference: Tensor,
    *,
    ppd: float = FLIP_DEFAULT_PPD,
    inputs_srgb: bool = True,
    reduction: str = "mean",
) -> Tensor:
    """Differentiable LDR-FLIP, matching ``flip_evaluator.evaluate(ref, test, "LDR")``.

    Inputs follow the tool's convention: LDR images in [0, 1], sRGB-encoded by default
    (``inputsRGB=True``), or linear with ``inputs_srgb=False``. They are clamped to [0, 1] after
    decoding (zero gradient outside).

    Args:
        test: ``(N, 3, H, W)`` float test image, any device.
        reference: ``(N, 3, H, W)`` float reference image, same device.
        ppd: pixels per degree of visual angle.
        inputs_srgb: whether inputs are sRGB-encoded (else linear RGB).
        reduction: ``"mean"`` (scalar over batch and pixels) or ``"none"`` (``(N, H, W)`` map).

    Returns:
        Mean FLIP error (scalar) or the per-pixel error map, values in [0, 1].
    """
    _check_pair(test, reference)
    if inputs_srgb:
        test, reference = srgb_decode(test), srgb_decode(reference)
    return _reduce(_ldr_flip_map(test, reference, ppd), reduction)


def _check_tonemapper(tonemapper: str) -> str:
    """Return the lower-cased tone-mapper name or raise ``ValueError``."""
    name = tonemapper.lower()
    if name not in _TONE_CURVES:
        raise ValueError(f"unknown tone mapper {tonemapper!r}; valid: {sorted(_TONE_CURVES)}")
    return name


def flip_exposures(reference: Tensor, *, tonemapper: str = "aces") -> tuple[Tensor, Tensor]:
    """HDR-FLIP's automatic exposure range, computed per image from the reference.

    ``start = log2(x_max / Y_max)``, ``stop = log2(x_max / max(Y_median, FLT_EPSILON))`` with
    ``x_max`` the input the tone curve maps to 0.85 and ``Y_median`` the upper median of the
    luminance, as in FLIP v1.7. Deviation: for an all-black reference the tool aborts; here
    ``Y_max`` is also clamped to ``FLT_EPSILON`` (giving ``start == stop``).

    Args:
        reference: ``(N, 3, H, W)`` float linear HDR reference, any device.
        tonemapper: ``"aces"`` (tool default), ``"hable"`` or ``"reinhard"``.

    Returns:
        ``(start, stop)``: two ``(N,)`` float32 tensors on the reference's device.
    """
    a, b, c, d, e, f = _TONE_CURVES[_check_tonemapper(tonemapper)]
    t = 0.85
    qa, qb, qc = a - t * d, b - t * e, c - t * f
    if qa == 0.0:
        x_max = -qc / qb
    else:
        half = -0.5 * qb / qa
        x_max = half + math.sqrt(half * half - qc / qa)
    weights = reference.new_tensor([0.2126, 0.7152, 0.0722], dtype=torch.float32)
    lum = torch.einsum("c,nchw->nhw", weights, reference.detach().float()).flatten(1)
    y_max = lum.amax(1).clamp_min(_EPS32)
    y_median = lum.kthvalue(lum.shape[1] // 2 + 1, dim=1).values.clamp_min(_EPS32)
    return torch.log2(x_max / y_max), torch.log2(x_max / y_median)


def _tonemap(x: Tensor, tonemapper: str) -> Tensor:
    """HDR-FLIP tone mappers on linear ``(B, 3, H, W)`` (luminance Reinhard, ACES, Hable)."""
    if tonemapper == "reinhard":
        weights = x.new_tensor([0.2126, 0.7152, 0.0722]).view(1, 3, 1, 1)
        return x / (1.0 + (x * weights).sum(1, keepdim=True))
    a, b, c, d, e, f = _TONE_CURVES[tonemapper]
    return (a * x * x + b * x + c) / (d * x * x + e * x + f)


def hdr_flip(
    test: Tensor,
    reference: Tensor,
    *,
    ppd: float = FLIP_DEFAULT_PPD,
    tonemapper: str = "aces",
    start_exposure: float | None = None,
    stop_exposure: float | None = None,
    num_exposures: int | None = None,
    reduction: str = "mean",
) -> Tensor:
    """Differentiable HDR-FLIP, matching ``flip_evaluator.evaluate(ref, test, "HDR")`` defaults.

    For each image, exposures ``c_i`` run evenly from ``start`` to ``stop``
    (:func:`flip_exposures` unless given; ``max(2, ceil(stop - start))`` steps unless given);
    both images are scaled by ``2**c_i``, tone-mapped, clamped to [0, 1] and compared with
    LDR-FLIP; the per-pixel maximum over exposures is the HDR-FLIP error. All exposures of the
    whole batch go through one batched LDR-FLIP evaluation, so memory grows with their total.

    Args:
        test: ``(N, 3, H, W)`` float linear HDR test image (negatives are clamped to 0), any
            device.
        reference: ``(N, 3, H, W)`` float linear HDR reference, same device.
        ppd: pixels per degree of visual angle.
        tonemapper: ``"aces"`` (tool default), ``"hable"`` or ``"reinhard"``.
        start_exposure: shared start exposure (log2 units); default per image from the reference.
        stop_exposure: shared stop exposure; default per image from the reference.
        num_exposures: shared number of exposures (>= 2); default per image.
        reduction: ``"mean"`` (scalar) or ``"none"`` (``(N, H, W)`` map).

    Returns:
        Mean HDR-FLIP error (scalar) or the per-pixel error map.
    """
    _check_pair(test, reference)
    tonemapper = _check_tonemapper(tonemapper)
    test, reference = test.clamp_min(0.0), reference.clamp_min(0.0)
    n = test.shape[0]
    start, stop = flip_exposures(reference, tonemapper=tonemapper)
    if start_exposure is not None:
        start = torch.full_like(start, start_exposure)
    if stop_exposure is not None:
        stop = torch.full_like(stop, stop_exposure)
    if bool((start > stop).any()):
        raise ValueError(f"start exposure must be <= stop exposure, got {start} > {stop}")
    if num_exposures is None:
        counts = torch.ceil(stop - start).clamp_min(2).long()
    else:
        if num_exposures < 2:
            raise ValueError(f"num_exposures must be >= 2, got {num_exposures}")
        counts = torch.full_like(start, num_exposures, dtype=torch.long)

    image = torch.repeat_interleave(torch.arange(n, device=counts.device), counts)
    first = torch.cumsum(counts, 0) - counts
    step_index = torch.arange(image.numel(), device=counts.device) - first[image]
    step = (stop - start) / (counts - 1).float()
    exposure = start[image] + step_index.float() * step[image]
    scale = torch.exp2(exposure).to(test.dtype).view(-1, 1, 1, 1)
    maps = _ldr_flip_map(
        _tonemap(test[image] * scale, tonemapper).clamp(0.0, 1.0),
        _tonemap(reference[image] * scale, tonemapper).clamp(0.0, 1.0),
        ppd,
    )
    per_image = maps.new_zeros(n, int(counts.max()), *maps.shape[1:])
    per_image = per_image.index_put((image, step_index), maps)
    return _reduce(per_image.amax(1), reduction)


class FLIPLoss(nn.Module):
    """FLIP as a loss on linear HDR ``(N, 3, H, W)`` tensors.

    ``mode="ldr"``: LDR-FLIP on ``clamp(R(x), 0, 1)`` (NGPT Reinhard, the image E-LPIPS sees
    sRGB-encoded). ``mode="hdr"``: HDR-FLIP on the linear images (exposures from the target;
    costs one LDR-FLIP per exposure, typically 2-15).

    Args:
        mode: ``"ldr"`` or ``"hdr"``.
        ppd: pixels per degree of visual angle.
        tonemapper: HDR-FLIP tone mapper (``mode="hdr"`` only).
    """

    def __init__(
        self, mode: str = "ldr", *, ppd: float = FLIP_DEFAULT_PPD, tonemapper: str = "aces"
    ) -> None:
        super().__init__()
        if mode not in ("ldr", "hdr"):
            raise ValueError(f"mode must be 'ldr' or 'hdr', got {mode!r}")
        self.mode, self.ppd, self.tonemapper = mode, ppd, _check_tonemapper(tonemapper)

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        """Mean FLIP error of ``pred`` against ``target`` (``(N, 3, H, W)``) -> scalar."""
        if self.mode == "hdr":
            return hdr_flip(pred, target, ppd=self.ppd, tonemapper=self.tonemapper)
        return ldr_flip(reinhard(pred), reinhard(target), ppd=self.ppd, inputs_srgb=False)


# ---------------------------------------------------------------------------------------------
# E-LPIPS (Kettunen et al. 2019), after mkettune/elpips
# ---------------------------------------------------------------------------------------------

#: Environment variable naming the local E-LPIPS weight file.
ELPIPS_WEIGHTS_ENV = "GDPT_ELPIPS_WEIGHTS"

Dropout = Callable[[Tensor], Tensor]


class ELPIPSWeightsError(FileNotFoundError):
    """Raised when the local E-LPIPS weight file is missing or malformed."""


@dataclass(frozen=True)
class ELPIPSConfig:
    """E-LPIPS ensemble configuration; defaults are ``elpips.Config`` (E-LPIPS evaluation).

    Attributes:
        average_over: number of independent ensemble samples averaged per call.
        num_scales: downscale factors ``1..num_scales`` drawn with ``P(s) ~ 1/s^2``; the reference
            suggests ``max(1, min(H, W) // 64)``.
        offset_max: maximal random translation in pixels (inclusive).
        dropout_keep_prob: keep probability of the dropout on every backbone conv input.
        enable_dropout: backbone dropout (mask shared by the two images of a pair).
        enable_offset: random translation (reflect pad, or crop when fast).
        enable_flip: stratified random flips (x, y, xy, none).
        enable_swap: transpose with probability 1/2, shared by the batch.
        enable_color_permutation: stratified random RGB permutation per image.
        enable_color_multiplication: stratified per-channel factors in [0.2, 1].
        enable_scale: random box downscaling.
        color_multiplication_mode: ``"color"`` (independent R, G, B) or ``"brightness"``.
        fast_and_approximate: crop instead of padding (faster; may skip image edges).
    """

    average_over: int = 1
    num_scales: int = 8
    offset_max: int = 7
    dropout_keep_prob: float = 0.99
    enable_dropout: bool = True
    enable_offset: bool = True
    enable_flip: bool = True
    enable_swap: bool = True
    enable_color_permutation: bool = True
    enable_color_multiplication: bool = True
    enable_scale: bool = True
    color_multiplication_mode: str = "color"
    fast_and_approximate: bool = False

    def __post_init__(self) -> None:
        """Validate the fields."""
        if self.average_over < 1 or self.num_scales < 1 or self.offset_max < 0:
            raise ValueError(f"invalid E-LPIPS config {self}")
        if not 0.0 < self.dropout_keep_prob <= 1.0:
            raise ValueError(f"dropout_keep_prob must be in (0, 1], got {self.dropout_keep_prob}")
        if self.color_multiplication_mode not in ("color", "brightness"):
            raise ValueError(f"unknown color_multiplication_mode {self.color_multiplication_mode}")

    @classmethod
    def ngpt_training(cls) -> ELPIPSConfig:
        """NGPT's training setting: 2 scale levels, fast mode, 3 samples averaged."""
        return cls(average_over=3, num_scales=2, fast_and_approximate=True)


@dataclass(frozen=True)
class EnsembleSample:
    """One sampled E-LPIPS input transformation for a batch of ``N`` images.

    Attributes:
        scale: downscale factor shared by the batch (1 = none).
        scale_offset: ``(oy, ox)`` in ``[0, scale)``, shared by the batch.
        offsets: ``(N, 2)`` long ``(oy, ox)`` translations in ``[0, offset_max]``.
        flips: ``(N,)`` long, 0 = flip x, 1 = flip y, 2 = flip both, 3 = none.
        swap: whether to transpose x and y (shared by the batch).
        permutations: ``(N, 3)`` long channel orders.
        color_factors: ``(N, 3)`` float channel multipliers in [0.2, 1].
    """

    scale: int
    scale_offset: tuple[int, int]
    offsets: Tensor
    flips: Tensor
    swap: bool
    permutations: Tensor
    color_factors: Tensor


def _stratified_shuffle(values: Tensor, n: int, generator: torch.Generator | None) -> Tensor:
    """Tile ``values`` (along dim 0) to at least ``n`` rows, shuffle, keep ``n`` rows."""
    tiled = values.repeat(-(-n // values.shape[0]), *([1] * (values.ndim - 1)))
    order = torch.randperm(tiled.shape[0], generator=generator, device=values.device)
    return tiled[order[:n]]


def sample_ensemble(
    n: int,
    config: ELPIPSConfig,
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str = "cpu",
) -> EnsembleSample:
    """Sample one random E-LPIPS transformation for ``n`` images (Latin-hypercube over the batch).

    Args:
        n: batch size.
        config: ensemble configuration.
        generator: random generator on ``device`` (``None``: torch's global RNG).
        device: device of the sampled tensors.

    Returns:
        The sampled transformation.
    """

    def uniform(*shape: int) -> Tensor:
        return torch.rand(shape, generator=generator, device=device)

    weights = [1.0 / s**2 for s in range(1, config.num_scales + 1)]
    cumulative = np.cumsum(weights)
    u = cumulative[-1] * float(uniform(1))
    scale = next((i + 1 for i, c in enumerate(cumulative[:-1]) if u < c), config.num_scales)
    oy, ox = (int(v) for v in (uniform(2) * scale).floor().long().clamp_max(scale - 1))
    offsets = (uniform(n, 2) * (config.offset_max + 1)).floor().long()
    offsets = offsets.clamp_max(config.offset_max)
    flips = _stratified_shuffle(torch.arange(4, device=device), n, generator)
    swap = bool(uniform(1) < 0.5)
    colors = torch.stack(
        [
            _stratified_shuffle((uniform(n) + torch.arange(n, device=device)) / n, n, generator)
            for _ in range(3)
        ],
        1,
    )
    if config.color_multiplication_mode == "brightness":
        colors = colors[:, :1].expand(n, 3)
    all_perms = torch.tensor(list(itertools.permutations(range(3))), device=device)
    return EnsembleSample(
        scale=scale,
        scale_offset=(oy, ox),
        offsets=offsets,
        flips=flips,
        swap=swap,
        permutations=_stratified_shuffle(all_perms, n, generator),
        color_factors=0.2 + 0.8 * colors,
    )


def apply_ensemble(x: Tensor, sample: EnsembleSample, config: ELPIPSConfig) -> Tensor:
    """Apply a sampled E-LPIPS transformation to a batch (order as in ``mkettune/elpips``).

    Downscale (box filter after reflect padding, or cropping when fast), translate, flip,
    transpose, permute colours, multiply colours.

    Args:
        x: ``(N, C, H, W)`` float images, ``N`` equal to the sampled batch size; any device.
        sample: the transformation from :func:`sample_ensemble`.
        config: the configuration the sample was drawn with.

    Returns:
        ``(N, C, H', W')`` transformed images.
    """
    n = x.shape[0]
    s = sample.scale
    if config.enable_scale and s > 1:
        oy, ox = sample.scale_offset
        h, w = x.shape[-2:]
        if config.fast_and_approximate:
            hh, ww = (h - s + 1) // s * s, (w - s + 1) // s * s
            x = x[..., oy : oy + hh, ox : ox + ww]
        else:
            hh, ww = (2 * s - 2 + h) // s * s, (2 * s - 2 + w) // s * s
            x = F.pad(x, (ox, ww - w - ox, oy, hh - h - oy), mode="reflect")
        x = F.avg_pool2d(x, s)
    if config.enable_offset:
        m = config.offset_max
        h, w = x.shape[-2:]
        rows = []
        for i, (oy, ox) in enumerate(sample.offsets.tolist()):
            if config.fast_and_approximate:
                rows.append(x[i : i + 1, :, oy : oy + h - m, ox : ox + w - m])
            else:
                rows.append(F.pad(x[i : i + 1], (m - ox, ox, m - oy, oy), mode="reflect"))
        x = torch.cat(rows)
    if config.enable_flip:
        flips = sample.flips.view(n, 1, 1, 1)
        x = torch.where(
            flips == 0,
            x.flip(-1),
            torch.where(flips == 1, x.flip(-2), torch.where(flips == 2, x.flip(-1, -2), x)),
        )
    if config.enable_swap and sample.swap:
        x = x.transpose(-1, -2)
    if config.enable_color_permutation:
        index = sample.permutations.view(n, 3, 1, 1).expand(-1, -1, *x.shape[-2:])
        x = torch.gather(x, 1, index)
    if config.enable_color_multiplication:
        x = x * sample.color_factors.to(x.dtype).view(n, 3, 1, 1)
    return x


def _relu_conv(conv: nn.Conv2d, x: Tensor, drop: Dropout) -> Tensor:
    """``relu(conv(drop(x)))``: the E-LPIPS conv unit (dropout on every conv input)."""
    return F.relu(conv(drop(x)))


class _Fire(nn.Module):
    """SqueezeNet fire module with torchvision's parameter names."""

    def __init__(self, c_in: int, c_squeeze: int, c_expand: int) -> None:
        super().__init__()
        self.squeeze = nn.Conv2d(c_in, c_squeeze, 1)
        self.expand1x1 = nn.Conv2d(c_squeeze, c_expand, 1)
        self.expand3x3 = nn.Conv2d(c_squeeze, c_expand, 3, padding=1)

    def forward(self, x: Tensor, drop: Dropout) -> Tensor:
        """Squeeze, then the two expand branches, concatenated along channels."""
        x = _relu_conv(self.squeeze, x, drop)
        return torch.cat(
            [_relu_conv(self.expand1x1, x, drop), _relu_conv(self.expand3x3, x, drop)], 1
        )


class SqueezeNetFeatures(nn.Module):
    """SqueezeNet 1.1 trunk of E-LPIPS ``squeeze_ensemble_maxpool`` (10 feature layers).

    Parameter names match ``torchvision.models.squeezenet1_1().state_dict()`` (``features.*``).
    Max pooling is 3x3/2 without ceil mode (TF ``VALID``), as in E-LPIPS. Needs inputs of at least
    31 px after the ensemble transforms (downscaling, and cropping in fast mode).
    """

    #: Channels of the layers fed to the linear heads (the input image first).
    channels = (3, 64, 128, 128, 256, 256, 384, 384, 512, 512)
    _fires = {
        "3": (64, 16, 64),
        "4": (128, 16, 64),
        "6": (128, 32, 128),
        "7": (256, 32, 128),
        "9": (256, 48, 192),
        "10": (384, 48, 192),
        "11": (384, 64, 256),
        "12": (512, 64, 256),
    }

    def __init__(self) -> None:
        super().__init__()
        layers: dict[str, nn.Module] = {"0": nn.Conv2d(3, 64, 3, stride=2)}
        layers.update({k: _Fire(*v) for k, v in self._fires.items()})
        self.features = nn.ModuleDict(layers)

    def forward(self, x: Tensor, drop: Dropout) -> list[Tensor]:
        """Feature maps ``(B, C_l, H_l, W_l)`` of ``x`` ``(B, 3, H, W)``, see :attr:`channels`."""
        f = self.features
        out = [x, _relu_conv(f["0"], x, drop)]
        for pool_then in (("3", "4"), ("6", "7"), ("9", "10", "11", "12")):
            h = F.max_pool2d(out[-1], 3, 2)
            for key in pool_then:
                h = f[key](h, drop)
                out.append(h)
        return out


class VGG16Features(nn.Module):
    """VGG16 trunk of E-LPIPS ``vgg_ensemble`` (average pooling, 14 feature layers).

    Parameter names match ``torchvision.models.vgg16().state_dict()`` (``features.*``).
    """

    #: Channels of the layers fed to the linear heads (the input image first).
    channels = (3, 64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512)
    _convs = ("0", "2", "5", "7", "10", "12", "14", "17", "19", "21", "24", "26", "28")
    _pool_before = frozenset({"5", "10", "17", "24"})

    def __init__(self) -> None:
        super().__init__()
        self.features = nn.ModuleDict(
            {
                k: nn.Conv2d(self.channels[i], self.channels[i + 1], 3, padding=1)
                for i, k in enumerate(self._convs)
            }
        )

    def forward(self, x: Tensor, drop: Dropout) -> list[Tensor]:
        """Feature maps ``(B, C_l, H_l, W_l)`` of ``x`` ``(B, 3, H, W)``, see :attr:`channels`."""
        out = [x]
        for key in self._convs:
            h = F.avg_pool2d(out[-1], 2) if key in self._pool_before else out[-1]
            out.append(_relu_conv(self.features[key], h, drop))
        return out


_BACKBONES: dict[str, tuple[str, type[nn.Module]]] = {
    "squeeze": ("features.3.squeeze.weight", SqueezeNetFeatures),
    "vgg": ("features.28.weight", VGG16Features),
}


def load_elpips_weights(
    path: str | os.PathLike[str] | None = None,
    config: ELPIPSConfig | None = None,
    *,
    seed: int | None = None,
) -> ELPIPS:
    """Build E-LPIPS from a local weight file (no download is ever attempted).

    File format: ``.safetensors``, ``.pt``/``.pth`` (a flat ``dict[str, Tensor]``, loaded with
    ``weights_only=True``) or ``.npz``, holding

    * the backbone in PyTorch layout under torchvision's names: the ``features.*`` entries of
      ``squeezenet1_1`` (``squeezenet1_1-b8a52dc0.pth``) or of ``vgg16`` (``vgg16-397923af.pth``);
      the backbone kind is detected from the keys;
    * the E-LPIPS linear heads ``lin0`` ... ``lin9`` (SqueezeNet, ``squeeze_full_maxpool.npy``) or
      ``lin0`` ... ``lin13`` (VGG, ``vgg_full_avg.npy``) from ``mkettune/elpips``, under the key
      ``lin{i}.weight`` or ``lin{i}.model.1.weight``, any shape with ``C_i`` elements.

    The E-LPIPS repository's ``*_pytorch_transposed_nonlinear_features.npy`` backbones are the
    same torchvision weights in TF layout: prefix the keys with ``features.`` and transpose conv
    weights with ``w.transpose(3, 2, 0, 1)``.

    Args:
        path: weight file; default: the ``GDPT_ELPIPS_WEIGHTS`` environment variable.
        config: ensemble configuration (default: E-LPIPS evaluation defaults).
        seed: see :class:`ELPIPS`.

    Returns:
        An :class:`ELPIPS` on the CPU (move it with ``.to(device)``).

    Raises:
        ELPIPSWeightsError: no path given, file missing, unknown format or missing keys.
    """
    path = path if path is not None else os.environ.get(ELPIPS_WEIGHTS_ENV)
    hint = (
        f"E-LPIPS needs a local weight file: pass its path or set {ELPIPS_WEIGHTS_ENV} to a "
        ".safetensors/.pt/.npz file holding the torchvision squeezenet1_1 or vgg16 'features.*' "
        "state dict plus the E-LPIPS linear heads 'lin{i}.weight' (squeeze_full_maxpool.npy or "
        "vgg_full_avg.npy from mkettune/elpips); see gdpt.reconstruct.losses.load_elpips_weights."
        " No download is attempted."
    )
    if not path:
        raise ELPIPSWeightsError(hint)
    file = Path(path)
    if not file.is_file():
        raise ELPIPSWeightsError(f"{file} does not exist. {hint}")
    suffix = file.suffix.lower()
    if suffix == ".safetensors":
        from safetensors.torch import load_file  # noqa: PLC0415 (optional, only for this format)

        state = load_file(str(file))
    elif suffix in (".pt", ".pth"):
        state = torch.load(file, map_location="cpu", weights_only=True)
    elif suffix == ".npz":
        with np.load(file, allow_pickle=False) as data:
            state = {k: torch.from_numpy(data[k]) for k in data.files}
    else:
        raise ELPIPSWeightsError(f"unsupported weight file type {suffix!r}. {hint}")

    kind = next((k for k, (key, _) in _BACKBONES.items() if key in state), None)
    if kind is None:
        raise ELPIPSWeightsError(f"{file}: no SqueezeNet/VGG16 'features.*' keys found. {hint}")
    backbone = _BACKBONES[kind][1]()
    backbone_state = {k: v.float() for k, v in state.items() if k.startswith("features.")}
    try:
        backbone.load_state_dict(backbone_state)
    except RuntimeError as err:
        raise ELPIPSWeightsError(f"{file}: backbone mismatch: {err}. {hint}") from err
    heads = []
    for i in range(len(backbone.channels)):
        head = state.get(f"lin{i}.weight", state.get(f"lin{i}.model.1.weight"))
        if head is None:
            raise ELPIPSWeightsError(f"{file}: linear head lin{i} missing. {hint}")
        heads.append(head.float().reshape(-1))
    return ELPIPS(backbone, heads, config, seed=seed)


class ELPIPS(nn.Module):
    """E-LPIPS distance: LPIPS over a random ensemble of input transformations.

    Per sample: one random transformation (:func:`sample_ensemble`) is applied to both images,
    which go through the backbone together with *shared* dropout masks; features are unit-
    normalised over channels, squared differences are averaged spatially, weighted by the linear
    heads and summed over layers. ``config.average_over`` samples are averaged.

    With equal random draws the distance is symmetric and is exactly 0 for identical images.

    Args:
        backbone: module with a ``channels`` tuple attribute and
            ``forward(x, drop) -> list[Tensor]`` that applies ``drop`` to every conv input; e.g.
            :class:`SqueezeNetFeatures` or :class:`VGG16Features`. Its parameters are frozen.
        lin_weights: one 1-D non-negative weight vector per feature layer, ``len == channels``.
        config: ensemble configuration (default: E-LPIPS evaluation defaults).
        seed: if given, all random draws come from a generator seeded with it (one per device),
            making the sequence of results reproducible; otherwise torch's global RNG is used.
    """

    def __init__(
        self,
        backbone: nn.Module,
        lin_weights: Sequence[Tensor],
        config: ELPIPSConfig | None = None,
        *,
        seed: int | None = None,
    ) -> None:
        super().__init__()
        channels = tuple(getattr(backbone, "channels", ()))
        if len(channels) != len(lin_weights) or any(
            w.numel() != c for w, c in zip(lin_weights, channels, strict=False)
        ):
            raise ValueError(
                f"linear heads {[w.numel() for w in lin_weights]} do not match backbone "
                f"channels {channels}"
            )
        self.backbone = backbone.requires_grad_(False)
        self.config = config or ELPIPSConfig()
        self.seed = seed
        self._generators: dict[torch.device, torch.Generator] = {}
        for i, w in enumerate(lin_weights):
            self.register_buffer(f"lin{i}", w.detach().reshape(-1).float().clone())
        self.num_layers = len(lin_weights)
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))

    @property
    def heads(self) -> list[Tensor]:
        """The linear-head weight vectors, one ``(C_l,)`` float32 tensor per feature layer."""
        return [getattr(self, f"lin{i}") for i in range(self.num_layers)]

    def _generator(self, device: torch.device) -> torch.Generator | None:
        """The seeded generator for ``device`` (created on first use), or ``None``."""
        if self.seed is None:
            return None
        if device not in self._generators:
            self._generators[device] = torch.Generator(device=device).manual_seed(self.seed)
        return self._generators[device]

    def _sample_distance(self, image: Tensor, reference: Tensor) -> Tensor:
        """One ensemble sample of the distance, ``(N,)``."""
        n, device = image.shape[0], image.device
        generator = self._generator(device)
        sample = sample_ensemble(n, self.config, generator=generator, device=device)
        x = torch.cat(
            [
                apply_ensemble(image, sample, self.config),
                apply_ensemble(reference, sample, self.config),
            ]
        )
        x = (2.0 * x - 1.0 - self.shift.to(x.dtype)) / self.scale.to(x.dtype)
        keep = self.config.dropout_keep_prob

        def drop(t: Tensor) -> Tensor:
            if not self.config.enable_dropout or keep == 1.0:
                return t
            noise = torch.rand(t[:n].shape, generator=generator, device=device)
            mask = (noise < keep).to(t.dtype) / keep
            return t * torch.cat([mask, mask])

        distance = image.new_zeros(n)
        for i, feat in enumerate(self.backbone(x, drop)):
            feat = feat / (torch.linalg.vector_norm(feat, dim=1, keepdim=True) + 1e-10)
            diff = (feat[:n] - feat[n:]).square().mean(dim=(2, 3))
            distance = distance + diff @ self.heads[i].to(diff.dtype)
        return distance

    def forward(self, image: Tensor, reference: Tensor) -> Tensor:
        """E-LPIPS distance per image.

        Args:
            image: ``(N, 3, H, W)`` float sRGB-encoded image in [0, 1], any device.
            reference: ``(N, 3, H, W)`` float sRGB-encoded reference, same device.

        Returns:
            ``(N,)`` distances, averaged over ``config.average_over`` samples.
        """
        _check_pair(image, reference)
        total = self._sample_distance(image, reference)
        for _ in range(self.config.average_over - 1):
            total = total + self._sample_distance(image, reference)
        return total / self.config.average_over


class ELPIPSLoss(nn.Module):
    """E-LPIPS on ``sRGB(max(0, R(x)))`` of linear HDR images, as in NGPT (Eq. 7-8).

    Args:
        elpips: the distance module (e.g. from :func:`load_elpips_weights`).
    """

    def __init__(self, elpips: ELPIPS) -> None:
        super().__init__()
        self.elpips = elpips

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        """Batch-mean E-LPIPS of ``(N, 3, H, W)`` linear HDR ``pred`` vs ``target`` -> scalar."""

        def display(x: Tensor) -> Tensor:
            return srgb_encode(reinhard(x).clamp_min(0.0))

        return self.elpips(display(pred), display(target)).mean()


# ---------------------------------------------------------------------------------------------
# Combined NGPT-style losses and registry
# ---------------------------------------------------------------------------------------------


class NGPTLoss(nn.Module):
    """``perceptual + beta L1(R(x), R(y)) + gamma L1(R~(grad x), R~(grad y)) + delta l1_log
    + rho l1_relative``.

    NGPT Eq. 8 with a pluggable perceptual term (Kettunen et al. 2019: E-LPIPS, beta = gamma =
    0.01, delta = rho = 0). ``perceptual=None`` drops the term (NGPT config 102: beta = 1,
    gamma = 0.01). ``delta`` and ``rho`` weigh :func:`l1_log` and :func:`l1_relative`, our
    additions for short training runs (see :data:`LOSSES`).

    Args:
        perceptual: module ``(pred, target) -> scalar`` on linear HDR ``(N, 3, H, W)``, or None.
        beta: weight of :func:`l1_tonemapped`.
        gamma: weight of :func:`gradient_l1_tonemapped`.
        delta: weight of :func:`l1_log`.
        rho: weight of :func:`l1_relative`.
    """

    def __init__(
        self,
        perceptual: nn.Module | None,
        *,
        beta: float = 0.01,
        gamma: float = 0.01,
        delta: float = 0.0,
        rho: float = 0.0,
    ) -> None:
        super().__init__()
        self.perceptual, self.beta, self.gamma = perceptual, beta, gamma
        self.delta, self.rho = delta, rho

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        """Loss of ``(N, 3, H, W)`` linear HDR ``pred`` against ``target`` -> scalar tensor."""
        loss = self.beta * l1_tonemapped(pred, target)
        loss = loss + self.gamma * gradient_l1_tonemapped(pred, target)
        if self.delta:
            loss = loss + self.delta * l1_log(pred, target)
        if self.rho:
            loss = loss + self.rho * l1_relative(pred, target)
        if self.perceptual is not None:
            loss = loss + self.perceptual(pred, target)
        return loss


def _elpips_loss(
    weights: str | os.PathLike[str] | None = None,
    *,
    config: ELPIPSConfig | None = None,
    seed: int | None = None,
) -> NGPTLoss:
    """NGPT config 100: E-LPIPS (NGPT training config) + 0.01 L1(R) + 0.01 gradient L1."""
    elpips = load_elpips_weights(weights, config or ELPIPSConfig.ngpt_training(), seed=seed)
    return NGPTLoss(ELPIPSLoss(elpips))


#: Loss name -> factory; every factory returns a module ``(pred, target) -> scalar`` on linear
#: HDR ``(N, 3, H, W)`` tensors.
LOSSES: Registry[Callable[..., nn.Module]] = Registry("loss")
LOSSES.register("flip", lambda **kw: NGPTLoss(FLIPLoss("ldr", **kw)))
LOSSES.register("flip_hdr", lambda **kw: NGPTLoss(FLIPLoss("hdr", **kw)))
LOSSES.register("flip_log", lambda **kw: NGPTLoss(FLIPLoss("ldr", **kw), delta=0.1))
LOSSES.register("flip_rel", lambda **kw: NGPTLoss(FLIPLoss("ldr", **kw), rho=1.0))
LOSSES.register("elpips", _elpips_loss)
LOSSES.register("l1", lambda **kw: NGPTLoss(None, beta=1.0, gamma=0.01, **kw))


def get_loss(name: str, **kwargs: object) -> nn.Module:
    """Build a training loss by name.

    * ``"flip"``: LDR-FLIP on ``clamp(R(x), 0, 1)`` + 0.01 L1(R) + 0.01 gradient L1 (default).
    * ``"flip_hdr"``: HDR-FLIP (ACES, exposures from the target) + the same L1 terms.
    * ``"flip_log"``: ``"flip"`` + 0.1 :func:`l1_log`. Not in the paper: LDR-FLIP and the
      Reinhard L1 saturate on bright pixels, and in CPU-length runs (~1e3 times fewer updates
      than the paper's) networks trained without it put emitters off by orders of magnitude.
    * ``"flip_rel"``: ``"flip"`` + :func:`l1_relative`. Not in the paper: the relMSE metric is
      dominated by dark regions and fireflies, which FLIP and the log term hardly weigh; in
      CPU-length runs networks trained without it tinted dark regions (relMSE worse than
      their noisy input while FLIP improved).
    * ``"elpips"``: NGPT config 100, E-LPIPS (weights from ``weights=`` or
      ``GDPT_ELPIPS_WEIGHTS``; NGPT training config) + the same L1 terms.
    * ``"l1"``: NGPT config 102, L1(R) + 0.01 gradient L1.

    Args:
        name: one of :data:`LOSSES`.
        **kwargs: forwarded to the factory (e.g. ``ppd=``, ``weights=``, ``seed=``).

    Returns:
        Module mapping ``(pred, target)`` ``(N, 3, H, W)`` linear HDR tensors to a scalar.

    Raises:
        KeyError: unknown name (the message lists the valid names).
        ELPIPSWeightsError: ``"elpips"`` without a weight file.
    """
    return LOSSES[name](**kwargs)
