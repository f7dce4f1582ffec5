"""Intel Open Image Denoise's U-Net in PyTorch, running Intel's published weights.

Source of the architecture, the input/output processing and the weights: Intel Open Image
Denoise, https://github.com/RenderKit/oidn (Apache-2.0): ``training/model.py`` (``UNet``,
``UNet(small=True)``, ``UNetLarge``), ``core/unet_filter.cpp`` (inference graph, model choice by
quality), ``core/rt_filter.cpp`` (weights per input combination, transfer functions),
``core/color.h``/``.cpp`` (PU and sRGB transfer functions), ``devices/cpu/cpu_autoexposure.cpp``,
``devices/cpu/cpu_input_process.isph`` and ``cpu_output_process.isph``. This is a
re-implementation from reading that code; the weights are read at run time from the
OpenImageDenoise library that ``mitsuba-oidn`` installs (or a user's ``.tza``, see
:mod:`reconstruct.tza`) and never stored here.

Network (``OIDNUNet``; 3x3 convs with zero padding, ReLU after every conv but the last, 2x2 max
pool, 2x nearest upsampling, decoder concatenation ``[upsampled, skip]``)::

    base / small:  enc_conv0 -> enc_conv1 -> pool1 -> enc_conv2 -> pool2 -> enc_conv3 -> pool3
                   -> enc_conv4 -> pool4 -> enc_conv5a -> enc_conv5b -> up -> [., pool3]
                   -> dec_conv4a,b -> up -> [., pool2] -> dec_conv3a,b -> up -> [., pool1]
                   -> dec_conv2a,b -> up -> [., input] -> dec_conv1a,b -> dec_conv0
    widths (base, OIDN's ``balanced`` and, without a large model, ``high`` quality):
        enc 32 32 48 64 80 96 96, dec 112 112 96 96 64 64 64 32, out 3
    small (``fast``): enc 32 x7, dec 64 64 64 64 64 32 32 32;
    large (``high`` where OIDN ships one, e.g. ``rt_hdr_calb_cnrm_large``): two convs per
        encoder level (enc_conv1a,b ... 4a,b), 64 96 128 192 256, last conv ``dec_conv1c``.

The module's output is the last conv's raw output (no ReLU: OIDN's inference graph ends in a
ReLU, its output stage clamps to >= 0, and :func:`decode_output` does that clamp, so the result is
the same while training still gets gradients for negative outputs).

Input encoding (:func:`encode_inputs`, as OIDN's RT filter with ``hdr=True``, channels in this
order)::

    colour  : c * s, NaN -> 0, clamp [0, FLT_MAX], PU(.) / PU(65504)       (3 channels)
    albedo  : NaN -> 0, clamp [0, 1]                                       (3, if given)
    normal  : NaN -> 0, clamp [-1, 1], * 0.5 + 0.5 (pass normals in [-1, 1]) (3, if given)

``s`` is OIDN's autoexposure (:func:`autoexposure`): the image is cut into
``ceil(H/16) x ceil(W/16)`` bins, ``L`` = mean luminance of the clamped colour in a bin, and
``s = 0.18 / 2^mean(log2 L over bins with L > 1e-8)`` (1 if there is none). With ``hdr=False``
the colour is clamped to [0, 1], sRGB-encoded and ``s = 1``. The encoded image is padded with
zeros at the bottom and right to a multiple of 16 (OIDN's ``minTileAlignment``; OIDN zero-pads
its tile buffer the same way) and the output cropped back; the output is clamped to
``[0, FLT_MAX]``, inverse-transformed, (LDR: clamped to <= 1) and divided by ``s``. Non-finite
inputs therefore give a finite output; an output that overflows the inverse transfer is also
mapped to a finite value (OIDN would return ``inf`` there).

Not reproduced: OIDN's tiling of images larger than 2160 x 2160 pixels (this runs one tile, so
such images can differ slightly near OIDN's tile seams), the directional lightmap mode and the
``RTLightmap`` filter (its blobs load, but :func:`denoise` runs the ``RT`` filter only), and the
reduced precision of OIDN's ``balanced``/``fast`` modes on some devices.

Extra input channels (the gradient inputs of ``gdpt.reconstruct.oidn_finetune``):
``OIDNUNet(..., extra_channels=k)`` / ``OIDNUNet.from_weights(..., extra_channels=k)`` appends
``k`` input channels after OIDN's (``enc_conv0`` reads ``[oidn inputs, extra]``; so does
``dec_conv1a`` after the upsampled features, since the input joins the last skip). Their
weights in both layers are initialised to zero, so at step 0 the network's output equals OIDN's
bit for bit regardless of the extra inputs; fine-tuning then learns to use them. Pass them to
:func:`denoise` as ``extra=`` (``(H, W, k)``, already transformed as the caller wishes, e.g.
signed-log gradients).

All tensors are float32 on the device of the input colour (no device is hard-coded).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .tza import load_weights, unet_kind

__all__ = [
    "ALIGNMENT",
    "OIDNUNet",
    "autoexposure",
    "decode_output",
    "denoise",
    "encode_inputs",
    "pu_forward",
    "pu_inverse",
    "select_weights",
    "srgb_forward",
    "srgb_inverse",
]

ALIGNMENT = 16  # OIDN's UNetFilter::minTileAlignment
_FLT_MAX = float(np.finfo(np.float32).max)

# Layer widths of training/model.py (OIDN); (name, output channels) in forward order.
_WIDTHS = {
    "base": dict(ec1=32, ec2=48, ec3=64, ec4=80, ec5=96, dc4=112, dc3=96, dc2a=64, dc2b=64,
                 dc1a=64, dc1b=32),
    "small": dict(ec1=32, ec2=32, ec3=32, ec4=32, ec5=32, dc4=64, dc3=64, dc2a=64, dc2b=32,
                  dc1a=32, dc1b=32),
    "large": dict(ec1=64, ec2=96, ec3=128, ec4=192, ec5=256, dc4=192, dc3=128, dc2=96, dc1=64),
}  # fmt: skip


def _layer_specs(kind: str, ic: int, oc: int) -> list[tuple[str, int, int]]:
    """``(name, in, out)`` of every conv of OIDN's U-Net ``kind``."""
    w = _WIDTHS[kind]
    if kind == "large":
        e1, e2, e3, e4, e5 = (w[k] for k in ("ec1", "ec2", "ec3", "ec4", "ec5"))
        d4, d3, d2, d1 = (w[k] for k in ("dc4", "dc3", "dc2", "dc1"))
        return [
            ("enc_conv1a", ic, e1), ("enc_conv1b", e1, e1), ("enc_conv2a", e1, e2),
            ("enc_conv2b", e2, e2), ("enc_conv3a", e2, e3), ("enc_conv3b", e3, e3),
            ("enc_conv4a", e3, e4), ("enc_conv4b", e4, e4), ("enc_conv5a", e4, e5),
            ("enc_conv5b", e5, e5), ("dec_conv4a", e5 + e3, d4), ("dec_conv4b", d4, d4),
            ("dec_conv3a", d4 + e2, d3), ("dec_conv3b", d3, d3), ("dec_conv2a", d3 + e1, d2),
            ("dec_conv2b", d2, d2), ("dec_conv1a", d2 + ic, d1), ("dec_conv1b", d1, d1),
            ("dec_conv1c", d1, oc),
        ]  # fmt: skip
    e1, e2, e3, e4, e5 = (w[k] for k in ("ec1", "ec2", "ec3", "ec4", "ec5"))
    return [
        ("enc_conv0", ic, e1), ("enc_conv1", e1, e1), ("enc_conv2", e1, e2),
        ("enc_conv3", e2, e3), ("enc_conv4", e3, e4), ("enc_conv5a", e4, e5),
        ("enc_conv5b", e5, e5), ("dec_conv4a", e5 + e3, w["dc4"]),
        ("dec_conv4b", w["dc4"], w["dc4"]), ("dec_conv3a", w["dc4"] + e2, w["dc3"]),
        ("dec_conv3b", w["dc3"], w["dc3"]), ("dec_conv2a", w["dc3"] + e1, w["dc2a"]),
        ("dec_conv2b", w["dc2a"], w["dc2b"]), ("dec_conv1a", w["dc2b"] + ic, w["dc1a"]),
        ("dec_conv1b", w["dc1a"], w["dc1b"]), ("dec_conv0", w["dc1b"], oc),
    ]  # fmt: skip


