"""The single entry point that turns gradient-domain buffers into a final image.

:func:`reconstruct` looks a method up by name in :data:`METHODS` and applies it. Each entry is a
function ``f(buffers, *, alpha, **options) -> (H, W, 3) tensor``:

* ``'l2'`` / ``'l1'``: screened Poisson reconstruction (:mod:`gdpt.reconstruct.poisson`), the
  closed-form L2 solution and its iteratively reweighted L1 variant.

To add a method (e.g. the NGPT network from :mod:`gdpt.reconstruct.ngpt`), write such a function
in this module and add it to :data:`METHODS`; the CLI offers every key of :data:`METHODS`.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch

    from gdpt.buffers import GradientBuffers

#: ``f(buffers, *, alpha, **options) -> (H, W, 3) float32 tensor on buffers.device``.
Method = Callable[..., "torch.Tensor"]


def _poisson(
    buffers: GradientBuffers, *, method: str, alpha: float, **options: Any
) -> torch.Tensor:
    """Screened Poisson reconstruction from ``primal``, ``dx`` and ``dy``."""
    if buffers.dx is None or buffers.dy is None:
        raise ValueError(
            f"method {method!r} needs dx and dy; this render has none (primal-only mode)"
        )
    from gdpt.reconstruct import poisson

    return poisson.reconstruct(
        buffers.primal, buffers.dx, buffers.dy, method=method, alpha=alpha, **options
    )


#: Method name -> implementation. Extension point for learned reconstructions ('ngpt').
METHODS: dict[str, Method] = {
    "l1": partial(_poisson, method="l1"),
    "l2": partial(_poisson, method="l2"),
}


def reconstruct(
    buffers: GradientBuffers, method: str = "l1", *, alpha: float = 0.2, **options: Any
) -> torch.Tensor:
    """Reconstruct the final image from a gradient-domain render.

    Args:
        buffers (GradientBuffers): the render; the Poisson methods need ``dx`` and ``dy``.
        method (str): a key of :data:`METHODS` (``'l1'``, ``'l2'``).
        alpha (float): weight of the primal term relative to the gradient terms (screened
            Poisson); methods that have no such weight ignore it.
        **options: method-specific options, passed through unchanged.

    Returns:
        ``(H, W, 3)`` float32 tensor on ``buffers.device``.

    Raises:
        ValueError: unknown ``method``, or the buffers lack what the method needs.
    """
    if method not in METHODS:
        raise ValueError(
            f"unknown reconstruction method {method!r}; valid methods: {', '.join(METHODS)}"
        )
    return METHODS[method](buffers, alpha=alpha, **options)
