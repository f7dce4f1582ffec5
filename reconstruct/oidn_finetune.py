"""NGPT on Intel Open Image Denoise's U-Net: OIDN fine-tuned with gradient inputs.

The inputs follow NGPT (Kettunen et al. 2019: the gradients as extra network inputs, their
signed-log transform of eq. 4); the network and its starting weights are OIDN's (Intel Open
Image Denoise, ``rt_hdr_alb_nrm``).

A *design* (:data:`DESIGNS`) says which inputs OIDN's U-Net (:mod:`.oidn_unet`, Intel's
``rt_hdr_alb_nrm`` weights) reads in addition to its own colour, albedo and normal, all after
OIDN's input scale ``s`` (autoexposure of the colour)::

    design          extra channels (appended with zero weights: step 0 is OIDN exactly)
    oidn-grad       sign(dx) log(1 + |s dx|), sign(dy) log(1 + |s dy|)          6  (eq. 4)
    oidn-grad-l1    the above + PU(s * L1-Poisson(primal, dx, dy)) ('l1-fast')  9
    oidn-grad-pool  as oidn-grad, trained on pooled inputs (below)              6
    oidn-grad-nbr   oidn-grad-pool + PU(s * neighbour_estimate(primal, dx, dy))  9
    oidn-nograd     none: OIDN itself fine-tuned (the no-gradient ablation)     0

A *pooled* design is trained on (and must be given) a gradient-domain render whose primal
also averages independent plain path samples, ``primal_spp_factor`` per gradient sample, and
whose features are those of the plain samples (``gdpt.render(..., primal_spp=...)``): plain
path samples cost a third to a half of a gradient sample, so at equal time the network sees a
primal of nearly the path tracer's sample count and gradients besides. The factor is the card's
``sampling.primal_spp_factor``.

:func:`assemble` builds the network input, :func:`predict` runs it and maps the output back
to radiance (OIDN's output stage); both run on the device of the buffers.

Checkpoint (delta) format: Intel's weights are read at run time from mitsuba-oidn's library (or a
``.tza`` given by the user) and never stored; a fine-tuned model is two files::

    model.safetensors   per tensor: fine-tuned minus OIDN (the extra channels' OIDN weights
                        are zero), float32
    model.json          card: {"format": DELTA_FORMAT, "design", "base_weights", "features",
                        "parameter_count", optionally "refine", ...training information...}

A card's optional ``"refine"`` entry (gradient designs only) makes :class:`OIDNReconstructor`
follow the network with the gated screened-Poisson refinement of :mod:`.refine` (its
``alpha``, ``tau``, ``window``, ``preset``).

:func:`load_model` adds the deltas to OIDN's weights (one float32 rounding per weight, about
1e-7 relative); it fails with :class:`~.tza.OIDNWeightsError` (which says how to pass a
``.tza``) when the base weights cannot be read.

The fine-tuning losses are :data:`FINETUNE_LOSSES` (weights of :func:`finetune_loss`). The
designs, losses and checkpoint format form the ``oidn-finetune`` family of :mod:`.families`.

Only torch, numpy and safetensors are imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save

from .autograd import records
from .cards import read_card
from .losses import forward_differences
from .oidn_unet import OIDNUNet, autoexposure, decode_output, encode_inputs, pu_forward
from .refine import GatedRefinement
from .registry import Registry

__all__ = [
    "CARD_KEYS",
    "DELTA_FORMAT",
    "DESIGNS",
    "FINETUNE_LOSSES",
    "Design",
    "OIDNReconstructor",
    "assemble",
    "base_model",
    "encode_delta",
    "finetune_loss",
    "load_model",
    "neighbour_estimate",
    "predict",
    "signed_log",
]

#: ``"format"`` of the model card of a delta checkpoint.
DELTA_FORMAT = "gdpt-oidn-delta/1"
#: OIDN's weights the designs start from (HDR colour + albedo + normal; OIDN's ``high`` quality
#: uses these too, there is no ``_large`` variant of them).
BASE_WEIGHTS = "rt_hdr_alb_nrm"
#: Card keys written by :func:`encode_delta` (the rest of a card is training information).
CARD_KEYS = ("format", "design", "description", "base_weights", "features", "parameter_count")


@dataclass(frozen=True)
class Design:
    """Inputs of one fine-tuned OIDN network.

    Attributes:
        gradients: reads ``dx`` and ``dy`` (6 extra channels).
        l1: also reads the L1 Poisson solution of ``primal, dx, dy`` (3 more; needs gradients).
        description: one line for cards and reports.
        pooled: trained on gradient-domain renders with plain path samples pooled into the
            primal, the features from those samples (needs gradients; see the module
            docstring).
        neighbours: also reads :func:`neighbour_estimate` (3 more; needs gradients).
    """

    gradients: bool
    l1: bool
    description: str
    pooled: bool = False
    neighbours: bool = False

    @property
    def input_kind(self) -> str:
        """The training input (``gdpt.training.dataset.INPUT_KINDS``): ``"pool"``, ``"gdpt"``
        or ``"pt"``."""
        return "pool" if self.pooled else "gdpt" if self.gradients else "pt"

    @property
    def extra_channels(self) -> int:
        """Extra input channels after OIDN's 9."""
        return 6 * self.gradients + 3 * self.l1 + 3 * self.neighbours

    @property
    def features(self) -> tuple[str, ...]:
        """Buffers read, in order."""
        return ("primal", "albedo", "normal") + (("dx", "dy") if self.gradients else ())


