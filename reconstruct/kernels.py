"""Per-pixel kernel application: the filtering step of kernel-predicting networks.

A network predicts, at every pixel ``p``, logits over the taps ``t`` of a ``k x k``
neighbourhood of ``K`` images; their softmax ``w`` is a convex combination::

    out[p] = sum_{c, t} w[p, c, t] * image_c[p + t],   w >= 0,   sum_{c, t} w[p, c, t] = 1

This is the kernel prediction of KPCN (Bako et al. 2017, "Kernel-predicting convolutional
networks for denoising Monte Carlo renderings", SIGGRAPH, eq. 5-6: softmax-normalised weights
applied to the noisy neighbourhood), used by KPCN itself (:mod:`.kpcn`, one image) and by the
combiner (:mod:`.combiner`, ``K`` candidate images).

Only torch is imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

__all__ = ["apply_kernels"]


def apply_kernels(cands: torch.Tensor, logits: torch.Tensor, kernel: int) -> torch.Tensor:
    """Per-pixel convex combination of the candidates' ``k x k`` neighbourhoods.

    Args:
        cands: ``(N, K, C, H, W)`` float candidate images.
        logits: ``(N, K * k * k, H, W)`` float (candidate-major, taps row-major), same device.
        kernel: ``k`` (odd); neighbourhoods are edge-replicated at the border.

    Returns:
        ``(N, C, H, W)``; at each pixel a weighted mean of candidate values (softmax weights).

    Raises:
        ValueError: ``logits`` do not fit ``cands`` and ``kernel``.
    """
    n, k_cand, ch, h, w = cands.shape
    taps = kernel * kernel
    if logits.shape != (n, k_cand * taps, h, w):
        raise ValueError(
            f"logits of shape {tuple(logits.shape)} do not fit {k_cand} candidates of "
            f"{h}x{w} with {kernel}x{kernel} kernels"
        )
    weights = torch.softmax(logits, 1).reshape(n, k_cand, 1, taps, h, w)
    r = kernel // 2
    flat = cands.reshape(n, k_cand * ch, h, w)
    if r:
        flat = F.pad(flat, (r, r, r, r), mode="replicate")
    patches = F.unfold(flat, kernel).reshape(n, k_cand, ch, taps, h, w)
    return (weights * patches).sum((1, 3))