class OIDNUNet(nn.Module):
    """OIDN's U-Net (training/model.py of RenderKit/oidn) with optional extra input channels.

    Args:
        in_channels: OIDN's input channels (3 colour [+ 3 albedo [+ 3 normal]]).
        out_channels: output channels (3).
        kind: ``"base"``, ``"small"`` or ``"large"`` (see the module docstring).
        extra_channels: extra inputs appended after OIDN's; their weights in ``enc_conv0`` (or
            ``enc_conv1a``) and ``dec_conv1a`` are zero after :meth:`load_oidn_state_dict`.

    ``forward(x)``: ``x`` float32 ``(N, in_channels + extra_channels, H, W)`` with ``H`` and
    ``W`` multiples of 16, any device; returns ``(N, out_channels, H, W)``, the raw output of the
    last conv (OIDN then clamps it to >= 0, see :func:`decode_output`).
    """

    def __init__(
        self,
        in_channels: int = 9,
        out_channels: int = 3,
        kind: str = "base",
        extra_channels: int = 0,
    ) -> None:
        super().__init__()
        if kind not in _WIDTHS:
            raise ValueError(f"kind must be one of {sorted(_WIDTHS)}, got {kind!r}")
        if extra_channels < 0:
            raise ValueError("extra_channels must be >= 0")
        self.kind = kind
        self.in_channels = in_channels
        self.extra_channels = extra_channels
        self.out_channels = out_channels
        self.alignment = ALIGNMENT
        ic = in_channels + extra_channels
        specs = _layer_specs(kind, ic, out_channels)
        self.layer_names = [name for name, _, _ in specs]
        for name, cin, cout in specs:
            self.add_module(name, nn.Conv2d(cin, cout, 3, padding=1))
        self._first = self.layer_names[0]

    @classmethod
    def from_weights(
        cls,
        weights: str | Path | dict = "rt_hdr_alb_nrm",
        *,
        extra_channels: int = 0,
        library: str | Path | None = None,
        device: torch.device | str | None = None,
    ) -> OIDNUNet:
        """Build the U-Net that ``weights`` describe and load them.

        Args:
            weights: built-in blob name (e.g. ``"rt_hdr_alb_nrm"``), ``.tza`` path or a state
                dict (see :func:`reconstruct.tza.load_weights`).
            extra_channels: extra zero-weight input channels.
            library: OpenImageDenoise library holding built-in weights (default:
                mitsuba-oidn's).
            device: where to put the module (default CPU).

        Returns:
            The module in eval mode.
        """
        state = load_weights(weights, library=library)
        kind, ic = unet_kind(state)
        last = "dec_conv1c" if kind == "large" else "dec_conv0"
        net = cls(ic, int(state[f"{last}.weight"].shape[0]), kind, extra_channels)
        net.load_oidn_state_dict(state)
        return net.to(device).eval()

    def load_oidn_state_dict(self, state: dict) -> None:
        """Load OIDN's state dict (numpy or torch tensors); the extra channels' weights become
        zero. Shapes must match OIDN's (without the extra channels)."""
        ic, extra = self.in_channels, self.extra_channels
        with torch.no_grad():
            for name in self.layer_names:
                conv: nn.Conv2d = getattr(self, name)
                w = torch.as_tensor(np.asarray(_np(state[f"{name}.weight"])), dtype=torch.float32)
                b = torch.as_tensor(np.asarray(_np(state[f"{name}.bias"])), dtype=torch.float32)
                target = conv.weight
                if name == self._first:
                    full = torch.zeros_like(target, device="cpu")
                    full[:, :ic] = w
                    w = full
                elif name == "dec_conv1a":
                    skip_in = target.shape[1] - ic - extra  # upsampled-feature channels
                    full = torch.zeros_like(target, device="cpu")
                    full[:, : skip_in + ic] = w
                    w = full
                if w.shape != target.shape or b.shape != conv.bias.shape:
                    raise ValueError(
                        f"{name}: weights {tuple(w.shape)} do not fit the layer "
                        f"{tuple(target.shape)}"
                    )
                target.copy_(w)
                conv.bias.copy_(b)

    def extra_input_masks(self) -> dict[str, torch.Tensor]:
        """Parameter name -> float32 mask (1 on the weights that read the extra input channels,
        0 elsewhere; the shape and device of the parameter), for the two layers that read the
        input; empty without extra channels."""
        if not self.extra_channels:
            return {}
        masks = {}
        for name, columns in (
            (self._first, slice(self.in_channels, None)),
            ("dec_conv1a", slice(-self.extra_channels, None)),
        ):
            weight = getattr(self, name).weight
            mask = torch.zeros_like(weight)
            mask[:, columns] = 1.0
            masks[f"{name}.weight"] = mask
        return masks

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        c = lambda name, t: getattr(self, name)(t)  # noqa: E731
        relu = F.relu
        if x.shape[-1] % ALIGNMENT or x.shape[-2] % ALIGNMENT:
            raise ValueError(
                f"spatial size {tuple(x.shape[-2:])} is not a multiple of "
                f"{ALIGNMENT}; pad the input (encode_inputs does)"
            )
        pool = lambda t: F.max_pool2d(t, 2, 2)  # noqa: E731
        up = lambda t: F.interpolate(t, scale_factor=2.0, mode="nearest")  # noqa: E731
        inp = x
        if self.kind == "large":
            x = relu(c("enc_conv1b", relu(c("enc_conv1a", x))))
            p1 = x = pool(x)
            x = relu(c("enc_conv2b", relu(c("enc_conv2a", x))))
            p2 = x = pool(x)
            x = relu(c("enc_conv3b", relu(c("enc_conv3a", x))))
            p3 = x = pool(x)
            x = pool(relu(c("enc_conv4b", relu(c("enc_conv4a", x)))))
            last = ("dec_conv1b", "dec_conv1c")
        else:
            x = relu(c("enc_conv1", relu(c("enc_conv0", x))))
            p1 = x = pool(x)
            p2 = x = pool(relu(c("enc_conv2", x)))
            p3 = x = pool(relu(c("enc_conv3", x)))
            x = pool(relu(c("enc_conv4", x)))
            last = ("dec_conv1b", "dec_conv0")
        x = relu(c("enc_conv5b", relu(c("enc_conv5a", x))))
        for level, skip in (("4", p3), ("3", p2), ("2", p1), ("1", inp)):
            x = torch.cat((up(x), skip), 1)
            x = relu(c(f"dec_conv{level}a", x))
            if level != "1":
                x = relu(c(f"dec_conv{level}b", x))
        x = relu(c(last[0], x))
        return c(last[1], x)


