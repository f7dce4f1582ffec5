"""The training data of a run: the train/validation split of the datasets, the network input
and target of one sample, and the batch of an update.

Every sample is one input level of one random crop (optionally a random sub-crop), augmented
(:mod:`gdpt.training.augment`), transformed, and mirror-padded by ``pad`` pixels with the
padding offset varied by ``+-vary_padding``. The batch of update ``s`` (crop choice,
augmentations, padding offsets) is seeded from ``(seed, s, rank)`` (:func:`step_seed`), so there
is no RNG state to carry for an exact resume.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from gdpt.reconstruct.transforms import pad_buffers, stack_input, transform_buffers
from gdpt.training.augment import AugmentParams, augment, padding_of, sample_augmentation
from gdpt.training.dataset import CropDataset

if TYPE_CHECKING:
    from gdpt.training.config import TrainConfig


def split_datasets(config: TrainConfig, kind: str) -> tuple[CropDataset, CropDataset]:
    """``(train_set, val_set)`` of ``kind`` inputs: ``data`` and ``val_data``, or ``data`` split
    by holding out every ``holdout_every``-th scene.

    Raises:
        ValueError: a dataset is unusable, or the split leaves one side empty.
    """
    if config.val_data is not None:
        return CropDataset(config.data, kind=kind), CropDataset(config.val_data, kind=kind)
    every = config.holdout_every
    try:
        train_set = CropDataset(config.data, kind=kind, scenes=lambda s: s % every != every - 1)
        val_set = CropDataset(config.data, kind=kind, scenes=lambda s: s % every == every - 1)
    except ValueError as error:
        raise ValueError(
            f"{error}; holding out every {every}th scene leaves no training or "
            "validation crop: pass --val-data or another --holdout-every"
        ) from None
    return train_set, val_set


def prepare_sample(
    item: Mapping[str, Any], params: AugmentParams, features: tuple[str, ...], pad: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Network input and target of one dataset element.

    Args:
        item: a :class:`~gdpt.training.dataset.CropDataset` element (``inputs``, ``target``).
        params: its augmentation draw.
        features: network input buffers, in order.
        pad: base padding.

    Returns:
        ``(x, target)``: ``(C, h + 2 pad, w + 2 pad)`` transformed, padded input and
        ``(3, h + 2 pad, w + 2 pad)`` linear target (reflect-padded), on the item's device.
    """
    buffers = augment({**item["inputs"], "target": item["target"]}, params)
    target = buffers.pop("target")
    inputs = transform_buffers(buffers, features, depth_scale=params.depth_scale)
    padded = pad_buffers({**inputs, "target": target}, padding_of(params, pad))
    x = stack_input(padded, features)[0]
    return x, padded["target"].permute(2, 0, 1)


def make_batch(
    dataset: CropDataset, config: TrainConfig, step: int, rank: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """The batch of update ``step`` on process ``rank`` (a pure function of the seeds).

    Returns:
        ``(x, target)``: ``(batch, C, H, W)`` input and ``(batch, 3, H, W)`` target, CPU.
    """
    generator = torch.Generator().manual_seed(step_seed(config.seed, step, rank))
    indices = torch.randint(len(dataset), (config.batch,), generator=generator).tolist()
    shape = (dataset.resolution[1], dataset.resolution[0])
    xs, targets = [], []
    for index in indices:
        params = sample_augmentation(generator, config, shape)
        x, target = prepare_sample(dataset[index], params, dataset.features, config.pad)
        xs.append(x)
        targets.append(target)
    return torch.stack(xs), torch.stack(targets)


def step_seed(seed: int, step: int, rank: int) -> int:
    """63-bit seed of update ``step`` on ``rank``."""
    state = np.random.SeedSequence([seed, step, rank]).generate_state(2, np.uint32)
    return int(state[0]) << 31 | int(state[1]) >> 1
