"""Deprecated module (removed in :data:`gdpt.deprecated.REMOVED_IN`): its names moved to
:mod:`gdpt.methods` (``Method``, ``METHODS``, ``reconstruct_image``, ``register_checkpoint``),
:mod:`gdpt.checkpoints` (``MODEL_DIR``, ``MODEL_ENV``, ``model_path``, ``load_reconstructor``),
:mod:`gdpt.adapters` (``FUSE_PRIMAL_SPP_FACTOR``) and :mod:`gdpt.oidn`
(``oidn_check``, ``oidn_denoise``); importing it warns. :func:`reconstruct` is the deprecated
name of :func:`gdpt.reconstruct_image`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from gdpt.adapters import FUSE_PRIMAL_SPP_FACTOR
from gdpt.checkpoints import MODEL_DIR, MODEL_ENV, load_reconstructor, model_path
from gdpt.deprecated import MODEL_ENV_DEPRECATED, warn
from gdpt.methods import (
    DIFFERENTIABLE_FAMILIES,
    METHODS,
    Method,
    reconstruct_image,
    register_checkpoint,
)
from gdpt.oidn import OIDN_IMPLEMENTATIONS as OIDN_BACKENDS
from gdpt.oidn import oidn_check, oidn_denoise

if TYPE_CHECKING:
    import torch

    from gdpt.buffers import GradientBuffers

__all__ = [
    "DIFFERENTIABLE_FAMILIES",
    "FUSE_PRIMAL_SPP_FACTOR",
    "METHODS",
    "MODEL_DIR",
    "MODEL_ENV",
    "MODEL_ENV_DEPRECATED",
    "Method",
    "OIDN_BACKENDS",
    "load_reconstructor",
    "model_path",
    "oidn_check",
    "oidn_denoise",
    "reconstruct",
    "reconstruct_image",
    "register_checkpoint",
]

warn("gdpt.denoise", "import gdpt.methods, gdpt.checkpoints or gdpt.oidn")


def reconstruct(
    buffers: GradientBuffers, method: str = "l1-fast", *, alpha: float = 0.2, **options: Any
) -> torch.Tensor:
    """Deprecated name of :func:`gdpt.reconstruct_image` (same arguments and result); warns.

    Raises:
        ValueError: as :func:`gdpt.reconstruct_image`.
    """
    warn("gdpt.denoise.reconstruct", "use gdpt.reconstruct_image (same arguments)")
    return reconstruct_image(buffers, method, alpha=alpha, **options)
