"""Intel Open Image Denoise's own kernels through ``mitsuba-oidn``, with OIDN's built-in weights
or a fine-tuned network's, on the render's tensors without a copy.

``mitsuba-oidn`` (https://github.com/mitsuba-renderer/mitsuba-oidn, BSD-3-Clause) binds Intel
Open Image Denoise (https://github.com/RenderKit/oidn, Apache-2.0) through DLPack: an OIDN
device binds a tensor it can address (``Device.can_share``: contiguous float32 CPU tensors on
its CPU device, CUDA tensors on its CUDA device) without copying it, and the output is written
into a tensor allocated here. Its CPU device shares Dr.Jit's thread pool.

:func:`denoise` runs OIDN's ``RT`` filter (HDR, quality ``high``, colour + albedo + normal) with
OIDN's built-in weights (``rt_hdr_alb_nrm``) or user weights: a TZA blob
(:func:`gdpt.reconstruct.tza.write_tza`) of the same network, checked tensor by tensor before
any filtering. :func:`network_weights` exports a fine-tuned OIDN network that keeps OIDN's
inputs and architecture (the ``oidn-nograd`` design, ``oidn-tuned``) once per network and
process; :func:`reconstruct` runs such a reconstructor natively when no input requires
gradients (autograd, training and networks with other inputs keep the torch path).

Non-finite input values are replaced by 0 (a copy of the buffer that has them), counted and
reported with a ``RuntimeWarning``; the output is finite.
"""

from __future__ import annotations

import importlib.util
import threading
import warnings
import weakref
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch

    from gdpt.reconstruct.oidn_unet import OIDNUNet

__all__ = ["OIDN_WEIGHTS", "check", "check_weights", "denoise", "network_weights", "reconstruct"]

#: OIDN's built-in network that the ``RT`` filter runs for HDR colour + albedo + normal at
#: quality ``high`` (there is no large variant of it); user weights must have its tensors.
OIDN_WEIGHTS = "rt_hdr_alb_nrm"

_lock = threading.Lock()
_devices: dict[tuple[str, int], Any] = {}
_filters: dict[tuple, Any] = {}
_FILTER_CACHE_SIZE = 4
_exported: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def check() -> str | None:
    """``None`` when ``mitsuba-oidn`` (OIDN and its built-in weights) is installed, else why
    not."""
    if importlib.util.find_spec("mitsuba_oidn") is None:
        return "mitsuba-oidn is not installed (pip install mitsuba-oidn)"
    return None


def check_weights(blob: bytes) -> None:
    """Refuse a weights blob that is not a network OIDN's ``RT`` filter can run on colour +
    albedo + normal: every tensor of :data:`OIDN_WEIGHTS`, same names and shapes, float16 (OIDN's
    devices read no other weight type), nothing else.

    Raises:
        gdpt.reconstruct.tza.TZAError: the blob is not a TZA blob.
        ValueError: a tensor is missing, extra, of another shape or not float16 (named).
    """
    import numpy as np

    from gdpt.reconstruct.tza import builtin_weights, parse_tza

    tensors = parse_tza(blob, stored_dtype=True)
    expected = {k: tuple(v.shape) for k, v in builtin_weights()[OIDN_WEIGHTS].tensors.items()}
    for name, shape in expected.items():
        if name not in tensors:
            raise ValueError(f"weights: tensor {name!r} of OIDN's {OIDN_WEIGHTS} is missing")
        if tuple(tensors[name].shape) != shape:
            raise ValueError(
                f"weights: tensor {name!r} has shape {tuple(tensors[name].shape)}, OIDN's "
                f"{OIDN_WEIGHTS} network has {shape}"
            )
    if extra := sorted(set(tensors) - set(expected)):
        raise ValueError(f"weights: tensor {extra[0]!r} is not in OIDN's {OIDN_WEIGHTS} network")
    for name, value in tensors.items():
        if value.dtype != np.float16:
            raise ValueError(f"weights: tensor {name!r} is {value.dtype}; OIDN reads float16")


