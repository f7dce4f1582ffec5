"""Gated gradient-domain refinement of a denoised image: the L1 screened Poisson
reconstruction of gradient-domain path tracing (Kettunen et al. 2015) with the denoiser's
output as its data term, kept where it stays close to that output.

A denoiser's output ``n`` is smooth but loses what its input did not show clearly (shadow
edges, fine texture). The G-PT gradients carry exactly that. The refinement solves screened
Poisson L1 (:func:`.poisson.solve_l1`) with ``n`` as the data term, so the
gradients correct ``n``::

    r = argmin_x  alpha |x - n|_1 + |Dx x - dx|_1 + |Dy x - dy|_1      (IRLS preset ``refine``)

and then keeps ``r`` only where it stays close to ``n``. Where the gradients are unreliable
(high gradient variance relative to the primal's, the case of Fig. 5 of Kettunen et al. 2019:
caustics, glossy interreflections) ``r`` departs from ``n`` by far more than a blur correction
would, over whole regions. The gate measures that departure in OIDN's PU encoding
(perceptual, log-like; ``s``: OIDN's input scale)::

    d = maxpool_{window x window}( max_c |PU(s r) - PU(s n)| )
    g = exp(-(d / tau)^2)
    out = g r + (1 - g) n

The max-pool widens the gate around a failure so that the rim of a Poisson dipole is gated with
its centre. ``alpha``, ``tau`` and ``window`` are part of a model's card; ``gdpt
select-refinement`` chooses ``alpha`` and ``tau`` on procedural validation data
(:mod:`gdpt.training.refinement`), never on evaluation scenes.

Only torch is imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch.nn import functional as F

from .oidn_unet import autoexposure, pu_forward
from .poisson import get_l1_preset, solve_l1

__all__ = ["GatedRefinement"]


@dataclass(frozen=True)
class GatedRefinement:
    """Gated screened-Poisson L1 refinement (see the module docstring).

    Attributes:
        alpha: data weight of the L1 solve (> 0).
        tau: gate width in PU units (> 0; ``inf`` keeps the L1 solution everywhere).
        window: side of the max-pool that widens the gate (odd, >= 1).
        preset: IRLS schedule of the L1 solve (a key of
            :data:`gdpt.reconstruct.poisson.L1_PRESETS`).
    """

    alpha: float = 0.5
    tau: float = 0.02
    window: int = 5
    preset: str = "refine"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.alpha) and self.alpha > 0):
            raise ValueError(f"refinement alpha must be finite and > 0, got {self.alpha}")
        if not self.tau > 0:
            raise ValueError(f"refinement tau must be > 0, got {self.tau}")
        if self.window < 1 or self.window % 2 != 1:
            raise ValueError(f"refinement window must be odd and >= 1, got {self.window}")
        get_l1_preset(self.preset)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form (the ``"refine"`` entry of a model card; an infinite ``tau``
        is written as ``"inf"``)."""
        return {**asdict(self), "tau": self.tau if math.isfinite(self.tau) else "inf"}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> GatedRefinement:
        """Inverse of :meth:`to_dict`; unknown keys raise ``TypeError``."""
        return cls(**{**data, "tau": float(data.get("tau", cls.tau))})

    def solve(self, image: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor) -> torch.Tensor:
        """The ungated L1 solution ``r``: ``(H, W, 3)`` float32 (finite, >= 0) on the device of
        ``image``."""
        return solve_l1(
            image, dx.float(), dy.float(), alpha=self.alpha, preset=self.preset
        ).clamp_min(0)

    def gate(self, refined: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """``(H, W, 1)`` gate ``g`` in [0, 1] of ``refined`` against ``image``."""
        scale = autoexposure(image)
        d = (pu_forward(scale * refined) - pu_forward(scale * image)).abs().amax(-1)
        r = self.window // 2
        d = F.max_pool2d(d[None, None], self.window, stride=1, padding=r)[0, 0]
        return torch.exp(-((d / self.tau) ** 2))[..., None]

    def __call__(self, image: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor) -> torch.Tensor:
        """Refine ``image`` with the gradients.

        Args:
            image: ``(H, W, 3)`` denoised image (linear, finite, >= 0), any device.
            dx: ``(H, W, 3)`` horizontal forward differences, same device (non-finite values
                are dropped from the solve with a ``NonFiniteInputWarning``).
            dy: ``(H, W, 3)`` vertical forward differences.

        Returns:
            ``(H, W, 3)`` float32, finite and >= 0, on ``image``'s device.
        """
        image = image.float()
        refined = self.solve(image, dx, dy)
        g = self.gate(refined, image)
        return g * refined + (1.0 - g) * image