#: Design name -> :class:`Design`.
DESIGNS: Registry[Design] = Registry("OIDN fine-tuning design")
DESIGNS.register(
    "oidn-grad", Design(True, False, "OIDN U-Net + signed-log dx/dy inputs, fine-tuned")
)
DESIGNS.register(
    "oidn-grad-l1",
    Design(True, True, "OIDN U-Net + signed-log dx/dy + PU(L1 Poisson) inputs, fine-tuned"),
)
DESIGNS.register(
    "oidn-grad-pool",
    Design(
        True,
        False,
        "OIDN U-Net + signed-log dx/dy inputs, fine-tuned on primals pooled with plain path "
        "samples",
        pooled=True,
    ),
)
DESIGNS.register(
    "oidn-grad-nbr",
    Design(
        True,
        False,
        "OIDN U-Net + signed-log dx/dy + PU(neighbour estimate) inputs, fine-tuned on pooled "
        "primals",
        pooled=True,
        neighbours=True,
    ),
)
DESIGNS.register("oidn-nograd", Design(False, False, "OIDN U-Net fine-tuned, no gradient inputs"))


def signed_log(x: torch.Tensor) -> torch.Tensor:
    """``sign(x) log(1 + |x|)`` (NGPT's gradient transform, eq. 4); same shape/device."""
    return torch.sign(x) * torch.log1p(x.abs())


def neighbour_estimate(primal: torch.Tensor, dx: torch.Tensor, dy: torch.Tensor) -> torch.Tensor:
    """Each pixel predicted from its four neighbours and the gradients between them.

    ``mean(I[y, x-1] + dx[y, x-1], I[y, x+1] - dx[y, x], I[y-1, x] + dy[y-1, x],
    I[y+1, x] - dy[y, x])`` over the neighbours inside the image (forward differences:
    ``dx[y, x] = I[y, x+1] - I[y, x]``). It leaves out the pixel's own primal sample: where the
    shifts succeed it is a second estimate of the pixel with the gradients' low variance, and
    its difference from the primal marks primal noise (a firefly has no support from its
    neighbours). Linear in the inputs, so a network reading PU-encoded colour and signed-log
    gradients separately gets this relation explicitly.

    Args:
        primal, dx, dy: ``(H, W, C)`` float tensors on one device.

    Returns:
        ``(H, W, C)`` tensor like ``primal``; a 1x1 image returns ``primal``.
    """
    total = torch.zeros_like(primal)
    count = torch.zeros_like(primal[..., :1])
    total[:, 1:] += primal[:, :-1] + dx[:, :-1]
    total[:, :-1] += primal[:, 1:] - dx[:, :-1]
    total[1:] += primal[:-1] + dy[:-1]
    total[:-1] += primal[1:] - dy[:-1]
    count[:, 1:] += 1
    count[:, :-1] += 1
    count[1:] += 1
    count[:-1] += 1
    return torch.where(count > 0, total / count.clamp_min(1), primal)