def _validate(images: dict[str, torch.Tensor]) -> None:
    """Raise ``ValueError`` naming the buffer and its shape for an image the binding refuses."""
    import torch

    color = images["color"]
    for name, t in images.items():
        what = f"the {name!r} buffer"
        if not isinstance(t, torch.Tensor):
            raise ValueError(f"{what} must be a torch tensor, got {type(t).__name__}")
        shape = tuple(t.shape)
        if t.ndim != 3 or shape[-1] != 3:
            raise ValueError(f"{what} must have shape (H, W, 3), got {shape}")
        if shape != tuple(color.shape):
            raise ValueError(f"{what} has shape {shape}, the colour {tuple(color.shape)}")
        if t.dtype != torch.float32:
            raise ValueError(f"{what} {shape} must be float32, got {t.dtype}")
        if t.device != color.device:
            raise ValueError(f"{what} {shape} is on {t.device}, the colour on {color.device}")
        if t.stride(-1) != 1 or min(t.stride()) < 0 or (name == "output" and not t.is_contiguous()):
            raise ValueError(
                f"{what} {shape} has strides {t.stride()}; OIDN reads pixels of adjacent "
                "channels (and writes a contiguous output): pass .contiguous()"
            )


def _finite(images: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], int]:
    """The images with non-finite values replaced by 0 (copies only where there are some) and
    how many there were."""
    import torch

    count = 0
    out = {}
    for name, t in images.items():
        if bool(torch.isfinite(t.sum())):  # one pass: a NaN or inf makes the sum non-finite
            out[name] = t
            continue
        bad = int((~torch.isfinite(t)).sum())
        count += bad
        out[name] = torch.nan_to_num(t, nan=0.0, posinf=0.0, neginf=0.0) if bad else t
    return out, count


def _device(tensor: torch.Tensor) -> Any:
    """The cached OIDN device of a tensor's device (CPU, or CUDA with the tensor's ordinal)."""
    import mitsuba_oidn as oidn

    kind = tensor.device.type
    index = tensor.device.index or 0
    key = (kind, index)
    if key not in _devices:
        if kind == "cuda":
            _devices[key] = oidn.Device.cuda(index)
        elif kind == "cpu":
            _devices[key] = oidn.Device(oidn.DeviceType.CPU)
        else:
            raise ValueError(f"OIDN runs on CPU or CUDA tensors, got a tensor on {tensor.device}")
    return _devices[key]


def _filter(device: Any, height: int, width: int, weights: bytes | None) -> Any:
    """A cached ``RT`` filter (HDR, quality high) for one device, size and weights blob."""
    import mitsuba_oidn as oidn

    key = (id(device), height, width, None if weights is None else id(weights))
    if key in _filters:
        return _filters[key][0]
    flt = device.new_filter("RT")
    flt.hdr = True
    flt.quality = oidn.Quality.High
    if weights is not None:
        flt.set_data("weights", weights)
    _filters[key] = (flt, weights)  # the blob is kept alive with its filter (its id is the key)
    while len(_filters) > _FILTER_CACHE_SIZE:
        del _filters[next(iter(_filters))]
    return flt


def denoise(
    color: torch.Tensor,
    albedo: torch.Tensor,
    normal: torch.Tensor,
    *,
    weights: bytes | None = None,
    input_scale: float | None = None,
    output: torch.Tensor | None = None,
) -> torch.Tensor:
    """OIDN's ``RT`` filter (HDR, quality ``high``) with albedo and normal, run by OIDN.

    Args:
        color: ``(H, W, 3)`` float32 linear radiance, on the CPU or a CUDA device, channels
            adjacent (stride 1; pixels and rows may be strided, e.g. views of a render's packed
            buffers; OIDN clamps it to >= 0).
        albedo: ``(H, W, 3)`` float32 albedo, same device and layout rule (clamped to [0, 1]).
        normal: ``(H, W, 3)`` float32 normals in [-1, 1], same device and layout rule.
        weights: ``None`` (OIDN's built-in :data:`OIDN_WEIGHTS`) or a TZA blob of a network
            with the same tensors (:func:`check_weights`; checked once per blob object).
        input_scale: OIDN's ``inputScale`` (``None``: OIDN's autoexposure).
        output: ``(H, W, 3)`` float32 contiguous tensor on the same device to write the image
            into (``None``: a new one).

    Returns:
        ``(H, W, 3)`` float32 on ``color``'s device (``output`` itself when given), finite.

    Raises:
        ValueError: an image OIDN cannot bind (wrong shape, dtype, device or layout; named with
            its shape), or ``weights`` whose tensors are not OIDN's network (named).
        RuntimeError: ``mitsuba-oidn`` is not installed.
    """
    return _execute(_checked_inputs(color, albedo, normal, output), weights, input_scale, output)


