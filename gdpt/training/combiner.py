"""The training plan of the ``combiner`` family: the kernel-predicting combiner
(:mod:`gdpt.reconstruct.combiner`) trained on a :mod:`gdpt.training.dataset`.

``gdpt train --config combiner-grad --base-model RUN/model.safetensors`` (or
``combiner-nograd``) runs :func:`combiner_plan` in the training loop
(:mod:`gdpt.training.loop`). The base network
(a fine-tuned OIDN delta checkpoint, :mod:`gdpt.reconstruct.oidn_finetune`) is frozen: its output
and the other candidates are computed once per dataset element, on the un-augmented buffers,
and then augmented with the element (flips, transposition and colour scalings commute with the
candidates up to the base network's own equivariance error; a sub-crop of a candidate stands in
for the candidate of the sub-crop). Train the combiner on a dataset the base network did not
see (another ``gdpt dataset --seed``), so that its candidates are as good as they are on new
scenes, not as good as on the base network's training set.

The augmentations, held-out split and per-step seeding are the fine-tuning plan's
(:mod:`gdpt.training.oidn_finetune`). The loss (:data:`~gdpt.reconstruct.combiner.COMBINER_LOSSES`,
:func:`~gdpt.reconstruct.combiner.combiner_loss`) is OIDN's PU-L1 plus a relative error
against the base image. The run directory holds a copy of the base network (``base.*``, the
card's ``base_model``), so it is a complete model. Validation (``val.jsonl``) scores the
combiner and each candidate alone (``candidate_base_*``, ``candidate_l1_*``).
"""

from __future__ import annotations

import torch

from gdpt.reconstruct.cards import read_card
from gdpt.reconstruct.combiner import (
    COMBINER_DESIGNS,
    COMBINER_LOSSES,
    CombinerDesign,
    CombinerNet,
    candidates,
    combine,
    combiner_input,
    combiner_loss,
    encode_combiner,
)
from gdpt.reconstruct.losses import FLIPLoss
from gdpt.reconstruct.oidn_finetune import OIDNReconstructor
from gdpt.training.augment import augment, sample_augmentation
from gdpt.training.batches import split_datasets, step_seed
from gdpt.training.checkpoint import write_checkpoint
from gdpt.training.config import TrainConfig
from gdpt.training.dataset import CropDataset
from gdpt.training.loop import RunContext, TrainingPlan
from gdpt.training.validation import held_out_elements, image_metrics

__all__ = [
    "BASE_NAME",
    "CandidateCache",
    "combiner_plan",
    "make_combiner_batch",
]

#: Name of the run directory's copy of the base network (the card's ``base_model``).
BASE_NAME = "base"


class CandidateCache:
    """Candidates of dataset elements (``(K, H, W, 3)``, CPU), computed on first use.

    Args:
        design: the combiner design.
        base: the frozen base network.
    """

    def __init__(self, design: CombinerDesign, base: OIDNReconstructor) -> None:
        self.design, self.base = design, base
        self._cache: dict[int, torch.Tensor] = {}

    def __call__(self, index: int, inputs: dict[str, torch.Tensor]) -> torch.Tensor:
        if index not in self._cache:
            with torch.inference_mode():
                self._cache[index] = candidates(inputs, self.base(inputs), self.design)
        return self._cache[index]


def _augmented(
    item: dict, cands: torch.Tensor, params
) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    """``(inputs, candidates (K, h, w, 3), target (h, w, 3))`` of one augmented element."""
    buffers = augment({**item["inputs"], "target": item["target"]}, params)
    target = buffers.pop("target")
    cands = torch.stack([augment({"primal": c}, params)["primal"] for c in cands])
    return buffers, cands, target


def make_combiner_batch(
    dataset: CropDataset,
    config: TrainConfig,
    design: CombinerDesign,
    step: int,
    cache: CandidateCache,
    rank: int = 0,
) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    """The batch of update ``step`` on process ``rank`` (a pure function of ``config.seed``,
    ``step`` and ``rank``).

    Returns:
        ``(buffers, candidates, target)``: name -> ``(N, h, w, 3)``, ``(N, K, h, w, 3)`` and
        ``(N, h, w, 3)``, CPU float32.
    """
    generator = torch.Generator().manual_seed(step_seed(config.seed, step, rank))
    indices = torch.randint(len(dataset), (config.batch,), generator=generator).tolist()
    shape = (dataset.resolution[1], dataset.resolution[0])
    parts: list[tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]] = []
    for index in indices:
        params = sample_augmentation(generator, config, shape)
        item = dataset[index]
        parts.append(_augmented(item, cache(index, item["inputs"]), params))
    buffers = {n: torch.stack([p[0][n] for p in parts]) for n in design.features}
    return buffers, torch.stack([p[1] for p in parts]), torch.stack([p[2] for p in parts])


