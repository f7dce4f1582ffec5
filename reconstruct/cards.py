"""Checkpoint cards: the two files of every network checkpoint and the reading of its card.

A checkpoint of any family (:mod:`.families`) is two files next to each other::

    model.safetensors   the weights
    model.json          the model card: a JSON object whose ``"format"`` names the family's
                        checkpoint format, then the family's keys and free-form training
                        information

Each family encodes and decodes its own weights; this module only finds the two files and
reads the card. Only safetensors, json and the standard library are imported (layering rule
of ``gdpt.reconstruct``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from safetensors import SafetensorError, safe_open

__all__ = ["CheckpointMismatchError", "checkpoint_paths", "read_card"]


class CheckpointMismatchError(ValueError):
    """A checkpoint's card does not match the code or its weights."""


def checkpoint_paths(path: str | Path) -> tuple[Path, Path]:
    """``(weights_path, card_path)``: ``path`` with the suffixes ``.safetensors`` and ``.json``."""
    path = Path(path)
    return path.with_suffix(".safetensors"), path.with_suffix(".json")


def read_card(path: str | Path) -> tuple[Path, Path, dict[str, Any]]:
    """``(weights_path, card_path, card)`` of the checkpoint at ``path`` (either of its two
    files; any checkpoint format of gdpt).

    The weights file's header is parsed (not its tensors), so a corrupt or truncated file is
    refused here, before any work that would need it.

    Raises:
        FileNotFoundError: one of the two files is missing.
        ValueError: the weights are not a readable safetensors file (corrupt, truncated, not
            safetensors), or the card is not a JSON object; the message names the file.
    """
    weights_path, card_path = checkpoint_paths(path)
    for p in (weights_path, card_path):
        if not p.is_file():
            raise FileNotFoundError(f"checkpoint file {p} not found (need .safetensors + .json)")
    try:
        with safe_open(str(weights_path), framework="pt"):
            pass
    except SafetensorError as error:
        raise ValueError(f"{weights_path}: not a readable safetensors file ({error})") from None
    try:
        card = json.loads(card_path.read_text())
    except (UnicodeDecodeError, ValueError) as error:
        raise ValueError(f"{card_path}: model card is not valid JSON ({error})") from None
    if not isinstance(card, dict):
        raise ValueError(f"{card_path}: model card is not a JSON object")
    return weights_path, card_path, card
