"""KPCN: the kernel-predicting convolutional network of Bako et al. 2017.

Bako, Vogels, McWilliams, Meyer, Novák, Harvill, Sen, DeRose and Rousselle, "Kernel-predicting
convolutional networks for denoising Monte Carlo renderings", ACM Transactions on Graphics
36(4) (SIGGRAPH 2017). A stack of convolutions (the paper: 9 layers of 5x5 convolutions with
100 channels, ReLU, the last layer linear) predicts at every pixel ``k x k = 21 x 21 = 441``
logits; their softmax is a kernel that is applied to the pixel's neighbourhood of the
preprocessed noisy buffer (:func:`.kernels.apply_kernels`, section 4.2 of the paper). The
output is a convex combination of noisy values, so it cannot leave their range.

**One branch.** The paper filters a diffuse and a specular buffer with two networks; the
``gdpt`` integrator renders one radiance buffer, so this is the single-branch variant, and the
buffer it filters combines both of the paper's transforms::

    y = log(1 + x / (a + eps)),   eps = 0.00316        x: radiance, a: albedo (per channel)
    out = (a + eps) * (exp(sum_t w_t y[p + t]) - 1)   (remodulated at the end)

Demodulation by the albedo (the paper's diffuse branch) takes texture out of what is filtered,
so a wide kernel does not blur it; the logarithm (the paper's specular branch) keeps a bright
neighbour (a light source, a caustic, a highlight that demodulation does not flatten) from
bleeding into dark pixels: in linear space a 1% weight on a neighbour 1000x brighter adds 10x
the pixel's value, in log space a few percent. One buffer holds both kinds of light here, so
it gets both transforms.

**Input** (:func:`kpcn_input`, 31 channels; the paper's preprocessing, section 5.1): ``y``
(3), the variance of ``y`` (1), the normal as rendered (3), depth divided by the image's
largest depth (1), the albedo (3), and the forward differences in x and y of ``y``, normal,
depth and albedo (6 + 6 + 2 + 6; zero in the last column / row). These differences are
image-space finite differences of the noisy buffers, as in KPCN; they are *not* the
gradient-domain renderer's ``dx``/``dy``, which KPCN does not read. The variance of ``y`` is
the delta-method transform of the render's ``var_primal`` (variance of the pixel mean of the
channel average): ``var_primal / mean_c((x_c + a_c + eps)^2)``, as ``d y / d x = 1 / (x + a +
eps)``. The paper also feeds the variances of the features; the ``gdpt`` integrator does not
render them, so they are left out.

**Convolutions** zero-pad (``same`` size), so any image size works; at inference the image is
cut into row bands that overlap by the receptive radius (:class:`KPCNReconstructor`), which
gives the whole-image result.

Designs (:data:`KPCN_DESIGNS`; the paper's initialisation: Xavier-uniform weights, zero
biases)::

    design       layers x width   conv   kernel   parameters   what for
    kpcn         5 x 32           3x3    11x11    0.07 M       training on a CPU
    kpcn-paper   9 x 100          5x5    21x21    2.9 M        the paper's network (a GPU)

``kpcn`` needs about 40x fewer multiply-adds per pixel than the paper's network (72 k against
2.9 M), so a few thousand updates of 8 crops of 64x64 take an hour or less on one CPU core; its
receptive radius is 5 pixels and its kernels reach 5 pixels, against 18 and 10.

Loss (:data:`KPCN_LOSSES`, :func:`kpcn_loss`): L1 of the filtered ``y`` against the target in
the same transform (with the input's albedo), the paper's L1 loss in its branch's space.

Checkpoint: ``model.safetensors`` (float32 weights) and ``model.json`` (card: ``{"format":
KPCN_FORMAT, "design", "layers", "width", "conv", "kernel", "features", ...training
information...}``). The designs, the loss and the checkpoint format form the ``kpcn`` family
of :mod:`.families`.

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

from .cards import read_card
from .kernels import apply_kernels
from .registry import Registry

__all__ = [
    "ALBEDO_EPS",
    "CARD_KEYS",
    "FEATURES",
    "IN_CHANNELS",
    "KPCNDesign",
    "KPCNNet",
    "KPCNReconstructor",
    "KPCN_DESIGNS",
    "KPCN_FORMAT",
    "KPCN_LOSSES",
    "encode_kpcn",
    "kpcn_filter",
    "kpcn_input",
    "kpcn_loss",
    "load_kpcn",
    "remodulate",
]

#: ``"format"`` of a KPCN model card.
KPCN_FORMAT = "gdpt-kpcn/1"
#: Card keys written by :func:`encode_kpcn` (the rest of a card is training information).
CARD_KEYS = (
    "format",
    "design",
    "description",
    "layers",
    "width",
    "conv",
    "kernel",
    "features",
    "parameter_count",
)
#: Added to the albedo before demodulating (the paper's epsilon).
ALBEDO_EPS = 0.00316
#: Buffers KPCN reads, in :func:`kpcn_input` order.
FEATURES = ("primal", "albedo", "normal", "depth", "var_primal")
#: Network input channels (see the module docstring).
IN_CHANNELS = 31
#: Largest float32: a remodulated output that overflows is clamped to it.
_FLOAT32_MAX = torch.finfo(torch.float32).max


@dataclass(frozen=True)
class KPCNDesign:
    """A KPCN network's shape.

    Attributes:
        layers: convolutions (``layers - 1`` with ReLU, the last linear).
        width: channels of the hidden layers.
        conv: side of each convolution (odd).
        kernel: side ``k`` of the predicted kernels (odd): ``k * k`` logits per pixel.
        description: one line for cards and reports.
    """

    layers: int
    width: int
    conv: int
    kernel: int
    description: str

    def __post_init__(self) -> None:
        if self.layers < 1 or self.width < 1:
            raise ValueError(f"layers and width must be >= 1, got {self.layers}, {self.width}")
        if self.conv % 2 != 1 or self.kernel % 2 != 1:
            raise ValueError(f"conv and kernel must be odd, got {self.conv}, {self.kernel}")

    @property
    def halo(self) -> int:
        """Rows beyond a band that determine its output: the larger of the convolutions'
        receptive radius and the kernel's radius."""
        return max(self.layers * (self.conv // 2), self.kernel // 2)


#: Design name -> :class:`KPCNDesign` (``gdpt train --config``).
KPCN_DESIGNS: Registry[KPCNDesign] = Registry("kpcn design")
KPCN_DESIGNS.register(
    "kpcn",
    KPCNDesign(5, 32, 3, 11, "KPCN, CPU-sized: 5 x 32 channels of 3x3, 11x11 kernels"),
)
KPCN_DESIGNS.register(
    "kpcn-paper",
    KPCNDesign(
        9, 100, 5, 21, "KPCN as in Bako et al. 2017: 9 x 100 channels of 5x5, 21x21 kernels"
    ),
)


class KPCNNet(nn.Module):
    """The convolution stack: ``(N, IN_CHANNELS, H, W) -> (N, k * k, H, W)`` kernel logits
    (taps row-major), float32, on the module's device; any ``H``, ``W`` (zero padding).

    Args:
        design: its shape.
    """

    def __init__(self, design: KPCNDesign) -> None:
        super().__init__()
        self.design = design
        widths = [IN_CHANNELS] + [design.width] * (design.layers - 1) + [design.kernel**2]
        layers: list[nn.Module] = []
        for index, (cin, cout) in enumerate(zip(widths[:-1], widths[1:], strict=True)):
            conv = nn.Conv2d(cin, cout, design.conv, padding=design.conv // 2)
            nn.init.xavier_uniform_(conv.weight)
            nn.init.zeros_(conv.bias)
            layers.append(conv)
            if index < design.layers - 1:
                layers.append(nn.ReLU(inplace=True))
        self.body = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body(x)


def _finite(t: torch.Tensor) -> torch.Tensor:
    return torch.nan_to_num(t.float(), nan=0.0, posinf=0.0, neginf=0.0)


def _differences(t: torch.Tensor) -> torch.Tensor:
    """``(N, C, H, W) -> (N, 2C, H, W)``: forward differences along x, then y (zero in the last
    column / row)."""
    dx = torch.zeros_like(t)
    dy = torch.zeros_like(t)
    dx[..., :, :-1] = t[..., :, 1:] - t[..., :, :-1]
    dy[..., :-1, :] = t[..., 1:, :] - t[..., :-1, :]
    return torch.cat([dx, dy], 1)


def kpcn_input(
    buffers: Mapping[str, torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Preprocess a batch of renders (module docstring; Bako et al. 2017, section 5.1).

    Non-finite values are treated as 0; radiance and variance are clamped to ``>= 0``, albedo
    to ``[0, 1]``, normals to ``[-1, 1]``, depth to ``>= 0``.

    Args:
        buffers: name -> ``(N, H, W, C)`` float tensors on one device for every name in
            :data:`FEATURES` (``C``: 3, and 1 for ``depth`` and ``var_primal``).

    Returns:
        ``(x, y, scale)``, float32 on the buffers' device: ``x`` the ``(N, IN_CHANNELS, H, W)``
        network input, ``y`` the ``(N, 3, H, W)`` buffer that is filtered (log of demodulated
        radiance), ``scale`` the ``(N, 3, H, W)`` albedo + :data:`ALBEDO_EPS` that remodulates
        it (:func:`remodulate`).

    Raises:
        KeyError: a buffer of :data:`FEATURES` is missing (all missing ones are named).
    """
    missing = [name for name in FEATURES if buffers.get(name) is None]
    if missing:
        raise KeyError(
            f"KPCN reads {', '.join(FEATURES)}; the buffers lack {', '.join(missing)} (render "
            "with the gdpt properties features=True and variance=True)"
        )

    def nchw(name: str) -> torch.Tensor:
        return _finite(buffers[name]).permute(0, 3, 1, 2)

    radiance = nchw("primal").clamp_min(0.0)
    albedo = nchw("albedo").clamp(0.0, 1.0)
    normal = nchw("normal").clamp(-1.0, 1.0)
    depth = nchw("depth").clamp_min(0.0)
    depth = depth / depth.amax((1, 2, 3), keepdim=True).clamp_min(1e-12)
    scale = albedo + ALBEDO_EPS
    # log(1 + x / s) as a difference of logs: finite for every finite x
    y = torch.log(radiance + scale) - torch.log(scale)
    variance = nchw("var_primal").clamp_min(0.0)
    variance = variance / (radiance + scale).square().mean(1, keepdim=True)
    plain = [y, variance, normal, depth, albedo]
    x = torch.cat(plain + [_differences(t) for t in (y, normal, depth, albedo)], 1)
    return x.contiguous(), y.contiguous(), scale.contiguous()


def kpcn_filter(
    net: KPCNNet,
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    forward: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> torch.Tensor:
    """Predict the kernels from ``x`` and apply them to ``y``.

    Args:
        net: the network.
        x: ``(N, IN_CHANNELS, H, W)`` input (:func:`kpcn_input`), on ``net``'s device.
        y: ``(N, 3, H, W)`` buffer to filter, same device.
        forward: what computes ``net``'s logits (default ``net``; in training, e.g. its
            ``DistributedDataParallel`` wrapper).

    Returns:
        ``(N, 3, H, W)`` filtered ``y`` (at each pixel a convex combination of ``y`` values).
    """
    logits = (forward or net)(x)
    return apply_kernels(y[:, None], logits, net.design.kernel)


def remodulate(y: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Radiance ``scale * (exp(y) - 1)`` of a filtered buffer (:func:`kpcn_input`'s transform
    inverted), clamped to ``[0, float32 max]``; any shape, ``y`` and ``scale`` alike."""
    return (torch.expm1(y) * scale).clamp(0.0, _FLOAT32_MAX)


def kpcn_loss(filtered: torch.Tensor, target: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """L1 between the filtered buffer and the target in the same transform.

    ``mean |filtered - log(1 + t / scale)|`` (Bako et al. 2017 train with L1 in each branch's
    space; the target is demodulated with the input's albedo, as the output is remodulated
    with it).

    Args:
        filtered: ``(N, 3, H, W)`` :func:`kpcn_filter` output.
        target: ``(N, 3, H, W)`` linear target radiance, same device (non-finite values are
            treated as 0, negative ones as 0).
        scale: ``(N, 3, H, W)`` albedo + :data:`ALBEDO_EPS` of the input.

    Returns:
        Scalar tensor.
    """
    t = _finite(target).clamp_min(0.0)
    return (filtered - (torch.log(t + scale) - torch.log(scale))).abs().mean()


#: Loss name (``gdpt train --loss``) -> description (:func:`kpcn_loss`).
KPCN_LOSSES: Registry[str] = Registry("kpcn loss")
KPCN_LOSSES.register("l1", "L1 of the filtered log-demodulated radiance (kpcn_loss)")


def encode_kpcn(net: KPCNNet, design_name: str, card: Mapping[str, Any]) -> tuple[bytes, str]:
    """The two files of a KPCN checkpoint: ``.safetensors`` bytes and ``.json`` text.

    Args:
        net: the network (any device; stored as CPU float32).
        design_name: its key in :data:`KPCN_DESIGNS`.
        card: JSON-serialisable training information (``training``, ``steps``, ...).

    Raises:
        ValueError: ``net`` is not of the design ``design_name``.
    """
    design = KPCN_DESIGNS[design_name]
    if net.design != design:
        raise ValueError(f"a {design_name!r} checkpoint needs a network of that design")
    state = {
        k: v.detach().to("cpu", torch.float32).contiguous() for k, v in net.state_dict().items()
    }
    full = {
        "format": KPCN_FORMAT,
        "design": design_name,
        "description": design.description,
        "layers": design.layers,
        "width": design.width,
        "conv": design.conv,
        "kernel": design.kernel,
        "features": list(FEATURES),
        "parameter_count": sum(p.numel() for p in net.parameters()),
        **card,
    }
    weights = save(state, metadata={"format": KPCN_FORMAT, "design": design_name})
    return weights, json.dumps(full, indent=2) + "\n"


def load_kpcn(path: str | Path) -> tuple[KPCNNet, dict[str, Any]]:
    """Rebuild a network written by :func:`encode_kpcn`.

    Args:
        path: its ``.safetensors`` or ``.json`` (the other next to it).

    Returns:
        ``(net, card)``: the network on the CPU in eval mode.

    Raises:
        FileNotFoundError: a file is missing.
        ValueError: not a KPCN card, an unknown design, or weights that do not fit it.
    """
    weights_path, card_path, card = read_card(path)
    if card.get("format") != KPCN_FORMAT:
        raise ValueError(f"{card_path}: format {card.get('format')!r}, expected {KPCN_FORMAT!r}")
    if card.get("design") not in KPCN_DESIGNS:
        raise ValueError(
            f"{card_path}: design {card.get('design')!r} is not one of {', '.join(KPCN_DESIGNS)}"
        )
    net = KPCNNet(KPCN_DESIGNS[card["design"]])
    try:
        net.load_state_dict(load_file(str(weights_path)))
    except RuntimeError as error:
        raise ValueError(
            f"{weights_path} does not fit design {card['design']!r}: {error}"
        ) from None
    return net.eval(), card


class KPCNReconstructor:
    """A KPCN network applied to one render, on the render's device, in row bands.

    The whole image is preprocessed (the depth normalisation needs its largest depth), then the
    network and its kernels run on bands of rows that overlap by the design's
    :attr:`~KPCNDesign.halo`, so the result equals the whole-image one while the memory of the
    kernels (``3 k^2`` values per pixel) stays bounded.

    Args:
        net: the network, set to eval mode; used as it is on its own device (so it sees later
            changes of its weights), copied to other devices on first use.
        card: the model card, kept as :attr:`card`.
        band_pixels: about how many pixels (with the halo) one band holds.
    """

    features = FEATURES

    def __init__(
        self, net: KPCNNet, card: Mapping[str, Any] | None = None, *, band_pixels: int = 1 << 16
    ) -> None:
        self.design = net.design
        self.card = dict(card or {})
        self.band_pixels = band_pixels
        self._net = net.eval()
        self._per_device: dict[torch.device, KPCNNet] = {}

    @classmethod
    def from_checkpoint(cls, path: str | Path) -> KPCNReconstructor:
        """Load with :func:`load_kpcn`."""
        net, card = load_kpcn(path)
        return cls(net, card)

    def _net_on(self, device: torch.device) -> KPCNNet:
        """``net`` itself on its own device, else a copy made on first use."""
        if device == next(self._net.parameters()).device:
            return self._net
        if device not in self._per_device:
            import copy  # noqa: PLC0415

            self._per_device[device] = copy.deepcopy(self._net).to(device)
        return self._per_device[device]

    @torch.inference_mode()
    def __call__(self, buffers: Mapping[str, torch.Tensor] | Any) -> torch.Tensor:
        """Reconstruct one image.

        Args:
            buffers: name -> ``(H, W, C)`` float tensor for every name in :data:`FEATURES`,
                on one device, or an object with them as attributes
                (``gdpt.buffers.GradientBuffers``).

        Returns:
            ``(H, W, 3)`` float32 radiance (finite, >= 0) on the buffers' device.

        Raises:
            KeyError: a buffer KPCN reads is missing (named).
        """
        if not isinstance(buffers, Mapping):
            buffers = {n: getattr(buffers, n, None) for n in FEATURES}
        batch = {n: None if buffers.get(n) is None else buffers[n][None] for n in FEATURES}
        x, y, scale = kpcn_input(batch)
        net = self._net_on(x.device)
        height, width = y.shape[-2:]
        halo = self.design.halo
        rows = max(16, self.band_pixels // width - 2 * halo)
        out = torch.empty_like(y)
        for top in range(0, height, rows):
            bottom = min(height, top + rows)
            lo, hi = max(0, top - halo), min(height, bottom + halo)
            band = kpcn_filter(net, x[..., lo:hi, :], y[..., lo:hi, :])
            out[..., top:bottom, :] = band[..., top - lo : bottom - lo, :]
        return remodulate(out, scale)[0].permute(1, 2, 0).contiguous()
