"""The dense U-Net's checkpoints (safetensors + JSON model card) and its tiled reconstructor.

A checkpoint is two files next to each other (:mod:`.cards`)::

    model.safetensors   the DenseUNet state dict (float32)
    model.json          the model card: {"format", "config_name", "config", "features",
                        "parameter_count", ...free-form training information...}

The free-form part of the card is whatever the trainer passes to :func:`encode_checkpoint`; the
expected keys are ``"training"`` (data description), ``"steps"`` and ``"validation"``
(metric name -> value). :func:`load_checkpoint` rebuilds the network from the card's config and
fails with a readable message (not a shape traceback) when the card disagrees with the code's
registered configuration of the same name, or with the stored weights. Cards with a
:data:`FORMER_CARD_FORMATS` format are read like current ones.

:class:`DenseUNetReconstructor` turns a buffer dict into the reconstruction::

    rec = DenseUNetReconstructor.from_checkpoint("runs/00007-paper/model.safetensors")
    image = rec({"primal": p, "dx": dx, "dy": dy, "albedo": a, "normal": n, "depth": d})

The dense U-Net's configurations, losses and this checkpoint format form the ``dense-unet``
family of :mod:`.families`.

Layout, dtype, device: HWC float tensors as in ``gdpt.buffers``; the network runs on the device
of the input buffers (the weights are copied there on first use) in channels-last memory format
under ``torch.inference_mode``, unless autograd records an input buffer: then the result is
differentiable w.r.t. the buffers (not the weights, which are frozen). Only torch, safetensors
and the standard library are imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

import copy
import dataclasses
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save

from .autograd import records
from .cards import CheckpointMismatchError, read_card
from .dense_unet import CONFIGS, DenseUNet, ModelConfig, parameter_count
from .transforms import (
    FEATURE_CHANNELS,
    FEATURES_WITH_GRADIENTS,
    FEATURES_WITHOUT_GRADIENTS,
    OUTPUT_TRANSFORM,
    crop,
    pad_buffers,
    padding_for,
    stack_input,
    transform_buffers,
)

#: Value of the card's ``"format"`` key written by this version.
CARD_FORMAT = "gdpt-dense-unet-checkpoint/1"
#: Former values of the card's ``"format"`` key, still read (cards written by gdpt 0.1).
FORMER_CARD_FORMATS = ("gdpt-ngpt-checkpoint/1",)
#: Card keys written by :func:`encode_checkpoint` (the rest of a card is training information).
CARD_KEYS = ("format", "config_name", "config", "features", "parameter_count")


def default_features(in_channels: int) -> tuple[str, ...]:
    """Feature names for a network with ``in_channels`` inputs (16: with gradients, 10: without).

    Raises:
        ValueError: no standard feature set has that many channels.
    """
    for features in (FEATURES_WITH_GRADIENTS, FEATURES_WITHOUT_GRADIENTS):
        if sum(FEATURE_CHANNELS[f] for f in features) == in_channels:
            return features
    raise ValueError(f"no standard feature set has {in_channels} channels; pass features=")


def encode_checkpoint(
    model: DenseUNet,
    card: Mapping[str, Any] | None = None,
    *,
    features: Sequence[str] | None = None,
) -> tuple[bytes, str]:
    """The two files of a checkpoint: safetensors weights and the JSON model card.

    Writing them is the caller's job (:func:`gdpt.training.checkpoint.save_checkpoint` writes
    them atomically); :func:`load_checkpoint` reads them back.

    Args:
        model: the network (any device; weights are stored as CPU float32).
        card: JSON-serialisable training information (``"training"``, ``"steps"``,
            ``"validation"``, ...); must not use the reserved keys ``format``, ``config_name``,
            ``config``, ``features``, ``parameter_count``.
        features: input buffer names in network order (default: from ``in_channels``).

    Returns:
        ``(weights, card_text)``: the ``.safetensors`` bytes and the ``.json`` text.

    Raises:
        ValueError: reserved keys in ``card``, or a feature list that does not match the model.
        TypeError: ``card`` is not JSON-serialisable.
    """
    card = dict(card or {})
    clash = sorted(set(card) & set(CARD_KEYS))
    if clash:
        raise ValueError(f"card keys {clash} are reserved (written by encode_checkpoint)")
    features = tuple(features or default_features(model.config.in_channels))
    if sum(FEATURE_CHANNELS[f] for f in features) != model.config.in_channels:
        raise ValueError(
            f"features {features} do not add up to {model.config.in_channels} input channels"
        )
    full = {
        "format": CARD_FORMAT,
        "config_name": model.name,
        "config": model.config.to_dict(),
        "features": list(features),
        "parameter_count": parameter_count(model),
        **card,
    }
    text = json.dumps(full, indent=2)
    state = {
        k: v.detach().to("cpu", torch.float32).contiguous() for k, v in model.state_dict().items()
    }
    weights = save(state, metadata={"format": CARD_FORMAT, "config_name": str(model.name)})
    return weights, text + "\n"


def _config_diff(a: ModelConfig, b: ModelConfig) -> list[str]:
    return [
        f"{f.name}: card {getattr(a, f.name)!r} vs code {getattr(b, f.name)!r}"
        for f in dataclasses.fields(ModelConfig)
        if getattr(a, f.name) != getattr(b, f.name)
    ]


def load_checkpoint(
    path: str | Path, *, device: torch.device | str = "cpu"
) -> tuple[DenseUNet, dict[str, Any]]:
    """Rebuild a network saved by :func:`encode_checkpoint`.

    Args:
        path: the ``.safetensors`` or ``.json`` path (either; the other is found next to it).
        device: where to put the weights.

    Returns:
        ``(model, card)`` with ``model`` in eval mode.

    Raises:
        FileNotFoundError: one of the two files is missing.
        CheckpointMismatchError: unknown card format, a config that differs from the code's
            registered config of the same name, or weights whose names/shapes do not match
            the card's config.
    """
    weights_path, card_path, card = read_card(path)
    if card.get("format") not in (CARD_FORMAT, *FORMER_CARD_FORMATS):
        raise CheckpointMismatchError(
            f"{card_path}: format {card.get('format')!r}, this code reads {CARD_FORMAT!r}"
        )
    try:
        config = ModelConfig.from_dict(card["config"])
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointMismatchError(f"{card_path}: invalid model config: {err}") from err
    name = card.get("config_name")
    if name in CONFIGS and CONFIGS[name] != config:
        diff = "; ".join(_config_diff(config, CONFIGS[name]))
        raise CheckpointMismatchError(
            f"{card_path}: config {name!r} in the card differs from the code's {name!r}: {diff}"
        )
    model = DenseUNet(config, name=name)
    state = load_file(str(weights_path), device=str(device))
    expected = model.state_dict()
    problems = [f"missing {k}" for k in expected if k not in state]
    problems += [f"unexpected {k}" for k in state if k not in expected]
    problems += [
        f"{k}: stored {tuple(state[k].shape)} vs config {tuple(v.shape)}"
        for k, v in expected.items()
        if k in state and state[k].shape != v.shape
    ]
    if problems:
        shown = "; ".join(problems[:6]) + (
            f" (+{len(problems) - 6} more)" if len(problems) > 6 else ""
        )
        raise CheckpointMismatchError(
            f"{weights_path} does not match the config in {card_path.name}: {shown}"
        )
    model.load_state_dict(state)
    return model.to(device).eval(), card


def _as_mapping(buffers: Any, names: Sequence[str]) -> Mapping[str, torch.Tensor]:
    """Accept a mapping or an object with the buffers as attributes (``GradientBuffers``)."""
    if isinstance(buffers, Mapping):
        return buffers
    return {n: getattr(buffers, n) for n in names if getattr(buffers, n, None) is not None}


class DenseUNetReconstructor:
    """Apply a dense U-Net to gradient-domain buffers, tiled, on the inputs' device.

    The input is transformed (:mod:`~gdpt.reconstruct.transforms`), mirror-padded by ``margin``
    and up to the network alignment, cut into tiles of ``tile_size`` output pixels that overlap
    by the receptive radius rounded up to the alignment (so tiling does not change the result
    beyond float rounding), run through the network, mapped back with ``exp(y) - 1``, clamped to
    ``>= 0`` (radiance; residual networks can undershoot ``y = 0`` in dark regions) and
    cropped. The weights are snapshotted (with weight normalisation folded) at construction.

    Args:
        model: the network.
        features: input buffer names in network order (default: from ``in_channels``).
        tile_size: output pixels per tile side (rounded up to the alignment); ``None`` = untiled.
        margin: mirror padding added on every side before alignment (8 in the reference).
        card: the checkpoint's model card, kept as :attr:`card`.
    """

    def __init__(
        self,
        model: DenseUNet,
        *,
        features: Sequence[str] | None = None,
        tile_size: int | None = 512,
        margin: int = 8,
        card: Mapping[str, Any] | None = None,
    ) -> None:
        self.features = tuple(features or default_features(model.config.in_channels))
        if sum(FEATURE_CHANNELS[f] for f in self.features) != model.config.in_channels:
            raise ValueError(
                f"features {self.features} do not match the model's "
                f"{model.config.in_channels} input channels"
            )
        self.alignment = model.alignment
        self.overlap = -(-model.receptive_radius // self.alignment) * self.alignment
        self.tile_size = (
            None if tile_size is None else -(-tile_size // self.alignment) * self.alignment
        )
        self.margin = margin
        self.card = dict(card or {})
        self._model = (
            model.fuse().eval().requires_grad_(False).to(memory_format=torch.channels_last)
        )
        self._per_device: dict[torch.device, DenseUNet] = {}

    @classmethod
    def from_checkpoint(cls, path: str | Path, **kwargs: Any) -> DenseUNetReconstructor:
        """Load with :func:`load_checkpoint`; ``kwargs`` go to the constructor.

        The card's ``features`` are used unless ``features`` is given.
        """
        model, card = load_checkpoint(path)
        kwargs.setdefault("features", card.get("features"))
        return cls(model, card=card, **kwargs)

    def _model_on(self, device: torch.device) -> DenseUNet:
        if device not in self._per_device:
            home = next(self._model.parameters()).device
            on_device = self._model if device == home else copy.deepcopy(self._model).to(device)
            self._per_device[device] = on_device
        return self._per_device[device]

    def __call__(self, buffers: Mapping[str, torch.Tensor] | Any) -> torch.Tensor:
        """Reconstruct one image (or a batch).

        Args:
            buffers: name -> ``(H, W, C)`` (or ``(N, H, W, C)``) float tensor for every name in
                :attr:`features`, all on one device; or an object with those attributes
                (``gdpt.buffers.GradientBuffers``). Non-finite values are treated as 0.

        Returns:
            ``(H, W, 3)`` (or ``(N, H, W, 3)``) float32 radiance on the buffers' device;
            differentiable w.r.t. the buffers that require gradients (in gradient mode).

        Raises:
            KeyError: feature buffers missing (all are named).
            ValueError: wrong channel counts or mismatched sizes/devices.
        """
        buffers = _as_mapping(buffers, self.features)
        with torch.inference_mode(not records(buffers.get(n) for n in self.features)):
            return self._reconstruct(buffers)

    def _reconstruct(self, buffers: Mapping[str, torch.Tensor]) -> torch.Tensor:
        inputs = transform_buffers(buffers, self.features)
        first = inputs[self.features[0]]
        devices = {t.device for t in inputs.values()}
        if len(devices) > 1:
            raise ValueError(f"feature buffers are on several devices: {sorted(map(str, devices))}")
        h, w = first.shape[-3], first.shape[-2]
        padding = padding_for(h, w, self.alignment, self.margin)
        x = stack_input(pad_buffers(inputs, padding), self.features)
        x = x.contiguous(memory_format=torch.channels_last)
        y = self._run_tiled(self._model_on(first.device), x)
        out = crop(OUTPUT_TRANSFORM.inverse(y).clamp_min(0).permute(0, 2, 3, 1), padding)
        out = out.float().contiguous()
        return out[0] if first.dim() == 3 else out

    def tiles(
        self, height: int, width: int
    ) -> list[tuple[tuple[int, int, int, int], tuple[int, int, int, int]]]:
        """Tiles for a padded network input of ``height x width`` (multiples of alignment).

        Returns:
            ``[(interior, window), ...]`` as ``(y0, y1, x0, x1)`` boxes: the network runs on
            ``window`` and its output is kept on ``interior``; interiors partition the image.
        """
        t, o = self.tile_size, self.overlap
        if t is None or (height <= t and width <= t):
            return [((0, height, 0, width), (0, height, 0, width))]
        boxes = []
        for y0 in range(0, height, t):
            y1 = min(y0 + t, height)
            for x0 in range(0, width, t):
                x1 = min(x0 + t, width)
                window = (max(0, y0 - o), min(height, y1 + o), max(0, x0 - o), min(width, x1 + o))
                boxes.append(((y0, y1, x0, x1), window))
        return boxes

    def _run_tiled(self, model: DenseUNet, x: torch.Tensor) -> torch.Tensor:
        """``(N, C, H, W) -> (N, 3, H, W)`` over the aligned, overlapping :meth:`tiles`."""
        n, _, h, w = x.shape
        boxes = self.tiles(h, w)
        if len(boxes) == 1:
            return model(x)
        out = x.new_empty((n, model.config.out_channels, h, w))
        for (y0, y1, x0, x1), (wy0, wy1, wx0, wx1) in boxes:
            tile = model(x[:, :, wy0:wy1, wx0:wx1])
            out[:, :, y0:y1, x0:x1] = tile[:, :, y0 - wy0 : y1 - wy0, x0 - wx0 : x1 - wx0]
        return out