def _checked_inputs(
    color: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor, output: torch.Tensor | None
) -> dict[str, torch.Tensor]:
    """:func:`denoise`'s images, validated (a named ``ValueError``), non-finite values replaced
    by 0 (counted in a warning); one pass over each image."""
    if reason := check():
        raise RuntimeError(reason)
    images = {"color": color, "albedo": albedo, "normal": normal}
    _validate(images if output is None else {**images, "output": output})
    images, nonfinite = _finite({k: t.detach() for k, t in images.items()})
    if nonfinite:
        warnings.warn(
            f"oidn: {nonfinite} non-finite input values were replaced by 0",
            RuntimeWarning,
            stacklevel=3,
        )
    return images


def _execute(
    images: dict[str, torch.Tensor],
    weights: bytes | None,
    input_scale: float | None,
    output: torch.Tensor | None,
) -> torch.Tensor:
    """OIDN's filter on images :func:`_checked_inputs` returned (see :func:`denoise`)."""
    import torch

    color = images["color"]
    height, width, _ = color.shape
    if output is None:
        output = torch.empty((height, width, 3), dtype=torch.float32, device=color.device)
    bound = (*images.items(), ("output", output))
    with _lock:
        if weights is not None and not any(w is weights for _, w in _filters.values()):
            check_weights(weights)
        flt = _filter(_device(color), height, width, weights)
        try:
            for name, image in bound:
                flt.set_image(name, image)
            flt.input_scale = input_scale
            flt.execute()
        finally:  # the cached filter must not keep the render's buffers alive
            for name, _ in bound:
                flt.unset_image(name)
    return output


def network_weights(net: OIDNUNet) -> bytes | None:
    """The TZA blob of a fine-tuned OIDN network that OIDN's ``RT`` filter can run (OIDN's
    base U-Net on colour + albedo + normal, no extra inputs), exported once per network object
    and process; ``None`` for any other network.

    The tensors are rounded to float16: OIDN's devices read only float16 weights and biases
    (its built-in blobs are float16 too; a float32 blob fails with "unsupported weight layout
    or data type"), so a fine-tuned network's float32 weights lose up to 2^-11 relative."""
    if net in _exported:
        return _exported[net]
    blob = None
    if net.kind == "base" and (net.in_channels, net.extra_channels, net.out_channels) == (9, 0, 3):
        from gdpt.reconstruct.tza import write_tza

        state = {k: v.detach().cpu().half().numpy() for k, v in net.state_dict().items()}
        blob = write_tza(state)
        check_weights(blob)
    _exported[net] = blob
    return blob


def reconstruct(reconstructor: Any, buffers: Any) -> torch.Tensor | None:
    """A fine-tuned OIDN reconstructor's image computed by OIDN's kernels, or ``None`` when it
    needs the torch path: not an :class:`~gdpt.reconstruct.oidn_finetune.OIDNReconstructor`,
    a network :func:`network_weights` cannot export, a refinement, ``mitsuba-oidn`` missing, or
    an input that autograd records.

    The input is the torch path's (:func:`gdpt.reconstruct.oidn_finetune.assemble`):
    non-finite values as 0 and OIDN's input scale computed from that primal
    (:func:`gdpt.reconstruct.oidn_unet.autoexposure`), passed to OIDN as ``inputScale``.

    Args:
        reconstructor: a checkpoint's reconstructor (:func:`gdpt.checkpoints.load_reconstructor`).
        buffers: ``GradientBuffers`` or a mapping with ``primal``, ``albedo``, ``normal``.

    Returns:
        ``(H, W, 3)`` float32 on the buffers' device, or ``None``.
    """
    from gdpt.reconstruct.autograd import records
    from gdpt.reconstruct.oidn_finetune import OIDNReconstructor
    from gdpt.reconstruct.oidn_unet import autoexposure

    if not isinstance(reconstructor, OIDNReconstructor) or reconstructor.refine is not None:
        return None
    if check() is not None:
        return None
    if not isinstance(buffers, Mapping):
        buffers = {n: getattr(buffers, n, None) for n in reconstructor.features}
    images = [buffers.get(n) for n in ("primal", "albedo", "normal")]
    if any(t is None for t in images) or records(images):
        return None
    blob = network_weights(reconstructor.net)
    if blob is None:
        return None
    finite = _checked_inputs(*images, None)
    return _execute(finite, blob, float(autoexposure(finite["color"])), None)
