"""The orthonormal 2-D DCT-II (by FFT, Makhoul's reordering) and the closed-form solve of
``(a I + c L) z = r`` it gives for the reflecting-boundary graph Laplacian ``L``, whose
eigenvalues are ``(2 - 2cos(pi k/W)) + (2 - 2cos(pi l/H))``.

Layout, dtype, device: :func:`dct2` / :func:`idct2` transform the last two dimensions of any
real floating tensor on its device; :class:`LaplaceDCT` works on ``(B, C, H, W)``.
"""

from __future__ import annotations

import math

import torch


def _twiddle(n: int, like: torch.Tensor) -> torch.Tensor:
    """``exp(-i pi k / (2n))`` for ``k = 0 .. n//2``, complex, on ``like``'s device."""
    k = torch.arange(n // 2 + 1, dtype=torch.float64, device=like.device)
    ang = (-math.pi / (2 * n)) * k
    ctype = torch.complex128 if like.dtype == torch.float64 else torch.complex64
    return torch.polar(torch.ones_like(ang), ang).to(ctype)


def _dct_last(x: torch.Tensor, tw: torch.Tensor | None = None) -> torch.Tensor:
    """Unnormalised DCT-II along the last dim: ``y_k = sum_n x_n cos(pi k (2n+1) / (2N))``."""
    n = x.shape[-1]
    if n == 1:
        return x.clone()
    if tw is None:
        tw = _twiddle(n, x)
    v = torch.cat([x[..., ::2], x[..., 1::2].flip(-1)], dim=-1)
    z = torch.fft.rfft(v, dim=-1) * tw
    m = (n - 1) // 2
    return torch.cat([z.real, z.imag[..., 1 : m + 1].flip(-1).neg()], dim=-1)


def _idct_last(y: torch.Tensor, tw: torch.Tensor | None = None) -> torch.Tensor:
    """Exact inverse of :func:`_dct_last` (a scaled DCT-III) along the last dim."""
    n = y.shape[-1]
    if n == 1:
        return y.clone()
    if tw is None:
        tw = _twiddle(n, y)
    h = n // 2 + 1
    im = torch.zeros_like(y[..., :h])
    # Z_k = y_k - i y_{n-k} for k = 1 .. h-1 (y_n := 0).
    im[..., 1:h] = y[..., n - h + 1 :].flip(-1).neg()
    z = torch.complex(y[..., :h].contiguous(), im) * tw.conj()
    v = torch.fft.irfft(z, n=n, dim=-1)
    x = torch.empty_like(v)
    c = (n + 1) // 2
    x[..., ::2] = v[..., :c]
    x[..., 1::2] = v[..., c:].flip(-1)
    return x


def _ortho_scale(n: int, like: torch.Tensor) -> torch.Tensor:
    s = torch.full((n,), math.sqrt(2.0 / n), dtype=like.dtype, device=like.device)
    s[0] = math.sqrt(1.0 / n)
    return s


def dct2(x: torch.Tensor) -> torch.Tensor:
    """Orthonormal 2-D DCT-II over the last two dimensions (same as SciPy ``norm="ortho"``).

    Args:
        x: ``(..., H, W)`` real floating tensor, any device.

    Returns:
        ``(..., H, W)`` coefficients, same dtype and device; ``[..., l, k]`` is the coefficient
        of vertical frequency ``l`` and horizontal frequency ``k``.
    """
    h, w = x.shape[-2:]
    y = _dct_last(x) * _ortho_scale(w, x)
    y = _dct_last(y.transpose(-1, -2)) * _ortho_scale(h, x)
    return y.transpose(-1, -2)


def idct2(y: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`dct2` (orthonormal 2-D DCT-III over the last two dimensions).

    Args:
        y: ``(..., H, W)`` real floating tensor of DCT-II coefficients, any device.

    Returns:
        ``(..., H, W)`` image, same dtype and device.
    """
    h, w = y.shape[-2:]
    x = _idct_last(y.transpose(-1, -2) / _ortho_scale(h, y))
    return _idct_last(x.transpose(-1, -2) / _ortho_scale(w, y))


class LaplaceDCT:
    """Solves ``(a * alpha^2 I + c * L) z = r`` for ``(B, C, H, W)`` tensors with the DCT.

    ``a`` and ``c`` are scalars or ``(B, 1, 1, 1)`` / ``(B, C, 1, 1)`` tensors.
    """

    def __init__(self, h: int, w: int, like: torch.Tensor) -> None:
        self.h, self.w = h, w
        self.tw_w = _twiddle(w, like) if w > 1 else None
        self.tw_h = _twiddle(h, like) if h > 1 else None
        dt, dev = like.dtype, like.device
        kx = torch.arange(w, dtype=torch.float64, device=dev)
        ky = torch.arange(h, dtype=torch.float64, device=dev)
        lx = 2.0 - 2.0 * torch.cos(math.pi * kx / w)
        ly = 2.0 - 2.0 * torch.cos(math.pi * ky / h)
        # Eigenvalues of L, laid out like the transformed tensor (B, C, W, H) -> here (H, W).
        self.lam = (ly[:, None] + lx[None, :]).to(dt)

    def forward(self, r: torch.Tensor) -> torch.Tensor:
        """Unnormalised 2-D DCT, returned in ``(B, C, W, H)`` (transposed) layout."""
        y = _dct_last(r, self.tw_w) if self.w > 1 else r
        y = y.transpose(-1, -2)
        return _dct_last(y, self.tw_h) if self.h > 1 else y.contiguous()

    def inverse(self, y: torch.Tensor) -> torch.Tensor:
        x = _idct_last(y, self.tw_h) if self.h > 1 else y
        x = x.transpose(-1, -2)
        return _idct_last(x, self.tw_w) if self.w > 1 else x.contiguous()

    def solve(
        self, r: torch.Tensor, a2: float | torch.Tensor, c: float | torch.Tensor = 1.0
    ) -> torch.Tensor:
        """``z = (a2 I + c L)^-1 r`` (``a2`` already includes ``alpha^2``)."""
        y = self.forward(r)
        denom = self.lam.transpose(0, 1) * c + a2  # (W, H) layout, broadcast over (B, C)
        return self.inverse(y / denom)
