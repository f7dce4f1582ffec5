"""Training the kernel-predicting combiner (:mod:`gdpt.reconstruct.combiner`) on a
:mod:`gdpt.training.dataset`.

``gdpt train --config combiner-grad --base-model RUN/model.safetensors`` (or
``combiner-nograd``) lands here through :func:`gdpt.training.train.train`. The base network
(a fine-tuned OIDN delta checkpoint, :mod:`gdpt.reconstruct.oidn_ngpt`) is frozen: its output
and the other candidates are computed once per dataset element, on the un-augmented buffers,
and then augmented with the element (flips, transposition and colour scalings commute with the
candidates up to the base network's own equivariance error; a sub-crop of a candidate stands in
for the candidate of the sub-crop). Train the combiner on a dataset the base network did not
see (another ``gdpt dataset --seed``), so that its candidates are as good as they are on new
scenes, not as good as on the base network's training set.

Everything else is the fine-tuning trainer's (:mod:`gdpt.training.finetune`): run directory,
schedule, held-out split, per-step seeding (exact resume), checkpoints every
``ckpt_every`` steps with the optimizer state in the run's ``.pt`` files. The loss
(:data:`COMBINER_LOSSES`, :func:`combiner_loss`) is OIDN's PU-L1 plus a relative error
against the base image. Validation
(``val.jsonl``) scores the combiner and each candidate alone (``candidate_base_*``,
``candidate_l1_*``).
"""

from __future__ import annotations

from pathlib import Path

import torch

from gdpt.io.atomic import atomic_write
from gdpt.reconstruct.combiner import (
    COMBINER_DESIGNS,
    CombinerDesign,
    CombinerNet,
    candidates,
    combine,
    combiner_input,
    encode_combiner,
)
from gdpt.reconstruct.losses import FLIPLoss
from gdpt.reconstruct.oidn_ngpt import OIDNReconstructor
from gdpt.reconstruct.oidn_unet import pu_forward
from gdpt.training.augment import augment, sample_augmentation
from gdpt.training.batches import split_datasets, step_seed
from gdpt.training.checkpoint import write_checkpoint
from gdpt.training.config import TrainConfig
from gdpt.training.dataset import CropDataset
from gdpt.training.loop import optimise, resume_state
from gdpt.training.run_dir import (
    prepare_run,
    write_json,
)
from gdpt.training.step import make_optimizer
from gdpt.training.validation import held_out_elements, image_metrics

__all__ = [
    "BASE_NAME",
    "COMBINER_LOSSES",
    "CandidateCache",
    "combiner_loss",
    "make_combiner_batch",
    "train_combiner",
]

#: Name of the run directory's copy of the base network (the card's ``base_model``).
BASE_NAME = "base"


def _copy_base(source: Path, dest: Path) -> None:
    """Copy the base checkpoint (``.safetensors`` + ``.json``) to ``dest``; on resume the copy
    must be identical."""
    for suffix in (".safetensors", ".json"):
        data = source.with_suffix(suffix).read_bytes()
        target = dest.with_suffix(suffix)
        if target.is_file():
            if target.read_bytes() != data:
                raise ValueError(
                    f"{target} differs from the base network {source.with_suffix(suffix)}"
                )
            continue
        atomic_write(target, data)


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
) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    """The batch of update ``step`` (a pure function of ``config.seed`` and ``step``).

    Returns:
        ``(buffers, candidates, target)``: name -> ``(N, h, w, 3)``, ``(N, K, h, w, 3)`` and
        ``(N, h, w, 3)``, CPU float32.
    """
    generator = torch.Generator().manual_seed(step_seed(config.seed, step, 0))
    indices = torch.randint(len(dataset), (config.batch,), generator=generator).tolist()
    shape = (dataset.resolution[1], dataset.resolution[0])
    parts: list[tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]] = []
    for index in indices:
        params = sample_augmentation(generator, config, shape)
        item = dataset[index]
        parts.append(_augmented(item, cache(index, item["inputs"]), params))
    buffers = {n: torch.stack([p[0][n] for p in parts]) for n in design.features}
    return buffers, torch.stack([p[1] for p in parts]), torch.stack([p[2] for p in parts])


#: ``config.loss`` of a combiner -> the relative term of :func:`combiner_loss`.
COMBINER_LOSSES = {"l1": None, "l1_relabs": "abs", "l1_huber": "huber"}


