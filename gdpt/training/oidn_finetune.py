"""The training plan of the ``oidn-finetune`` family: OIDN's U-Net fine-tuned with gradient
inputs (:mod:`gdpt.reconstruct.oidn_finetune`) on a :mod:`gdpt.training.dataset`.

``gdpt train --config oidn-grad`` (or another design of ``DESIGNS``, e.g. ``oidn-nograd``)
runs :func:`finetune_plan` in the training loop (:mod:`gdpt.training.loop`: run directory,
schedule, exact resume, ``torchrun``). It shares the augmentations
(:mod:`gdpt.training.augment`: sub-crop, flips, transposition, RGB permutation, colour and
brightness multipliers), per-step seeding and held-out split (:mod:`gdpt.training.batches`)
with the dense U-Net's plan; what differs:

* the network starts as OIDN (Intel's ``rt_hdr_alb_nrm`` weights, the extra inputs with zero
  weights), so step 0 reproduces OIDN exactly; or, with ``config.base_model``, as that
  fine-tuned checkpoint of the same design (its checkpoints still store the difference to
  OIDN's weights);
* a design without gradients reads the path-traced input ``pt<k>``, or with ``config.input``
  the primal and features of the G-PT input ``in<k>`` (``gdpt``; e.g. a ``gdpt dataset
  --primal mis``) or that primal pooled with ``pt<k>`` (``pool``);
* ``extra_lr_scale`` lets the extra inputs' weights move faster than the rest (the fine-tuning
  rate is small to keep OIDN's skill, and zero-started weights would stay near zero under it);
* inputs are OIDN's encoding (:func:`~gdpt.reconstruct.oidn_finetune.assemble`); sub-crops
  (``crop``) must be multiples of 16; there is no mirror padding (``pad`` and
  ``vary_padding`` are ignored: OIDN's convolutions zero-pad, as at inference);
* loss (``config.loss``, :data:`~gdpt.reconstruct.oidn_finetune.FINETUNE_LOSSES`): ``l1`` is
  OIDN's own L1 in its PU space,
  ``l1_rel`` adds the Noise2Noise relative MSE (:func:`~gdpt.reconstruct.oidn_finetune
  .finetune_loss`), unbiased under the zero-mean noise of path-traced targets
  (``gdpt dataset --target pt``), ``l1_grad`` an L1 on the PU image's forward differences
  (NGPT's gradient term);
* the ``oidn-grad-l1`` design's L1 Poisson input is solved once per dataset element
  ('l1-fast', alpha 0.2) and augmented like the primal (flips and scalings commute with the
  solve; a sub-crop of the solution stands in for the solution of the sub-crop);
* checkpoints store the difference to OIDN's weights (:func:`~gdpt.reconstruct.oidn_finetune
  .encode_delta`); the exact weights and the Adam state go to the ``.pt`` file of the run
  (never committed), which resume reads (as for every family);
* validation (``val.jsonl``) scores the network, OIDN on the same input (step 0), OIDN on the
  path-traced input of the same crop and level (``pt+oidn`` at equal time) and L1 Poisson on
  the G-PT input: ``relmse``, ``flip``, ``oidn_*``, ``pt_oidn_*``, ``l1_*``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch

from gdpt.reconstruct.losses import FLIPLoss
from gdpt.reconstruct.oidn_finetune import (
    DESIGNS,
    FINETUNE_LOSSES,
    Design,
    assemble,
    base_model,
    encode_delta,
    finetune_loss,
    load_model,
    predict,
)
from gdpt.reconstruct.oidn_unet import OIDNUNet
from gdpt.training.augment import augment, sample_augmentation
from gdpt.training.batches import split_datasets, step_seed
from gdpt.training.checkpoint import write_checkpoint
from gdpt.training.config import TrainConfig
from gdpt.training.dataset import CropDataset
from gdpt.training.loop import RunContext, TrainingPlan
from gdpt.training.manifest import CONFIG_FILE
from gdpt.training.step import UpdateScale
from gdpt.training.validation import held_out_elements, image_metrics

__all__ = [
    "FinetuneBatch",
    "finetune_plan",
    "make_finetune_batch",
    "validate_finetune",
]


def primal_spp_factor(data: str | Path) -> float:
    """Plain path samples per gradient sample of a dataset's pooled inputs (its ``pt_factor``).

    Raises:
        ValueError: the dataset has no ``dataset.json`` with a ``pt_factor``.
    """
    path = Path(data) / CONFIG_FILE
    try:
        return float(json.loads(path.read_text())["config"]["pt_factor"])
    except (OSError, KeyError, ValueError) as error:
        raise ValueError(f"{path}: no readable 'config.pt_factor' ({error})") from None


@dataclass
class FinetuneBatch:
    """One training batch.

    Attributes:
        x: ``(N, 9 + extra, h, w)`` encoded inputs (:func:`assemble`), CPU float32.
        target: ``(N, 3, h, w)`` linear targets.
        scale: ``(N,)`` OIDN input scales.
    """

    x: torch.Tensor
    target: torch.Tensor
    scale: torch.Tensor


class L1Cache:
    """L1 Poisson solutions of dataset elements ('l1-fast', alpha 0.2), solved on first use."""

    def __init__(self) -> None:
        self._cache: dict[int, torch.Tensor] = {}

    def __call__(self, index: int, inputs: dict[str, torch.Tensor]) -> torch.Tensor:
        """``(H, W, 3)`` solution for element ``index`` with buffers ``inputs``."""
        if index not in self._cache:
            from gdpt.reconstruct.poisson import solve

            p, dx, dy = inputs["primal"], inputs["dx"], inputs["dy"]
            self._cache[index] = solve(p, dx, dy, solver="l1-fast", alpha=0.2)
        return self._cache[index]


def _sample(
    item: dict, design: Design, params, l1: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(x (C, h, w), target (3, h, w), scale)`` of one augmented element."""
    buffers = augment({**item["inputs"], "target": item["target"]}, params)
    target = buffers.pop("target")
    l1_aug = None if l1 is None else augment({"primal": l1}, params)["primal"]
    x, scale = assemble(buffers, design, l1=l1_aug)
    h, w = target.shape[:2]
    return x[0, :, :h, :w], target.permute(2, 0, 1), scale


