"""Intel Open Image Denoise's ``RT`` filter (https://github.com/RenderKit/oidn), run by
``pyoidn`` or by the torch port of its U-Net (:mod:`.oidn_unet`).

``pyoidn`` is an optional dependency, imported only when used; importing this module imports
neither it nor torch.
"""

from __future__ import annotations

import importlib.util
import os
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

#: Implementations :func:`oidn_denoise` can run (``implementation=``).
OIDN_IMPLEMENTATIONS = ("auto", "pyoidn", "torch")


def oidn_check() -> str | None:
    """``None`` when Intel Open Image Denoise (``pyoidn``, which also holds the weights of the
    torch port) can run here, else why not."""
    if importlib.util.find_spec("pyoidn") is None:
        return "pyoidn is not installed (pip install pyoidn)"
    return None


def oidn_denoise(
    primal: torch.Tensor,
    albedo: torch.Tensor,
    normal: torch.Tensor,
    *,
    backend: str = "auto",
    weights: str | os.PathLike | None = None,
) -> torch.Tensor:
    """OIDN's ``RT`` filter, HDR, quality ``high``, with albedo and normal.

    Colour is clamped to >= 0, albedo to [0, 1] and normals to [-1, 1] as OIDN expects.

    Args:
        primal: ``(H, W, 3)`` float32 linear radiance, on the CPU or a CUDA device.
        albedo: ``(H, W, 3)`` float32 albedo, same device.
        normal: ``(H, W, 3)`` float32 normals in [-1, 1], same device.
        backend: one of :data:`OIDN_IMPLEMENTATIONS`. ``"pyoidn"``: ``pyoidn.denoise`` on the
            tensors' device (its CPU device, or its own CUDA device for CUDA tensors);
            ``"torch"``: OIDN's U-Net in torch (:func:`.oidn_unet.denoise`, Intel's weights,
            agrees with pyoidn to 1e-4 relative) on the tensors' device without a host round
            trip; ``"auto"``: ``pyoidn`` on the CPU, ``torch`` on CUDA (and wherever
            ``weights`` is given).
        weights: the torch port only: a ``.tza`` file of Intel's ``rt_hdr_alb_nrm`` weights
            (https://github.com/RenderKit/oidn-weights), for machines without ``pyoidn``.

    Returns:
        ``(H, W, 3)`` float32 on the device of ``primal``, no gradients.

    Raises:
        ValueError: unknown ``backend``, or ``weights`` with ``backend="pyoidn"``.
        RuntimeError: ``pyoidn`` is needed (its package or weights) and not installed.
    """
    if backend not in OIDN_IMPLEMENTATIONS:
        valid = ", ".join(OIDN_IMPLEMENTATIONS)
        raise ValueError(f"oidn backend must be one of {valid}, got {backend!r}")
    if backend == "pyoidn" and weights is not None:
        raise ValueError("oidn: weights= is an option of the torch backend, not of pyoidn")
    import torch

    if backend == "auto":
        backend = "pyoidn" if primal.device.type == "cpu" and weights is None else "torch"
    if backend == "torch":
        from .oidn_unet import denoise

        with torch.no_grad():  # (not inference mode: callers may change the image in place)
            return denoise(primal, albedo, normal, weights=weights, hdr=True, quality="high")
    if reason := oidn_check():
        raise RuntimeError(reason)
    import pyoidn  # noqa: PLC0415 (optional dependency)

    out = pyoidn.denoise(
        primal.clamp_min(0.0).contiguous(),
        albedo.clamp(0.0, 1.0).contiguous(),
        normal.clamp(-1.0, 1.0).contiguous(),
        hdr=True,
        quality="high",
    )
    return torch.as_tensor(out, device=primal.device)
