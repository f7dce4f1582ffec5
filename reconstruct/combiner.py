"""Kernel-predicting combiner over candidate reconstructions.

A small U-Net reads the candidates and the primal (each PU-encoded after OIDN's input scale
``s``), albedo,
normal and, for the gradient design, the signed-log gradients (eq. 4 of Kettunen et al. 2019),
and predicts at every pixel one softmax over ``K`` candidates x ``k x k`` neighbourhood taps. The
output is that convex combination of the candidates' neighbourhoods in OIDN's PU encoding
``u = PU(s x)`` (perceptual, log-like), decoded back to radiance::

    out[p] = PU^-1( sum_{c, t} w[p, c, t] * u_c[p + t] ) / s,   w >= 0,  sum_{c, t} w[p, c, t] = 1

It is the kernel prediction of KPCN (Bako et al. 2017; :func:`.kernels.apply_kernels`) applied
across candidates, which is what the NGPT paper's conclusion lists as future work for
gradient-domain reconstruction. PU is
monotone, so every output pixel lies within the range of the candidate values it mixes (no new
fireflies, no negative radiance); mixing encoded values rather than radiance keeps a light
source from bleeding into its dark neighbours (KPCN filters its specular buffer in log space
for the same reason): a 1% weight on a neighbour 1000x brighter would otherwise add 10x.

Designs (:data:`COMBINER_DESIGNS`)::

    design            candidates                                       gradient inputs
    combiner-grad     base(G-PT), L1-Poisson(base, dx, dy)             yes
    combiner-nograd   base(PT)                                         no

``base`` is a fine-tuned OIDN network (:mod:`.oidn_finetune`) applied to the same buffers; the L1
candidate is screened Poisson L1 (:mod:`.poisson`, preset ``fast``) with the base network's
image as its data term, so the gradients correct what the denoiser blurred. The noisy primal is
not a candidate: a weight of 1e-3 on a firefly is already a visible error. The ``nograd``
combiner, with the base network as its only candidate, is a learned per-pixel filter.

Checkpoint: ``model.safetensors`` (the combiner's own weights, float32) and ``model.json``
(card: ``{"format": COMBINER_FORMAT, "design", "base_model": file name of the base network's
delta checkpoint next to the card, "kernel", "widths", ...training information...}``).

Training loss: :func:`combiner_loss`, chosen by name from :data:`COMBINER_LOSSES`. The designs,
losses and checkpoint format form the ``combiner`` family of :mod:`.families`.

Only torch and safetensors are imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save
from torch import nn
from torch.nn import functional as F

from .cards import read_card
from .kernels import apply_kernels
from .oidn_finetune import OIDNReconstructor, signed_log
from .oidn_unet import autoexposure, pu_forward, pu_inverse
from .refine import GatedRefinement
from .registry import Registry

__all__ = [
    "CARD_KEYS",
    "COMBINER_DESIGNS",
    "COMBINER_FORMAT",
    "COMBINER_LOSSES",
    "CombinerDesign",
    "CombinerNet",
    "CombinerReconstructor",
    "candidates",
    "combine",
    "combiner_input",
    "combiner_loss",
    "encode_combiner",
    "load_combiner",
]

#: ``"format"`` of a combiner's model card.
COMBINER_FORMAT = "gdpt-combiner/1"
#: Card keys written by :func:`encode_combiner` (the rest of a card, ``base_model`` included,
#: comes from the caller).
CARD_KEYS = ("format", "design", "description", "kernel", "widths", "features", "parameter_count")
#: Logit of the base network's centre tap at initialisation: step 0 gives the base network's
#: pixel a weight of ``e^8 / (e^8 + K k^2 - 1)`` (99.4% for 2 candidates and 3x3 taps).
INIT_LOGIT = 8.0


@dataclass(frozen=True)
class CombinerDesign:
    """What a combiner reads.

    Attributes:
        gradients: reads ``dx``/``dy`` (as inputs and for the L1 candidate).
        alpha: data weight of the L1 candidate's screened Poisson solve.
        description: one line for cards and reports.
    """

    gradients: bool
    alpha: float
    description: str

    @property
    def candidate_names(self) -> tuple[str, ...]:
        """Candidates, in order (``base`` first: it gets the initial weight)."""
        return ("base", "l1") if self.gradients else ("base",)

    @property
    def features(self) -> tuple[str, ...]:
        """Buffers read, in order."""
        return ("primal", "albedo", "normal") + (("dx", "dy") if self.gradients else ())

    @property
    def in_channels(self) -> int:
        """Network input channels: 3 per candidate, primal, albedo, normal (+ 6 gradient
        channels)."""
        return 3 * len(self.candidate_names) + 9 + 6 * self.gradients


#: Design name -> :class:`CombinerDesign`.
COMBINER_DESIGNS: Registry[CombinerDesign] = Registry("combiner design")
COMBINER_DESIGNS.register(
    "combiner-grad",
    CombinerDesign(
        True, 0.5, "per-pixel kernels over fine-tuned OIDN and the L1 Poisson solution with it"
    ),
)
COMBINER_DESIGNS.register(
    "combiner-nograd",
    CombinerDesign(False, 0.5, "per-pixel kernels over fine-tuned OIDN"),
)


def _conv(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1),
        nn.ReLU(inplace=True),
    )


class CombinerNet(nn.Module):
    """Three-level U-Net predicting kernel logits.

    Args:
        in_channels: input channels (:attr:`CombinerDesign.in_channels`).
        candidates: number of candidates ``K``.
        kernel: neighbourhood side ``k`` (odd).
        widths: channels of the three levels.

    Input ``(N, in_channels, H, W)`` with ``H`` and ``W`` multiples of 4; output
    ``(N, K * k * k, H, W)`` logits (candidate-major, taps row-major). The last layer starts at
    zero with the base candidate's centre tap biased by :data:`INIT_LOGIT`.
    """

    def __init__(
        self, in_channels: int, candidates: int, kernel: int = 3, widths=(32, 48, 64)
    ) -> None:
        super().__init__()
        if kernel % 2 != 1 or kernel < 1:
            raise ValueError(f"kernel must be an odd positive side, got {kernel}")
        a, b, c = widths
        self.candidates, self.kernel, self.widths = candidates, kernel, tuple(widths)
        self.enc0, self.enc1, self.mid = _conv(in_channels, a), _conv(a, b), _conv(b, c)
        self.dec1, self.dec0 = _conv(c + b, b), _conv(b + a, a)
        self.head = nn.Conv2d(a, candidates * kernel * kernel, 1)
        nn.init.zeros_(self.head.weight)
        with torch.no_grad():
            self.head.bias.zero_()
            self.head.bias[kernel * kernel // 2] = INIT_LOGIT

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s0 = self.enc0(x)
        s1 = self.enc1(F.max_pool2d(s0, 2))
        m = self.mid(F.max_pool2d(s1, 2))
        d1 = self.dec1(torch.cat([F.interpolate(m, scale_factor=2.0), s1], 1))
        d0 = self.dec0(torch.cat([F.interpolate(d1, scale_factor=2.0), s0], 1))
        return self.head(d0)


def candidates(
    buffers: Mapping[str, torch.Tensor], base_image: torch.Tensor, design: CombinerDesign
) -> torch.Tensor:
    """``(K, H, W, 3)`` candidate images (linear, finite) in :attr:`~CombinerDesign
    .candidate_names` order, on the buffers' device.

    Args:
        buffers: name -> ``(H, W, 3)`` tensors (``dx``, ``dy`` for the gradient design).
        base_image: ``(H, W, 3)`` output of the base network on these buffers.
        design: the combiner design.
    """
    out = {"base": base_image.float()}
    if design.gradients:  # the refinement's ungated solve, on the schedule it was trained with
        solver = GatedRefinement(alpha=design.alpha, preset="fast")
        out["l1"] = solver.solve(out["base"], buffers["dx"], buffers["dy"])
    return torch.stack([out[name] for name in design.candidate_names])


def combiner_input(
    buffers: Mapping[str, torch.Tensor], cands: torch.Tensor, design: CombinerDesign
) -> tuple[torch.Tensor, torch.Tensor]:
    """Network input of a batch.

    Args:
        buffers: name -> ``(N, H, W, 3)`` tensors for ``design.features`` (``normal`` in
            [-1, 1]); non-finite values are treated as 0.
        cands: ``(N, K, H, W, 3)`` candidates.
        design: the combiner design.

    Returns:
        ``(x, scale)``: ``(N, in_channels, H, W)`` float32 and ``(N,)`` OIDN input scales
        (autoexposure of the primal), on the buffers' device.
    """

    def finite(t: torch.Tensor) -> torch.Tensor:
        return torch.nan_to_num(t.float(), nan=0.0, posinf=0.0, neginf=0.0)

    primal = finite(buffers["primal"])
    scale = torch.stack([autoexposure(p) for p in primal])
    s = scale.reshape(-1, 1, 1, 1)
    parts = [pu_forward((s * cands[:, i]).clamp_min(0.0)) for i in range(cands.shape[1])]
    parts.append(pu_forward((s * primal).clamp_min(0.0)))
    parts.append(finite(buffers["albedo"]).clamp(0.0, 1.0))
    parts.append(finite(buffers["normal"]).clamp(-1.0, 1.0) * 0.5 + 0.5)
    if design.gradients:
        parts += [signed_log(s * finite(buffers["dx"])), signed_log(s * finite(buffers["dy"]))]
    return torch.cat(parts, -1).permute(0, 3, 1, 2).contiguous(), scale


def _pad4(x: torch.Tensor) -> torch.Tensor:
    h, w = x.shape[-2:]
    return F.pad(x, (0, -w % 4, 0, -h % 4), mode="replicate")


def combine(
    net: CombinerNet,
    x: torch.Tensor,
    scale: torch.Tensor,
    *,
    forward: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> torch.Tensor:
    """Run ``net`` on a :func:`combiner_input` batch and apply its kernels in PU space.

    Args:
        net: the combiner.
        x: ``(N, C, H, W)`` input (any ``H``, ``W``: padded to multiples of 4 inside); its
            first ``3 K`` channels are the PU-encoded candidates.
        scale: ``(N,)`` OIDN input scales of the batch.
        forward: what computes ``net``'s logits (default ``net``; in training, e.g. its
            ``DistributedDataParallel`` wrapper).

    Returns:
        ``(N, H, W, 3)`` float32 radiance (finite, >= 0) on ``x``'s device.
    """
    n, _, h, w = x.shape
    logits = (forward or net)(_pad4(x))[..., :h, :w]
    cands = x[:, : 3 * net.candidates].reshape(n, net.candidates, 3, h, w)
    y = apply_kernels(cands, logits, net.kernel)
    out = pu_inverse(y.clamp(0.0, 1.0)) / scale.reshape(-1, 1, 1, 1)
    return torch.nan_to_num(out, nan=0.0, posinf=0.0).clamp_min(0.0).permute(0, 2, 3, 1)


def encode_combiner(
    net: CombinerNet, design_name: str, card: Mapping[str, Any]
) -> tuple[bytes, str]:
    """The two files of a combiner checkpoint: ``.safetensors`` bytes and ``.json`` text.

    Args:
        net: the combiner (any device).
        design_name: a key of :data:`COMBINER_DESIGNS`.
        card: JSON-serialisable card entries; ``"base_model"`` (required) is the file name
            (no suffix) of the base network's delta checkpoint, stored next to the card; the
            rest is training information.

    Raises:
        ValueError: ``card`` has no ``"base_model"`` string.
    """
    if not isinstance(card.get("base_model"), str):
        raise ValueError("a combiner card needs 'base_model': its base checkpoint's file name")
    state = {
        k: v.detach().to("cpu", torch.float32).contiguous() for k, v in net.state_dict().items()
    }
    design = COMBINER_DESIGNS[design_name]
    full = {
        "format": COMBINER_FORMAT,
        "design": design_name,
        "description": design.description,
        "kernel": net.kernel,
        "widths": list(net.widths),
        "features": list(design.features),
        "parameter_count": sum(p.numel() for p in net.parameters()),
        **card,
    }
    weights = save(state, metadata={"format": COMBINER_FORMAT, "design": design_name})
    return weights, json.dumps(full, indent=2) + "\n"


def load_combiner(path: str | Path) -> tuple[CombinerNet, CombinerDesign, dict[str, Any], Path]:
    """Rebuild a combiner from its checkpoint.

    Returns:
        ``(net, design, card, base_path)``: the network (CPU, eval mode) and the path of its
        base network's checkpoint.

    Raises:
        FileNotFoundError: a file (also the base network's) is missing.
        ValueError: not a combiner card, or the stored tensors do not fit it.
    """
    weights_path, card_path, card = read_card(path)
    if card.get("format") != COMBINER_FORMAT:
        raise ValueError(
            f"{card_path}: format {card.get('format')!r}, expected {COMBINER_FORMAT!r}"
        )
    design = COMBINER_DESIGNS[card["design"]]
    base_path = card_path.parent / card["base_model"]
    if not base_path.with_suffix(".safetensors").is_file():
        raise FileNotFoundError(
            f"{card_path}: its base network {base_path} is missing (it must sit next to the card)"
        )
    net = CombinerNet(
        design.in_channels, len(design.candidate_names), card["kernel"], card["widths"]
    )
    try:
        net.load_state_dict(load_file(str(weights_path)))
    except RuntimeError as error:
        raise ValueError(
            f"{weights_path} does not fit design {card['design']!r}: {error}"
        ) from None
    return net.eval(), design, card, base_path


class CombinerReconstructor:
    """Base network, candidates and combiner applied to one render, on its device.

    Args:
        net: the combiner.
        design: its design.
        base: the base network's reconstructor (reads the same buffers).
        card: the model card, kept as :attr:`card`.
    """

    def __init__(
        self,
        net: CombinerNet,
        design: CombinerDesign,
        base: OIDNReconstructor,
        card: Mapping[str, Any] | None = None,
    ) -> None:
        self.design, self.base, self.card = design, base, dict(card or {})
        self.features = tuple(dict.fromkeys(design.features + base.features))
        self._net = net.eval()
        self._per_device: dict[torch.device, CombinerNet] = {}

    @classmethod
    def from_checkpoint(cls, path: str | Path) -> CombinerReconstructor:
        """Load with :func:`load_combiner` and the base network's checkpoint."""
        net, design, card, base_path = load_combiner(path)
        return cls(net, design, OIDNReconstructor.from_checkpoint(base_path), card)

    def _net_on(self, device: torch.device) -> CombinerNet:
        if device not in self._per_device:
            import copy  # noqa: PLC0415

            self._per_device[device] = copy.deepcopy(self._net).to(device)
        return self._per_device[device]

    @torch.inference_mode()
    def __call__(self, buffers: Mapping[str, torch.Tensor] | Any) -> torch.Tensor:
        """Reconstruct one image: ``(H, W, 3)`` float32 radiance (finite, >= 0) on the
        buffers' device.

        Raises:
            KeyError: a buffer the model reads is missing (named).
        """
        if not isinstance(buffers, Mapping):
            buffers = {n: getattr(buffers, n, None) for n in self.features}
        missing = [n for n in self.features if buffers.get(n) is None]
        if missing:
            raise KeyError(
                f"the buffers lack {', '.join(missing)}, which this model reads "
                f"({self.design.description}); render them (gdpt properties gradients/features)"
            )
        base_image = self.base(buffers)
        cands = candidates(buffers, base_image, self.design)[None]
        batch = {n: buffers[n][None] for n in self.design.features}
        x, scale = combiner_input(batch, cands, self.design)
        return combine(self._net_on(x.device), x, scale)[0].contiguous()


#: Combiner loss name (``gdpt train --loss``) -> keyword arguments of :func:`combiner_loss`
#: (its relative term).
COMBINER_LOSSES: Registry[dict[str, str | None]] = Registry("combiner loss")
COMBINER_LOSSES.register("l1", {"relative": None})
COMBINER_LOSSES.register("l1_relabs", {"relative": "abs"})
COMBINER_LOSSES.register("l1_huber", {"relative": "huber"})


def combiner_loss(
    out: torch.Tensor,
    target: torch.Tensor,
    base: torch.Tensor,
    scale: torch.Tensor,
    *,
    relative: str | None,
    eps: float = 1e-2,
) -> torch.Tensor:
    """PU-L1 plus a relative error whose denominator is the base network's image.

    With ``r = s (out - t) / (eps + s mean_c(base))`` (``s``: OIDN's input scale):
    ``mean |PU(s out) - PU(s t)| + mean rho(r)`` where ``rho`` is ``|r|`` (``"abs"``) or the
    Huber function with threshold 1 (``"huber"``), or 0 (``None``: OIDN's PU-L1 alone).

    PU-L1 grows like the log of an overshoot, so it barely charges a combiner for mixing a
    failed candidate (a Poisson dipole, a firefly) into a dark pixel, which the evaluation's
    relMSE charges quadratically. The relative term charges it linearly. Its denominator comes
    from the base image, which does not depend on the target's noise, and ``rho`` grows at
    most linearly, so the target's own fireflies (512-spp path-traced targets) cannot dominate
    a batch as they do in a squared relative error.

    Args:
        out: ``(N, H, W, 3)`` combiner output (linear).
        target: ``(N, H, W, 3)`` linear target, same device.
        base: ``(N, H, W, 3)`` base network image (the first candidate).
        scale: ``(N,)`` OIDN input scales.
        relative: ``None``, ``"abs"`` or ``"huber"``.
        eps: denominator offset, in units of the scaled image (mean about 0.18).

    Returns:
        Scalar tensor.
    """
    s = scale.reshape(-1, 1, 1, 1)
    l1 = pu_forward((s * out).clamp_min(0.0)) - pu_forward((s * target).clamp_min(0.0))
    l1 = l1.abs().mean()
    if relative is None:
        return l1
    r = s * (out - target) / (eps + s * base.detach().mean(-1, keepdim=True))
    if relative == "abs":
        return l1 + r.abs().mean()
    if relative == "huber":
        return l1 + F.huber_loss(r, torch.zeros_like(r), delta=1.0)
    raise ValueError(f"unknown relative term {relative!r}; valid: 'abs', 'huber' or None")
