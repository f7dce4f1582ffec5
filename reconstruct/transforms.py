"""Input/output transforms, network-input assembly, padding and geometric augmentation for NGPT.

Everything here acts on the project's HWC buffers (``(..., H, W, C)`` float tensors, at most one
leading batch dimension where noted) and follows the reference implementation of Kettunen et al.
2019 (and its public code, ``github.com/mkettune/ngpt``):

==========  ========  ======================================  ===============================
buffer      channels  transform (:data:`INPUT_TRANSFORMS`)    padding (:func:`pad_buffers`)
==========  ========  ======================================  ===============================
primal      3         ``log(1 + max(0, x))``                  reflect
dx          3         ``sign(x) log(1 + |x|)``                antisymmetric in x, reflect in y
dy          3         ``sign(x) log(1 + |x|)``                antisymmetric in y, reflect in x
albedo      3         raw                                     reflect
normal      3         raw (camera space)                      reflect
depth       1         ``x * s / (1e-10 + max(x))``, ``s=1``   odd reflect
==========  ========  ======================================  ===============================

The network output ``y`` maps back to radiance with :data:`OUTPUT_TRANSFORM` (``exp(y) - 1``).

Gradient convention (``gdpt.buffers``)::

    dx[y, x] = I[y, x + 1] - I[y, x]      (last column unused, 0)
    dy[y, x] = I[y + 1, x] - I[y, x]      (last row unused, 0)

The antisymmetric padding of ``dx`` (drop the unused last column, mirror with negation in x,
append a zero column, reflect in y) is exactly the forward difference of the reflect-padded image
(:func:`pad_buffers`); likewise the geometric augmentations :func:`flip_x`, :func:`flip_y` and
:func:`transpose` map the gradients of an image to the gradients of the flipped/transposed image
(with the unused last column/row set to 0; the reference code fills it with a copy instead).

Non-finite policy: NaN and +-Inf in any input buffer are replaced by 0 *before* the transform
(:func:`sanitize`), so the network never sees them and never produces NaN from them.

Only ``torch`` is imported (layering rule of ``gdpt.reconstruct``); every function runs on the
device of its inputs.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import torch

from .channels import CHANNELS

#: Buffer name -> channel count of the network input features, in network-input order (the
#: first six rows of :data:`.channels.CHANNELS`).
FEATURE_CHANNELS: dict[str, int] = {
    name: CHANNELS[name] for name in ("primal", "dx", "dy", "albedo", "normal", "depth")
}
#: Feature sets of the registered models (16 and 10 input channels).
FEATURES_WITH_GRADIENTS: tuple[str, ...] = ("primal", "dx", "dy", "albedo", "normal", "depth")
FEATURES_WITHOUT_GRADIENTS: tuple[str, ...] = ("primal", "albedo", "normal", "depth")

#: Gradient-like buffers: name -> (axis it differentiates along, negate on a flip of that axis).
#: Variances of gradients shift like the gradients but do not change sign.
_GRADIENTS: dict[str, tuple[str, bool]] = {
    "dx": ("x", True),
    "dy": ("y", True),
    "var_dx": ("x", False),
    "var_dy": ("y", False),
}
#: Buffers swapped by :func:`transpose`.
_TRANSPOSE_SWAP: dict[str, str] = {"dx": "dy", "dy": "dx", "var_dx": "var_dy", "var_dy": "var_dx"}


# ----------------------------------------------------------------------------- transforms
#: Largest log-radiance the output transform maps back: ``exp(40) - 1 ~ 2.4e17`` stays finite
#: in float32 even when squared by a loss, so an untrained or diverging network cannot make the
#: loss NaN through an overflowing ``exp``.
LOG_RADIANCE_MAX = 40.0


class Log1p:
    """Primal / output transform: ``forward(x) = log(1 + max(0, x))``,
    ``inverse(y) = exp(min(y, LOG_RADIANCE_MAX)) - 1``.

    ``inverse(forward(x)) == x`` for ``0 <= x <= exp(LOG_RADIANCE_MAX) - 1`` (to float rounding).
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Tensor of any shape -> same shape/dtype/device."""
        return torch.log1p(x.clamp_min(0))

    def inverse(self, y: torch.Tensor) -> torch.Tensor:
        """Tensor of any shape -> same shape/dtype/device."""
        return torch.expm1(y.clamp_max(LOG_RADIANCE_MAX))


class SignedLog1p:
    """Gradient transform: ``forward(x) = sign(x) log(1 + |x|)``; exact inverse."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Tensor of any shape -> same shape/dtype/device."""
        return torch.sign(x) * torch.log1p(x.abs())

    def inverse(self, y: torch.Tensor) -> torch.Tensor:
        """Tensor of any shape -> same shape/dtype/device."""
        return torch.sign(y) * torch.expm1(y.abs())