def _validation(
    dataset: CropDataset, design: CombinerDesign, base: OIDNReconstructor, count: int
) -> list[tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor, dict[str, float]]]:
    flip = FLIPLoss("ldr")
    elements = []
    for inputs, target, _ in held_out_elements(dataset, count, torch.device("cpu")):
        with torch.inference_mode():
            cands = candidates(inputs, base(inputs), design)
        scores = {}
        for name, image in zip(design.candidate_names, cands, strict=True):
            metrics = image_metrics(image, target, flip)
            scores.update({f"candidate_{name}_{k}": v for k, v in metrics.items()})
        elements.append((inputs, cands, target, scores))
    if not elements:
        raise ValueError(f"{dataset.root}: no readable validation element")
    return elements


@torch.no_grad()
def _validate(net: CombinerNet, design: CombinerDesign, elements) -> dict[str, float]:
    flip = FLIPLoss("ldr")
    totals: dict[str, float] = {}
    was_training = net.training
    net.eval()
    for inputs, cands, target, baselines in elements:
        batch = {n: inputs[n][None] for n in design.features}
        x, scale = combiner_input(batch, cands[None], design)
        scores = image_metrics(combine(net, x, scale)[0], target, flip)
        for key, value in {**scores, **baselines}.items():
            totals[key] = totals.get(key, 0.0) + value
    net.train(was_training)
    return {k: v / len(elements) for k, v in totals.items()} | {"count": len(elements)}


def combiner_plan(config: TrainConfig, ctx: RunContext) -> TrainingPlan:
    """The plan of a combiner run: the design ``config.model`` on top of the frozen base network
    ``config.base_model``; see the module docstring.

    Raises:
        ValueError: no ``base_model``, a base network that reads other buffers than the design,
            or an unusable dataset.
    """
    design = COMBINER_DESIGNS[config.model]
    if config.base_model is None:
        raise ValueError(f"{config.model} trains on top of a base network: pass --base-model")
    # first, straight after the loop's seed: the initial weights depend on config.seed alone
    net = CombinerNet(design.in_channels, len(design.candidate_names)).to(ctx.device).train()
    base = OIDNReconstructor.from_checkpoint(config.base_model)
    if base.design.gradients != design.gradients:
        raise ValueError(
            f"base network {config.base_model} ({base.design.description}) and {config.model} "
            "must both read gradients or both not"
        )
    loss_options = COMBINER_LOSSES[config.loss]
    train_set, val_set = split_datasets(config, "gdpt" if design.gradients else "pt")
    val_elements = (
        _validation(val_set, design, base, config.val_crops)
        if ctx.rank == 0 and config.val_every
        else []
    )
    cache = CandidateCache(design, base)
    weights_path, card_path, _ = read_card(config.base_model)
    files = {
        f"{BASE_NAME}.safetensors": weights_path.read_bytes(),
        f"{BASE_NAME}.json": card_path.read_bytes(),
    }
    card = {
        "base_model": BASE_NAME,
        "training": {
            "data": config.data,
            "base_model": str(config.base_model),
            "crops": len(train_set.crops),
            "validation_crops": len(val_set.crops),
            "loss": f"{config.loss}: PU-L1 + relative term {loss_options['relative']} "
            "(combiner_loss)",
            "batch": config.batch * ctx.world,
            "lr": config.lr,
        },
    }

    def loss(forward, step: int) -> torch.Tensor:
        batch = make_combiner_batch(train_set, config, design, step, cache, ctx.rank)
        buffers = {n: t.to(ctx.device) for n, t in batch[0].items()}
        cands, target = batch[1].to(ctx.device), batch[2].to(ctx.device)
        x, scale = combiner_input(buffers, cands, design)
        out = combine(net, x, scale, forward=forward)
        return combiner_loss(out, target, cands[:, 0], scale, **loss_options)

    return TrainingPlan(
        net=net,
        loss=loss,
        validate=lambda: _validate(net, design, val_elements),
        save=lambda path, info: write_checkpoint(path, *encode_combiner(net, config.model, info)),
        card=card,
        files=files,
    )