def _finite(x: torch.Tensor) -> torch.Tensor:
    return torch.nan_to_num(x.float(), nan=0.0, posinf=0.0, neginf=0.0)


def assemble(
    buffers: Mapping[str, torch.Tensor], design: Design, *, l1: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Network input of one image.

    Args:
        buffers: name -> ``(H, W, 3)`` float tensor for every name in ``design.features``
            (``primal``, ``albedo``, ``normal`` in [-1, 1], ``dx``, ``dy``), one device.
            Non-finite values are treated as 0.
        design: the inputs to build.
        l1: ``(H, W, 3)`` L1 Poisson solution for ``design.l1`` (``None``: solved here with
            ``'l1-fast'``, ``alpha = 0.2``).

    Returns:
        ``(x, scale)``: ``(1, 9 + extra, H16, W16)`` float32 (zero-padded to multiples of 16)
        and OIDN's input scale (0-d), on the buffers' device.

    Raises:
        KeyError: a buffer the design reads is missing (all missing ones are named).
    """
    missing = [n for n in design.features if buffers.get(n) is None]
    if missing:
        raise KeyError(
            f"the buffers lack {', '.join(missing)}, which this model reads "
            f"({design.description}); render them (gdpt properties gradients/features)"
        )
    primal = _finite(buffers["primal"])
    scale = autoexposure(primal)
    extra = None
    if design.gradients:
        dx, dy = _finite(buffers["dx"]), _finite(buffers["dy"])
        parts = [signed_log(scale * dx), signed_log(scale * dy)]
        if design.l1:
            if l1 is None:
                from .poisson import solve  # noqa: PLC0415 (only this design solves)

                l1 = solve(primal, dx, dy, solver="l1-fast", alpha=0.2)
            parts.append(pu_forward((scale * _finite(l1)).clamp_min(0.0)))
        if design.neighbours:
            parts.append(pu_forward((scale * neighbour_estimate(primal, dx, dy)).clamp_min(0.0)))
        extra = torch.cat(parts, -1)
    albedo, normal = _finite(buffers["albedo"]), _finite(buffers["normal"])
    return encode_inputs(primal, albedo, normal, input_scale=scale, extra=extra)


def predict(net: OIDNUNet, x: torch.Tensor, height: int, width: int, scale: torch.Tensor):
    """Run ``net`` on an :func:`assemble` input; ``(height, width, 3)`` float32 radiance
    (finite, >= 0) on ``x``'s device."""
    return decode_output(net(x), height, width, scale)


def base_model(design: Design, *, weights: str | Path | dict = BASE_WEIGHTS) -> OIDNUNet:
    """OIDN's U-Net with Intel's weights and the design's zero-weight extra inputs (CPU,
    eval mode); its output equals OIDN's."""
    return OIDNUNet.from_weights(weights, extra_channels=design.extra_channels)


def parameter_count(net: torch.nn.Module) -> int:
    """Number of trainable scalars."""
    return sum(p.numel() for p in net.parameters())


def encode_delta(
    net: OIDNUNet,
    design_name: str,
    card: Mapping[str, Any] | None = None,
    *,
    base: OIDNUNet | None = None,
) -> tuple[bytes, str]:
    """The two files of a delta checkpoint (see the module docstring).

    Args:
        net: the fine-tuned network (any device).
        design_name: a key of :data:`DESIGNS`.
        card: JSON-serialisable training information (``"training"``, ``"steps"``,
            ``"validation"``, ...).
        base: OIDN's network with the same design (default: :func:`base_model`).

    Returns:
        ``(weights, card_text)``: ``.safetensors`` bytes and ``.json`` text.
    """
    design = DESIGNS[design_name]
    base = base if base is not None else base_model(design)
    ref = {k: v.detach().cpu() for k, v in base.state_dict().items()}
    state = {
        k: (v.detach().to("cpu", torch.float32) - ref[k]).contiguous()
        for k, v in net.state_dict().items()
    }
    full = {
        "format": DELTA_FORMAT,
        "design": design_name,
        "description": design.description,
        "base_weights": BASE_WEIGHTS,
        "features": list(design.features),
        "parameter_count": parameter_count(net),
        **dict(card or {}),
    }
    weights = save(state, metadata={"format": DELTA_FORMAT, "design": design_name})
    return weights, json.dumps(full, indent=2) + "\n"


def load_model(
    path: str | Path, *, weights: str | Path | dict | None = None
) -> tuple[OIDNUNet, Design, dict[str, Any]]:
    """Rebuild a fine-tuned network from a delta checkpoint.

    Args:
        path: the ``.safetensors`` or ``.json`` path.
        weights: OIDN's base weights (default: the card's ``base_weights`` from mitsuba-oidn's
            library; or a ``.tza`` path / state dict).

    Returns:
        ``(net, design, card)``, ``net`` on the CPU in eval mode.

    Raises:
        FileNotFoundError: a file is missing.
        ValueError: not a delta card, or the stored tensors do not fit the design.
        reconstruct.tza.OIDNWeightsError: OIDN's weights cannot be read.
    """
    weights_path, card_path, card = read_card(path)
    if card.get("format") != DELTA_FORMAT:
        raise ValueError(f"{card_path}: format {card.get('format')!r}, expected {DELTA_FORMAT!r}")
    design = DESIGNS[card["design"]]
    net = base_model(design, weights=weights or card.get("base_weights", BASE_WEIGHTS))
    delta = load_file(str(weights_path))
    state = net.state_dict()
    bad = sorted(set(state) ^ set(delta)) + [
        k for k in state if k in delta and delta[k].shape != state[k].shape
    ]
    if bad:
        raise ValueError(f"{weights_path} does not fit design {card['design']!r}: {bad[:6]}")
    net.load_state_dict({k: state[k] + delta[k] for k in state})
    return net.eval(), design, card


class OIDNReconstructor:
    """Apply a fine-tuned OIDN network (and the card's refinement, if any) to a render's
    buffers, on the buffers' device.

    Args:
        net: the network (weights copied to each device on first use).
        design: its inputs.
        card: the model card, kept as :attr:`card`; its ``"refine"`` entry, if present, is the
            :class:`~.refine.GatedRefinement` applied after the network (:attr:`refine`).

    Raises:
        ValueError: a refinement on a design without gradients, or bad refinement settings.
    """

    def __init__(self, net: OIDNUNet, design: Design, card: Mapping[str, Any] | None = None):
        self.design = design
        self.features = design.features
        self.card = dict(card or {})
        refine = self.card.get("refine")
        if refine is not None and not design.gradients:
            raise ValueError(f"a refinement needs gradients; {design.description} reads none")
        self.refine = GatedRefinement.from_dict(refine) if refine is not None else None
        self._net = net.eval()
        self._per_device: dict[torch.device, OIDNUNet] = {}

    @property
    def net(self) -> OIDNUNet:
        """The network as given (eval mode; the per-device copies are made from it)."""
        return self._net

    @classmethod
    def from_checkpoint(cls, path: str | Path) -> OIDNReconstructor:
        """Load with :func:`load_model`."""
        net, design, card = load_model(path)
        return cls(net, design, card)

    def _net_on(self, device: torch.device) -> OIDNUNet:
        if device not in self._per_device:
            import copy  # noqa: PLC0415

            with torch.inference_mode(False):  # usable later with autograd too
                net = copy.deepcopy(self._net).to(device).requires_grad_(False)
                # channels-last: about 1.6x faster convolutions on CPU (oneDNN), same results
                self._per_device[device] = net.to(memory_format=torch.channels_last)
        return self._per_device[device]

    def __call__(self, buffers: Mapping[str, torch.Tensor] | Any) -> torch.Tensor:
        """Reconstruct one image.

        Runs under ``torch.inference_mode`` unless autograd records a buffer the model reads;
        then the result is differentiable w.r.t. those buffers (the weights are frozen; the
        refinement's L1 solve differentiates through its last IRLS weights,
        :func:`~.poisson.solve_l1`).

        Args:
            buffers: name -> ``(H, W, 3)`` tensor for :attr:`features`, or an object with
                them as attributes (``gdpt.buffers.GradientBuffers``).

        Returns:
            ``(H, W, 3)`` float32 radiance (finite, >= 0) on the buffers' device: the network's
            output, refined with the gradients when the card has a ``"refine"`` entry.

        Raises:
            KeyError: a buffer the model reads is missing (named).
        """
        if not isinstance(buffers, Mapping):
            buffers = {n: getattr(buffers, n, None) for n in self.features}
        with torch.inference_mode(not records(buffers.get(n) for n in self.features)):
            return self._reconstruct(buffers)

    def _reconstruct(self, buffers: Mapping[str, torch.Tensor]) -> torch.Tensor:
        x, scale = assemble(buffers, self.design)
        h, w = buffers["primal"].shape[:2]
        x = x.contiguous(memory_format=torch.channels_last)
        out = predict(self._net_on(x.device), x, h, w, scale).contiguous()
        if self.refine is not None:
            out = self.refine(out, buffers["dx"], buffers["dy"])
        return out


def finetune_loss(
    y: torch.Tensor,
    target: torch.Tensor,
    scale: torch.Tensor,
    *,
    relative: float = 1.0,
    gradient: float = 0.0,
    eps: float = 1e-2,
) -> torch.Tensor:
    """Fine-tuning loss: L1 in OIDN's PU space plus a relative MSE that tolerates target noise
    and an L1 on the image's forward differences.

    ``mean |y - PU(s t)| + relative * mean (p - t)^2 / (eps + mean_c(p)^2)
    + gradient * (mean |Dx y - Dx PU(s t)| + mean |Dy y - Dy PU(s t)|)`` with ``p`` the decoded
    prediction (``PU^-1(clamp(y, 0, 1)) / s``), its denominator detached: the relative MSE of
    Noise2Noise (Lehtinen et al. 2018), whose minimiser is the target's expectation, so
    path-traced targets with zero-mean noise give an unbiased fit; the PU-L1 term is OIDN's own;
    the difference term is NGPT's L1 on the result's gradients (Kettunen et al. 2019, sec.
    3.2.3), here in PU space, which rewards edges that only the gradient inputs can place.

    Args:
        y: ``(N, 3, H, W)`` raw network output.
        target: ``(N, 3, H, W)`` linear HDR target, same device.
        scale: ``(N,)`` OIDN input scales of the samples.
        relative: weight of the relative-MSE term (0: OIDN's PU-L1 alone).
        gradient: weight of the forward-difference term (0: none).
        eps: denominator offset of the relative term.

    Returns:
        Scalar tensor.
    """
    from .oidn_unet import pu_inverse  # noqa: PLC0415

    s = scale.reshape(-1, 1, 1, 1)
    pu_target = pu_forward((s * target).clamp_min(0.0))
    pred = pu_inverse(y.clamp(0.0, 1.0)) / s
    denominator = eps + pred.detach().mean(1, keepdim=True).square()
    loss = (y - pu_target).abs().mean()
    if gradient:
        pairs = zip(forward_differences(y), forward_differences(pu_target), strict=True)
        for d_y, d_target in pairs:
            loss = loss + gradient * (d_y - d_target).abs().mean()
    if not relative:
        return loss
    return loss + relative * ((pred - target).square() / denominator).mean()


#: Fine-tuning loss name (``gdpt train --loss``) -> keyword weights of :func:`finetune_loss`
#: (its PU-L1 term always counts): ``l1`` is OIDN's own L1 in its PU space, ``l1_rel`` adds the
#: Noise2Noise relative MSE, ``l1_grad`` the L1 on the PU image's forward differences.
FINETUNE_LOSSES: Registry[dict[str, float]] = Registry("fine-tuning loss")
FINETUNE_LOSSES.register("l1", {"relative": 0.0})
FINETUNE_LOSSES.register("l1_rel", {"relative": 1.0})
FINETUNE_LOSSES.register("l1_grad", {"relative": 0.0, "gradient": 1.0})