class Identity:
    """Albedo / normal transform (raw values)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Returns ``x`` unchanged."""
        return x

    def inverse(self, y: torch.Tensor) -> torch.Tensor:
        """Returns ``y`` unchanged."""
        return y


@dataclass(frozen=True)
class DepthNormalize:
    """Depth transform: ``forward(x) = x * scale / (1e-10 + max(x))`` maps depth to ``[0, scale]``.

    The maximum is taken per image over ``(H, W, C)`` (per batch entry for ``(N, H, W, C)``).
    Inference uses ``scale = 1``; training draws ``scale ~ U(0.1, 1.1)`` per crop (reference), so
    that 1.0 is not an outlier. The inverse needs the maximum the forward pass divided by.

    Attributes:
        scale: upper end ``s`` of the output range ``[0, s]``.
    """

    scale: float = 1.0

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(H, W, C)`` or ``(N, H, W, C)`` -> same shape/dtype/device."""
        return x * (self.scale / (1e-10 + _image_max(x)))

    def inverse(self, y: torch.Tensor, depth_max: torch.Tensor | float) -> torch.Tensor:
        """Undo :meth:`forward` given the ``max(x)`` it used (scalar or ``(N, 1, 1, 1)``)."""
        return y * ((1e-10 + depth_max) / self.scale)


def _image_max(x: torch.Tensor) -> torch.Tensor:
    """Max over the last three dims, broadcastable against ``x``."""
    return x.amax(dim=(-3, -2, -1), keepdim=True)


#: Buffer name -> transform applied before the buffer enters the network.
INPUT_TRANSFORMS: dict[str, Log1p | SignedLog1p | Identity | DepthNormalize] = {
    "primal": Log1p(),
    "dx": SignedLog1p(),
    "dy": SignedLog1p(),
    "albedo": Identity(),
    "normal": Identity(),
    "depth": DepthNormalize(),
}
#: Network output (log space) -> radiance: ``exp(y) - 1``; its ``forward`` maps training
#: targets into the network's output space.
OUTPUT_TRANSFORM = Log1p()


def sanitize(x: torch.Tensor) -> torch.Tensor:
    """Replace NaN and +-Inf by 0 (the documented non-finite input policy); same shape."""
    return torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)


def transform_buffers(
    buffers: Mapping[str, torch.Tensor], features: Sequence[str], *, depth_scale: float = 1.0
) -> dict[str, torch.Tensor]:
    """Validate, sanitise and transform the feature buffers the network reads.

    Args:
        buffers: name -> ``(H, W, C)`` or ``(N, H, W, C)`` float tensor, all on one device with
            one spatial size; extra names are ignored.
        features: names to use, in network order (e.g. :data:`FEATURES_WITH_GRADIENTS`).
        depth_scale: ``scale`` of :class:`DepthNormalize` (1 at inference).

    Returns:
        name -> transformed tensor (same shape, float32 unless the input was float64).

    Raises:
        KeyError: buffers missing (all missing names are listed).
        ValueError: wrong rank or channel count, mismatched sizes, or an unknown feature.
    """
    unknown = [f for f in features if f not in FEATURE_CHANNELS]
    if unknown:
        raise ValueError(f"unknown features {unknown}; known: {list(FEATURE_CHANNELS)}")
    missing = [f for f in features if f not in buffers or buffers[f] is None]
    if missing:
        raise KeyError(f"missing feature buffers {missing}; the model reads {list(features)}")
    out: dict[str, torch.Tensor] = {}
    size = None
    for name in features:
        t = buffers[name]
        c = FEATURE_CHANNELS[name]
        if t.dim() not in (3, 4) or t.shape[-1] != c:
            raise ValueError(
                f"buffer '{name}' must have shape (H, W, {c}) or (N, H, W, {c}), "
                f"got {tuple(t.shape)}"
            )
        if size is None:
            size = tuple(t.shape[:-1])
        elif tuple(t.shape[:-1]) != size:
            raise ValueError(
                f"buffer '{name}' has shape {tuple(t.shape)}, expected {size} + "
                f"({c},) like '{features[0]}'"
            )
        if not t.is_floating_point() or t.dtype in (torch.float16, torch.bfloat16):
            t = t.float()
        transform = DepthNormalize(depth_scale) if name == "depth" else INPUT_TRANSFORMS[name]
        out[name] = transform.forward(sanitize(t))
    return out


def stack_input(buffers: Mapping[str, torch.Tensor], features: Sequence[str]) -> torch.Tensor:
    """Concatenate HWC buffers into the NCHW network input.

    Args:
        buffers: name -> ``(H, W, C)`` or ``(N, H, W, C)`` tensor (already transformed/padded).
        features: names in network order.

    Returns:
        ``(N, sum C, H, W)`` tensor (``N = 1`` for unbatched buffers), channels-last memory.
    """
    x = torch.cat([buffers[name] for name in features], dim=-1)
    if x.dim() == 3:
        x = x.unsqueeze(0)
    return x.permute(0, 3, 1, 2)


# ----------------------------------------------------------------------------- padding
@dataclass(frozen=True)
class Padding:
    """Pixels added on each side of an image.

    Attributes:
        top, bottom, left, right: non-negative pad widths.
    """

    top: int = 0
    bottom: int = 0
    left: int = 0
    right: int = 0


def padding_for(height: int, width: int, alignment: int, margin: int = 8) -> Padding:
    """Padding that puts ``margin`` pixels on every side and makes both sizes multiples of
    ``alignment`` (the remainder goes to the bottom/right).

    The reference pads 8 px on every side (``PAD_WIDTH``), which is what the network saw during
    training; ``margin=0`` gives the smallest aligned size.
    """

    def extra(n: int) -> int:
        return -(n + 2 * margin) % alignment

    return Padding(margin, margin + extra(height), margin, margin + extra(width))


def _reflect_index(n: int, before: int, after: int, device: torch.device) -> torch.Tensor:
    """Source index of every padded position for 'reflect' padding of any width (periodic
    mirror without repeating the edge, as repeated ``np.pad(..., 'reflect')``)."""
    pos = torch.arange(-before, n + after, device=device)
    if n == 1:
        return torch.zeros_like(pos)
    period = 2 * (n - 1)
    pos = pos.remainder(period)
    return torch.where(pos < n, pos, period - pos)


def _pad_axis(
    x: torch.Tensor, dim: int, before: int, after: int, kind: str, negate: bool = True
) -> torch.Tensor:
    """Pad one spatial axis of ``x``.

    Args:
        x: tensor to pad.
        dim: axis to pad.
        before, after: pad widths.
        kind: ``'reflect'``; ``'odd'`` (odd reflection about the edge value, folded repeatedly
            for pads wider than the image); ``'diff'`` (``x`` holds forward differences along
            ``dim``: the result is the forward difference of the reflect-padded image, with the
            unused last entry 0, i.e. the reference's antisymmetric padding).
        negate: for ``'diff'``, flip the sign of mirrored differences (``False`` for variances).
    """
    n = x.shape[dim]
    if before == after == 0:
        return x
    if kind == "reflect":
        return x.index_select(dim, _reflect_index(n, before, after, x.device))
    if kind == "odd":
        while before or after:
            b, a = (before, after) if n == 1 else (min(before, n - 1), min(after, n - 1))
            edge = torch.arange(-b, n + a, device=x.device).clamp(0, n - 1)
            mirror = _reflect_index(n, b, a, x.device)
            x = 2 * x.index_select(dim, edge) - x.index_select(dim, mirror)
            before, after, n = before - b, after - a, n + b + a
        return x
    # 'diff': padded[p] = I[r(p + 1)] - I[r(p)] = +-d[min(r(p), r(p + 1))]
    r = _reflect_index(n, before, after + 1, x.device)
    lo, hi = r[:-1], r[1:]
    sign = (hi - lo).to(x.dtype)
    if not negate:
        sign = sign.abs()
    shape = [1] * x.dim()
    shape[dim] = -1
    out = x.index_select(dim, torch.minimum(lo, hi).clamp_max(max(n - 2, 0))) * sign.view(shape)
    out.narrow(dim, out.shape[dim] - 1, 1).zero_()
    return out


def _pad_kinds(name: str) -> tuple[str, str, bool]:
    """(kind along y, kind along x, negate) for buffer ``name``."""
    if name in _GRADIENTS:
        axis, negate = _GRADIENTS[name]
        return ("diff", "reflect", negate) if axis == "y" else ("reflect", "diff", negate)
    if name == "depth":
        return "odd", "odd", True
    return "reflect", "reflect", True


def pad_buffers(buffers: Mapping[str, torch.Tensor], padding: Padding) -> dict[str, torch.Tensor]:
    """Mirror-pad every buffer as the reference does (see the module table).

    Works for any pad width (also wider than the image). Gradient buffers (``dx``, ``dy`` and
    their variances) get the antisymmetric padding, ``depth`` odd reflection, everything else
    reflection. The transforms are sign-odd (gradients) or pointwise, so padding commutes with
    them except for the depth normalisation (the reference transforms first, then pads).

    Args:
        buffers: name -> ``(H, W, C)`` or ``(N, H, W, C)`` tensor.
        padding: pad widths.

    Returns:
        name -> ``(..., H + top + bottom, W + left + right, C)`` tensor.
    """
    out = {}
    for name, t in buffers.items():
        kind_y, kind_x, negate = _pad_kinds(name)
        t = _pad_axis(t, t.dim() - 3, padding.top, padding.bottom, kind_y, negate)
        out[name] = _pad_axis(t, t.dim() - 2, padding.left, padding.right, kind_x, negate)
    return out


def crop(x: torch.Tensor, padding: Padding) -> torch.Tensor:
    """Remove ``padding`` from an ``(..., H, W, C)`` tensor (inverse of :func:`pad_buffers`)."""
    h, w = x.shape[-3], x.shape[-2]
    return x[..., padding.top : h - padding.bottom, padding.left : w - padding.right, :]


# ----------------------------------------------------------------------------- augmentation
def _shift_flip(t: torch.Tensor, dim: int, negate: bool) -> torch.Tensor:
    """Forward differences of the flipped image from those of the image (last entry 0)."""
    n = t.shape[dim]
    flipped = t.narrow(dim, 0, n - 1).flip(dim)
    return torch.cat(
        [-flipped if negate else flipped, torch.zeros_like(t.narrow(dim, 0, 1))], dim=dim
    )


def _flip(buffers: Mapping[str, torch.Tensor], axis: str) -> dict[str, torch.Tensor]:
    out = {}
    for name, t in buffers.items():
        dim = t.dim() - (2 if axis == "x" else 3)
        grad = _GRADIENTS.get(name)
        if grad is not None and grad[0] == axis:
            out[name] = _shift_flip(t, dim, negate=grad[1])
            continue
        t = t.flip(dim)
        if name == "normal":
            channel = 0 if axis == "x" else 1
            t = torch.cat(
                [t[..., :channel], -t[..., channel : channel + 1], t[..., channel + 1 :]], dim=-1
            )
        out[name] = t
    return out


def flip_x(buffers: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Mirror a buffer set left-right.

    Images flip; ``dx`` becomes the negated, one-pixel-shifted mirror (``dx'[x] = -dx[W-2-x]``,
    last column 0) and ``var_dx`` the same without negation; ``normal.x`` changes sign.

    Args:
        buffers: name -> ``(H, W, C)`` or ``(N, H, W, C)`` tensor (any device).

    Returns:
        name -> tensor of the same shape.
    """
    return _flip(buffers, "x")


def flip_y(buffers: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Mirror a buffer set top-bottom (``dy``/``var_dy`` shifted, ``normal.y`` negated).

    Args:
        buffers: name -> ``(H, W, C)`` or ``(N, H, W, C)`` tensor (any device).

    Returns:
        name -> tensor of the same shape.
    """
    return _flip(buffers, "y")


def transpose(buffers: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Swap the image axes of a buffer set: ``dx <-> dy`` (and their variances) swap,
    ``normal`` x and y components swap.

    Args:
        buffers: name -> ``(H, W, C)`` or ``(N, H, W, C)`` tensor (any device).

    Returns:
        name -> ``(..., W, H, C)`` tensor.
    """
    out = {}
    for name, t in buffers.items():
        t = t.transpose(-3, -2)
        if name == "normal":
            t = torch.cat([t[..., 1:2], t[..., 0:1], t[..., 2:]], dim=-1)
        out[_TRANSPOSE_SWAP.get(name, name)] = t
    return out


#: Name -> geometric augmentation (all eight flips/transposes are compositions of these).
AUGMENTATIONS: dict[str, Callable[[Mapping[str, torch.Tensor]], dict[str, torch.Tensor]]] = {
    "flip_x": flip_x,
    "flip_y": flip_y,
    "transpose": transpose,
}