def make_finetune_batch(
    dataset: CropDataset,
    config: TrainConfig,
    design: Design,
    step: int,
    l1_cache: L1Cache | None = None,
    rank: int = 0,
) -> FinetuneBatch:
    """The batch of update ``step`` on process ``rank`` (a pure function of ``config.seed``,
    ``step`` and ``rank``).

    Sub-crop sides (``config.crop`` or the dataset crop) must be multiples of 16.
    """
    generator = torch.Generator().manual_seed(step_seed(config.seed, step, rank))
    indices = torch.randint(len(dataset), (config.batch,), generator=generator).tolist()
    shape = (dataset.resolution[1], dataset.resolution[0])
    xs, targets, scales = [], [], []
    for index in indices:
        params = sample_augmentation(generator, config, shape)
        item = dataset[index]
        l1 = l1_cache(index, item["inputs"]) if design.l1 and l1_cache is not None else None
        x, target, scale = _sample(item, design, params, l1)
        xs.append(x)
        targets.append(target)
        scales.append(scale)
    return FinetuneBatch(torch.stack(xs), torch.stack(targets), torch.stack(scales))


@dataclass
class _ValElement:
    """A held-out element: network inputs, target and the baselines' scores."""

    inputs: dict[str, torch.Tensor]
    l1: torch.Tensor | None
    target: torch.Tensor
    baselines: dict[str, float]


def load_finetune_validation(
    dataset: CropDataset, design: Design, count: int, device: torch.device
) -> list[_ValElement]:
    """Up to ``count`` evenly spaced held-out elements with the baselines' scores: OIDN on the
    same input (``oidn_``), OIDN on the equal-time path-traced input (``pt_oidn_``) and L1
    Poisson on the equal-time G-PT input (``l1_``)."""
    from gdpt.reconstruct.oidn_unet import denoise
    from gdpt.reconstruct.poisson import solve

    flip = FLIPLoss("ldr")
    elements = []
    for inputs, target, buffers in held_out_elements(dataset, count, device, ("in", "pt")):
        g, pt = buffers["in"], buffers["pt"]
        l1 = solve(g.primal, g.dx, g.dy, solver="l1", alpha=0.2)
        l1_fast = None
        if design.l1:
            l1_fast = solve(g.primal, g.dx, g.dy, solver="l1-fast", alpha=0.2)
        with torch.no_grad():
            same = denoise(inputs["primal"], inputs["albedo"], inputs["normal"])
            pt_oidn = denoise(pt.primal, pt.albedo, pt.normal)
        baselines = {}
        for prefix, image in (("oidn_", same), ("pt_oidn_", pt_oidn), ("l1_", l1)):
            baselines.update({prefix + k: v for k, v in image_metrics(image, target, flip).items()})
        elements.append(_ValElement(inputs, l1_fast, target, baselines))
    if not elements:
        raise ValueError(f"{dataset.root}: no readable validation element")
    return elements


