"""Whether torch autograd records a computation on given tensors.

Reconstruction runs under ``torch.inference_mode`` (faster, less memory) unless a caller asks
for gradients: :func:`records` is true when gradient mode is on and an input requires
gradients, so ``torch.inference_mode(not records(...))`` keeps a differentiable caller's graph.

Only torch is imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

from collections.abc import Iterable

import torch

__all__ = ["records"]


def records(tensors: Iterable[object]) -> bool:
    """``True`` when autograd records an operation on one of ``tensors``.

    Args:
        tensors: tensors, or other objects (e.g. ``None`` for an absent buffer), which are
            ignored.

    Returns:
        ``torch.is_grad_enabled()`` and at least one tensor with ``requires_grad``.
    """
    return torch.is_grad_enabled() and any(
        isinstance(t, torch.Tensor) and t.requires_grad for t in tensors
    )
