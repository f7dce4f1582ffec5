"""Validation of a dense U-Net during training: held-out elements with their L1-Poisson
baseline scores, and the mean relMSE and FLIP of the network over them (``val.jsonl``).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from gdpt.reconstruct.dense_unet import DenseUNet
from gdpt.reconstruct.dense_unet_reconstructor import DenseUNetReconstructor
from gdpt.reconstruct.losses import FLIPLoss
from gdpt.training.dataset import CropDataset
from gdpt.training.manifest import DatasetWarning


@dataclass
class _ValElement:
    """A validation input (``(H, W, C)`` buffers), its target and the L1-Poisson scores."""

    inputs: dict[str, torch.Tensor]
    target: torch.Tensor
    l1: dict[str, float]


def image_metrics(pred: torch.Tensor, target: torch.Tensor, flip: FLIPLoss) -> dict[str, float]:
    """relMSE (NGPT convention) and LDR-FLIP of ``(H, W, 3)`` linear images."""
    from gdpt.metrics import relmse

    nchw = (pred.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None])
    return {"relmse": relmse(pred, target), "flip": float(flip(*nchw))}


def held_out_elements(
    dataset: CropDataset, count: int, device: torch.device, renders: tuple[str, ...] = ("in",)
) -> Iterator[tuple[dict[str, torch.Tensor], torch.Tensor, dict[str, Any]]]:
    """Up to ``count`` evenly spaced elements of ``dataset``, loaded on ``device``.

    Yields ``(inputs, target, buffers)``: the network inputs (name -> ``(H, W, C)``), the
    ``(H, W, 3)`` target, and for each prefix of ``renders`` the crop's render at the element's
    level as ``GradientBuffers`` (``"in"``: the gradient-domain input; ``"pt"``: the equal-time
    path-traced input of a path-traced dataset). Unreadable elements are skipped with a warning.
    """
    from gdpt.io.exr import load_buffers

    picks = sorted({round(float(i)) for i in np.linspace(0, len(dataset) - 1, count)})
    for index in picks:
        record, level = dataset.element(index)
        try:
            item = dataset.load(index)
            buffers = {
                prefix: load_buffers(dataset.root / record["files"][f"{prefix}{level}"]).to(device)
                for prefix in renders
            }
        except (ValueError, OSError) as error:
            warnings.warn(
                f"validation element {index} skipped: {error}", DatasetWarning, stacklevel=3
            )
            continue
        inputs = {k: v.to(device) for k, v in item["inputs"].items()}
        yield inputs, item["target"].to(device), buffers


def load_validation(dataset: CropDataset, count: int, device: torch.device) -> list[_ValElement]:
    """Up to ``count`` evenly spaced elements of ``dataset`` with their L1-Poisson metrics.

    The L1 Poisson baseline (``alpha = 0.2``) reconstructs the gradient-domain input of the same
    crop and level (for a path-traced dataset: the equal-time G-PT input). Unreadable elements
    are skipped with a warning.
    """
    from gdpt.reconstruct.poisson import solve

    flip = FLIPLoss("ldr")
    elements = []
    for inputs, target, buffers in held_out_elements(dataset, count, device):
        g = buffers["in"]
        l1 = solve(g.primal, g.dx, g.dy, solver="l1", alpha=0.2)
        elements.append(_ValElement(inputs, target, image_metrics(l1, target, flip)))
    if not elements:
        raise ValueError(f"{dataset.root}: no readable validation element")
    return elements


def validate(
    model: DenseUNet, elements: list[_ValElement], features: tuple[str, ...], margin: int
) -> dict[str, float]:
    """Mean relMSE and FLIP of the network and of L1 Poisson over the validation elements."""
    reconstructor = DenseUNetReconstructor(model, features=features, tile_size=None, margin=margin)
    flip = FLIPLoss("ldr")
    totals: dict[str, float] = {}
    for element in elements:
        scores = image_metrics(reconstructor(element.inputs), element.target, flip)
        scores.update({f"l1_{k}": v for k, v in element.l1.items()})
        for key, value in scores.items():
            totals[key] = totals.get(key, 0.0) + value
    return {k: v / len(elements) for k, v in totals.items()} | {"count": len(elements)}
