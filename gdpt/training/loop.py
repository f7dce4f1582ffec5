"""The training loop: one loop for every network family, single-process or under ``torchrun``.

The loop knows nothing about the network (as edm's ``training_loop``): a family's plan builder
(:data:`gdpt.training.train.PLANS`) turns the run settings into a :class:`TrainingPlan` (the
network, the loss of the batch of an update, validation, how to write a checkpoint) and the
loop does the rest:

* the run directory (:mod:`gdpt.training.run_dir`): ``config.json`` and the plan's extra
  files before the first update, ``log.jsonl`` per update, ``val.jsonl`` every ``val_every``
  updates, a checkpoint every ``ckpt_every`` updates, the final ``model`` files;
* Adam (:func:`~gdpt.training.step.make_optimizer`) at the learning rate of the schedule
  (:mod:`gdpt.training.schedule`), one :func:`~gdpt.training.step.update` per step;
* exact resume: a checkpoint's ``.pt`` file holds the exact weights, the Adam state, the step
  count and the training time; the batch of update ``s`` is a pure function of
  ``(seed, s, rank)`` (:func:`~gdpt.training.batches.step_seed`), and so is the global torch
  RNG during the update (seeded with it, e.g. for E-LPIPS's random ensemble), so there is no
  RNG state to carry: resuming from a checkpoint repeats the run bit for bit;
* multi-process: under ``torchrun`` (``WORLD_SIZE > 1``) the network is wrapped in
  ``DistributedDataParallel`` (gloo on CPU, nccl on CUDA), each rank draws its own batch, the
  logged loss is the mean over ranks, and rank 0 alone writes files and validates. The device
  is ``config.device``, else ``cuda:LOCAL_RANK`` when CUDA is available, else the CPU.
"""

from __future__ import annotations

import os
import pickle
import sys
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from gdpt.io.atomic import atomic_path, atomic_write
from gdpt.training.batches import step_seed
from gdpt.training.config import TrainConfig
from gdpt.training.run_dir import (
    append_jsonl,
    checkpoint_base,
    complete_checkpoints,
    prepare_run,
    prune_checkpoints,
    truncate_jsonl,
    write_json,
)
from gdpt.training.schedule import learning_rate
from gdpt.training.step import UpdateScale, make_optimizer, update

__all__ = ["PlanBuilder", "RunContext", "TrainingPlan", "training_loop"]


@dataclass(frozen=True)
class RunContext:
    """Where a plan runs.

    Attributes:
        run: the run directory.
        device: the torch device of this process.
        rank: this process's rank (0 without ``torchrun``).
        world: number of processes.
    """

    run: Path
    device: torch.device
    rank: int
    world: int


@dataclass
class TrainingPlan:
    """What one network family contributes to :func:`training_loop`.

    Attributes:
        net: the network being trained, on the run's device, in train mode.
        loss: ``(forward, step) -> scalar tensor``: the loss of this process's batch of update
            ``step`` (0-based); the forward pass must go through ``forward`` (``net`` or its
            ``DistributedDataParallel`` wrapper).
        validate: ``() -> scores`` of ``net`` on the validation set (rank 0 only).
        save: ``(path, card) -> None``: writes ``net`` as the checkpoint ``path`` (suffix
            replaced by ``.safetensors`` / ``.json``) with ``card`` (training information).
        card: training information of every checkpoint's card; the loop adds ``steps``,
            ``train_seconds`` and ``validation``.
        files: run-directory files (name -> content) written with ``config.json``; a resumed
            run must find them unchanged.
        update_scale: per-parameter update multipliers (:data:`~gdpt.training.step
            .UpdateScale`).
    """

    net: nn.Module
    loss: Callable[[Callable[[torch.Tensor], torch.Tensor], int], torch.Tensor]
    validate: Callable[[], dict[str, float]]
    save: Callable[[Path, Mapping[str, Any]], object]
    card: dict[str, Any]
    files: dict[str, bytes] = field(default_factory=dict)
    update_scale: Sequence[UpdateScale] = ()