@torch.no_grad()
def validate_finetune(
    net: OIDNUNet, design: Design, elements: list[_ValElement]
) -> dict[str, float]:
    """Mean scores of the network and of the baselines over ``elements``."""
    flip = FLIPLoss("ldr")
    totals: dict[str, float] = {}
    was_training = net.training
    net.eval()
    for element in elements:
        x, scale = assemble(element.inputs, design, l1=element.l1)
        h, w = element.target.shape[:2]
        scores = image_metrics(predict(net, x, h, w, scale), element.target, flip)
        for key, value in {**scores, **element.baselines}.items():
            totals[key] = totals.get(key, 0.0) + value
    net.train(was_training)
    return {k: v / len(elements) for k, v in totals.items()} | {"count": len(elements)}


def start_model(config: TrainConfig) -> OIDNUNet:
    """The network of checkpoint ``config.base_model`` (CPU), the start of a fine-tune.

    Raises:
        ValueError: the checkpoint is of another design than ``config.model``.
    """
    net, _, card = load_model(config.base_model)
    if card["design"] != config.model:
        raise ValueError(
            f"base_model {config.base_model} is a {card['design']!r} network, not {config.model!r}"
        )
    return net


def extra_update_scale(net: OIDNUNet, config: TrainConfig) -> list[UpdateScale]:
    """The plan's ``update_scale`` for ``config.extra_lr_scale``: the extra input channels'
    weights move ``extra_lr_scale`` times as fast as the rest (empty at 1)."""
    if config.extra_lr_scale == 1.0:
        return []
    params = dict(net.named_parameters())
    return [
        (params[name], 1.0 + (config.extra_lr_scale - 1.0) * mask)
        for name, mask in net.extra_input_masks().items()
    ]


def finetune_plan(config: TrainConfig, ctx: RunContext) -> TrainingPlan:
    """The plan of a fine-tuning run (``config.model`` a key of ``DESIGNS``); see the module
    docstring.

    Raises:
        ValueError: unusable dataset, or a crop that is not a multiple of 16.
    """
    design = DESIGNS[config.model]
    weights = FINETUNE_LOSSES[config.loss]
    if config.input is not None and design.gradients:
        raise ValueError(
            f"input={config.input!r}: {config.model} reads gradients, its input is fixed"
        )
    kind = config.input or design.input_kind
    train_set, val_set = split_datasets(config, kind)
    side = config.crop or min(train_set.resolution)
    if side > min(train_set.resolution) or side % 16:
        raise ValueError(
            f"crop {side} must fit the {train_set.resolution} dataset crops and be a multiple "
            "of 16 (OIDN's alignment)"
        )
    base = base_model(design)
    net = base_model(design) if config.base_model is None else start_model(config)
    net = net.to(ctx.device).train()
    val_elements = (
        load_finetune_validation(val_set, design, config.val_crops, ctx.device)
        if ctx.rank == 0 and config.val_every
        else []
    )
    l1_cache = L1Cache() if design.l1 else None
    card = {
        "training": {
            "data": config.data,
            "crops": len(train_set.crops),
            "validation_crops": len(val_set.crops),
            "loss": f"{config.loss}: finetune_loss, PU-L1 + weights {weights}",
            "batch": config.batch * ctx.world,
            "crop": side,
            "lr": config.lr,
            "extra_lr_scale": config.extra_lr_scale,
            "input": kind,
            "start": config.base_model or "OIDN",
        }
    }
    if design.pooled or kind == "pool":
        card["sampling"] = {"primal_spp_factor": primal_spp_factor(config.data)}

    def loss(forward, step: int) -> torch.Tensor:
        batch = make_finetune_batch(train_set, config, design, step, l1_cache, ctx.rank)
        y = forward(batch.x.to(ctx.device))
        d = ctx.device
        return finetune_loss(y, batch.target.to(d), batch.scale.to(d), **weights)

    def save(path: Path, info) -> None:
        write_checkpoint(path, *encode_delta(net, config.model, info, base=base))

    return TrainingPlan(
        net=net,
        loss=loss,
        validate=lambda: validate_finetune(net, design, val_elements),
        save=save,
        card=card,
        update_scale=extra_update_scale(net, config),
    )