def combiner_loss(
    out: torch.Tensor,
    target: torch.Tensor,
    base: torch.Tensor,
    scale: torch.Tensor,
    *,
    relative: str | None,
    eps: float = 1e-2,
) -> torch.Tensor:
    """PU-L1 plus a relative error whose denominator is the base network's image.

    With ``r = s (out - t) / (eps + s mean_c(base))`` (``s``: OIDN's input scale):
    ``mean |PU(s out) - PU(s t)| + mean rho(r)`` where ``rho`` is ``|r|`` (``"abs"``) or the
    Huber function with threshold 1 (``"huber"``), or 0 (``None``: OIDN's PU-L1 alone).

    PU-L1 grows like the log of an overshoot, so it barely charges a combiner for mixing a
    failed candidate (a Poisson dipole, a firefly) into a dark pixel, which the evaluation's
    relMSE charges quadratically. The relative term charges it linearly. Its denominator comes
    from the base image, which does not depend on the target's noise, and ``rho`` grows at
    most linearly, so the target's own fireflies (512-spp path-traced targets) cannot dominate
    a batch as they do in a squared relative error.

    Args:
        out: ``(N, H, W, 3)`` combiner output (linear).
        target: ``(N, H, W, 3)`` linear target, same device.
        base: ``(N, H, W, 3)`` base network image (the first candidate).
        scale: ``(N,)`` OIDN input scales.
        relative: ``None``, ``"abs"`` or ``"huber"``.
        eps: denominator offset, in units of the scaled image (mean about 0.18).

    Returns:
        Scalar tensor.
    """
    s = scale.reshape(-1, 1, 1, 1)
    l1 = pu_forward((s * out).clamp_min(0.0)) - pu_forward((s * target).clamp_min(0.0))
    l1 = l1.abs().mean()
    if relative is None:
        return l1
    r = s * (out - target) / (eps + s * base.detach().mean(-1, keepdim=True))
    if relative == "abs":
        return l1 + r.abs().mean()
    if relative == "huber":
        return l1 + torch.nn.functional.huber_loss(r, torch.zeros_like(r), delta=1.0)
    raise ValueError(f"unknown relative term {relative!r}; valid: 'abs', 'huber' or None")


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


def train_combiner(config: TrainConfig, *, resume: bool = False, progress: bool = True) -> Path:
    """Train (or continue training) the combiner design ``config.model`` on top of the frozen
    base network ``config.base_model``; see the module docstring.

    Returns:
        Path of the final combiner (``RUN_DIR/model.safetensors``); the run directory also
        holds a copy of the base network (``RUN_DIR/base.*``, the card's ``base_model``), so
        the run directory is a complete model.

    Raises:
        FileExistsError: ``config.out`` holds a run and ``resume`` is false.
        ConfigMismatchError: resuming with other training settings.
        ValueError: no ``base_model``, a base network that reads other buffers than the design,
            an unusable dataset or an unknown loss.
    """

    design = COMBINER_DESIGNS[config.model]
    if config.base_model is None:
        raise ValueError(f"{config.model} trains on top of a base network: pass --base-model")
    if config.loss not in COMBINER_LOSSES:
        raise ValueError(
            f"loss {config.loss!r} does not apply to a combiner; use one of "
            f"{', '.join(COMBINER_LOSSES)}"
        )
    base = OIDNReconstructor.from_checkpoint(config.base_model)
    if base.design.gradients != design.gradients:
        raise ValueError(
            f"base network {config.base_model} ({base.design.description}) and {config.model} "
            "must both read gradients or both not"
        )
    relative = COMBINER_LOSSES[config.loss]
    device = torch.device(config.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    run = Path(config.out)
    config = prepare_run(config, resume)
    train_set, val_set = split_datasets(config, "gdpt" if design.gradients else "pt")
    (run / "checkpoints").mkdir(parents=True, exist_ok=True)
    write_json(run / "config.json", config.to_dict())
    torch.manual_seed(config.seed)
    net = CombinerNet(design.in_channels, len(design.candidate_names)).to(device).train()
    optimizer = make_optimizer(net, config)
    start, elapsed = resume_state(run, net, optimizer, device, resume)
    val_elements = _validation(val_set, design, base, config.val_crops) if config.val_every else []
    cache = CandidateCache(design, base)
    _copy_base(Path(config.base_model), run / BASE_NAME)
    card = {
        "training": {
            "data": config.data,
            "base_model": str(config.base_model),
            "crops": len(train_set.crops),
            "validation_crops": len(val_set.crops),
            "loss": f"{config.loss}: PU-L1 + relative term {relative} (combiner_loss)",
            "batch": config.batch,
            "lr": config.lr,
        }
    }

    def save(base_path: Path, done: int, seconds: float, last_val: dict[str, float]) -> None:
        info = {**card, "steps": done, "train_seconds": round(seconds, 1), "validation": last_val}
        write_checkpoint(base_path, *encode_combiner(net, config.model, BASE_NAME, info))

    def loss_at(step: int) -> torch.Tensor:
        buffers, cands, target = make_combiner_batch(train_set, config, design, step, cache)
        buffers = {n: t.to(device) for n, t in buffers.items()}
        cands = cands.to(device)
        x, scale = combiner_input(buffers, cands, design)
        out = combine(net, x, scale)
        return combiner_loss(out, target.to(device), cands[:, 0], scale, relative=relative)

    optimise(
        config, run, net, optimizer, start=start, elapsed=elapsed, loss_at=loss_at,
        validate=lambda: _validate(net, design, val_elements), save=save,
        desc="combiner", progress=progress,
    )  # fmt: skip
    return run / "model.safetensors"
