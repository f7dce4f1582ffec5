"""Dense U-Net of NGPT (Kettunen, Haerkoenen, Lehtinen 2019) and configurable relatives.

The network maps a transformed feature stack (see :mod:`gdpt.reconstruct.transforms`) to the
reconstruction in ``log(1 + x)`` space; undoing that mapping (``exp(y) - 1``) is the caller's
job, so the backbone stays a plain ``nn.Module``.

Topology (``dense=True``): every resolution is one densely connected block. A *processing unit*
is ``1x1 conv -> 2k -> LeakyReLU -> 3x3 conv -> k -> LeakyReLU`` and reads the concatenation of
everything in its level's feature list; its output is appended to that list. Half way through a
level (after the encoder units) the concatenated list is pooled with a 2x2 stride-2 conv into the
next level. The coarsest level runs its encoder and decoder units back to back. The decoder of a
finer level appends the 2x2 transposed-conv unpooling of the coarser level's whole list to its own
(encoder) list and continues it with its decoder units. A final ``1x1`` conv (+ LeakyReLU, as in
the published code) maps the level-0 list to RGB. With ``dense=False`` the same units and
pool/unpool layers form a plain U-Net: a unit reads only the previous unit's output and a decoder
level starts from ``concat(skip, unpooled)``.

Every convolution is weight-normalised as in the reference code (``weight_norm=True``)::

    W_eff = W * s * sqrt(2) / sqrt(1e-8 + sum W^2)     (per output channel of a conv; per input
                                                        channel of a transposed conv, as in TF)

with a learnable ``s`` initialised to 1, He-initialised ``W`` and zero bias. The effective
weights are computed once per forward pass (they are tiny next to the activations).

Optional ``space_to_depth = s > 1``: the input is pixel-unshuffled by ``s`` so that the whole
U-Net runs at ``1/s`` resolution; the head pixel-shuffles back to full resolution, concatenates
the raw network input and applies one full-resolution 3x3 conv to RGB. This is how the ``fast*``
configurations save most of the full-resolution work.

Registered configurations (:data:`CONFIGS`). Parameters count ``W``, ``s`` and ``b``; GFLOP for
one 1280x720 image at 2 FLOP per multiply-add; time = median end-to-end CPU inference at
1280x720 (untiled, :class:`~gdpt.reconstruct.dense_unet_reconstructor.DenseUNetReconstructor`,
torch 2.13, 2 *shared* AMD EPYC cores, two runs of ``benchmarks/dense_unet_inference.py`` at
load average ~2 and ~4-5; OIDN ``high`` took 1.2 s and 1.8 s in the same runs):

============  ========  =======  ============  ================================================
name          params    GFLOP    time          notes
============  ========  =======  ============  ================================================
``paper``     4.36 M    2053     22 - 28 s     the published network, 16 input channels
``nograd``    4.35 M    2044     22 - 28 s     the same without dx/dy (10 input channels)
``unet``      4.33 M    1875     27 s          plain U-Net from the same units (dense ablation)
``fast``      1.27 M    206      1.4 - 4.6 s   2x space-to-depth, 3 levels, k = 32/48/64
``fast_xs``   0.47 M    83       1.9 - 2.9 s   2x space-to-depth, 3 levels, k = 24/32/48
============  ========  =======  ============  ================================================

``fast_xs_nograd`` is ``fast_xs`` without dx/dy (10 input channels), the matching ablation.
``fast_xs_res`` / ``fast_xs_res_nograd`` are the same networks predicting a correction of the
input primal (``ModelConfig.residual``; same parameters and cost): our addition for CPU-length
training, where direct prediction (the paper's) had not yet learnt to keep the input's colours.

Layout, dtype, device: :meth:`DenseUNet.forward` takes an ``(N, C_in, H, W)`` float tensor on the
module's device, in either memory format (``torch.channels_last`` is faster on CPU), with ``H``
and ``W`` multiples of :attr:`DenseUNet.alignment`, and returns ``(N, 3, H, W)`` in the same
dtype/device/memory format. Only ``torch`` is imported (layering rule of ``gdpt.reconstruct``).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

_SQRT2 = math.sqrt(2.0)


@dataclass(frozen=True)
class ModelConfig:
    """Hyper-parameters of a :class:`DenseUNet` (all sequences are tuples, one entry per level).

    Attributes:
        in_channels: channels of the network input (16 with gradients, 10 without).
        growth_rates: ``k`` per level; a unit outputs ``k`` channels (its bottleneck ``2k``).
        unit_counts: processing units per level in the encoder half.
        decoder_unit_counts: processing units per level in the decoder half (for the coarsest
            level these simply continue its encoder units).
        pool_features: output channels of the 2x2 stride-2 pooling conv from level ``l`` into
            ``l + 1``; ``levels - 1`` entries.
        unpool_features: output channels of the 2x2 transposed conv from level ``l + 1`` into
            ``l``; ``levels - 1`` entries (index ``l`` = target level).
        dense: dense blocks (NGPT) or a plain U-Net built from the same units.
        bottleneck_factor: a unit's 1x1 bottleneck has ``bottleneck_factor * k`` channels.
        space_to_depth: pixel-unshuffle factor applied to the input (1 = full-resolution net).
        head_features: with ``space_to_depth > 1``, channels pixel-shuffled back to full
            resolution before the final 3x3 conv.
        out_channels: output channels (RGB).
        relu_factor: negative slope of every LeakyReLU.
        weight_norm: weight-normalised convolutions (reference) or plain ones.
        residual: predict a correction of the (log-transformed) input primal, the first three
            input channels, instead of the image itself: the output is ``head(x) + x[:, :3]``
            with no final activation. Not in the paper; see the ``*_res`` configurations. (A
            zero-initialised last layer, i.e. an identity network at the start, trained far
            too slowly: with weight normalisation its gain alone sets the output scale.)
    """

    in_channels: int = 16
    growth_rates: tuple[int, ...] = (40, 80, 80, 80)
    unit_counts: tuple[int, ...] = (4, 3, 2, 2)
    decoder_unit_counts: tuple[int, ...] = (4, 3, 2, 2)
    pool_features: tuple[int, ...] = (160, 160, 160)
    unpool_features: tuple[int, ...] = (80, 160, 160)
    dense: bool = True
    bottleneck_factor: int = 2
    space_to_depth: int = 1
    head_features: int = 0
    out_channels: int = 3
    relu_factor: float = 0.01
    weight_norm: bool = True
    residual: bool = False

    def __post_init__(self) -> None:
        levels = len(self.growth_rates)
        if levels < 1:
            raise ValueError("ModelConfig needs at least one level")
        per_level = {
            "unit_counts": self.unit_counts,
            "decoder_unit_counts": self.decoder_unit_counts,
        }
        for name, value in per_level.items():
            if len(value) != levels:
                raise ValueError(f"{name} has {len(value)} entries, expected {levels} (levels)")
        for name in ("pool_features", "unpool_features"):
            if len(getattr(self, name)) != levels - 1:
                raise ValueError(
                    f"{name} has {len(getattr(self, name))} entries, expected {levels - 1}"
                )
        if self.space_to_depth < 1:
            raise ValueError(f"space_to_depth must be >= 1, got {self.space_to_depth}")
        if self.space_to_depth > 1 and self.head_features < 1:
            raise ValueError("space_to_depth > 1 needs head_features >= 1")

    @property
    def levels(self) -> int:
        """Number of resolutions (``len(growth_rates)``)."""
        return len(self.growth_rates)

    def to_dict(self) -> dict[str, object]:
        """JSON-serialisable form (tuples become lists)."""
        return {
            k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()
        }

    @classmethod
    def from_dict(cls, data: dict[str, object]) -> ModelConfig:
        """Inverse of :meth:`to_dict`.

        Raises:
            ValueError: unknown keys (lists them) or inconsistent values.
        """
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown ModelConfig fields {unknown}; valid: {sorted(known)}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})


#: Named configurations (see the module docstring for sizes, FLOPs and timings).
CONFIGS: dict[str, ModelConfig] = {
    "paper": ModelConfig(),
    "nograd": ModelConfig(in_channels=10),
    "unet": ModelConfig(
        dense=False,
        growth_rates=(56, 112, 112, 112),
        pool_features=(112, 112, 112),
        unpool_features=(56, 112, 112),
    ),
    "fast": ModelConfig(
        space_to_depth=2,
        head_features=16,
        growth_rates=(32, 48, 64),
        unit_counts=(3, 2, 2),
        decoder_unit_counts=(3, 2, 2),
        pool_features=(96, 128),
        unpool_features=(64, 96),
    ),
    "fast_xs": ModelConfig(
        space_to_depth=2,
        head_features=8,
        growth_rates=(24, 32, 48),
        unit_counts=(2, 2, 1),
        decoder_unit_counts=(2, 2, 1),
        pool_features=(64, 96),
        unpool_features=(48, 64),
    ),
}
CONFIGS["fast_xs_nograd"] = dataclasses.replace(CONFIGS["fast_xs"], in_channels=10)
CONFIGS["fast_xs_res"] = dataclasses.replace(CONFIGS["fast_xs"], residual=True)
CONFIGS["fast_xs_res_nograd"] = dataclasses.replace(CONFIGS["fast_xs_nograd"], residual=True)


def get_config(name: str) -> ModelConfig:
    """The registered :class:`ModelConfig` called ``name``.

    Raises:
        ValueError: unknown name (the message lists the valid names).
    """
    if name not in CONFIGS:
        raise ValueError(f"unknown model config {name!r}; valid names: {', '.join(CONFIGS)}")
    return CONFIGS[name]


class Conv(nn.Module):
    """2-D convolution or transposed convolution with optional weight normalisation.

    ``weight`` uses torch's layout (``(C_out, C_in, kh, kw)``, or ``(C_in, C_out, kh, kw)`` when
    ``transposed``); normalisation is over dims 1-3, i.e. per output channel of a convolution
    and per input channel of a transposed convolution (the reference's TF convention). Odd
    kernels use ``SAME`` zero padding, even ones (the 2x2 stride-2 resampling) none.

    Args:
        in_channels: input channels.
        out_channels: output channels.
        kernel_size: square kernel size.
        stride: stride (2 for the pooling/unpooling layers, else 1).
        transposed: transposed convolution (unpooling).
        weight_norm: apply ``W * s * sqrt(2) / ||W||`` with a learnable ``s`` (``gain``).
        scale: resolution of this layer's *input* relative to the network input (bookkeeping
            for :meth:`DenseUNet.flops`).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int,
        *,
        stride: int = 1,
        transposed: bool = False,
        weight_norm: bool = True,
        scale: int = 1,
    ) -> None:
        super().__init__()
        self.in_channels, self.out_channels = in_channels, out_channels
        self.kernel_size, self.stride, self.transposed = kernel_size, stride, transposed
        self.scale = scale
        shape = (in_channels, out_channels) if transposed else (out_channels, in_channels)
        self.weight = nn.Parameter(torch.empty(*shape, kernel_size, kernel_size))
        fan_in = self.weight[0].numel()  # TF's fan-in for both layouts (see class docstring)
        nn.init.normal_(self.weight, std=math.sqrt(2.0 / fan_in))
        self.gain = nn.Parameter(torch.ones(shape[0])) if weight_norm else None
        self.bias = nn.Parameter(torch.zeros(out_channels))

    def effective_weight(self) -> torch.Tensor:
        """The weight the convolution applies (normalised when ``weight_norm`` is on)."""
        if self.gain is None:
            return self.weight
        norm = torch.rsqrt(1e-8 + self.weight.square().sum(dim=(1, 2, 3)))
        return self.weight * (self.gain * (_SQRT2 * norm)).view(-1, 1, 1, 1)

    def fold_weight_norm(self) -> None:
        """Replace ``weight`` by :meth:`effective_weight` and drop ``gain`` (inference only)."""
        if self.gain is not None:
            with torch.no_grad():
                self.weight.copy_(self.effective_weight())
            self.gain = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Apply the layer to an ``(N, C_in, H, W)`` tensor."""
        w = self.effective_weight()
        if self.transposed:
            return F.conv_transpose2d(x, w, self.bias, stride=self.stride)
        return F.conv2d(x, w, self.bias, stride=self.stride, padding=(self.kernel_size - 1) // 2)

    def flops(self, height: int, width: int) -> int:
        """FLOPs (2 per multiply-add) for a network input of ``height x width``."""
        h, w = height // self.scale, width // self.scale
        if self.transposed:
            out_pixels = h * w * self.stride**2
        else:
            out_pixels = (h // self.stride) * (w // self.stride)
        return 2 * self.in_channels * self.out_channels * self.kernel_size**2 * out_pixels


class Unit(nn.Module):
    """Processing unit: 1x1 conv to ``b*k`` + LeakyReLU, 3x3 conv to ``k`` + LeakyReLU.

    Args:
        in_channels: channels the unit reads.
        k: output channels (growth rate).
        cfg: supplies ``bottleneck_factor``, ``relu_factor`` and ``weight_norm``.
        scale: resolution of the unit's level relative to the network input.
    """

    def __init__(self, in_channels: int, k: int, cfg: ModelConfig, scale: int) -> None:
        super().__init__()
        wn, width = cfg.weight_norm, cfg.bottleneck_factor * k
        self.bottleneck = Conv(in_channels, width, 1, weight_norm=wn, scale=scale)
        self.conv = Conv(width, k, 3, weight_norm=wn, scale=scale)
        self.slope = cfg.relu_factor

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(N, C_in, H, W) -> (N, k, H, W)``."""
        x = F.leaky_relu(self.bottleneck(x), self.slope)
        return F.leaky_relu(self.conv(x), self.slope)

    def append_to(self, buf: torch.Tensor, used: int) -> int:
        """Inference: read ``buf[:, :used]``, write the output to ``buf[:, used:used + k]``.

        The 1x1 bottleneck is a matrix product on the channels-last buffer's ``(N*H*W, C)`` view,
        which reads the channel prefix in place; nothing is concatenated.

        Args:
            buf: ``(N, C_total, H, W)`` channels-last level buffer (no autograd).
            used: channels of ``buf`` already filled.

        Returns:
            The new number of filled channels.
        """
        n, c_total, h, w = buf.shape
        k = self.conv.out_channels
        flat = buf.permute(0, 2, 3, 1).view(-1, c_total)[:, :used]
        weight = self.bottleneck.effective_weight().view(-1, used)
        hidden = torch.addmm(self.bottleneck.bias, flat, weight.t())
        hidden = F.leaky_relu_(hidden, self.slope).view(n, h, w, -1).permute(0, 3, 1, 2)
        buf[:, used : used + k] = F.leaky_relu_(self.conv(hidden), self.slope)
        return used + k


