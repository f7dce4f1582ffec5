"""The single-process optimisation loop shared by OIDN fine-tuning
(:mod:`gdpt.training.finetune`) and the combiner (:mod:`gdpt.training.combine`).

Per update: the learning rate of the schedule, one loss evaluation and backward pass, an
optimizer step only if every gradient is finite (a skipped step is logged as ``"skipped"``;
the step's change of a parameter may be scaled element-wise, under Adam a per-weight
learning-rate multiplier), a ``log.jsonl`` record; validation every ``val_every`` steps
(``val.jsonl``); every ``ckpt_every`` steps a checkpoint whose ``.pt`` file holds the exact
weights and the optimizer state, which :func:`resume_state` reads back; at the end the run's
``model`` files.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

from gdpt.io.atomic import atomic_path
from gdpt.training.config import TrainConfig
from gdpt.training.run_dir import (
    append_jsonl,
    checkpoint_base,
    latest_checkpoint,
    prune_checkpoints,
    truncate_jsonl,
)
from gdpt.training.schedule import learning_rate

__all__ = ["optimise", "resume_state"]

#: ``save(base_path, steps_done, elapsed_seconds, last_validation)`` writes the model files.
SaveFn = Callable[[Path, int, float, dict[str, float]], None]


def resume_state(
    run: Path,
    net: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    device: torch.device,
    resume: bool,
) -> tuple[int, float]:
    """Load the newest checkpoint of ``run`` into ``net`` and ``optimizer`` (if ``resume``)
    and cut the logs back to it.

    Returns:
        ``(steps done, training seconds so far)``; ``(0, 0.0)`` for a new run.
    """
    start, elapsed = 0, 0.0
    found = latest_checkpoint(run) if resume else None
    if found is not None:
        state = torch.load(found[1].with_suffix(".pt"), map_location=device, weights_only=True)
        net.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        start, elapsed = int(state["step"]), float(state["elapsed"])
    for name in ("log.jsonl", "val.jsonl"):
        truncate_jsonl(run / name, start)
    return start, elapsed


def optimise(
    config: TrainConfig,
    run: Path,
    net: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    *,
    start: int,
    elapsed: float,
    loss_at: Callable[[int], torch.Tensor],
    validate: Callable[[], dict[str, float]],
    save: SaveFn,
    desc: str,
    progress: bool,
    update_scale: Sequence[tuple[torch.nn.Parameter, torch.Tensor]] = (),
) -> None:
    """Run updates ``start .. config.steps - 1`` (see the module docstring).

    Args:
        config: the run settings (steps, schedule, validation and checkpoint intervals).
        run: the run directory.
        net: the network being trained.
        optimizer: its optimizer.
        start: steps already done.
        elapsed: training seconds already spent.
        loss_at: ``step -> loss`` (builds the batch of ``step`` and evaluates the network).
        validate: scores on the validation set.
        save: writes the model files of a checkpoint or of the final model.
        desc: progress-bar label.
        progress: show a progress bar.
        update_scale: ``(parameter, multiplier)`` pairs: the optimizer's change of the
            parameter is multiplied element-wise by ``multiplier`` (same shape and device).
    """
    from tqdm.auto import tqdm

    last_val: dict[str, float] = {}
    bar = tqdm(total=config.steps, initial=start, unit="step", desc=desc,
               disable=not progress, dynamic_ncols=True)  # fmt: skip
    for step in range(start, config.steps):
        t0 = time.perf_counter()
        lr = learning_rate(step, config)
        for group in optimizer.param_groups:
            group["lr"] = lr
        optimizer.zero_grad(set_to_none=True)
        loss = loss_at(step)
        loss.backward()
        finite = all(bool(torch.isfinite(p.grad).all()) for p in net.parameters())
        if finite:
            before = [p.detach().clone() for p, _ in update_scale]
            optimizer.step()
            with torch.no_grad():
                for (p, multiplier), old in zip(update_scale, before, strict=True):
                    p.copy_(old + (p - old) * multiplier)
        seconds = time.perf_counter() - t0
        elapsed += seconds
        done = step + 1
        record = {"step": done, "loss": float(loss.detach()), "lr": lr,
                  "time": round(elapsed, 3), "step_seconds": round(seconds, 4)}  # fmt: skip
        append_jsonl(run / "log.jsonl", record | ({} if finite else {"skipped": True}))
        bar.update(1)
        bar.set_postfix(loss=f"{record['loss']:.4g}", lr=f"{lr:.2e}")
        final = done == config.steps
        if config.val_every and (done % config.val_every == 0 or final):
            last_val = validate()
            append_jsonl(run / "val.jsonl", {"step": done, "time": round(elapsed, 3), **last_val})
        if done % config.ckpt_every == 0 or final:
            base_path = checkpoint_base(run, done)
            save(base_path, done, elapsed, last_val)
            payload = {"step": done, "elapsed": elapsed, "world_size": 1,
                       "model": net.state_dict(), "optimizer": optimizer.state_dict()}  # fmt: skip
            with atomic_path(base_path.with_suffix(".pt")) as tmp:
                torch.save(payload, tmp)
            prune_checkpoints(run, config.keep_checkpoints)
        if final:
            save(run / "model", done, elapsed, last_val)
    bar.close()
