"""Writing network checkpoints (training runs, shipped models) atomically.

A checkpoint is two files, ``<path>.safetensors`` (weights) and ``<path>.json`` (model card),
encoded by its family (:attr:`gdpt.reconstruct.families.Family.encode`; a dense U-Net's by
:func:`gdpt.reconstruct.dense_unet_reconstructor.encode_checkpoint`, which
:func:`save_checkpoint` calls).
:func:`write_checkpoint` writes the weights first and the card last, each with
:func:`gdpt.io.atomic.atomic_write`, so a card on disk always describes complete weights.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from gdpt.io.atomic import atomic_write
from gdpt.reconstruct.cards import checkpoint_paths
from gdpt.reconstruct.dense_unet import DenseUNet
from gdpt.reconstruct.dense_unet_reconstructor import encode_checkpoint


def save_checkpoint(
    model: DenseUNet,
    path: str | Path,
    card: Mapping[str, Any] | None = None,
    *,
    features: Sequence[str] | None = None,
) -> tuple[Path, Path]:
    """Write ``model`` as ``<path>.safetensors`` plus the model card ``<path>.json``.

    Args:
        model: the network (any device; weights are stored as CPU float32).
        path: checkpoint path; the suffix is replaced by ``.safetensors`` / ``.json``.
        card: JSON-serialisable training information (see ``encode_checkpoint``).
        features: input buffer names in network order (default: from ``in_channels``).

    Returns:
        ``(weights_path, card_path)``.

    Raises:
        ValueError: reserved keys in ``card``, or a feature list that does not match the model.
        TypeError: ``card`` is not JSON-serialisable.
    """
    weights, text = encode_checkpoint(model, card, features=features)
    return write_checkpoint(path, weights, text)


def write_checkpoint(path: str | Path, weights: bytes, text: str) -> tuple[Path, Path]:
    """Write encoded checkpoint files: ``weights`` to ``<path>.safetensors`` first, then the
    card ``text`` to ``<path>.json``, each atomically (any family's encoder).

    Returns:
        ``(weights_path, card_path)``.
    """
    weights_path, card_path = checkpoint_paths(path)
    weights_path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(weights_path, weights)
    atomic_write(card_path, text)
    return weights_path, card_path
