"""The configuration of a training run (:class:`TrainConfig`) and the rule for resuming a run
with another one (:func:`check_resume`).

``config.json`` of a run directory (:mod:`gdpt.training.run_dir`) stores the resolved
:class:`TrainConfig`; resuming with different training-relevant settings raises
:class:`ConfigMismatchError`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

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

#: Dataset inputs a fine-tuned OIDN design without gradients may train on
#: (:attr:`TrainConfig.input`).
FINETUNE_INPUTS = ("pt", "gdpt", "pool")


class ConfigMismatchError(ValueError):
    """A run directory is resumed with settings that change the training."""


def require_positive(config: Any, names: tuple[str, ...]) -> None:
    """Raise ``ValueError`` naming the first of ``names`` whose value on ``config`` is < 1."""
    for name in names:
        if getattr(config, name) < 1:
            raise ValueError(f"{name} must be >= 1, got {getattr(config, name)}")


@dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a training run.

    Attributes:
        model: a design of a network family (:data:`gdpt.reconstruct.families.FAMILIES`): a
            dense U-Net configuration (``fast_xs``, ``paper``, ...; 16 input channels read the
            ``gdpt`` inputs, 10-channel ones the path-traced), a fine-tuned OIDN design
            (``oidn-grad``, ...; ``pad`` and ``vary_padding`` do not apply), a combiner
            design (``combiner-grad``, ``combiner-nograd``; trained on top of
            ``base_model``) or a KPCN design (``kpcn``, ``kpcn-paper``; ``pad`` and
            ``vary_padding`` do not apply).
        data: training dataset directory (:mod:`gdpt.training.dataset`).
        out: run directory.
        val_data: validation dataset directory; ``None`` holds out every ``holdout_every``-th
            scene of ``data`` (scene index ``% holdout_every == holdout_every - 1``).
        holdout_every: see ``val_data``.
        loss: a loss of the design's family (its ``losses``): for a dense U-Net ``flip``,
            ``flip_rel``, ``flip_log``, ``flip_hdr``, ``l1`` or ``elpips``
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
        base_model: a fine-tuned OIDN checkpoint (``.safetensors``): the frozen base network
            of a combiner design, or the start of a fine-tuned OIDN design (the same design;
            ``None``: Intel's weights); unused by the other models.
        input: the dataset input of a fine-tuned OIDN design without gradients (``None``:
            the design's, the path-traced ``pt``): ``gdpt`` trains on the primal and features
            of the G-PT input ``in<k>`` (rendered with ``gdpt dataset --primal``), ``pool`` on
            that primal pooled with ``pt<k>``.
        extra_lr_scale: learning-rate multiplier for the weights that read a fine-tuned OIDN
            design's extra input channels (zero at step 0; at OIDN's small fine-tuning rate they
            stay two orders of magnitude below the colour weights); 1 elsewhere.
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
    base_model: str | None = None
    input: str | None = None
    extra_lr_scale: float = 1.0

    def __post_init__(self) -> None:
        if not self.data or not self.out:
            raise ValueError("TrainConfig needs data= and out= directories")
        require_positive(
            self, ("steps", "batch", "holdout_every", "val_crops", "ckpt_every", "keep_checkpoints")
        )
        if self.val_every < 0 or self.pad < 0 or not 0 <= self.vary_padding <= self.pad:
            raise ValueError("need val_every >= 0 and 0 <= vary_padding <= pad")
        if not self.extra_lr_scale > 0:
            raise ValueError(f"extra_lr_scale must be > 0, got {self.extra_lr_scale}")
        if self.input not in (None, *FINETUNE_INPUTS):
            raise ValueError(f"input must be one of {FINETUNE_INPUTS}, got {self.input!r}")
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
