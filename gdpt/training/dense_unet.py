"""The training plan of the ``dense-unet`` family: NGPT's dense U-Net (Kettunen et al. 2019)
trained from scratch on a :mod:`gdpt.training.dataset`.

The recipe follows NGPT and its public code (``github.com/mkettune/ngpt``), one file per
concept: the learning-rate schedule (:mod:`gdpt.training.schedule`), the augmentations
(:mod:`gdpt.training.augment`), the batches (:mod:`gdpt.training.batches`: random crops and
sub-crops, augmented, transformed and mirror-padded by ``pad +- vary_padding``), the loss of a
batch (:func:`gdpt.training.step.compute_loss` with a loss of
:data:`gdpt.reconstruct.losses.LOSSES`) and validation (:mod:`gdpt.training.validation`:
relMSE and FLIP of the network and of L1 Poisson on held-out crops). The network reads the
G-PT input (16-channel configurations) or the path-traced one (10 channels). Checkpoints are
:mod:`gdpt.reconstruct.dense_unet_reconstructor` cards
(:func:`gdpt.training.checkpoint.save_checkpoint`).
"""

from __future__ import annotations

import torch

from gdpt.reconstruct.dense_unet import build_model
from gdpt.reconstruct.dense_unet_reconstructor import default_features
from gdpt.reconstruct.losses import get_loss
from gdpt.training.batches import make_batch, split_datasets
from gdpt.training.checkpoint import save_checkpoint
from gdpt.training.config import TrainConfig
from gdpt.training.loop import RunContext, TrainingPlan
from gdpt.training.step import compute_loss
from gdpt.training.validation import load_validation, validate

__all__ = ["dense_plan"]


def dense_plan(config: TrainConfig, ctx: RunContext) -> TrainingPlan:
    """The plan of a dense U-Net run (``config.model`` a key of
    :data:`gdpt.reconstruct.dense_unet.CONFIGS`).

    Raises:
        ValueError: unusable dataset, or crop and padding not aligned with the model.
    """
    model = build_model(config.model)
    features = default_features(model.config.in_channels)
    train_set, val_set = split_datasets(config, "gdpt" if "dx" in features else "pt")
    side = config.crop or min(train_set.resolution)
    if side > min(train_set.resolution) or (side + 2 * config.pad) % model.alignment:
        raise ValueError(
            f"crop {side} must fit the {train_set.resolution} dataset crops and "
            f"crop + 2 * pad ({config.pad}) must be a multiple of the "
            f"{config.model!r} alignment {model.alignment}"
        )
    loss_fn = get_loss(config.loss).to(ctx.device)
    model = model.to(ctx.device, memory_format=torch.channels_last)
    val_elements = (
        load_validation(val_set, config.val_crops, ctx.device)
        if ctx.rank == 0 and config.val_every
        else []
    )
    border = config.pad + config.vary_padding

    def loss(forward, step: int) -> torch.Tensor:
        x, target = make_batch(train_set, config, step, ctx.rank)
        return compute_loss(forward, loss_fn, x.to(ctx.device), target.to(ctx.device), border)

    return TrainingPlan(
        net=model,
        loss=loss,
        validate=lambda: validate(model, val_elements, features, config.pad),
        save=lambda path, card: save_checkpoint(model, path, card),
        card={
            "training": {
                "data": config.data,
                "crops": len(train_set.crops),
                "loss": config.loss,
                "batch": config.batch * ctx.world,
            }
        },
    )
