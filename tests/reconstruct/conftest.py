"""Fixtures of the colour, FLIP, E-LPIPS and loss tests.

* ``image_pair``: a factory of two close random ``(n, 3, size, size)`` float32 CPU images.
* ``tiny_elpips``: a factory of :class:`~gdpt.reconstruct.elpips.ELPIPS` on a small random
  backbone (channels 3, 4, 6).
* ``squeezenet_state``: a random SqueezeNet 1.1 state dict with E-LPIPS linear heads, in the
  layout :func:`~gdpt.reconstruct.elpips.load_elpips_weights` reads.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import pytest
import torch
import torch.nn.functional as F
from gdpt.reconstruct.elpips import ELPIPS, Dropout, ELPIPSConfig, SqueezeNetFeatures
from torch import nn


def _image_pair(n: int = 2, size: int = 32, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``(a, b)``: ``(n, 3, size, size)`` float32 in [0, 1), ``b = clamp(a + 0.2 U, 0, 1)``."""
    gen = torch.Generator().manual_seed(seed)
    a = torch.rand(n, 3, size, size, generator=gen)
    return a, (a + 0.2 * torch.rand(n, 3, size, size, generator=gen)).clamp(0, 1)


@pytest.fixture
def image_pair() -> Callable[..., tuple[torch.Tensor, torch.Tensor]]:
    """:func:`_image_pair`, as a fixture."""
    return _image_pair


class TinyBackbone(nn.Module):
    """Small random backbone with the E-LPIPS backbone interface (CPU, float32)."""

    channels = (3, 4, 6)

    def __init__(self) -> None:
        super().__init__()
        gen = torch.Generator().manual_seed(0)
        self.conv1 = nn.Conv2d(3, 4, 3, padding=1)
        self.conv2 = nn.Conv2d(4, 6, 3, stride=2, padding=1)
        for p in self.parameters():
            p.data = torch.randn(p.shape, generator=gen) * 0.5

    def forward(self, x: torch.Tensor, drop: Dropout) -> list[torch.Tensor]:
        """The input and two ReLU feature maps of ``x`` ``(B, 3, H, W)``."""
        h1 = F.relu(self.conv1(drop(x)))
        return [x, h1, F.relu(self.conv2(drop(h1)))]


def _tiny_elpips(
    config: ELPIPSConfig | None = None,
    seed: int | None = 0,
    heads: Sequence[torch.Tensor] | None = None,
) -> ELPIPS:
    """E-LPIPS on :class:`TinyBackbone` (default: seeded random heads, 2 scales)."""
    if heads is None:
        heads = [torch.rand(c, generator=torch.Generator().manual_seed(c)) for c in (3, 4, 6)]
    return ELPIPS(TinyBackbone(), heads, config or ELPIPSConfig(num_scales=2), seed=seed)


@pytest.fixture
def tiny_elpips() -> Callable[..., ELPIPS]:
    """:func:`_tiny_elpips`, as a fixture."""
    return _tiny_elpips


@pytest.fixture
def squeezenet_state() -> dict[str, torch.Tensor]:
    """Random SqueezeNet 1.1 ``features.*`` weights plus heads ``lin{i}.model.1.weight`` (CPU)."""
    torch.manual_seed(0)
    state = dict(SqueezeNetFeatures().state_dict())
    for i, c in enumerate(SqueezeNetFeatures.channels):
        state[f"lin{i}.model.1.weight"] = torch.rand(1, c, 1, 1)
    return state
