"""The loss of a batch and one optimizer update (Adam, ``gdpt-notes.md`` section 3.1).

The network predicts in log space; the loss sees ``exp(y) - 1`` (linear HDR radiance) on the
window interior without ``pad + vary_padding`` pixels on each side.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn

from gdpt.reconstruct.transforms import OUTPUT_TRANSFORM

if TYPE_CHECKING:
    from gdpt.training.config import TrainConfig


def _interior(t: torch.Tensor, border: int) -> torch.Tensor:
    return t[..., border : t.shape[-2] - border, border : t.shape[-1] - border]


def compute_loss(
    model: nn.Module, loss_fn: nn.Module, x: torch.Tensor, target: torch.Tensor, border: int
) -> torch.Tensor:
    """Loss of a batch: network in log space, ``exp(y) - 1``, interior without ``border``.

    Args:
        model: the network (or its DDP wrapper).
        loss_fn: ``(pred, target) -> scalar`` on linear ``(N, 3, h, w)``.
        x: ``(N, C, H, W)`` input on the model's device.
        target: ``(N, 3, H, W)`` linear target, same device.
        border: pixels dropped on each side before the loss.

    Returns:
        Scalar loss tensor.
    """
    pred = OUTPUT_TRANSFORM.inverse(model(x.contiguous(memory_format=torch.channels_last)))
    return loss_fn(_interior(pred, border), _interior(target, border))


def train_step(
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    loss_fn: nn.Module,
    x: torch.Tensor,
    target: torch.Tensor,
    border: int,
    lr: float,
) -> tuple[float, bool]:
    """One optimizer update at learning rate ``lr``.

    Non-finite gradients (identical on every rank after DDP's all-reduce) skip the update.

    Returns:
        ``(loss, updated)``: the loss of this process's batch before the update, and whether
        the parameters changed.
    """
    for group in optimizer.param_groups:
        group["lr"] = lr
    optimizer.zero_grad(set_to_none=True)
    loss = compute_loss(model, loss_fn, x, target, border)
    loss.backward()
    finite = all(
        bool(torch.isfinite(p.grad).all()) for p in model.parameters() if p.grad is not None
    )
    if finite:
        optimizer.step()
    return float(loss.detach()), finite


def make_optimizer(model: nn.Module, config: TrainConfig) -> torch.optim.Adam:
    """Adam with the reference's ``beta2`` and ``eps``."""
    return torch.optim.Adam(
        model.parameters(), lr=config.lr, betas=(config.beta1, config.beta2), eps=config.eps
    )
