"""The training plan of the ``kpcn`` family: KPCN (Bako et al. 2017;
:mod:`gdpt.reconstruct.kpcn`) trained from scratch on a :mod:`gdpt.training.dataset`.

``gdpt train --config kpcn`` (or ``kpcn-paper``) runs :func:`kpcn_plan` in the training loop
(:mod:`gdpt.training.loop`: run directory, schedule, exact resume, ``torchrun``). KPCN reads
the path-traced input of each crop and level with its variance (dataset kind ``pt-variance``:
a dataset rendered with ``gdpt dataset --variance``, the default), never the gradients.

* Batches: the augmentations, per-step seeding and held-out split of the other plans
  (:mod:`gdpt.training.augment`, :mod:`gdpt.training.batches`); ``var_primal`` scales with the
  square of the brightness multiplier. There is no mirror padding (``pad`` and
  ``vary_padding`` are ignored: the convolutions zero-pad, as at inference).
* Loss: :func:`~gdpt.reconstruct.kpcn.kpcn_loss` (L1 in the filtered buffer's space).
* Validation (``val.jsonl``): relMSE and LDR-FLIP of the network, of its noisy input
  (``input_*``) and of OIDN on the same input (``oidn_*``).
"""

from __future__ import annotations

import torch

from gdpt.reconstruct.kpcn import (
    FEATURES,
    KPCN_DESIGNS,
    KPCN_LOSSES,
    KPCNNet,
    KPCNReconstructor,
    encode_kpcn,
    kpcn_filter,
    kpcn_input,
    kpcn_loss,
)
from gdpt.reconstruct.losses import FLIPLoss
from gdpt.training.augment import augment, sample_augmentation
from gdpt.training.batches import split_datasets, step_seed
from gdpt.training.checkpoint import write_checkpoint
from gdpt.training.config import TrainConfig
from gdpt.training.dataset import CropDataset
from gdpt.training.loop import RunContext, TrainingPlan
from gdpt.training.validation import held_out_elements, image_metrics

__all__ = ["INPUT_KIND", "kpcn_plan", "make_kpcn_batch", "validate_kpcn"]

#: The dataset input kind KPCN reads.
INPUT_KIND = "pt-variance"


def make_kpcn_batch(
    dataset: CropDataset, config: TrainConfig, step: int, rank: int = 0
) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """The batch of update ``step`` on process ``rank`` (a pure function of ``config.seed``,
    ``step`` and ``rank``).

    Returns:
        ``(buffers, target)``: name -> ``(N, h, w, C)`` for the buffers KPCN reads, and the
        ``(N, h, w, 3)`` target; CPU float32.
    """
    generator = torch.Generator().manual_seed(step_seed(config.seed, step, rank))
    indices = torch.randint(len(dataset), (config.batch,), generator=generator).tolist()
    shape = (dataset.resolution[1], dataset.resolution[0])
    samples = []
    for index in indices:
        params = sample_augmentation(generator, config, shape)
        item = dataset[index]
        samples.append(augment({**item["inputs"], "target": item["target"]}, params))
    buffers = {n: torch.stack([s[n] for s in samples]) for n in FEATURES}
    return buffers, torch.stack([s["target"] for s in samples])


def _validation(dataset: CropDataset, count: int, device: torch.device) -> list:
    """Held-out elements with the scores of the noisy input and of OIDN on it."""
    from gdpt.reconstruct.oidn_unet import denoise

    flip = FLIPLoss("ldr")
    elements = []
    for inputs, target, _ in held_out_elements(dataset, count, device):
        with torch.no_grad():
            oidn = denoise(inputs["primal"], inputs["albedo"], inputs["normal"])
        scores = {}
        for prefix, image in (("input_", inputs["primal"]), ("oidn_", oidn)):
            scores.update({prefix + k: v for k, v in image_metrics(image, target, flip).items()})
        elements.append((inputs, target, scores))
    if not elements:
        raise ValueError(f"{dataset.root}: no readable validation element")
    return elements


def validate_kpcn(net: KPCNNet, elements: list) -> dict[str, float]:
    """Mean scores of ``net`` and of the baselines over ``elements`` (:func:`kpcn_plan`)."""
    flip = FLIPLoss("ldr")
    totals: dict[str, float] = {}
    was_training = net.training
    reconstruct = KPCNReconstructor(net)  # the network itself, in eval mode
    for inputs, target, baselines in elements:
        image = reconstruct(inputs)
        for key, value in {**image_metrics(image, target, flip), **baselines}.items():
            totals[key] = totals.get(key, 0.0) + value
    net.train(was_training)
    return {k: v / len(elements) for k, v in totals.items()} | {"count": len(elements)}


def kpcn_plan(config: TrainConfig, ctx: RunContext) -> TrainingPlan:
    """The plan of a KPCN run (``config.model`` a key of
    :data:`~gdpt.reconstruct.kpcn.KPCN_DESIGNS`); see the module docstring.

    Raises:
        ValueError: an unusable dataset (one without variances among them), or a crop larger
            than the dataset's.
    """
    design = KPCN_DESIGNS[config.model]
    # first, straight after the loop's seed: the initial weights depend on config.seed alone
    net = KPCNNet(design).to(ctx.device).train()
    train_set, val_set = split_datasets(config, INPUT_KIND)
    side = config.crop or min(train_set.resolution)
    if side > min(train_set.resolution):
        raise ValueError(f"crop {side} must fit the {train_set.resolution} dataset crops")
    val_elements = (
        _validation(val_set, config.val_crops, ctx.device)
        if ctx.rank == 0 and config.val_every
        else []
    )
    card = {
        "training": {
            "data": config.data,
            "crops": len(train_set.crops),
            "validation_crops": len(val_set.crops),
            "loss": f"{config.loss}: {KPCN_LOSSES[config.loss]}",
            "batch": config.batch * ctx.world,
            "crop": side,
            "lr": config.lr,
        }
    }

    def loss(forward, step: int) -> torch.Tensor:
        buffers, target = make_kpcn_batch(train_set, config, step, ctx.rank)
        x, y, scale = kpcn_input({n: t.to(ctx.device) for n, t in buffers.items()})
        filtered = kpcn_filter(net, x, y, forward=forward)
        return kpcn_loss(filtered, target.to(ctx.device).permute(0, 3, 1, 2), scale)

    return TrainingPlan(
        net=net,
        loss=loss,
        validate=lambda: validate_kpcn(net, val_elements),
        save=lambda path, info: write_checkpoint(path, *encode_kpcn(net, config.model, info)),
        card=card,
    )
