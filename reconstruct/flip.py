"""Differentiable FLIP (LDR and HDR), after NVlabs/flip v1.7 (separable C++ evaluator).

A re-implementation of NVIDIA's FLIP (Andersson et al. 2020, HDR-FLIP 2021) that follows the
separable C++ evaluator shipped as ``flip_evaluator``, so mean errors agree with it to well under
1 %. Images are ``(N, 3, H, W)`` float tensors on any one device; the results are on that device.

Argument order: the test image comes first and the reference second. FLIP is not symmetric (HDR
exposures are computed from the reference).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .colour import check_image_pair, srgb_decode

__all__ = ["FLIP_DEFAULT_PPD", "check_tonemapper", "flip_exposures", "hdr_flip", "ldr_flip"]


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
    cube_root = t.clamp_min(delta**3) ** (1.0 / 3.0)  # finite gradients below the threshold
    return torch.where(t > delta**3, cube_root, t / (3.0 * delta**2) + 4.0 / 29.0)


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
    check_image_pair(test, reference)
    if inputs_srgb:
        test, reference = srgb_decode(test), srgb_decode(reference)
    return _reduce(_ldr_flip_map(test, reference, ppd), reduction)


def check_tonemapper(tonemapper: str) -> str:
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
    a, b, c, d, e, f = _TONE_CURVES[check_tonemapper(tonemapper)]
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
    check_image_pair(test, reference)
    tonemapper = check_tonemapper(tonemapper)
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
