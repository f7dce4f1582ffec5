"""The network families: one registry of the trainable reconstruction networks.

A *family* is a kind of network with its own checkpoint format. Each one declares, in one
:class:`Family` entry of :data:`FAMILIES`:

* its *designs* (what ``gdpt train --config`` accepts) and *losses* (``--loss``);
* how to recognise its checkpoints (the card's ``"format"``), load them, encode them again
  (the card keys it writes itself) and turn them into a reconstructor;
* whether it builds on Intel's OIDN weights, and on another checkpoint stored next to its card.

=================  ==================================  =============================================
family             designs                             checkpoint (card ``"format"``)
=================  ==================================  =============================================
``dense-unet``     :data:`.dense_unet.CONFIGS`         :data:`.dense_unet_reconstructor.CARD_FORMAT`
``oidn-finetune``  :data:`.oidn_finetune.DESIGNS`      :data:`.oidn_finetune.DELTA_FORMAT`
``combiner``       :data:`.combiner.COMBINER_DESIGNS`  :data:`.combiner.COMBINER_FORMAT`
``kpcn``           :data:`.kpcn.KPCN_DESIGNS`          :data:`.kpcn.KPCN_FORMAT`
=================  ==================================  =============================================

``dense-unet`` is NGPT's network (Kettunen et al. 2019) trained from scratch;
``oidn-finetune`` is Intel Open Image Denoise's U-Net fine-tuned with gradient inputs;
``combiner`` is a kernel-predicting network (Bako et al. 2017) over a fine-tuned OIDN network
and its L1 Poisson refinement; ``kpcn`` is KPCN itself (Bako et al. 2017), per-pixel kernels
over the path-traced radiance, reading no gradients. Every caller asks this registry
(:func:`family_of`, :func:`family_of_design`) instead of branching on formats or design
tables. How a family
*trains* (batches, validation) needs the dataset and the run directory, which live in
:mod:`gdpt.training`, so its training plans are registered there, by family name.

Only torch and safetensors are imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from torch import nn

from . import combiner, dense_unet_reconstructor, kpcn, oidn_finetune
from .cards import read_card
from .dense_unet import CONFIGS, DenseUNet
from .losses import LOSSES
from .registry import Registry

__all__ = ["FAMILIES", "Family", "family_of", "family_of_design"]

#: ``(net (CPU, eval mode), design name, card)`` of a loaded checkpoint.
Loaded = tuple[nn.Module, str, dict[str, Any]]


@dataclass(frozen=True)
class Family:
    """One network family (see the module docstring).

    Attributes:
        name: the family's name.
        description: one line for messages and reports.
        card_format: the ``"format"`` of its model cards, which recognises its checkpoints.
        former_card_formats: formats its cards had before, recognised as well.
        designs: design name -> design (``gdpt train --config``).
        losses: loss name -> the family's loss entry (``gdpt train --loss``), consumed by its
            training plan.
        load: ``path -> (net, design name, card)`` of a checkpoint (``.safetensors`` or
            ``.json``); ``net`` on the CPU in eval mode.
        encode: ``(net, design name, card) -> (safetensors bytes, card text)``; ``card`` is
            the card without :attr:`card_keys`.
        reconstructor: ``path -> f``, ``f(buffers) -> (H, W, 3)`` float32 radiance on the
            buffers' device, with ``f.features`` (buffer names read) and ``f.card``.
        card_keys: card keys that :attr:`encode` writes itself.
        oidn_weights: its networks add to Intel's OIDN weights, read from ``mitsuba-oidn`` at load
            time.
        base: ``(card_path, card) -> path`` of the checkpoint its network builds on, named by
            the card's ``"base_model"`` (a file stem next to the card), or ``None``.
    """

    name: str
    description: str
    card_format: str
    designs: Mapping[str, Any]
    losses: Mapping[str, Any]
    load: Callable[[str | Path], Loaded]
    encode: Callable[[nn.Module, str, Mapping[str, Any]], tuple[bytes, str]]
    reconstructor: Callable[[str | Path], Any]
    card_keys: tuple[str, ...]
    former_card_formats: tuple[str, ...] = ()
    oidn_weights: bool = False
    base: Callable[[Path, Mapping[str, Any]], Path | None] = lambda _path, _card: None


# ------------------------------------------------------------------------------------ families
def _load_dense(path: str | Path) -> Loaded:
    model, card = dense_unet_reconstructor.load_checkpoint(path)
    return model, model.name, card


def _encode_dense(net: nn.Module, design: str, card: Mapping[str, Any]) -> tuple[bytes, str]:
    if not isinstance(net, DenseUNet) or net.name != design:
        raise ValueError(f"a dense-unet checkpoint of {design!r} needs that DenseUNet")
    return dense_unet_reconstructor.encode_checkpoint(net, card)


def _load_delta(path: str | Path) -> Loaded:
    net, _, card = oidn_finetune.load_model(path)
    return net, card["design"], card


def _load_combiner(path: str | Path) -> Loaded:
    net, _, card, _ = combiner.load_combiner(path)
    return net, card["design"], card


def _load_kpcn(path: str | Path) -> Loaded:
    net, card = kpcn.load_kpcn(path)
    return net, card["design"], card


#: Family name -> :class:`Family`, in registration order.
FAMILIES: Registry[Family] = Registry("network family")
FAMILIES.register(
    "dense-unet",
    Family(
        name="dense-unet",
        description="NGPT's dense U-Net, trained from scratch",
        card_format=dense_unet_reconstructor.CARD_FORMAT,
        designs=CONFIGS,
        losses=LOSSES,
        load=_load_dense,
        encode=_encode_dense,
        reconstructor=dense_unet_reconstructor.DenseUNetReconstructor.from_checkpoint,
        card_keys=dense_unet_reconstructor.CARD_KEYS,
        former_card_formats=dense_unet_reconstructor.FORMER_CARD_FORMATS,
    ),
)
FAMILIES.register(
    "oidn-finetune",
    Family(
        name="oidn-finetune",
        description="OIDN's U-Net fine-tuned with extra inputs (stored as a delta)",
        card_format=oidn_finetune.DELTA_FORMAT,
        designs=oidn_finetune.DESIGNS,
        losses=oidn_finetune.FINETUNE_LOSSES,
        load=_load_delta,
        encode=oidn_finetune.encode_delta,
        reconstructor=oidn_finetune.OIDNReconstructor.from_checkpoint,
        card_keys=oidn_finetune.CARD_KEYS,
        oidn_weights=True,
    ),
)
FAMILIES.register(
    "combiner",
    Family(
        name="combiner",
        description="per-pixel kernels over a fine-tuned OIDN network and its refinement",
        card_format=combiner.COMBINER_FORMAT,
        designs=combiner.COMBINER_DESIGNS,
        losses=combiner.COMBINER_LOSSES,
        load=_load_combiner,
        encode=combiner.encode_combiner,
        reconstructor=combiner.CombinerReconstructor.from_checkpoint,
        card_keys=combiner.CARD_KEYS,
        oidn_weights=True,
        base=lambda card_path, card: card_path.parent / card["base_model"],
    ),
)


FAMILIES.register(
    "kpcn",
    Family(
        name="kpcn",
        description="KPCN: per-pixel kernels over albedo-demodulated log radiance",
        card_format=kpcn.KPCN_FORMAT,
        designs=kpcn.KPCN_DESIGNS,
        losses=kpcn.KPCN_LOSSES,
        load=_load_kpcn,
        encode=kpcn.encode_kpcn,
        reconstructor=kpcn.KPCNReconstructor.from_checkpoint,
        card_keys=kpcn.CARD_KEYS,
    ),
)


# -------------------------------------------------------------------------------------- lookup
def family_of(path: str | Path) -> Family:
    """The family of the checkpoint at ``path`` (its ``.safetensors`` or ``.json``), from the
    card's ``"format"``; nothing is loaded but the card (and the weights' header).

    Raises:
        FileNotFoundError: a file of the checkpoint is missing.
        ValueError: an unreadable card, or a format of no known family (the message names the
            card and every known family with its format).
    """
    _, card_path, card = read_card(path)
    for family in FAMILIES.values():
        if card.get("format") in (family.card_format, *family.former_card_formats):
            return family
    known = ", ".join(f"{f.name} ({f.card_format!r})" for f in FAMILIES.values())
    raise ValueError(
        f"{card_path}: format {card.get('format')!r} belongs to no known network family; "
        f"known: {known}"
    )


def family_of_design(design: str) -> Family:
    """The family with the design ``design`` (``gdpt train --config``).

    Raises:
        ValueError: no family has it (the message lists each family's designs).
    """
    for family in FAMILIES.values():
        if design in family.designs:
            return family
    known = "; ".join(f"{f.name}: {', '.join(f.designs)}" for f in FAMILIES.values())
    raise ValueError(f"unknown network design {design!r}; known designs by family: {known}")
