"""Training the NGPT reconstruction network (Kettunen et al. 2019) on a
:mod:`gdpt.training.dataset`: the training loop.

The recipe follows the reference implementation (``gdpt-notes.md`` sections 3.1, 3.3, 3.4), in
one file per concept: the run settings (:mod:`gdpt.training.config`), the learning-rate schedule
(:mod:`gdpt.training.schedule`), the augmentations (:mod:`gdpt.training.augment`), the batches
(:mod:`gdpt.training.batches`), the loss and the optimizer update (:mod:`gdpt.training.step`),
validation (:mod:`gdpt.training.validation`) and the run directory
(:mod:`gdpt.training.run_dir`).

Exact resume: the batch of update ``s`` (crop choice, augmentations, padding offsets) and the
global torch RNG (used by the E-LPIPS ensemble) are seeded from ``(seed, s, rank)``, so there is
no RNG state to carry: restoring the weights, the Adam state and the step count reproduces the
run exactly (same next loss). Resuming with different training-relevant settings raises
:class:`~gdpt.training.config.ConfigMismatchError`.

Multi-process: under ``torchrun`` (``WORLD_SIZE > 1``) the model is wrapped in
``DistributedDataParallel`` (gloo on CPU, nccl on CUDA), each rank draws its own ``batch``, and
rank 0 alone writes files and validates. Nothing here assumes a device: it is ``cuda:LOCAL_RANK``
when CUDA is available, else the CPU, unless ``device`` is given.
"""

from __future__ import annotations

import os
import time
import warnings
from pathlib import Path

import torch
from torch import nn

from gdpt.reconstruct.dense_unet import build_model
from gdpt.reconstruct.losses import get_loss
from gdpt.reconstruct.ngpt import default_features, load_checkpoint
from gdpt.training.batches import make_batch, split_datasets, step_seed
from gdpt.training.checkpoint import save_checkpoint
from gdpt.training.config import TrainConfig
from gdpt.training.run_dir import (
    append_jsonl,
    latest_checkpoint,
    prepare_run,
    save_run_checkpoint,
    truncate_jsonl,
    write_json,
)
from gdpt.training.schedule import learning_rate
from gdpt.training.step import make_optimizer, train_step
from gdpt.training.validation import load_validation, validate


def _distributed() -> tuple[int, int, int]:
    """``(rank, local_rank, world_size)`` from the torchrun environment."""
    return (
        int(os.environ.get("RANK", "0")),
        int(os.environ.get("LOCAL_RANK", "0")),
        int(os.environ.get("WORLD_SIZE", "1")),
    )


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

    from gdpt.reconstruct.combiner import COMBINER_DESIGNS
    from gdpt.reconstruct.oidn_ngpt import DESIGNS

    if config.model in COMBINER_DESIGNS:  # a combiner over a frozen base network
        from gdpt.training.combine import train_combiner

        return train_combiner(config, resume=resume, progress=progress)
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
        train_set, val_set = split_datasets(config, kind)
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
            write_json(run / "config.json", config.to_dict())
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
                truncate_jsonl(run / name, start)
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
                append_jsonl(run / "log.jsonl", record | ({} if updated else {"skipped": True}))
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.4g}", lr=f"{lr:.2e}")
                final = done == config.steps
                if config.val_every and (done % config.val_every == 0 or final):
                    last_val = validate(model, val_elements, features, config.pad)
                    append_jsonl(
                        run / "val.jsonl", {"step": done, "time": round(elapsed, 3), **last_val}
                    )
                if done % config.ckpt_every == 0 or final:
                    save_run_checkpoint(
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