def _np(v: object) -> np.ndarray:
    detach = getattr(v, "detach", None)
    return detach().cpu().numpy() if detach is not None else np.asarray(v)


# ----------------------------------------------------------------------------------------------
# Transfer functions (core/color.h)
# ----------------------------------------------------------------------------------------------

_PU = dict(
    a=1.41283765e03,
    b=1.64593172e00,
    c=4.31384981e-01,
    d=-2.94139609e-03,
    e=1.92653254e-01,
    f=6.26026094e-03,
    g=9.98620152e-01,
    y0=1.57945760e-06,
    y1=3.22087631e-02,
    x0=2.23151711e-03,
    x1=3.70974749e-01,
)
_SRGB = dict(a=12.92, b=1.055, c=1.0 / 2.4, d=-0.055, y0=0.0031308, x0=0.04045)
_Y_MAX = 65504.0  # TransferFunction::yMax


def _pu_raw(y: torch.Tensor) -> torch.Tensor:
    p = _PU
    low = p["a"] * y
    mid = p["b"] * torch.pow(y.clamp_min(p["y0"]), p["c"]) + p["d"]
    high = p["e"] * torch.log(y.clamp_min(p["y1"]) + p["f"]) + p["g"]
    return torch.where(y <= p["y0"], low, torch.where(y <= p["y1"], mid, high))


