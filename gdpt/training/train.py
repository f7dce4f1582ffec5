"""Training the NGPT reconstruction network (Kettunen et al. 2019) on a
:mod:`gdpt.training.dataset`.

The recipe follows the reference implementation (``gdpt-notes.md`` sections 3.1, 3.3, 3.4):

* Adam (``beta2 = 0.99``, ``eps = 1e-8``), base learning rate ``5e-4``, geometric warm-up from
  ``lr / 1e4`` and an exponential ramp-down (:func:`learning_rate`). The reference warms up over
  10 k minibatches and halves the rate every 70 k after 50 k, for runs of ~600 k minibatches;
  CPU runs are ~1000x shorter, so by default the schedule is scaled to the run length: warm-up
  over 2 % of the steps, ramp-down from 25 % of the steps with a half-life of 25 % of the
  steps (the rate ends at 1/8 of the base). The resolved values are stored in ``config.json``.
  The reference's "no learning for 100 minibatches after a restart" is not needed: the Adam
  state is checkpointed.
* Every sample is one input level of one random crop (optionally a random sub-crop), augmented
  (:func:`augment`: x/y flips and transposition with the gradient rules of
  :mod:`gdpt.reconstruct.transforms`, RGB permutation, colour multiplier ``3 (u, v, w)`` uniform
  on the simplex (mean 1) on colour, gradients, albedo and target, log-normal brightness
  ``exp(N(0, 1)) / e^0.5`` (mean 1) on colour, gradients and target only, depth scale
  ``U(0.1, 1.1)``), transformed, and mirror-padded by ``pad`` pixels with the padding offset
  varied by ``+-vary_padding``. The loss sees the window interior without ``pad +
  vary_padding`` pixels on each side, on linear HDR radiance (``exp(y) - 1``).

Run directory (edm-style; the layout is part of the API)::

    RUN_DIR/config.json                     TrainConfig (written before any work)
    RUN_DIR/log.jsonl                       {"step", "loss", "lr", "time", "step_seconds"} per step
    RUN_DIR/val.jsonl                       {"step", "time", "relmse", "flip", "l1_relmse",
                                             "l1_flip", "count"} per validation
    RUN_DIR/checkpoints/ckpt-0000100.safetensors/.json   network + model card (save_checkpoint)
    RUN_DIR/checkpoints/ckpt-0000100.pt     optimizer state, step, elapsed time (written last)
    RUN_DIR/model.safetensors/.json         the final network

``step`` counts optimizer updates; ``log.jsonl`` line ``step = s`` is the loss of the batch of
update ``s``. Exact resume: the batch of update ``s`` (crop choice, augmentations, padding
offsets) and the global torch RNG (used by the E-LPIPS ensemble) are seeded from
``(seed, s, rank)``, so there is no RNG state to carry: restoring the weights, the Adam state and
the step count reproduces the run exactly (same next loss). Resuming with different
training-relevant settings raises :class:`ConfigMismatchError`.

Multi-process: under ``torchrun`` (``WORLD_SIZE > 1``) the model is wrapped in
``DistributedDataParallel`` (gloo on CPU, nccl on CUDA), each rank draws its own ``batch``, and
rank 0 alone writes files and validates. Nothing here assumes a device: it is ``cuda:LOCAL_RANK``
when CUDA is available, else the CPU, unless ``device`` is given.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from gdpt.io.atomic import atomic_path, atomic_write
from gdpt.reconstruct.dense_unet import DenseUNet, build_model
from gdpt.reconstruct.losses import FLIPLoss, get_loss
from gdpt.reconstruct.ngpt import (
    NGPTReconstructor,
    default_features,
    load_checkpoint,
)
from gdpt.reconstruct.transforms import (
    AUGMENTATIONS,
    OUTPUT_TRANSFORM,
    Padding,
    pad_buffers,
    stack_input,
    transform_buffers,
)
from gdpt.training.checkpoint import save_checkpoint
from gdpt.training.dataset import CropDataset, DatasetWarning

#: Buffers scaled by the colour multiplier and permuted by the channel permutation.
COLOUR_BUFFERS = ("primal", "dx", "dy", "albedo", "target")
#: Buffers scaled by the brightness multiplier (colour and gradients only, not albedo).
BRIGHTNESS_BUFFERS = ("primal", "dx", "dy", "target")
#: Config fields that may change when a run is resumed.
RESUMABLE_FIELDS = (
    "data",
    "val_data",
    "out",
    "steps",
    "val_every",
    "ckpt_every",
    "keep_checkpoints",
    "device",
)
_SCHEDULE_FIELDS = ("warmup_steps", "decay_start", "half_life")
_CKPT_PREFIX = "ckpt-"


class ConfigMismatchError(ValueError):
    """A run directory is resumed with settings that change the training."""


# --------------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run.

    Attributes:
        model: registered model configuration (``gdpt.reconstruct.dense_unet.CONFIGS``); models
            with 16 input channels read the ``gdpt`` inputs, 10-channel ones the path-traced.
            A design of :data:`gdpt.reconstruct.oidn_ngpt.DESIGNS` (``oidn-grad``, ...)
            fine-tunes OIDN's U-Net instead (:mod:`gdpt.training.finetune`; ``pad`` and
            ``vary_padding`` do not apply there).
        data: training dataset directory (:mod:`gdpt.training.dataset`).
        out: run directory.
        val_data: validation dataset directory; ``None`` holds out every ``holdout_every``-th
            scene of ``data`` (scene index ``% holdout_every == holdout_every - 1``).
        holdout_every: see ``val_data``.
        loss: ``flip``, ``flip_rel``, ``flip_log``, ``flip_hdr``, ``l1`` or ``elpips``
            (:func:`gdpt.reconstruct.losses.get_loss`).
        steps: total optimizer updates.
        batch: crops per update and process.
        crop: side of the random sub-crop taken from each dataset crop (``None``: the whole
            crop); ``crop + 2 * pad`` must be a multiple of the model alignment.
        pad: mirror padding on every side (reference: 8).
        vary_padding: random padding offset range ``+-vary_padding`` (reference: 7).
        augment: apply the random augmentations (off: identity, depth scale 1, no offset).
        lr: base learning rate.
        beta1: Adam beta1.
        beta2: Adam beta2.
        eps: Adam epsilon.
        warmup_steps: geometric warm-up length (``None``: 2 % of ``steps``).
        decay_start: step where the exponential ramp-down starts (``None``: 25 % of ``steps``).
        half_life: ramp-down half-life in steps (``None``: 25 % of ``steps``).
        seed: seeds the initial weights and every batch.
        val_every: validate every this many steps (and at the end); 0 disables.
        val_crops: validation elements used (evenly spaced over the validation set).
        ckpt_every: checkpoint every this many steps (and at the end).
        keep_checkpoints: checkpoints kept in ``checkpoints/`` (older ones are deleted).
        device: torch device (``None``: ``cuda:LOCAL_RANK`` if available, else ``cpu``).
    """

    model: str = "fast_xs"
    data: str = ""
    out: str = ""
    val_data: str | None = None
    holdout_every: int = 10
    loss: str = "flip"
    steps: int = 1000
    batch: int = 8
    crop: int | None = None
    pad: int = 8
    vary_padding: int = 7
    augment: bool = True
    lr: float = 5e-4
    beta1: float = 0.9
    beta2: float = 0.99
    eps: float = 1e-8
    warmup_steps: int | None = None
    decay_start: int | None = None
    half_life: int | None = None
    seed: int = 0
    val_every: int = 100
    val_crops: int = 32
    ckpt_every: int = 100
    keep_checkpoints: int = 3
    device: str | None = None

    def __post_init__(self) -> None:
        if not self.data or not self.out:
            raise ValueError("TrainConfig needs data= and out= directories")
        for name in (
            "steps",
            "batch",
            "holdout_every",
            "val_crops",
            "ckpt_every",
            "keep_checkpoints",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.val_every < 0 or self.pad < 0 or not 0 <= self.vary_padding <= self.pad:
            raise ValueError("need val_every >= 0 and 0 <= vary_padding <= pad")
        if self.crop is not None and self.crop < 2:
            raise ValueError(f"crop must be >= 2, got {self.crop}")

    def resolved(self) -> TrainConfig:
        """A copy with the schedule defaults (``None``) replaced by their values for ``steps``."""
        defaults = {
            "warmup_steps": self.steps // 50,
            "decay_start": self.steps // 4,
            "half_life": max(1, self.steps // 4),
        }
        return dataclasses.replace(
            self, **{k: v for k, v in defaults.items() if getattr(self, k) is None}
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable form."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TrainConfig:
        """Inverse of :meth:`to_dict`.

        Raises:
            ValueError: unknown keys.
        """
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown TrainConfig fields {unknown}")
        return cls(**data)


def learning_rate(step: int, config: TrainConfig) -> float:
    """Learning rate of update ``step`` (0-based) for a :meth:`TrainConfig.resolved` config.

    ``lr * 1e-4 * 1e4 ** min(1, (1 + step) / warmup_steps) * 0.5 ** (max(0, step - decay_start)
    / half_life)`` (reference formula with scaled lengths; no warm-up if ``warmup_steps == 0``).
    """
    warm = config.warmup_steps
    factor = 1.0 if not warm else 1e-4 * 1e4 ** min(1.0, (1 + step) / warm)
    return config.lr * factor * 0.5 ** (max(0, step - config.decay_start) / config.half_life)


# ---------------------------------------------------------------------------------- augmentation
@dataclass(frozen=True)
class AugmentParams:
    """One draw of the random augmentations of a training sample (identity by default).

    Attributes:
        origin: ``(y, x)`` of the sub-crop in the dataset crop.
        size: ``(height, width)`` of the sub-crop (``None``: the whole crop).
        flip_x: mirror left-right.
        flip_y: mirror top-bottom.
        transpose: swap the image axes (after the flips).
        permutation: RGB channel order.
        colour: per-channel multiplier (mean 1 when drawn).
        brightness: multiplier of colour and gradients (mean 1 when drawn).
        depth_scale: depth is normalised to ``[0, depth_scale]``.
        offset: ``(dy, dx)`` padding offset: top/left padding is ``pad + offset``.
    """

    origin: tuple[int, int] = (0, 0)
    size: tuple[int, int] | None = None
    flip_x: bool = False
    flip_y: bool = False
    transpose: bool = False
    permutation: tuple[int, int, int] = (0, 1, 2)
    colour: tuple[float, float, float] = (1.0, 1.0, 1.0)
    brightness: float = 1.0
    depth_scale: float = 1.0
    offset: tuple[int, int] = (0, 0)


def sample_augmentation(
    generator: torch.Generator, config: TrainConfig, shape: tuple[int, int]
) -> AugmentParams:
    """Draw the augmentations of one sample.

    Args:
        generator: CPU generator all draws come from.
        config: training settings (``crop``, ``vary_padding``, ``augment``).
        shape: ``(height, width)`` of the dataset crops.

    Returns:
        The draw; with ``config.augment`` false only the sub-crop position is random.
    """

    def uniform(n: int = 1) -> list[float]:
        return torch.rand(n, generator=generator, dtype=torch.float64).tolist()

    height, width = shape
    size = None if config.crop is None else (config.crop, config.crop)
    origin = (0, 0)
    if size is not None:
        origin = (
            int(torch.randint(height - size[0] + 1, (1,), generator=generator)),
            int(torch.randint(width - size[1] + 1, (1,), generator=generator)),
        )
    if not config.augment:
        return AugmentParams(origin=origin, size=size)
    flips = uniform(3)
    square = (size or shape)[0] == (size or shape)[1]
    simplex = -torch.log(torch.rand(3, generator=generator, dtype=torch.float64))
    v = config.vary_padding
    offset = torch.randint(-v, v + 1, (2,), generator=generator).tolist()
    return AugmentParams(
        origin=origin,
        size=size,
        flip_x=flips[0] < 0.5,
        flip_y=flips[1] < 0.5,
        transpose=square and flips[2] < 0.5,
        permutation=tuple(torch.randperm(3, generator=generator).tolist()),
        colour=tuple((3.0 * simplex / simplex.sum()).tolist()),
        brightness=math.exp(float(torch.randn(1, generator=generator, dtype=torch.float64)) - 0.5),
        depth_scale=0.1 + uniform()[0],
        offset=(int(offset[0]), int(offset[1])),
    )


def augment(buffers: Mapping[str, torch.Tensor], params: AugmentParams) -> dict[str, torch.Tensor]:
    """Apply :class:`AugmentParams` (except depth scale and padding) to a buffer set.

    Order: sub-crop (the unused last column of ``dx`` / row of ``dy`` is then set to 0, the
    buffer convention), flips and transposition (:data:`~gdpt.reconstruct.transforms
    .AUGMENTATIONS`: gradients are negated and shifted, swapped, normals follow), channel
    permutation and colour multiplier (:data:`COLOUR_BUFFERS`), brightness
    (:data:`BRIGHTNESS_BUFFERS`). Every step maps the buffers of an image to the buffers of the
    augmented image.

    Args:
        buffers: name -> ``(H, W, C)`` float tensor (``primal``, ``dx``, ``dy``, ``albedo``,
            ``normal``, ``depth``, ``target``; any subset), one device.
        params: the augmentation draw.

    Returns:
        name -> augmented ``(h, w, C)`` tensor on the same device.
    """
    out = dict(buffers)
    if params.size is not None:
        (y, x), (h, w) = params.origin, params.size
        out = {n: t[y : y + h, x : x + w] for n, t in out.items()}
        if "dx" in out:
            out["dx"] = torch.cat([out["dx"][:, :-1], torch.zeros_like(out["dx"][:, -1:])], 1)
        if "dy" in out:
            out["dy"] = torch.cat([out["dy"][:-1], torch.zeros_like(out["dy"][-1:])], 0)
    for name, active in (
        ("flip_x", params.flip_x),
        ("flip_y", params.flip_y),
        ("transpose", params.transpose),
    ):
        if active:
            out = AUGMENTATIONS[name](out)
    for name in COLOUR_BUFFERS:
        if name in out:
            t = out[name][..., list(params.permutation)]
            out[name] = t * t.new_tensor(params.colour)
    for name in BRIGHTNESS_BUFFERS:
        if name in out:
            out[name] = out[name] * params.brightness
    return out


def padding_of(params: AugmentParams, pad: int) -> Padding:
    """The padding of a sample: ``pad`` on every side, shifted by ``params.offset``."""
    oy, ox = params.offset
    return Padding(pad + oy, pad - oy, pad + ox, pad - ox)


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


# ------------------------------------------------------------------------------------- training
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


# ----------------------------------------------------------------------------------- validation
@dataclass
class _ValElement:
    """A validation input (``(H, W, C)`` buffers), its target and the L1-Poisson scores."""

    inputs: dict[str, torch.Tensor]
    target: torch.Tensor
    l1: dict[str, float]


def _metrics(pred: torch.Tensor, target: torch.Tensor, flip: FLIPLoss) -> dict[str, float]:
    """relMSE (NGPT convention) and LDR-FLIP of ``(H, W, 3)`` linear images."""
    from gdpt.metrics import relmse

    nchw = (pred.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None])
    return {"relmse": relmse(pred, target), "flip": float(flip(*nchw))}


def load_validation(dataset: CropDataset, count: int, device: torch.device) -> list[_ValElement]:
    """Up to ``count`` evenly spaced elements of ``dataset`` with their L1-Poisson metrics.

    The L1 Poisson baseline (``alpha = 0.2``) reconstructs the gradient-domain input of the same
    crop and level (for a path-traced dataset: the equal-time G-PT input). Unreadable elements
    are skipped with a warning.
    """
    from gdpt.io.exr import load_buffers
    from gdpt.reconstruct.poisson import reconstruct

    flip = FLIPLoss("ldr")
    picks = sorted({round(float(i)) for i in np.linspace(0, len(dataset) - 1, count)})
    elements = []
    for index in picks:
        record, level = dataset.element(index)
        try:
            item = dataset.load(index)
            g = load_buffers(dataset.root / record["files"][f"in{level}"]).to(device)
        except (ValueError, OSError) as error:
            warnings.warn(
                f"validation element {index} skipped: {error}", DatasetWarning, stacklevel=2
            )
            continue
        target = item["target"].to(device)
        l1 = reconstruct(g.primal, g.dx, g.dy, method="l1", alpha=0.2)
        inputs = {k: v.to(device) for k, v in item["inputs"].items()}
        elements.append(_ValElement(inputs, target, _metrics(l1, target, flip)))
    if not elements:
        raise ValueError(f"{dataset.root}: no readable validation element")
    return elements


def validate(
    model: DenseUNet, elements: list[_ValElement], features: tuple[str, ...], margin: int
) -> dict[str, float]:
    """Mean relMSE and FLIP of the network and of L1 Poisson over the validation elements."""
    reconstructor = NGPTReconstructor(model, features=features, tile_size=None, margin=margin)
    flip = FLIPLoss("ldr")
    totals: dict[str, float] = {}
    for element in elements:
        scores = _metrics(reconstructor(element.inputs), element.target, flip)
        scores.update({f"l1_{k}": v for k, v in element.l1.items()})
        for key, value in scores.items():
            totals[key] = totals.get(key, 0.0) + value
    return {k: v / len(elements) for k, v in totals.items()} | {"count": len(elements)}


# ------------------------------------------------------------------------------------- run dir
def _write_json(path: Path, data: Any) -> None:
    atomic_write(path, json.dumps(data, indent=2) + "\n")


def _append_jsonl(path: Path, record: Mapping[str, Any]) -> None:
    with path.open("a") as f:
        f.write(json.dumps(record) + "\n")


def _truncate_jsonl(path: Path, step: int) -> None:
    """Drop the lines of steps after ``step`` (written after the checkpoint resumed from)."""
    if path.is_file():
        lines = [
            line
            for line in path.read_text().splitlines()
            if line.strip() and json.loads(line)["step"] <= step
        ]
        atomic_write(path, "".join(line + "\n" for line in lines))


def check_resume(stored: TrainConfig, requested: TrainConfig) -> TrainConfig:
    """The config to continue a run with: ``requested`` with unset schedule fields taken from
    ``stored``.

    Raises:
        ConfigMismatchError: a field outside :data:`RESUMABLE_FIELDS` differs (all are listed).
    """
    fill = {k: getattr(stored, k) for k in _SCHEDULE_FIELDS if getattr(requested, k) is None}
    config = dataclasses.replace(requested, **fill).resolved()
    diff = [
        f"{f.name}: {getattr(stored, f.name)!r} (run) vs {getattr(config, f.name)!r} (now)"
        for f in dataclasses.fields(TrainConfig)
        if f.name not in RESUMABLE_FIELDS and getattr(stored, f.name) != getattr(config, f.name)
    ]
    if diff:
        raise ConfigMismatchError(
            f"cannot resume {requested.out} with another config: {'; '.join(diff)} "
            "(use a new --out directory)"
        )
    return config


def prepare_run(config: TrainConfig, resume: bool) -> TrainConfig:
    """Check the run directory against ``config`` (read-only) and return the effective config.

    Raises:
        FileExistsError: the run directory has a ``config.json`` and ``resume`` is false.
        ConfigMismatchError: resuming with training-relevant changes.
    """
    path = Path(config.out) / "config.json"
    if not path.is_file():
        return config.resolved()
    if not resume:
        raise FileExistsError(
            f"{config.out} already holds a run; pass --resume to continue it "
            "or choose another --out"
        )
    return check_resume(TrainConfig.from_dict(json.loads(path.read_text())), config)


def latest_checkpoint(run: Path) -> tuple[int, Path] | None:
    """``(step, path without suffix)`` of the newest complete checkpoint, or ``None``."""
    best = None
    for state in (run / "checkpoints").glob(f"{_CKPT_PREFIX}*.pt"):
        base = state.with_suffix("")
        if base.with_suffix(".safetensors").is_file() and base.with_suffix(".json").is_file():
            step = int(base.name[len(_CKPT_PREFIX) :])
            best = max(best or (step, base), (step, base))
    return best


def _save(
    run: Path,
    model: DenseUNet,
    optimizer: torch.optim.Optimizer,
    step: int,
    elapsed: float,
    config: TrainConfig,
    card: dict[str, Any],
    world: int,
) -> None:
    base = checkpoint_base(run, step)
    save_checkpoint(model, base, card)
    state = {
        "step": step,
        "elapsed": elapsed,
        "world_size": world,
        "optimizer": optimizer.state_dict(),
    }
    with atomic_path(base.with_suffix(".pt")) as tmp:
        torch.save(state, tmp)
    prune_checkpoints(run, config.keep_checkpoints)


def checkpoint_base(run: Path, step: int) -> Path:
    """``RUN_DIR/checkpoints/ckpt-<step:07d>`` (no suffix)."""
    return run / "checkpoints" / f"{_CKPT_PREFIX}{step:07d}"


def prune_checkpoints(run: Path, keep: int) -> None:
    """Delete all but the newest ``keep`` checkpoints (``.pt``, ``.safetensors``, ``.json``)."""
    states = sorted((run / "checkpoints").glob(f"{_CKPT_PREFIX}*.pt"))
    for old in states[:-keep]:
        for suffix in (".pt", ".safetensors", ".json"):
            old.with_suffix(suffix).unlink(missing_ok=True)


# --------------------------------------------------------------------------------------- driver
def _distributed() -> tuple[int, int, int]:
    """``(rank, local_rank, world_size)`` from the torchrun environment."""
    return (
        int(os.environ.get("RANK", "0")),
        int(os.environ.get("LOCAL_RANK", "0")),
        int(os.environ.get("WORLD_SIZE", "1")),
    )


def _datasets(config: TrainConfig, kind: str) -> tuple[CropDataset, CropDataset]:
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


def train(config: TrainConfig, *, resume: bool = False, progress: bool = True) -> Path:
    """Train (or continue training) a network; see the module docstring for the run directory.

    Args:
        config: the run settings.
        resume: continue the run in ``config.out`` from its newest checkpoint (starts afresh
            if the directory holds no run yet).
        progress: show a progress bar (rank 0).

    Returns:
        Path of the final network (``RUN_DIR/model.safetensors``).

    Raises:
        FileExistsError: ``config.out`` holds a run and ``resume`` is false.
        ConfigMismatchError: resuming with other training settings.
        ValueError: unusable dataset, or crop and padding not aligned with the model.
    """
    import torch.distributed as dist
    from tqdm.auto import tqdm

    from gdpt.reconstruct.oidn_ngpt import DESIGNS

    if config.model in DESIGNS:  # OIDN's U-Net fine-tuned (gdpt.training.finetune)
        from gdpt.training.finetune import finetune

        return finetune(config, resume=resume, progress=progress)
    rank, local_rank, world = _distributed()
    if config.device is not None:
        device = torch.device(config.device)
    elif torch.cuda.is_available():
        device = torch.device("cuda", local_rank)
    else:
        device = torch.device("cpu")
    owns_group = world > 1 and not dist.is_initialized()
    if owns_group:
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    try:
        run = Path(config.out)
        config = prepare_run(config, resume)
        torch.manual_seed(config.seed)
        model = build_model(config.model)
        features = default_features(model.config.in_channels)
        kind = "gdpt" if "dx" in features else "pt"
        train_set, val_set = _datasets(config, kind)
        side = config.crop or min(train_set.resolution)
        if side > min(train_set.resolution) or (side + 2 * config.pad) % model.alignment:
            raise ValueError(
                f"crop {side} must fit the {train_set.resolution} dataset crops and "
                f"crop + 2 * pad ({config.pad}) must be a multiple of the "
                f"{config.model!r} alignment {model.alignment}"
            )
        loss_fn = get_loss(config.loss).to(device)
        if world > 1:
            dist.barrier()  # every rank has checked the run dir before rank 0 writes it
        if rank == 0:
            (run / "checkpoints").mkdir(parents=True, exist_ok=True)
            _write_json(run / "config.json", config.to_dict())
        model = model.to(device, memory_format=torch.channels_last)
        optimizer = make_optimizer(model, config)
        start, elapsed = 0, 0.0
        found = latest_checkpoint(run) if resume else None
        if found is not None:
            loaded, _ = load_checkpoint(found[1], device=device)
            model.load_state_dict(loaded.state_dict())
            state = torch.load(found[1].with_suffix(".pt"), map_location=device, weights_only=True)
            optimizer.load_state_dict(state["optimizer"])
            start, elapsed = int(state["step"]), float(state["elapsed"])
            if state["world_size"] != world:
                warnings.warn(
                    f"resuming a {state['world_size']}-process run with {world} "
                    "processes: batches differ from the original run",
                    stacklevel=2,
                )
        if rank == 0:
            for name in ("log.jsonl", "val.jsonl"):
                _truncate_jsonl(run / name, start)
        net = model
        if world > 1:
            net = nn.parallel.DistributedDataParallel(
                model, device_ids=[device.index] if device.type == "cuda" else None
            )
        val_elements = (
            load_validation(val_set, config.val_crops, device)
            if rank == 0 and config.val_every
            else []
        )
        card = {
            "training": {
                "data": config.data,
                "crops": len(train_set.crops),
                "loss": config.loss,
                "batch": config.batch * world,
            }
        }
        border = config.pad + config.vary_padding
        last_val: dict[str, float] = {}
        bar = tqdm(
            total=config.steps,
            initial=start,
            unit="step",
            desc="train",
            disable=not progress or rank != 0,
            dynamic_ncols=True,
        )
        for step in range(start, config.steps):
            t0 = time.perf_counter()
            torch.manual_seed(step_seed(config.seed, step, rank) ^ 1)
            x, target = make_batch(train_set, config, step, rank)
            lr = learning_rate(step, config)
            loss, updated = train_step(
                net, optimizer, loss_fn, x.to(device), target.to(device), border, lr
            )
            if world > 1:
                total = torch.tensor([loss], dtype=torch.float64)
                dist.all_reduce(total)
                loss = float(total) / world
            seconds = time.perf_counter() - t0
            elapsed += seconds
            done = step + 1
            if rank == 0:
                record = {
                    "step": done,
                    "loss": loss,
                    "lr": lr,
                    "time": round(elapsed, 3),
                    "step_seconds": round(seconds, 4),
                }
                _append_jsonl(run / "log.jsonl", record | ({} if updated else {"skipped": True}))
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.4g}", lr=f"{lr:.2e}")
                final = done == config.steps
                if config.val_every and (done % config.val_every == 0 or final):
                    last_val = validate(model, val_elements, features, config.pad)
                    _append_jsonl(
                        run / "val.jsonl", {"step": done, "time": round(elapsed, 3), **last_val}
                    )
                if done % config.ckpt_every == 0 or final:
                    _save(
                        run,
                        model,
                        optimizer,
                        done,
                        elapsed,
                        config,
                        {**card, "steps": done, "validation": last_val},
                        world,
                    )
                if final:
                    save_checkpoint(
                        model, run / "model", {**card, "steps": done, "validation": last_val}
                    )
            if world > 1 and (
                done % config.ckpt_every == 0
                or done == config.steps
                or (config.val_every and done % config.val_every == 0)
            ):
                dist.barrier()
        bar.close()
        return run / "model.safetensors"
    finally:
        if owns_group:
            dist.destroy_process_group()