#: ``(config, context) -> plan``: a family's training plan for a resolved config. It checks
#: the config against the data before any file is written (``ValueError``) and seeds nothing
#: (the loop seeds the global RNG with ``config.seed`` before calling it).
PlanBuilder = Callable[[TrainConfig, RunContext], TrainingPlan]


def _distributed() -> tuple[int, int, int]:
    """``(rank, local_rank, world_size)`` from the torchrun environment."""
    return (
        int(os.environ.get("RANK", "0")),
        int(os.environ.get("LOCAL_RANK", "0")),
        int(os.environ.get("WORLD_SIZE", "1")),
    )


def _meet_before_leaving(world: int) -> None:
    """Return once all ``world`` ranks have called it, meeting on the rendezvous store.

    Destroying a gloo group closes the rank's connections; a peer still completing the last
    collective then fails (pytorch/gloo#155: a barrier followed by the context's destruction).
    The store's connection is not the group's, so after this no rank closes its connections
    while another still communicates. Only after a run every rank finished: a rank that
    failed never arrives.
    """
    import torch.distributed as dist

    store = dist.distributed_c10d._get_default_store()
    if store.add("gdpt/finished", 1) == world:
        store.set("gdpt/all_finished", "1")
    store.wait(["gdpt/all_finished"])


def _write_files(run: Path, files: Mapping[str, bytes]) -> None:
    """Write the plan's extra files; an existing one must be identical (a resumed run)."""
    for name, data in files.items():
        path = run / name
        if path.is_file():
            if path.read_bytes() != data:
                raise ValueError(
                    f"{path} differs from the one this run needs; resume with the same inputs "
                    "or choose another --out"
                )
            continue
        atomic_write(path, data)


def _resume(
    run: Path,
    net: nn.Module,
    optimizer: torch.optim.Optimizer,
    device: torch.device,
    world: int,
) -> tuple[int, float, str | None]:
    """Load the newest readable checkpoint's ``.pt`` state into ``net`` and ``optimizer``.

    A checkpoint whose ``.pt`` file cannot be read (truncated, damaged) is skipped for the one
    before it; nothing is deleted.

    Returns:
        ``(steps done, training seconds so far, one line saying where the run resumes)``;
        ``(0, 0.0, None)`` without a checkpoint.

    Raises:
        ValueError: a checkpoint of an older gdpt (no network state), or no checkpoint readable.
    """
    found = complete_checkpoints(run)
    skipped: list[str] = []
    for _, base in found:
        path = base.with_suffix(".pt")
        try:
            state = torch.load(path, map_location=device, weights_only=True)
        except (RuntimeError, EOFError, OSError, pickle.UnpicklingError) as error:
            skipped.append(f"{path.name} is unreadable ({str(error).splitlines()[0]})")
            continue
        if "model" not in state:
            raise ValueError(f"{path}: no network state (an older gdpt's run); start a new run")
        net.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        if state["world_size"] != world:
            warnings.warn(
                f"resuming a {state['world_size']}-process run with {world} processes: "
                "batches differ from the original run",
                stacklevel=3,
            )
        said = "; ".join(skipped + [f"resuming {run} from step {int(state['step'])} ({path.name})"])
        return int(state["step"]), float(state["elapsed"]), said
    if skipped:
        raise ValueError(f"{run}: no readable checkpoint: " + "; ".join(skipped))
    return 0, 0.0, None