_PU_NORM = float(np.float32(1.0) / _pu_raw(torch.tensor(_Y_MAX, dtype=torch.float32)).item())


def pu_forward(y: torch.Tensor) -> torch.Tensor:
    """OIDN's PU transfer function normalised so that ``pu_forward(65504) = 1``; ``y >= 0``.
    Same shape/dtype/device as ``y``."""
    return _pu_raw(y) * _PU_NORM


def pu_inverse(x: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`pu_forward` for ``x >= 0``."""
    p = _PU
    x = x * (1.0 / _PU_NORM)
    low = x / p["a"]
    mid = torch.pow(((x.clamp_min(p["x0"]) - p["d"]) / p["b"]), 1.0 / p["c"])
    high = torch.exp((x.clamp_min(p["x1"]) - p["g"]) / p["e"]) - p["f"]
    return torch.where(x <= p["x0"], low, torch.where(x <= p["x1"], mid, high))


def srgb_forward(y: torch.Tensor) -> torch.Tensor:
    """sRGB encoding as OIDN's LDR transfer function (``y`` in [0, 1])."""
    s = _SRGB
    return torch.where(
        y <= s["y0"], s["a"] * y, s["b"] * torch.pow(y.clamp_min(s["y0"]), s["c"]) + s["d"]
    )


def srgb_inverse(x: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`srgb_forward`."""
    s = _SRGB
    return torch.where(
        x <= s["x0"], x / s["a"], torch.pow((x.clamp_min(s["x0"]) - s["d"]) / s["b"], 1.0 / s["c"])
    )


# ----------------------------------------------------------------------------------------------
# Input / output processing
# ----------------------------------------------------------------------------------------------


def _sanitize(x: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    return torch.where(torch.isnan(x), torch.zeros((), dtype=x.dtype, device=x.device), x).clamp(
        lo, hi
    )


def _bin_index(n: int, bins: int, device: torch.device) -> torch.Tensor:
    """Bin of each of ``n`` pixels when OIDN splits them into ``bins`` bins
    (bin ``i`` spans ``[i*n // bins, (i+1)*n // bins)``)."""
    bounds = [i * n // bins for i in range(bins + 1)]
    sizes = torch.tensor(np.diff(bounds), device=device)
    return torch.repeat_interleave(torch.arange(bins, device=device), sizes)


def autoexposure(color: torch.Tensor) -> torch.Tensor:
    """OIDN's autoexposure (``devices/cpu/cpu_autoexposure.cpp``) of an HDR colour image.

    Args:
        color: ``(H, W, 3)`` float32, any device.

    Returns:
        0-d float32 tensor on ``color``'s device: ``0.18 / 2^mean(log2 L)`` over the
        ``16 x 16``-pixel-ish bins whose mean luminance ``L`` exceeds 1e-8, or 1.
    """
    h, w, _ = color.shape
    c = _sanitize(color.float(), 0.0, _FLT_MAX)
    lum = 0.212671 * c[..., 0] + 0.715160 * c[..., 1] + 0.072169 * c[..., 2]
    bh, bw = math.ceil(h / 16), math.ceil(w / 16)
    rows, cols = _bin_index(h, bh, c.device), _bin_index(w, bw, c.device)
    ids = (rows[:, None] * bw + cols[None, :]).reshape(-1)
    sums = torch.zeros(bh * bw, dtype=torch.float32, device=c.device).index_add_(
        0, ids, lum.reshape(-1)
    )
    counts = torch.zeros_like(sums).index_add_(0, ids, torch.ones_like(lum.reshape(-1)))
    mean = sums / counts
    valid = mean > 1e-8
    n = valid.sum()
    log_sum = torch.where(valid, torch.log2(mean.clamp_min(1e-30)), torch.zeros_like(mean)).sum()
    scale = 0.18 / torch.exp2(log_sum / n.clamp_min(1).float())
    return torch.where(n > 0, scale, torch.ones_like(scale))


def encode_inputs(
    color: torch.Tensor,
    albedo: torch.Tensor | None = None,
    normal: torch.Tensor | None = None,
    *,
    hdr: bool = True,
    input_scale: float | torch.Tensor | None = None,
    extra: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """OIDN's input processing (RT filter) and 16-px zero padding.

    Args:
        color: ``(H, W, 3)`` linear colour (HDR: >= 0; LDR: [0, 1]), float32, any device.
        albedo: ``(H, W, 3)`` albedo or ``None``.
        normal: ``(H, W, 3)`` normals in [-1, 1] or ``None`` (needs ``albedo``, as in OIDN).
        hdr: PU-encode with autoexposure (``True``) or sRGB-encode (``False``).
        input_scale: OIDN's ``inputScale``; ``None``: autoexposure (HDR) or 1 (LDR).
        extra: ``(H, W, k)`` extra channels appended as they are (zero-padded), or ``None``.

    Returns:
        ``(x, scale)``: ``x`` float32 ``(1, C, H16, W16)`` on ``color``'s device (``H16``,
        ``W16``: ``H``, ``W`` rounded up to multiples of 16; zeros in the padding) and the
        input scale as a 0-d tensor.
    """
    if color.ndim != 3 or color.shape[-1] != 3:
        raise ValueError(f"color must have shape (H, W, 3), got {tuple(color.shape)}")
    if normal is not None and albedo is None:
        raise ValueError("OIDN has no model for colour + normal without albedo; pass albedo too")
    dev = color.device
    color = color.float()
    h, w, _ = color.shape
    for name, t in (("albedo", albedo), ("normal", normal), ("extra", extra)):
        if t is not None and (t.shape[:2] != (h, w) or t.ndim != 3):
            raise ValueError(f"{name} must have shape ({h}, {w}, C), got {tuple(t.shape)}")
    if input_scale is None:
        scale = autoexposure(color) if hdr else torch.ones((), device=dev)
    else:
        scale = torch.as_tensor(input_scale, dtype=torch.float32, device=dev).reshape(())
    if hdr:
        chans = [pu_forward(_sanitize(color * scale, 0.0, _FLT_MAX))]
    else:
        chans = [srgb_forward(_sanitize(color * scale, 0.0, 1.0))]
    if albedo is not None:
        chans.append(_sanitize(albedo.to(dev, torch.float32), 0.0, 1.0))
    if normal is not None:
        chans.append(_sanitize(normal.to(dev, torch.float32), -1.0, 1.0) * 0.5 + 0.5)
    if extra is not None:
        chans.append(extra.to(dev, torch.float32))
    x = torch.cat(chans, -1).permute(2, 0, 1)[None]
    ph, pw = (-h) % ALIGNMENT, (-w) % ALIGNMENT
    if ph or pw:
        x = F.pad(x, (0, pw, 0, ph))
    return x.contiguous(), scale


def decode_output(
    y: torch.Tensor, height: int, width: int, scale: torch.Tensor, *, hdr: bool = True
) -> torch.Tensor:
    """OIDN's output processing: crop, clamp to [0, FLT_MAX], inverse transfer, divide by the
    input scale (0 if it is 0), and map any overflow to a finite value.

    Args:
        y: ``(1, 3, H16, W16)`` network output.
        height, width: the unpadded size.
        scale: the input scale from :func:`encode_inputs`.
        hdr: as for :func:`encode_inputs`.

    Returns:
        ``(height, width, 3)`` float32 on ``y``'s device.
    """
    v = _sanitize(y[0, :, :height, :width].permute(1, 2, 0), 0.0, _FLT_MAX)
    v = pu_inverse(v) if hdr else srgb_inverse(v).clamp_max(1.0)
    out_scale = torch.where(scale != 0, 1.0 / torch.where(scale != 0, scale, 1.0), 0.0)
    return torch.nan_to_num(v * out_scale, nan=0.0, posinf=_FLT_MAX, neginf=0.0)


def select_weights(
    *,
    albedo: bool,
    normal: bool,
    hdr: bool = True,
    clean_aux: bool = False,
    quality: str = "high",
    available: set[str] | None = None,
) -> str:
    """Name of the built-in blob that OIDN's RT filter uses (``core/unet_filter.cpp``,
    ``getWeights``): ``high`` -> ``<model>_large`` if it exists else ``<model>``, ``balanced`` ->
    ``<model>``, ``fast`` -> ``<model>_small`` if it exists else ``<model>``."""
    if normal and not albedo:
        raise ValueError("OIDN has no model for colour + normal without albedo")
    model = "rt_" + ("hdr" if hdr else "ldr")
    if albedo:
        model += ("_calb_cnrm" if clean_aux else "_alb_nrm") if normal else "_alb"
    if available is None:
        from .tza import builtin_weights  # noqa: PLC0415

        available = set(builtin_weights())
    if quality in ("high", "default"):
        return f"{model}_large" if f"{model}_large" in available else model
    if quality == "balanced":
        return model
    if quality == "fast":
        return f"{model}_small" if f"{model}_small" in available else model
    raise ValueError("quality must be 'high', 'balanced', 'fast' or 'default'")


_MODELS: dict[tuple[str, int, str], OIDNUNet] = {}


def denoise(
    color: torch.Tensor,
    albedo: torch.Tensor | None = None,
    normal: torch.Tensor | None = None,
    *,
    weights: str | Path | dict | OIDNUNet | None = None,
    hdr: bool = True,
    quality: str = "high",
    clean_aux: bool = False,
    input_scale: float | None = None,
    extra: torch.Tensor | None = None,
) -> torch.Tensor:
    """Denoise like OIDN's ``RT`` filter (``mitsuba_oidn.denoise(color, albedo, normal,
    hdr=hdr, quality=quality)``).

    Args:
        color: ``(H, W, 3)`` float32 linear colour, any device (the computation runs there).
        albedo: ``(H, W, 3)`` albedo in [0, 1], or ``None``.
        normal: ``(H, W, 3)`` normals in [-1, 1], or ``None`` (requires ``albedo``).
        weights: ``None`` (OIDN's choice for the given inputs, ``hdr``, ``clean_aux`` and
            ``quality`` from mitsuba-oidn's library), a built-in blob name, a ``.tza`` path, a state
            dict, or an :class:`OIDNUNet` (e.g. one with extra channels, being fine-tuned).
        hdr, quality, clean_aux: as in OIDN's RT filter.
        input_scale: OIDN's ``inputScale`` (``None``: autoexposure for HDR).
        extra: ``(H, W, k)`` extra inputs for a module with ``extra_channels = k``.

    Returns:
        ``(H, W, 3)`` float32, finite, on ``color``'s device. Gradients flow if the module's
        parameters (or the inputs) require them; wrap in ``torch.no_grad()`` for inference.
    """
    if isinstance(weights, OIDNUNet):
        net = weights
    else:
        if weights is None:
            weights = select_weights(
                albedo=albedo is not None,
                normal=normal is not None,
                hdr=hdr,
                clean_aux=clean_aux,
                quality=quality,
            )
        key = (str(weights), 0, str(color.device))
        if isinstance(weights, dict) or key not in _MODELS:
            net = OIDNUNet.from_weights(weights, device=color.device)
            if not isinstance(weights, dict):
                _MODELS[key] = net
        else:
            net = _MODELS[key]
    k = 0 if extra is None else extra.shape[-1]
    n_in = 3 + 3 * (albedo is not None) + 3 * (normal is not None)
    if (net.in_channels, net.extra_channels) != (n_in, k):
        raise ValueError(
            f"the weights expect {net.in_channels} OIDN + {net.extra_channels} "
            f"extra input channels, the inputs give {n_in} + {k}"
        )
    x, scale = encode_inputs(color, albedo, normal, hdr=hdr, input_scale=input_scale, extra=extra)
    h, w, _ = color.shape
    return decode_output(net(x), h, w, scale, hdr=hdr)
