"""The run directory of a training run (edm-style; the layout is part of the API)::

    RUN_DIR/config.json                     TrainConfig (written before any work)
    RUN_DIR/log.jsonl                       {"step", "loss", "lr", "time", "step_seconds"} per step
    RUN_DIR/val.jsonl                       {"step", "time", scores...} per validation (the
                                             family's: "relmse", "flip", baselines, "count")
    RUN_DIR/checkpoints/ckpt-0000100.safetensors/.json   network + model card (the family's
                                                         checkpoint format)
    RUN_DIR/checkpoints/ckpt-0000100.pt     exact weights, optimizer state, step, elapsed time,
                                            world size (written last: marks a complete one)
    RUN_DIR/model.safetensors/.json         the final network
    RUN_DIR/...                             a family's extra files (a combiner's base.*)

``step`` counts optimizer updates; ``log.jsonl`` line ``step = s`` is the loss of the batch of
update ``s``. Files are replaced through :mod:`gdpt.io.atomic`, networks written by
:mod:`gdpt.training.checkpoint`; :mod:`gdpt.training.loop` writes the run.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from gdpt.io.atomic import atomic_write
from gdpt.training.config import TrainConfig, check_resume

_CKPT_PREFIX = "ckpt-"


def write_json(path: Path, data: Any) -> None:
    """Replace ``path`` by ``data`` as indented JSON (atomically)."""
    atomic_write(path, json.dumps(data, indent=2) + "\n")


def append_jsonl(path: Path, record: Mapping[str, Any]) -> None:
    """Append ``record`` as one JSON line (``log.jsonl``, ``val.jsonl``)."""
    with path.open("a") as f:
        f.write(json.dumps(record) + "\n")


def read_jsonl(path: Path) -> list[dict[str, Any]]:
    """The records of a JSON-lines file (``[]`` if it does not exist)."""
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def truncate_jsonl(path: Path, step: int) -> None:
    """Drop the lines of steps after ``step`` (written after the checkpoint resumed from)."""
    if path.is_file():
        lines = [
            line
            for line in path.read_text().splitlines()
            if line.strip() and json.loads(line)["step"] <= step
        ]
        atomic_write(path, "".join(line + "\n" for line in lines))


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


def complete_checkpoints(run: Path) -> list[tuple[int, Path]]:
    """``(step, path without suffix)`` of every complete checkpoint, newest first."""
    found = []
    for state in (run / "checkpoints").glob(f"{_CKPT_PREFIX}*.pt"):
        base = state.with_suffix("")
        if base.with_suffix(".safetensors").is_file() and base.with_suffix(".json").is_file():
            found.append((int(base.name[len(_CKPT_PREFIX) :]), base))
    return sorted(found, reverse=True)


def checkpoint_base(run: Path, step: int) -> Path:
    """``RUN_DIR/checkpoints/ckpt-<step:07d>`` (no suffix)."""
    return run / "checkpoints" / f"{_CKPT_PREFIX}{step:07d}"


def prune_checkpoints(run: Path, keep: int) -> None:
    """Delete all but the newest ``keep`` checkpoints (``.pt``, ``.safetensors``, ``.json``)."""
    states = sorted((run / "checkpoints").glob(f"{_CKPT_PREFIX}*.pt"))
    for old in states[:-keep]:
        for suffix in (".pt", ".safetensors", ".json"):
            old.with_suffix(suffix).unlink(missing_ok=True)
