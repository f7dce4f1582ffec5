"""One optimizer update (every family), the optimizer, and the dense U-Net's batch loss.

The optimizer is Adam with the run's settings (:class:`~gdpt.training.config.TrainConfig`,
whose defaults follow NGPT, Kettunen et al. 2019). :func:`update` is the step of
:func:`gdpt.training.loop.training_loop`; an update whose gradients are not all finite is
skipped (weights and Adam state stay as they were).

The dense U-Net predicts in log space; its loss (:func:`compute_loss`) sees ``exp(y) - 1``
(linear HDR radiance) on the window interior without ``pad + vary_padding`` pixels on each
side.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import torch
from torch import nn

from gdpt.reconstruct.transforms import OUTPUT_TRANSFORM

if TYPE_CHECKING:
    from gdpt.training.config import TrainConfig

#: ``(parameter, multiplier)``: the optimizer's change of the parameter is multiplied
#: element-wise by ``multiplier`` (same shape and device).
UpdateScale = tuple[nn.Parameter, torch.Tensor]


def _interior(t: torch.Tensor, border: int) -> torch.Tensor:
    return t[..., border : t.shape[-2] - border, border : t.shape[-1] - border]


def compute_loss(
    model: Callable[[torch.Tensor], torch.Tensor],
    loss_fn: nn.Module,
    x: torch.Tensor,
    target: torch.Tensor,
    border: int,
) -> torch.Tensor:
    """Loss of a dense U-Net batch: network in log space, ``exp(y) - 1``, interior without
    ``border``.

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


def update(
    net: nn.Module,
    optimizer: torch.optim.Optimizer,
    loss_fn: Callable[[], torch.Tensor],
    lr: float,
    update_scale: Sequence[UpdateScale] = (),
) -> tuple[float, bool]:
    """One optimizer update of ``net`` at learning rate ``lr``.

    Non-finite gradients (identical on every rank after DDP's all-reduce) skip the update.

    Args:
        net: the network whose parameters ``optimizer`` updates.
        optimizer: its optimizer.
        loss_fn: evaluates the loss of this update's batch (forward pass included).
        lr: the learning rate of this update.
        update_scale: :data:`UpdateScale` pairs (under Adam, per-weight learning-rate
            multipliers).

    Returns:
        ``(loss, updated)``: the loss before the update, and whether the parameters changed.
    """
    for group in optimizer.param_groups:
        group["lr"] = lr
    optimizer.zero_grad(set_to_none=True)
    loss = loss_fn()
    loss.backward()
    finite = all(bool(torch.isfinite(p.grad).all()) for p in net.parameters() if p.grad is not None)
    if finite:
        before = [p.detach().clone() for p, _ in update_scale]
        optimizer.step()
        with torch.no_grad():
            for (p, multiplier), old in zip(update_scale, before, strict=True):
                p.copy_(old + (p - old) * multiplier)
    return float(loss.detach()), finite


def make_optimizer(model: nn.Module, config: TrainConfig) -> torch.optim.Adam:
    """Adam with the run's ``lr``, ``beta1``, ``beta2`` and ``eps``."""
    return torch.optim.Adam(
        model.parameters(), lr=config.lr, betas=(config.beta1, config.beta2), eps=config.eps
    )
