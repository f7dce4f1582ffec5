"""Intel Open Image Denoise's ``RT`` filter (https://github.com/RenderKit/oidn) on a render's
primal, albedo and normal: OIDN's own kernels through ``mitsuba-oidn`` (:mod:`gdpt.oidn_native`)
or the torch port of its U-Net (:mod:`gdpt.reconstruct.oidn_unet`).

Importing this module imports neither ``mitsuba-oidn`` nor torch.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

from gdpt.deprecated import OIDN_IMPLEMENTATION_ALIASES, warn

if TYPE_CHECKING:
    import torch

#: Implementations :func:`oidn_denoise` can run (its ``backend=``).
OIDN_IMPLEMENTATIONS = ("auto", "native", "torch")


def oidn_check() -> str | None:
    """``None`` when Intel Open Image Denoise (``mitsuba-oidn``, which also holds the weights of
    the torch port) can run here, else why not."""
    from gdpt.oidn_native import check

    return check()


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
        backend: one of :data:`OIDN_IMPLEMENTATIONS`. ``"native"``: OIDN itself through
            ``mitsuba-oidn`` (:func:`gdpt.oidn_native.denoise`) on the tensors' device, reading
            them in place (copied first only where a pixel's channels are not adjacent);
            ``"torch"``: OIDN's U-Net in torch (:func:`gdpt.reconstruct.oidn_unet.denoise`,
            Intel's weights, agrees with OIDN to 1e-4 relative); ``"auto"``: ``native``, or
            ``torch`` where ``weights`` is given. ``"pyoidn"``, the former name of ``native``,
            still works with a ``DeprecationWarning``.
        weights: the torch port only: a ``.tza`` file of Intel's ``rt_hdr_alb_nrm`` weights
            (https://github.com/RenderKit/oidn-weights), for machines without ``mitsuba-oidn``
            (which otherwise supplies them).

    Returns:
        ``(H, W, 3)`` float32 on the device of ``primal``, no gradients.

    Raises:
        ValueError: unknown ``backend``, ``weights`` with ``backend="native"``, or an image
            OIDN cannot read (named with its shape: not ``(H, W, 3)`` float32 like the primal).
        RuntimeError: ``mitsuba-oidn`` is needed (its package or weights) and not installed.
    """
    if backend in OIDN_IMPLEMENTATION_ALIASES:
        warn(f"oidn backend {backend!r}", f"use {OIDN_IMPLEMENTATION_ALIASES[backend]!r}")
        backend = OIDN_IMPLEMENTATION_ALIASES[backend]
    if backend not in OIDN_IMPLEMENTATIONS:
        valid = ", ".join(OIDN_IMPLEMENTATIONS)
        raise ValueError(f"oidn backend must be one of {valid}, got {backend!r}")
    if backend == "native" and weights is not None:
        raise ValueError("oidn: weights= is an option of the torch backend, not of native OIDN")
    import torch

    if backend == "auto":
        backend = "native" if weights is None else "torch"
    if backend == "torch":
        from gdpt.reconstruct.oidn_unet import denoise

        with torch.no_grad():  # (not inference mode: callers may change the image in place)
            return denoise(primal, albedo, normal, weights=weights, hdr=True, quality="high")
    from gdpt import oidn_native

    images = (primal, albedo, normal)
    return oidn_native.denoise(
        *(
            t.contiguous() if isinstance(t, torch.Tensor) and t.stride(-1) != 1 else t
            for t in images
        )
    )
