"""The single entry point that turns gradient-domain buffers into a final image.

:func:`reconstruct` looks a method up by name in :data:`METHODS` and applies it. Each entry is a
function ``f(buffers, *, alpha, **options) -> (H, W, 3) tensor``:

* ``'l2'`` / ``'l1'`` / ``'l1-fast'``: screened Poisson reconstruction
  (:mod:`gdpt.reconstruct.poisson`): the closed-form L2 solution, the reference IRLS L1 preset
  and the accelerated L1 solver (same or lower L1 energy, fewer CG iterations).
* ``'ngpt'`` / ``'ngpt-nograd'``: the dense U-Net (:mod:`gdpt.reconstruct.ngpt`) with a
  checkpoint given as ``model=PATH``, ``$GDPT_NGPT_MODEL``, or shipped in ``gdpt/models/``.

To add a method (e.g. the NGPT network from :mod:`gdpt.reconstruct.ngpt`), write such a function
in this module and add it to :data:`METHODS`; the CLI offers every key of :data:`METHODS`.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from functools import lru_cache, partial
from pathlib import Path
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


#: Folder of the models shipped with the package (``<name>.safetensors`` + ``<name>.json``).
MODEL_DIR = Path(__file__).parent / "models"


def model_path(name: str, model: str | os.PathLike | None = None) -> Path:
    """The checkpoint to use: ``model``, else ``$GDPT_NGPT_MODEL`` (for ``ngpt``), else shipped.

    Raises:
        FileNotFoundError: no such checkpoint; the message says what to provide.
    """
    if model is None and name == "ngpt":
        model = os.environ.get("GDPT_NGPT_MODEL")
    path = Path(model) if model is not None else MODEL_DIR / f"{name}.safetensors"
    if not path.is_file():
        raise FileNotFoundError(
            f"NGPT checkpoint not found: {path}. Pass model=PATH (a checkpoint written by "
            f"'gdpt train'), or set GDPT_NGPT_MODEL for 'ngpt'"
        )
    return path


@lru_cache(maxsize=4)
def _reconstructor(path: Path) -> Any:
    from gdpt.reconstruct.ngpt import NGPTReconstructor

    return NGPTReconstructor.from_checkpoint(path)


def _ngpt(
    buffers: GradientBuffers, *, name: str, alpha: float, model: str | None = None, **_: Any
) -> torch.Tensor:
    """Neural reconstruction with a trained dense U-Net (``alpha`` does not apply)."""
    return _reconstructor(model_path(name, model).resolve())(buffers)


#: Method name -> implementation.
METHODS: dict[str, Method] = {
    "l1": partial(_poisson, method="l1"),
    "l2": partial(_poisson, method="l2"),
    "l1-fast": partial(_poisson, method="l1_fast"),
    "ngpt": partial(_ngpt, name="ngpt"),
    "ngpt-nograd": partial(_ngpt, name="ngpt-nograd"),
}


#: Method name -> the integrator outputs it reads (``gdpt`` properties ``gradients`` and
#: ``features``); :func:`gdpt.render_and_denoise` renders only these unless told otherwise.
NEEDS: dict[str, dict[str, bool]] = {
    "l1": {"gradients": True, "features": False},
    "l2": {"gradients": True, "features": False},
    "l1-fast": {"gradients": True, "features": False},
    "ngpt": {"gradients": True, "features": True},
    "ngpt-nograd": {"gradients": False, "features": True},
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
