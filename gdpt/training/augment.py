"""The random augmentations of a training sample, after NGPT's (Kettunen et al. 2019; the
augmentations and padding variation enabled in ``reconstruct/config.py`` of the public code,
``github.com/mkettune/ngpt``).

:func:`sample_augmentation` draws an :class:`AugmentParams`: a random sub-crop, x/y flips and
transposition (applied with the gradient rules of :mod:`gdpt.reconstruct.transforms`), RGB
permutation, colour multiplier ``3 (u, v, w)`` uniform on the simplex (mean 1) on colour,
gradients, albedo and target, log-normal brightness ``exp(N(0, 1)) / e^0.5`` (mean 1) on colour,
gradients and target only, depth scale ``U(0.1, 1.1)`` and a mirror-padding offset in
``+-vary_padding``. :func:`augment` applies it to a buffer set, :func:`padding_of` gives the
padding.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from gdpt.reconstruct.transforms import AUGMENTATIONS, Padding

if TYPE_CHECKING:
    from gdpt.training.config import TrainConfig

#: Buffers scaled by the colour multiplier and permuted by the channel permutation.
COLOUR_BUFFERS = ("primal", "dx", "dy", "albedo", "target")
#: Buffers scaled by the brightness multiplier (colour and gradients only, not albedo).
BRIGHTNESS_BUFFERS = ("primal", "dx", "dy", "target")
#: Variances of the mean of a colour buffer, scaled by the brightness multiplier squared (not by
#: the colour multiplier: the variance of a colour-scaled image's channel average depends on the
#: covariance of its channels, which a render does not store; the multiplier's mean is 1).
VARIANCE_BUFFERS = ("var_primal",)


@dataclass(frozen=True)
class AugmentParams:
    """One draw of the random augmentations of a training sample (identity by default).

    Attributes:
        origin: ``(y, x)`` of the sub-crop in the dataset crop.
        size: ``(height, width)`` of the sub-crop (``None``: the whole crop).
        flip_x: mirror left-right.
        flip_y: mirror top-bottom.
        transpose: swap the image axes (after the flips).
        permutation: RGB channel order.
        colour: per-channel multiplier (mean 1 when drawn).
        brightness: multiplier of colour and gradients (mean 1 when drawn).
        depth_scale: depth is normalised to ``[0, depth_scale]``.
        offset: ``(dy, dx)`` padding offset: top/left padding is ``pad + offset``.
    """

    origin: tuple[int, int] = (0, 0)
    size: tuple[int, int] | None = None
    flip_x: bool = False
    flip_y: bool = False
    transpose: bool = False
    permutation: tuple[int, int, int] = (0, 1, 2)
    colour: tuple[float, float, float] = (1.0, 1.0, 1.0)
    brightness: float = 1.0
    depth_scale: float = 1.0
    offset: tuple[int, int] = (0, 0)


def sample_augmentation(
    generator: torch.Generator, config: TrainConfig, shape: tuple[int, int]
) -> AugmentParams:
    """Draw the augmentations of one sample.

    Args:
        generator: CPU generator all draws come from.
        config: training settings (``crop``, ``vary_padding``, ``augment``).
        shape: ``(height, width)`` of the dataset crops.

    Returns:
        The draw; with ``config.augment`` false only the sub-crop position is random.
    """

    def uniform(n: int = 1) -> list[float]:
        return torch.rand(n, generator=generator, dtype=torch.float64).tolist()

    height, width = shape
    size = None if config.crop is None else (config.crop, config.crop)
    origin = (0, 0)
    if size is not None:
        origin = (
            int(torch.randint(height - size[0] + 1, (1,), generator=generator)),
            int(torch.randint(width - size[1] + 1, (1,), generator=generator)),
        )
    if not config.augment:
        return AugmentParams(origin=origin, size=size)
    flips = uniform(3)
    square = (size or shape)[0] == (size or shape)[1]
    simplex = -torch.log(torch.rand(3, generator=generator, dtype=torch.float64))
    v = config.vary_padding
    offset = torch.randint(-v, v + 1, (2,), generator=generator).tolist()
    return AugmentParams(
        origin=origin,
        size=size,
        flip_x=flips[0] < 0.5,
        flip_y=flips[1] < 0.5,
        transpose=square and flips[2] < 0.5,
        permutation=tuple(torch.randperm(3, generator=generator).tolist()),
        colour=tuple((3.0 * simplex / simplex.sum()).tolist()),
        brightness=math.exp(float(torch.randn(1, generator=generator, dtype=torch.float64)) - 0.5),
        depth_scale=0.1 + uniform()[0],
        offset=(int(offset[0]), int(offset[1])),
    )


def augment(buffers: Mapping[str, torch.Tensor], params: AugmentParams) -> dict[str, torch.Tensor]:
    """Apply :class:`AugmentParams` (except depth scale and padding) to a buffer set.

    Order: sub-crop (the unused last column of ``dx`` / row of ``dy`` is then set to 0, the
    buffer convention), flips and transposition (:data:`~gdpt.reconstruct.transforms
    .AUGMENTATIONS`: gradients are negated and shifted, swapped, normals follow), channel
    permutation and colour multiplier (:data:`COLOUR_BUFFERS`), brightness
    (:data:`BRIGHTNESS_BUFFERS`; its square on :data:`VARIANCE_BUFFERS`). Every step maps the
    buffers of an image to the buffers of the augmented image (the variance's up to the colour
    multiplier).

    Args:
        buffers: name -> ``(H, W, C)`` float tensor (``primal``, ``dx``, ``dy``, ``albedo``,
            ``normal``, ``depth``, ``var_primal``, ``target``; any subset), one device.
        params: the augmentation draw.

    Returns:
        name -> augmented ``(h, w, C)`` tensor on the same device.
    """
    out = dict(buffers)
    if params.size is not None:
        (y, x), (h, w) = params.origin, params.size
        out = {n: t[y : y + h, x : x + w] for n, t in out.items()}
        if "dx" in out:
            out["dx"] = torch.cat([out["dx"][:, :-1], torch.zeros_like(out["dx"][:, -1:])], 1)
        if "dy" in out:
            out["dy"] = torch.cat([out["dy"][:-1], torch.zeros_like(out["dy"][-1:])], 0)
    for name, active in (
        ("flip_x", params.flip_x),
        ("flip_y", params.flip_y),
        ("transpose", params.transpose),
    ):
        if active:
            out = AUGMENTATIONS[name](out)
    for name in COLOUR_BUFFERS:
        if name in out:
            t = out[name][..., list(params.permutation)]
            out[name] = t * t.new_tensor(params.colour)
    for name in BRIGHTNESS_BUFFERS:
        if name in out:
            out[name] = out[name] * params.brightness
    for name in VARIANCE_BUFFERS:
        if name in out:
            out[name] = out[name] * params.brightness**2
    return out


def padding_of(params: AugmentParams, pad: int) -> Padding:
    """The padding of a sample: ``pad`` on every side, shifted by ``params.offset``."""
    oy, ox = params.offset
    return Padding(pad + oy, pad - oy, pad + ox, pad - ox)