def training_loop(
    config: TrainConfig,
    build: PlanBuilder,
    *,
    resume: bool = False,
    progress: bool = True,
    desc: str = "train",
) -> Path:
    """Train (or continue training) the network of ``build``; see the module docstring.

    Args:
        config: the run settings.
        build: the family's plan builder.
        resume: continue the run in ``config.out`` from its newest checkpoint (starts afresh
            if the directory holds no run yet).
        progress: show a progress bar (rank 0).
        desc: progress-bar label.

    Returns:
        Path of the final network (``RUN_DIR/model.safetensors``).

    Raises:
        FileExistsError: ``config.out`` holds a run and ``resume`` is false.
        ConfigMismatchError: resuming with other training settings.
        ValueError: the plan refuses the config or the data, or a resumed run's extra files
            or checkpoint do not fit.
    """
    import torch.distributed as dist
    from tqdm.auto import tqdm

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
    finished = False
    try:
        run = Path(config.out)
        config = prepare_run(config, resume)
        torch.manual_seed(config.seed)
        plan = build(config, RunContext(run, device, rank, world))
        if world > 1:
            dist.barrier()  # every rank has checked the run dir before rank 0 writes it
        if rank == 0:
            (run / "checkpoints").mkdir(parents=True, exist_ok=True)
            write_json(run / "config.json", config.to_dict())
            _write_files(run, plan.files)
        optimizer = make_optimizer(plan.net, config)
        start, elapsed, said = (
            _resume(run, plan.net, optimizer, device, world) if resume else (0, 0.0, None)
        )
        if said and rank == 0:
            print(f"gdpt train: {said}", file=sys.stderr, flush=True)
        if rank == 0:
            for name in ("log.jsonl", "val.jsonl"):
                truncate_jsonl(run / name, start)
        forward = plan.net
        if world > 1:
            forward = nn.parallel.DistributedDataParallel(
                plan.net, device_ids=[device.index] if device.type == "cuda" else None
            )
        last_val: dict[str, float] = {}
        bar = tqdm(
            total=config.steps,
            initial=start,
            unit="step",
            desc=desc,
            disable=not progress or rank != 0,
            dynamic_ncols=True,
        )
        with bar:  # closed before an interrupted command's last line
            for step in range(start, config.steps):
                t0 = time.perf_counter()
                torch.manual_seed(step_seed(config.seed, step, rank) ^ 1)
                lr = learning_rate(step, config)
                loss, updated = update(
                    plan.net, optimizer, lambda s=step: plan.loss(forward, s), lr, plan.update_scale
                )
                if world > 1:
                    total = torch.tensor([loss], dtype=torch.float64)
                    dist.all_reduce(total)
                    loss = float(total) / world
                seconds = time.perf_counter() - t0
                elapsed += seconds
                done = step + 1
                final = done == config.steps
                validating = bool(config.val_every) and (done % config.val_every == 0 or final)
                saving = done % config.ckpt_every == 0 or final
                if rank == 0:
                    record = {"step": done, "loss": loss, "lr": lr, "time": round(elapsed, 3),
                              "step_seconds": round(seconds, 4)}  # fmt: skip
                    append_jsonl(run / "log.jsonl", record | ({} if updated else {"skipped": True}))
                    bar.update(1)
                    bar.set_postfix(loss=f"{loss:.4g}", lr=f"{lr:.2e}")
                    if validating:
                        last_val = plan.validate()
                        append_jsonl(
                            run / "val.jsonl", {"step": done, "time": round(elapsed, 3), **last_val}
                        )
                    card = {**plan.card, "steps": done, "train_seconds": round(elapsed, 1),
                            "validation": last_val}  # fmt: skip
                    if saving:
                        base = checkpoint_base(run, done)
                        plan.save(base, card)  # the network first: a .pt marks it complete
                        state = {"step": done, "elapsed": elapsed, "world_size": world,
                                 "model": plan.net.state_dict(),
                                 "optimizer": optimizer.state_dict()}  # fmt: skip
                        with atomic_path(base.with_suffix(".pt")) as tmp:
                            torch.save(state, tmp)
                        prune_checkpoints(run, config.keep_checkpoints)
                    if final:
                        plan.save(run / "model", card)
                if world > 1 and (saving or validating):
                    dist.barrier()
        finished = True
        return run / "model.safetensors"
    finally:
        if owns_group:
            if finished:
                _meet_before_leaving(world)
            dist.destroy_process_group()
