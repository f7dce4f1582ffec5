"""E-LPIPS (Kettunen et al. 2019), after ``mkettune/elpips``.

LPIPS over a random ensemble of input transformations: the same ensemble, backbone dropout and
linear heads as the reference; the weights are read from a local file (see
:func:`load_elpips_weights`); nothing is ever downloaded. Images are ``(N, 3, H, W)`` float
sRGB-encoded tensors in [0, 1] on any one device.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .colour import check_image_pair

__all__ = [
    "ELPIPS",
    "ELPIPS_WEIGHTS_ENV",
    "Dropout",
    "ELPIPSConfig",
    "ELPIPSWeightsError",
    "EnsembleSample",
    "SqueezeNetFeatures",
    "VGG16Features",
    "apply_ensemble",
    "load_elpips_weights",
    "sample_ensemble",
]

#: Environment variable naming the local E-LPIPS weight file.
ELPIPS_WEIGHTS_ENV = "GDPT_ELPIPS_WEIGHTS"

Dropout = Callable[[Tensor], Tensor]


class ELPIPSWeightsError(FileNotFoundError):
    """Raised when the local E-LPIPS weight file is missing or malformed."""


@dataclass(frozen=True)
class ELPIPSConfig:
    """E-LPIPS ensemble configuration; defaults are ``elpips.Config`` (E-LPIPS evaluation).

    Attributes:
        average_over: number of independent ensemble samples averaged per call.
        num_scales: downscale factors ``1..num_scales`` drawn with ``P(s) ~ 1/s^2``; the reference
            suggests ``max(1, min(H, W) // 64)``.
        offset_max: maximal random translation in pixels (inclusive).
        dropout_keep_prob: keep probability of the dropout on every backbone conv input.
        enable_dropout: backbone dropout (mask shared by the two images of a pair).
        enable_offset: random translation (reflect pad, or crop when fast).
        enable_flip: stratified random flips (x, y, xy, none).
        enable_swap: transpose with probability 1/2, shared by the batch.
        enable_color_permutation: stratified random RGB permutation per image.
        enable_color_multiplication: stratified per-channel factors in [0.2, 1].
        enable_scale: random box downscaling.
        color_multiplication_mode: ``"color"`` (independent R, G, B) or ``"brightness"``.
        fast_and_approximate: crop instead of padding (faster; may skip image edges).
    """

    average_over: int = 1
    num_scales: int = 8
    offset_max: int = 7
    dropout_keep_prob: float = 0.99
    enable_dropout: bool = True
    enable_offset: bool = True
    enable_flip: bool = True
    enable_swap: bool = True
    enable_color_permutation: bool = True
    enable_color_multiplication: bool = True
    enable_scale: bool = True
    color_multiplication_mode: str = "color"
    fast_and_approximate: bool = False

    def __post_init__(self) -> None:
        """Validate the fields."""
        if self.average_over < 1 or self.num_scales < 1 or self.offset_max < 0:
            raise ValueError(f"invalid E-LPIPS config {self}")
        if not 0.0 < self.dropout_keep_prob <= 1.0:
            raise ValueError(f"dropout_keep_prob must be in (0, 1], got {self.dropout_keep_prob}")
        if self.color_multiplication_mode not in ("color", "brightness"):
            raise ValueError(f"unknown color_multiplication_mode {self.color_multiplication_mode}")

    @classmethod
    def for_training(cls) -> ELPIPSConfig:
        """NGPT's training setting: 2 scale levels, fast mode, 3 samples averaged."""
        return cls(average_over=3, num_scales=2, fast_and_approximate=True)


@dataclass(frozen=True)
class EnsembleSample:
    """One sampled E-LPIPS input transformation for a batch of ``N`` images.

    Attributes:
        scale: downscale factor shared by the batch (1 = none).
        scale_offset: ``(oy, ox)`` in ``[0, scale)``, shared by the batch.
        offsets: ``(N, 2)`` long ``(oy, ox)`` translations in ``[0, offset_max]``.
        flips: ``(N,)`` long, 0 = flip x, 1 = flip y, 2 = flip both, 3 = none.
        swap: whether to transpose x and y (shared by the batch).
        permutations: ``(N, 3)`` long channel orders.
        color_factors: ``(N, 3)`` float channel multipliers in [0.2, 1].
    """

    scale: int
    scale_offset: tuple[int, int]
    offsets: Tensor
    flips: Tensor
    swap: bool
    permutations: Tensor
    color_factors: Tensor


def _stratified_shuffle(values: Tensor, n: int, generator: torch.Generator | None) -> Tensor:
    """Tile ``values`` (along dim 0) to at least ``n`` rows, shuffle, keep ``n`` rows."""
    tiled = values.repeat(-(-n // values.shape[0]), *([1] * (values.ndim - 1)))
    order = torch.randperm(tiled.shape[0], generator=generator, device=values.device)
    return tiled[order[:n]]


def sample_ensemble(
    n: int,
    config: ELPIPSConfig,
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str = "cpu",
) -> EnsembleSample:
    """Sample one random E-LPIPS transformation for ``n`` images (Latin-hypercube over the batch).

    Args:
        n: batch size.
        config: ensemble configuration.
        generator: random generator on ``device`` (``None``: torch's global RNG).
        device: device of the sampled tensors.

    Returns:
        The sampled transformation.
    """

    def uniform(*shape: int) -> Tensor:
        return torch.rand(shape, generator=generator, device=device)

    weights = [1.0 / s**2 for s in range(1, config.num_scales + 1)]
    cumulative = np.cumsum(weights)
    u = cumulative[-1] * float(uniform(1))
    scale = next((i + 1 for i, c in enumerate(cumulative[:-1]) if u < c), config.num_scales)
    oy, ox = (int(v) for v in (uniform(2) * scale).floor().long().clamp_max(scale - 1))
    offsets = (uniform(n, 2) * (config.offset_max + 1)).floor().long()
    offsets = offsets.clamp_max(config.offset_max)
    flips = _stratified_shuffle(torch.arange(4, device=device), n, generator)
    swap = bool(uniform(1) < 0.5)
    colors = torch.stack(
        [
            _stratified_shuffle((uniform(n) + torch.arange(n, device=device)) / n, n, generator)
            for _ in range(3)
        ],
        1,
    )
    if config.color_multiplication_mode == "brightness":
        colors = colors[:, :1].expand(n, 3)
    all_perms = torch.tensor(list(itertools.permutations(range(3))), device=device)
    return EnsembleSample(
        scale=scale,
        scale_offset=(oy, ox),
        offsets=offsets,
        flips=flips,
        swap=swap,
        permutations=_stratified_shuffle(all_perms, n, generator),
        color_factors=0.2 + 0.8 * colors,
    )


def apply_ensemble(x: Tensor, sample: EnsembleSample, config: ELPIPSConfig) -> Tensor:
    """Apply a sampled E-LPIPS transformation to a batch (order as in ``mkettune/elpips``).

    Downscale (box filter after reflect padding, or cropping when fast), translate, flip,
    transpose, permute colours, multiply colours.

    Args:
        x: ``(N, C, H, W)`` float images, ``N`` equal to the sampled batch size; any device.
        sample: the transformation from :func:`sample_ensemble`.
        config: the configuration the sample was drawn with.

    Returns:
        ``(N, C, H', W')`` transformed images.
    """
    n = x.shape[0]
    s = sample.scale
    if config.enable_scale and s > 1:
        oy, ox = sample.scale_offset
        h, w = x.shape[-2:]
        if config.fast_and_approximate:
            hh, ww = (h - s + 1) // s * s, (w - s + 1) // s * s
            x = x[..., oy : oy + hh, ox : ox + ww]
        else:
            hh, ww = (2 * s - 2 + h) // s * s, (2 * s - 2 + w) // s * s
            x = F.pad(x, (ox, ww - w - ox, oy, hh - h - oy), mode="reflect")
        x = F.avg_pool2d(x, s)
    if config.enable_offset:
        m = config.offset_max
        h, w = x.shape[-2:]
        rows = []
        for i, (oy, ox) in enumerate(sample.offsets.tolist()):
            if config.fast_and_approximate:
                rows.append(x[i : i + 1, :, oy : oy + h - m, ox : ox + w - m])
            else:
                rows.append(F.pad(x[i : i + 1], (m - ox, ox, m - oy, oy), mode="reflect"))
        x = torch.cat(rows)
    if config.enable_flip:
        flips = sample.flips.view(n, 1, 1, 1)
        x = torch.where(
            flips == 0,
            x.flip(-1),
            torch.where(flips == 1, x.flip(-2), torch.where(flips == 2, x.flip(-1, -2), x)),
        )
    if config.enable_swap and sample.swap:
        x = x.transpose(-1, -2)
    if config.enable_color_permutation:
        index = sample.permutations.view(n, 3, 1, 1).expand(-1, -1, *x.shape[-2:])
        x = torch.gather(x, 1, index)
    if config.enable_color_multiplication:
        x = x * sample.color_factors.to(x.dtype).view(n, 3, 1, 1)
    return x


def _relu_conv(conv: nn.Conv2d, x: Tensor, drop: Dropout) -> Tensor:
    """``relu(conv(drop(x)))``: the E-LPIPS conv unit (dropout on every conv input)."""
    return F.relu(conv(drop(x)))


class _Fire(nn.Module):
    """SqueezeNet fire module with torchvision's parameter names."""

    def __init__(self, c_in: int, c_squeeze: int, c_expand: int) -> None:
        super().__init__()
        self.squeeze = nn.Conv2d(c_in, c_squeeze, 1)
        self.expand1x1 = nn.Conv2d(c_squeeze, c_expand, 1)
        self.expand3x3 = nn.Conv2d(c_squeeze, c_expand, 3, padding=1)

    def forward(self, x: Tensor, drop: Dropout) -> Tensor:
        """Squeeze, then the two expand branches, concatenated along channels."""
        x = _relu_conv(self.squeeze, x, drop)
        return torch.cat(
            [_relu_conv(self.expand1x1, x, drop), _relu_conv(self.expand3x3, x, drop)], 1
        )


class SqueezeNetFeatures(nn.Module):
    """SqueezeNet 1.1 trunk of E-LPIPS ``squeeze_ensemble_maxpool`` (10 feature layers).

    Parameter names match ``torchvision.models.squeezenet1_1().state_dict()`` (``features.*``).
    Max pooling is 3x3/2 without ceil mode (TF ``VALID``), as in E-LPIPS. Needs inputs of at least
    31 px after the ensemble transforms (downscaling, and cropping in fast mode).
    """

    #: Channels of the layers fed to the linear heads (the input image first).
    channels = (3, 64, 128, 128, 256, 256, 384, 384, 512, 512)
    _fires = {
        "3": (64, 16, 64),
        "4": (128, 16, 64),
        "6": (128, 32, 128),
        "7": (256, 32, 128),
        "9": (256, 48, 192),
        "10": (384, 48, 192),
        "11": (384, 64, 256),
        "12": (512, 64, 256),
    }

    def __init__(self) -> None:
        super().__init__()
        layers: dict[str, nn.Module] = {"0": nn.Conv2d(3, 64, 3, stride=2)}
        layers.update({k: _Fire(*v) for k, v in self._fires.items()})
        self.features = nn.ModuleDict(layers)

    def forward(self, x: Tensor, drop: Dropout) -> list[Tensor]:
        """Feature maps ``(B, C_l, H_l, W_l)`` of ``x`` ``(B, 3, H, W)``, see :attr:`channels`."""
        f = self.features
        out = [x, _relu_conv(f["0"], x, drop)]
        for pool_then in (("3", "4"), ("6", "7"), ("9", "10", "11", "12")):
            h = F.max_pool2d(out[-1], 3, 2)
            for key in pool_then:
                h = f[key](h, drop)
                out.append(h)
        return out


class VGG16Features(nn.Module):
    """VGG16 trunk of E-LPIPS ``vgg_ensemble`` (average pooling, 14 feature layers).

    Parameter names match ``torchvision.models.vgg16().state_dict()`` (``features.*``).
    """

    #: Channels of the layers fed to the linear heads (the input image first).
    channels = (3, 64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512)
    _convs = ("0", "2", "5", "7", "10", "12", "14", "17", "19", "21", "24", "26", "28")
    _pool_before = frozenset({"5", "10", "17", "24"})

    def __init__(self) -> None:
        super().__init__()
        self.features = nn.ModuleDict(
            {
                k: nn.Conv2d(self.channels[i], self.channels[i + 1], 3, padding=1)
                for i, k in enumerate(self._convs)
            }
        )

    def forward(self, x: Tensor, drop: Dropout) -> list[Tensor]:
        """Feature maps ``(B, C_l, H_l, W_l)`` of ``x`` ``(B, 3, H, W)``, see :attr:`channels`."""
        out = [x]
        for key in self._convs:
            h = F.avg_pool2d(out[-1], 2) if key in self._pool_before else out[-1]
            out.append(_relu_conv(self.features[key], h, drop))
        return out


_BACKBONES: dict[str, tuple[str, type[nn.Module]]] = {
    "squeeze": ("features.3.squeeze.weight", SqueezeNetFeatures),
    "vgg": ("features.28.weight", VGG16Features),
}


def load_elpips_weights(
    path: str | os.PathLike[str] | None = None,
    config: ELPIPSConfig | None = None,
    *,
    seed: int | None = None,
) -> ELPIPS:
    """Build E-LPIPS from a local weight file (no download is ever attempted).

    File format: ``.safetensors``, ``.pt``/``.pth`` (a flat ``dict[str, Tensor]``, loaded with
    ``weights_only=True``) or ``.npz``, holding

    * the backbone in PyTorch layout under torchvision's names: the ``features.*`` entries of
      ``squeezenet1_1`` (``squeezenet1_1-b8a52dc0.pth``) or of ``vgg16`` (``vgg16-397923af.pth``);
      the backbone kind is detected from the keys;
    * the E-LPIPS linear heads ``lin0`` ... ``lin9`` (SqueezeNet, ``squeeze_full_maxpool.npy``) or
      ``lin0`` ... ``lin13`` (VGG, ``vgg_full_avg.npy``) from ``mkettune/elpips``, under the key
      ``lin{i}.weight`` or ``lin{i}.model.1.weight``, any shape with ``C_i`` elements.

    The E-LPIPS repository's ``*_pytorch_transposed_nonlinear_features.npy`` backbones are the
    same torchvision weights in TF layout: prefix the keys with ``features.`` and transpose conv
    weights with ``w.transpose(3, 2, 0, 1)``.

    Args:
        path: weight file; default: the ``GDPT_ELPIPS_WEIGHTS`` environment variable.
        config: ensemble configuration (default: E-LPIPS evaluation defaults).
        seed: see :class:`ELPIPS`.

    Returns:
        An :class:`ELPIPS` on the CPU (move it with ``.to(device)``).

    Raises:
        ELPIPSWeightsError: no path given, file missing, unknown format or missing keys.
    """
    path = path if path is not None else os.environ.get(ELPIPS_WEIGHTS_ENV)
    hint = (
        f"E-LPIPS needs a local weight file: pass its path or set {ELPIPS_WEIGHTS_ENV} to a "
        ".safetensors/.pt/.npz file holding the torchvision squeezenet1_1 or vgg16 'features.*' "
        "state dict plus the E-LPIPS linear heads 'lin{i}.weight' (squeeze_full_maxpool.npy or "
        "vgg_full_avg.npy from mkettune/elpips); see gdpt.reconstruct.elpips.load_elpips_weights."
        " No download is attempted."
    )
    if not path:
        raise ELPIPSWeightsError(hint)
    file = Path(path)
    if not file.is_file():
        raise ELPIPSWeightsError(f"{file} does not exist. {hint}")
    suffix = file.suffix.lower()
    if suffix == ".safetensors":
        from safetensors.torch import load_file  # noqa: PLC0415 (optional, only for this format)

        state = load_file(str(file))
    elif suffix in (".pt", ".pth"):
        state = torch.load(file, map_location="cpu", weights_only=True)
    elif suffix == ".npz":
        with np.load(file, allow_pickle=False) as data:
            state = {k: torch.from_numpy(data[k]) for k in data.files}
    else:
        raise ELPIPSWeightsError(f"unsupported weight file type {suffix!r}. {hint}")

    kind = next((k for k, (key, _) in _BACKBONES.items() if key in state), None)
    if kind is None:
        raise ELPIPSWeightsError(f"{file}: no SqueezeNet/VGG16 'features.*' keys found. {hint}")
    backbone = _BACKBONES[kind][1]()
    backbone_state = {k: v.float() for k, v in state.items() if k.startswith("features.")}
    try:
        backbone.load_state_dict(backbone_state)
    except RuntimeError as err:
        raise ELPIPSWeightsError(f"{file}: backbone mismatch: {err}. {hint}") from err
    heads = []
    for i in range(len(backbone.channels)):
        head = state.get(f"lin{i}.weight", state.get(f"lin{i}.model.1.weight"))
        if head is None:
            raise ELPIPSWeightsError(f"{file}: linear head lin{i} missing. {hint}")
        heads.append(head.float().reshape(-1))
    return ELPIPS(backbone, heads, config, seed=seed)


class ELPIPS(nn.Module):
    """E-LPIPS distance: LPIPS over a random ensemble of input transformations.

    Per sample: one random transformation (:func:`sample_ensemble`) is applied to both images,
    which go through the backbone together with *shared* dropout masks; features are unit-
    normalised over channels, squared differences are averaged spatially, weighted by the linear
    heads and summed over layers. ``config.average_over`` samples are averaged.

    With equal random draws the distance is symmetric and is exactly 0 for identical images.

    Args:
        backbone: module with a ``channels`` tuple attribute and
            ``forward(x, drop) -> list[Tensor]`` that applies ``drop`` to every conv input; e.g.
            :class:`SqueezeNetFeatures` or :class:`VGG16Features`. Its parameters are frozen.
        lin_weights: one 1-D non-negative weight vector per feature layer, ``len == channels``.
        config: ensemble configuration (default: E-LPIPS evaluation defaults).
        seed: if given, all random draws come from a generator seeded with it (one per device),
            making the sequence of results reproducible; otherwise torch's global RNG is used.
    """

    def __init__(
        self,
        backbone: nn.Module,
        lin_weights: Sequence[Tensor],
        config: ELPIPSConfig | None = None,
        *,
        seed: int | None = None,
    ) -> None:
        super().__init__()
        channels = tuple(getattr(backbone, "channels", ()))
        if len(channels) != len(lin_weights) or any(
            w.numel() != c for w, c in zip(lin_weights, channels, strict=False)
        ):
            raise ValueError(
                f"linear heads {[w.numel() for w in lin_weights]} do not match backbone "
                f"channels {channels}"
            )
        self.backbone = backbone.requires_grad_(False)
        self.config = config or ELPIPSConfig()
        self.seed = seed
        self._generators: dict[torch.device, torch.Generator] = {}
        for i, w in enumerate(lin_weights):
            self.register_buffer(f"lin{i}", w.detach().reshape(-1).float().clone())
        self.num_layers = len(lin_weights)
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))

    @property
    def heads(self) -> list[Tensor]:
        """The linear-head weight vectors, one ``(C_l,)`` float32 tensor per feature layer."""
        return [getattr(self, f"lin{i}") for i in range(self.num_layers)]

    def _generator(self, device: torch.device) -> torch.Generator | None:
        """The seeded generator for ``device`` (created on first use), or ``None``."""
        if self.seed is None:
            return None
        if device not in self._generators:
            self._generators[device] = torch.Generator(device=device).manual_seed(self.seed)
        return self._generators[device]

    def _sample_distance(self, image: Tensor, reference: Tensor) -> Tensor:
        """One ensemble sample of the distance, ``(N,)``."""
        n, device = image.shape[0], image.device
        generator = self._generator(device)
        sample = sample_ensemble(n, self.config, generator=generator, device=device)
        x = torch.cat(
            [
                apply_ensemble(image, sample, self.config),
                apply_ensemble(reference, sample, self.config),
            ]
        )
        x = (2.0 * x - 1.0 - self.shift.to(x.dtype)) / self.scale.to(x.dtype)
        keep = self.config.dropout_keep_prob

        def drop(t: Tensor) -> Tensor:
            if not self.config.enable_dropout or keep == 1.0:
                return t
            noise = torch.rand(t[:n].shape, generator=generator, device=device)
            mask = (noise < keep).to(t.dtype) / keep
            return t * torch.cat([mask, mask])

        distance = image.new_zeros(n)
        for i, feat in enumerate(self.backbone(x, drop)):
            feat = feat / (torch.linalg.vector_norm(feat, dim=1, keepdim=True) + 1e-10)
            diff = (feat[:n] - feat[n:]).square().mean(dim=(2, 3))
            distance = distance + diff @ self.heads[i].to(diff.dtype)
        return distance

    def forward(self, image: Tensor, reference: Tensor) -> Tensor:
        """E-LPIPS distance per image.

        Args:
            image: ``(N, 3, H, W)`` float sRGB-encoded image in [0, 1], any device.
            reference: ``(N, 3, H, W)`` float sRGB-encoded reference, same device.

        Returns:
            ``(N,)`` distances, averaged over ``config.average_over`` samples.
        """
        check_image_pair(image, reference)
        total = self._sample_distance(image, reference)
        for _ in range(self.config.average_over - 1):
            total = total + self._sample_distance(image, reference)
        return total / self.config.average_over