class DenseUNet(nn.Module):
    """Dense (or plain) U-Net described by a :class:`ModelConfig`.

    Under autograd the dense lists are concatenated with ``torch.cat``; without autograd
    (``torch.no_grad``/``torch.inference_mode``) each level is one preallocated channels-last
    buffer that the units append to in place (same result, roughly half the time on CPU).

    Args:
        config: the hyper-parameters.
        name: registry name recorded in checkpoints (``None`` for an unregistered config).

    Example::

        model = build_model("paper")                 # 4.36 M parameters
        y = model(x)                                 # x: (1, 16, 720, 1280), 720 % 8 == 0
    """

    def __init__(self, config: ModelConfig, name: str | None = None) -> None:
        super().__init__()
        self.config, self.name = config, name
        cfg, s, wn = config, config.space_to_depth, config.weight_norm
        self.encoders = nn.ModuleList()
        self.decoders = nn.ModuleList()
        self.pools = nn.ModuleList()
        self.unpools = nn.ModuleList()
        #: Per level: channels of the feature list after the encoder and at the very end.
        self.list_widths: list[tuple[int, int]] = []

        def add_units(count: int, width: int, level: int) -> tuple[nn.ModuleList, int]:
            """``count`` units reading a list of ``width`` channels; return them + new width."""
            units, k, scale = nn.ModuleList(), cfg.growth_rates[level], s * 2**level
            for _ in range(count):
                units.append(Unit(width, k, cfg, scale))
                width = width + k if cfg.dense else k
            return units, width

        width = cfg.in_channels * s * s
        for level in range(cfg.levels):
            units, width = add_units(cfg.unit_counts[level], width, level)
            self.encoders.append(units)
            self.list_widths.append((width, width))
            if level < cfg.levels - 1:
                self.pools.append(
                    Conv(
                        width,
                        cfg.pool_features[level],
                        2,
                        stride=2,
                        weight_norm=wn,
                        scale=s * 2**level,
                    )
                )
                width = cfg.pool_features[level]
        for level in reversed(range(cfg.levels)):
            if level < cfg.levels - 1:
                self.unpools.insert(
                    0,
                    Conv(
                        width,
                        cfg.unpool_features[level],
                        2,
                        stride=2,
                        transposed=True,
                        weight_norm=wn,
                        scale=s * 2 ** (level + 1),
                    ),
                )
                width = self.list_widths[level][0] + cfg.unpool_features[level]
            units, width = add_units(cfg.decoder_unit_counts[level], width, level)
            self.decoders.insert(0, units)
            self.list_widths[level] = (self.list_widths[level][0], width)
        if s == 1:
            self.head = nn.ModuleList([Conv(width, cfg.out_channels, 1, weight_norm=wn)])
        else:
            self.head = nn.ModuleList(
                [
                    Conv(width, cfg.head_features * s * s, 1, weight_norm=wn, scale=s),
                    Conv(cfg.head_features + cfg.in_channels, cfg.out_channels, 3, weight_norm=wn),
                ]
            )

    @property
    def alignment(self) -> int:
        """Input height and width must be multiples of this (``space_to_depth * 2**(L-1)``)."""
        return self.config.space_to_depth * 2 ** (self.config.levels - 1)

    @property
    def receptive_radius(self) -> int:
        """Upper bound in pixels on how far an input pixel can influence an output pixel.

        Output pixels farther than this from a tile border are unaffected by the border, which is
        what tiled inference relies on. Each 3x3 conv at scale ``f`` adds ``f``, each 2x2
        (un)pooling between scales ``f`` and ``2f`` adds ``2f``; space-to-depth by ``s`` adds
        ``2s`` and the full-resolution head conv 1.
        """
        cfg, s = self.config, self.config.space_to_depth
        radius = 2 * s + 1 if s > 1 else 0
        for level in range(cfg.levels):
            f = s * 2**level
            radius += f * (cfg.unit_counts[level] + cfg.decoder_unit_counts[level])
            if level < cfg.levels - 1:
                radius += 2 * (2 * f)  # pool in, unpool out
        return radius

    def flops(self, height: int, width: int) -> int:
        """FLOPs (2 per multiply-add) of one forward pass at ``height x width``."""
        return sum(m.flops(height, width) for m in self.modules() if isinstance(m, Conv))

    def fuse(self) -> DenseUNet:
        """An inference copy with weight normalisation folded into the weights.

        Same outputs (to float rounding), fewer small ops per call; not meant for training.
        """
        fused = copy.deepcopy(self)
        for module in fused.modules():
            if isinstance(module, Conv):
                module.fold_weight_norm()
        fused.config = dataclasses.replace(self.config, weight_norm=False)
        return fused

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Reconstruct in log space.

        Args:
            x: ``(N, C_in, H, W)`` float tensor on the module's device; ``H`` and ``W``
                multiples of :attr:`alignment`.

        Returns:
            ``(N, 3, H, W)`` tensor, same dtype and device as ``x`` (channels-last when ``x`` is
            or when autograd is off).

        Raises:
            ValueError: wrong channel count or unaligned size.
        """
        cfg = self.config
        if x.dim() != 4 or x.shape[1] != cfg.in_channels:
            raise ValueError(f"expected input (N, {cfg.in_channels}, H, W), got {tuple(x.shape)}")
        a = self.alignment
        if x.shape[2] % a or x.shape[3] % a:
            raise ValueError(
                f"input size {x.shape[2]}x{x.shape[3]} must be a multiple of {a} (pad first)"
            )
        net_in = x
        if cfg.space_to_depth > 1:
            x = F.pixel_unshuffle(x, cfg.space_to_depth)
        if cfg.dense and not torch.is_grad_enabled():
            y = self._forward_buffers(x.contiguous(memory_format=torch.channels_last))
        else:
            y = self._forward_lists(x)
        if cfg.space_to_depth > 1:
            y = F.leaky_relu(self.head[0](y), cfg.relu_factor)
            y = self.head[1](torch.cat([F.pixel_shuffle(y, cfg.space_to_depth), net_in], dim=1))
        else:
            y = self.head[0](y)
        if cfg.residual:
            return y + net_in[:, :3]
        return F.leaky_relu(y, cfg.relu_factor)

    def _forward_lists(self, x: torch.Tensor) -> torch.Tensor:
        """Encoder/decoder with Python lists of feature maps (autograd-friendly)."""
        cfg, slope = self.config, self.config.relu_factor
        skips: list[list[torch.Tensor]] = []
        features = [x]
        for level in range(cfg.levels):
            features = self._run_units(self.encoders[level], features)
            skips.append(features)
            if level < cfg.levels - 1:
                features = [F.leaky_relu(self.pools[level](_cat(features)), slope)]
        for level in reversed(range(cfg.levels)):
            if level < cfg.levels - 1:
                up = F.leaky_relu(self.unpools[level](_cat(features)), slope)
                if cfg.dense:
                    features = [*skips[level], up]
                else:
                    features = [torch.cat([skips[level][-1], up], dim=1)]
            features = self._run_units(self.decoders[level], features)
        return _cat(features)

    def _run_units(self, units: nn.ModuleList, features: list[torch.Tensor]) -> list[torch.Tensor]:
        for unit in units:
            out = unit(_cat(features))
            features = [*features, out] if self.config.dense else [out]
        return features

    def _forward_buffers(self, x: torch.Tensor) -> torch.Tensor:
        """Dense encoder/decoder on one preallocated channels-last buffer per level."""
        cfg, slope = self.config, self.config.relu_factor
        buffers: list[torch.Tensor] = []
        used: list[int] = []
        level_in = x
        for level in range(cfg.levels):
            n, c, h, w = level_in.shape
            buf = torch.empty(
                (n, self.list_widths[level][1], h, w),
                dtype=x.dtype,
                device=x.device,
                memory_format=torch.channels_last,
            )
            buf[:, :c] = level_in
            for unit in self.encoders[level]:
                c = unit.append_to(buf, c)
            buffers.append(buf)
            used.append(c)
            if level < cfg.levels - 1:
                level_in = F.leaky_relu_(self.pools[level](buf[:, :c]), slope)
        for level in reversed(range(cfg.levels)):
            buf, c = buffers[level], used[level]
            if level < cfg.levels - 1:
                up = F.leaky_relu_(self.unpools[level](buffers.pop()), slope)
                buf[:, c : c + up.shape[1]] = up
                c += up.shape[1]
            for unit in self.decoders[level]:
                c = unit.append_to(buf, c)
        return buffers[0]


def _cat(features: list[torch.Tensor]) -> torch.Tensor:
    return features[0] if len(features) == 1 else torch.cat(features, dim=1)


def build_model(name: str) -> DenseUNet:
    """A freshly initialised :class:`DenseUNet` for the registered configuration ``name``.

    Raises:
        ValueError: unknown name (lists the valid ones).
    """
    return DenseUNet(get_config(name), name=name)


def parameter_count(model: nn.Module) -> int:
    """Number of scalar parameters of ``model``."""
    return sum(p.numel() for p in model.parameters())
