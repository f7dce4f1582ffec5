"""Colour images ``(N, 3, H, W)``: the pair check, NGPT's Reinhard tone map, sRGB transfer.

The display transforms the perceptual terms see (NGPT [Kettunen et al. 2019, Eq. 6-8]):

* ``R(x) = x / (1 + mean_c |x|)`` (per-pixel Reinhard; it is odd, so the same formula is the
  "odd reflection" the paper applies to gradients),
* ``sRGB(R(x))`` (IEC 61966-2-1 encoding) for E-LPIPS,
* ``clamp(R(x), 0, 1)`` (linear) for LDR-FLIP.

Every function is element-wise (or per pixel) and differentiable, and runs on the device of its
input.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["check_image_pair", "reinhard", "srgb_decode", "srgb_encode"]


def check_image_pair(pred: Tensor, target: Tensor) -> None:
    """Raise ``ValueError`` unless both are ``(N, 3, H, W)`` tensors of equal shape."""
    if pred.ndim != 4 or pred.shape[1] != 3 or pred.shape != target.shape:
        raise ValueError(
            "expected pred and target of equal shape (N, 3, H, W), got "
            f"pred {tuple(pred.shape)} and target {tuple(target.shape)}"
        )


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
