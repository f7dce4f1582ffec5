"""OpenEXR storage of :class:`~gdpt.buffers.GradientBuffers` and of plain RGB images.

A render is stored as ONE single-part, multi-layer OpenEXR file. Each buffer is a layer whose
channels follow the usual ``layer.channel`` naming, so any EXR viewer can browse them::

    primal.R primal.G primal.B   dx.R dx.G dx.B   dy.R dy.G dy.B   albedo.R albedo.G albedo.B
    normal.X normal.Y normal.Z   depth.Y   var_primal.Y   var_dx.Y   var_dy.Y

Absent (``None``) buffers have no channels. Gradients a masked render did not trace
(``buffers.gradient_mask``) are stored as NaN, with infinite variance: missing for every reader
(the mask itself is not stored). The header carries ``gdpt.spp`` (int),
``gdpt.metadata`` (the metadata dict as a JSON string), ``gdpt.version`` (the gdpt version that
wrote the file) and ``gdpt.formatVersion`` (:data:`FORMAT_VERSION`). Pixels are stored as 32-bit
float (lossless round trip) or 16-bit half, both ZIP-compressed. The readers refuse a file of a
newer format version (naming both versions) and a ``gdpt.metadata`` that is not a JSON object.

Writes are atomic: the file is written to a temporary name in the target directory and moved
into place with :func:`os.replace`, so a failed write leaves neither a partial file nor a
temporary one behind. Existing files are only overwritten with ``force=True``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR
import torch

from gdpt.buffers import CHANNELS, REQUIRED, GradientBuffers, fill_untraced
from gdpt.io.atomic import atomic_path
from gdpt.version import __version__

#: Version of the on-disk layout described in this module; bumped on incompatible changes.
FORMAT_VERSION = 1

_RGB = ("R", "G", "B")
_SUFFIXES: dict[str, tuple[str, ...]] = {
    name: ("X", "Y", "Z") if name.startswith("normal") else _RGB if c == 3 else ("Y",)
    for name, c in CHANNELS.items()
}
_KEY_SPP = "gdpt.spp"
_KEY_METADATA = "gdpt.metadata"
_KEY_VERSION = "gdpt.version"
_KEY_FORMAT = "gdpt.formatVersion"

PathLike = str | os.PathLike[str]
ImageLike = torch.Tensor | np.ndarray


def channel_names(buffer: str) -> tuple[str, ...]:
    """EXR channel names of a buffer, e.g. ``('normal.X', 'normal.Y', 'normal.Z')``.

    Raises:
        ValueError: ``buffer`` is not a key of :data:`gdpt.buffers.CHANNELS`.
    """
    if buffer not in _SUFFIXES:
        raise ValueError(f"unknown buffer {buffer!r}; valid buffers: {', '.join(CHANNELS)}")
    return tuple(f"{buffer}.{s}" for s in _SUFFIXES[buffer])


# ---------------------------------------------------------------------------------------- write
def save_buffers(
    path: PathLike, buffers: GradientBuffers, *, half: bool = False, force: bool = False
) -> Path:
    """Write all present buffers and the metadata to one multi-layer EXR file.

    Args:
        path (str | os.PathLike): destination file; its directory must exist.
        buffers (GradientBuffers): the render; tensors may live on any device.
        half (bool): store 16-bit half floats instead of 32-bit floats. Values beyond the half
            range (|x| > 65504) become +-inf.
        force (bool): overwrite an existing file.

    Returns:
        The destination path.

    Raises:
        FileExistsError: ``path`` exists and ``force`` is false.
        TypeError: ``buffers.metadata`` is not JSON-serialisable.
    """
    header = _gdpt_header(buffers.metadata)
    header[_KEY_SPP] = int(buffers.spp)
    channels: dict[str, np.ndarray] = {}
    for name, tensor in fill_untraced(buffers, torch.nan, torch.nan).items():
        channels.update(_split_channels(channel_names(name), tensor, half))
    return _write_exr(Path(path), header, channels, force)


def save_image(
    path: PathLike,
    image: ImageLike,
    *,
    metadata: dict[str, Any] | None = None,
    force: bool = False,
) -> Path:
    """Write a plain RGB EXR (channels ``R``, ``G``, ``B``, 32-bit float).

    Args:
        path (str | os.PathLike): destination file; its directory must exist.
        image (torch.Tensor | np.ndarray): ``(H, W, 3)`` real-valued image on any device.
        metadata (dict | None): JSON-serialisable information stored as ``gdpt.metadata``.
        force (bool): overwrite an existing file.

    Returns:
        The destination path.

    Raises:
        ValueError: ``image`` is not ``(H, W, 3)``.
        FileExistsError: ``path`` exists and ``force`` is false.
        TypeError: ``metadata`` is not JSON-serialisable.
    """
    array = _to_numpy(image)
    if array.ndim != 3 or array.shape[2] != 3 or 0 in array.shape:
        raise ValueError(f"image must have shape (H, W, 3), got {tuple(array.shape)}")
    header = _gdpt_header(metadata or {})
    channels = _split_channels(_RGB, torch.from_numpy(array), half=False)
    return _write_exr(Path(path), header, channels, force)


def _gdpt_header(metadata: dict[str, Any]) -> dict[str, Any]:
    """Header attributes common to every file gdpt writes."""
    try:
        encoded = json.dumps(metadata, sort_keys=True)
    except (TypeError, ValueError) as error:
        raise TypeError(f"metadata is not JSON-serialisable: {error}") from error
    return {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        _KEY_METADATA: encoded,
        _KEY_VERSION: __version__,
        _KEY_FORMAT: FORMAT_VERSION,
    }


def _to_numpy(image: ImageLike) -> np.ndarray:
    """A float32 CPU numpy copy/view of a tensor or array."""
    if isinstance(image, torch.Tensor):
        image = image.detach().to("cpu", torch.float32).numpy()
    return np.asarray(image, dtype=np.float32)


def _split_channels(
    names: tuple[str, ...], tensor: torch.Tensor, half: bool
) -> dict[str, np.ndarray]:
    """``(H, W, C)`` tensor -> ``{name: contiguous (H, W) array}`` in float32 or float16."""
    array = tensor.detach().to("cpu").numpy()
    dtype = np.float16 if half else np.float32
    with np.errstate(over="ignore"):  # out-of-range values become +-inf in half, as documented
        return {n: np.ascontiguousarray(array[:, :, i], dtype=dtype) for i, n in enumerate(names)}


def _write_exr(
    path: Path, header: dict[str, Any], channels: dict[str, np.ndarray], force: bool
) -> Path:
    """Write an EXR atomically (:func:`gdpt.io.atomic.atomic_path`)."""
    check_writable(path, force=force)
    with atomic_path(path) as tmp:
        OpenEXR.File(header, channels).write(str(tmp))
        check_writable(path, force=force)  # another process may have created it meanwhile
    return path


def check_writable(path: PathLike, *, force: bool) -> None:
    """Check that ``path`` may be written, before doing expensive work that would produce it.

    Raises:
        IsADirectoryError: ``path`` is a directory.
        FileExistsError: ``path`` exists and ``force`` is false.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a directory")
    if path.exists() and not force:
        raise FileExistsError(f"{path}: file exists (pass force=True / --force to overwrite)")


# ----------------------------------------------------------------------------------------- read
def load_buffers(path: PathLike, *, aov_kinds: dict[str, str] | None = None) -> GradientBuffers:
    """Read a file written by :func:`save_buffers`, or by Mitsuba's ``aov`` integrator.

    A Mitsuba AOV EXR (the image's ``R, G, B`` channels beside AOV layers such as
    ``albedo.R/G/B``, ``nn.X/Y/Z``, ``dd.y.T``; :mod:`gdpt.io.mitsuba_aov`) gives buffers with
    ``primal`` and whichever of ``albedo``, ``normal``, ``depth`` it holds, no gradients,
    ``spp`` 0 and ``metadata["source"] = "mitsuba-aov-exr"`` (with the layers read, in
    ``metadata["aovs"]``).

    Args:
        path (str | os.PathLike): an EXR file with the ``primal.R/G/B`` channels, or a Mitsuba
            AOV EXR.
        aov_kinds (dict[str, str] | None): for a Mitsuba AOV EXR, ``{kind: layer}`` where the
            layer of a kind (``primal``, ``albedo``, ``normal``, ``depth``) is ambiguous, e.g.
            ``{"normal": "nn"}``.

    Returns:
        The buffers as ``float32`` CPU tensors (half-stored files are widened), with ``spp``
        and ``metadata`` from the header (``0`` and ``{}`` if absent).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        IsADirectoryError: ``path`` is a directory.
        ValueError: not an OpenEXR file, truncated or corrupt, written in a newer format
            version, ``gdpt.metadata`` not a JSON object, a required channel or part of a layer
            is missing (and the file is no Mitsuba AOV EXR, or an ambiguous one), a channel has
            the wrong size or type, or the buffers are inconsistent. The message names the file
            (and the channels found, or the channel or header attribute).
    """
    path = Path(path)
    header, channels = _read_exr(path)
    return _buffers(path, header, channels, aov_kinds)


def _buffers(
    path: Path,
    header: dict[str, Any],
    channels: dict[str, np.ndarray],
    aov_kinds: dict[str, str] | None,
) -> GradientBuffers:
    """:func:`load_buffers` of a file already read."""
    if "primal.R" not in channels and not _written_by_gdpt(header):
        return _aov_buffers(path, header, channels, aov_kinds)
    if aov_kinds:
        raise ValueError(f"{path}: a gdpt buffers EXR; aov_kinds (--aov) applies to AOV EXRs")
    tensors: dict[str, torch.Tensor] = {}
    for name in CHANNELS:
        names = channel_names(name)
        found = [n for n in names if n in channels]
        if not found and name not in REQUIRED:
            continue
        missing = [n for n in names if n not in channels]
        if missing:
            what = "required channel" if not found else f"channel of layer '{name}':"
            hint = "" if found else _image_hint(channels)
            raise ValueError(
                f"{path}: missing {what} '{missing[0]}' "
                f"(channels present: {', '.join(sorted(channels)) or 'none'}){hint}"
            )
        tensors[name] = _stack(path, names, channels)
    try:
        spp = int(header.get(_KEY_SPP, 0))
    except (TypeError, ValueError) as error:
        raise ValueError(
            f"{path}: header attribute '{_KEY_SPP}' is not an integer: {error}"
        ) from None
    metadata = _metadata(path, header)
    try:
        return GradientBuffers(**tensors, spp=spp, metadata=metadata)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: {error}") from error


def _written_by_gdpt(header: dict[str, Any]) -> bool:
    return _KEY_FORMAT in header or _KEY_METADATA in header


def _image_hint(channels: dict[str, np.ndarray]) -> str:
    """What a gdpt file with ``R, G, B`` and no ``primal`` layer is (for the error message)."""
    if {"R", "G", "B"} <= set(channels):
        return (
            ": a reconstructed image (gdpt reconstruct / render-and-denoise), not buffers; "
            "reconstruct from the EXR of 'gdpt render'"
        )
    return ""


def _aov_buffers(
    path: Path,
    header: dict[str, Any],
    channels: dict[str, np.ndarray],
    aov_kinds: dict[str, str] | None,
) -> GradientBuffers:
    """Buffers of a Mitsuba AOV EXR (:mod:`gdpt.io.mitsuba_aov`)."""
    from gdpt.io import mitsuba_aov

    try:
        recognised = mitsuba_aov.recognise(channels, aov_kinds)
        arrays = mitsuba_aov.aov_arrays(channels, recognised)
    except ValueError as error:
        raise ValueError(
            f"{path}: missing required channel 'primal.R' of a gdpt render, and not readable as "
            f"a Mitsuba AOV EXR: {error}"
        ) from None
    metadata = {
        "source": mitsuba_aov.SOURCE,
        "aovs": {kind: list(names) for kind, names in recognised.items()},
    }
    if isinstance(header.get("generatedBy"), str):
        metadata["generated_by"] = header["generatedBy"]
    tensors = {kind: torch.from_numpy(array) for kind, array in arrays.items()}
    return GradientBuffers(**tensors, spp=0, metadata=metadata)


def load_image(path: PathLike, layer: str | None = None) -> torch.Tensor:
    """Read an RGB image, or one layer of a multi-layer file.

    Args:
        path (str | os.PathLike): an EXR file.
        layer (str | None): ``None`` reads channels ``R, G, B``; a buffer name from
            :data:`gdpt.buffers.CHANNELS` reads that layer (e.g. ``'dx'`` or ``'depth'``); any
            other name reads ``<layer>.R/G/B``.

    Returns:
        ``(H, W, C)`` float32 CPU tensor, ``C`` = 3 (or 1 for single-channel layers).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        IsADirectoryError: ``path`` is a directory.
        ValueError: not a readable OpenEXR file, written in a newer format version, or a
            channel is missing (the message names the channel and the file).
    """
    path = Path(path)
    if layer is None:
        names = _RGB
    elif layer in CHANNELS:
        names = channel_names(layer)
    else:
        names = tuple(f"{layer}.{s}" for s in _RGB)
    _, channels = _read_exr(path)
    for name in names:
        if name not in channels:
            raise ValueError(
                f"{path}: missing channel '{name}' "
                f"(channels present: {', '.join(sorted(channels)) or 'none'})"
            )
    return _stack(path, names, channels)


def _read_exr(path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Header and ``{channel name: (H, W) array}`` of the first part of an EXR file."""
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a directory")
    if not OpenEXR.isOpenExrFile(str(path)):
        raise ValueError(f"{path}: not an OpenEXR file")
    try:
        exr = OpenEXR.File(str(path), separate_channels=True)
        if not exr.parts:  # the bindings warn and return an empty File on bad pixel data
            raise RuntimeError("no readable part")
        header = exr.header()
        channels = {name: ch.pixels for name, ch in exr.channels().items()}
    except (RuntimeError, ValueError, IndexError) as error:
        raise ValueError(
            f"{path}: unreadable OpenEXR file (truncated or corrupt): {error}"
        ) from None
    _check_format_version(path, header)
    return header, channels


def _check_format_version(path: Path, header: dict[str, Any]) -> None:
    """Refuse a file whose ``gdpt.formatVersion`` is not an integer or newer than ours."""
    version = header.get(_KEY_FORMAT)
    if version is None:  # not written by gdpt (or by a version before the attribute)
        return
    if not isinstance(version, int) or isinstance(version, bool):
        raise ValueError(f"{path}: header attribute '{_KEY_FORMAT}' is {version!r}, not an integer")
    if version > FORMAT_VERSION:
        writer = header.get(_KEY_VERSION, "an unknown version")
        raise ValueError(
            f"{path}: gdpt EXR format version {version} (written by gdpt {writer}); this gdpt "
            f"{__version__} reads format versions up to {FORMAT_VERSION}: upgrade gdpt"
        )


def _metadata(path: Path, header: dict[str, Any]) -> dict[str, Any]:
    """The ``gdpt.metadata`` header attribute as a dict (``{}`` when absent)."""
    text = header.get(_KEY_METADATA, "{}")
    try:
        metadata = json.loads(text)
    except (TypeError, ValueError) as error:
        raise ValueError(
            f"{path}: header attribute '{_KEY_METADATA}' is not valid JSON: {error}"
        ) from None
    if not isinstance(metadata, dict):
        raise ValueError(f"{path}: header attribute '{_KEY_METADATA}' is not a JSON object")
    return metadata


def _stack(path: Path, names: tuple[str, ...], channels: dict[str, np.ndarray]) -> torch.Tensor:
    """Stack named ``(H, W)`` channels into an ``(H, W, C)`` float32 tensor, checking them."""
    shape = channels[names[0]].shape
    for name in names:
        pixels = channels[name]
        if pixels.dtype not in (np.float16, np.float32):
            raise ValueError(f"{path}: channel '{name}' has type {pixels.dtype}, not half/float")
        if pixels.shape != shape:
            raise ValueError(
                f"{path}: channel '{name}' is {pixels.shape} but '{names[0]}' is {shape} "
                "(subsampled channels are not supported)"
            )
    return torch.from_numpy(np.stack([channels[n] for n in names], axis=-1).astype(np.float32))


# ------------------------------------------------------------------------------------- describe
def describe_exr(path: PathLike) -> str:
    """A readable description of an EXR file (what ``gdpt info`` prints): its kind (gdpt
    buffers, a reconstructed image, a Mitsuba AOV EXR, another EXR), size, spp, the buffers
    or layers with their channels and NaN/Inf counts, and the metadata.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        IsADirectoryError: ``path`` is a directory.
        ValueError: not a readable OpenEXR file, or a gdpt buffers EXR that
            :func:`load_buffers` refuses (the message names the file).
    """
    from gdpt.io import mitsuba_aov

    path = Path(path)
    header, channels = _read_exr(path)
    rows: list[tuple[str, list[str]]] = []
    lines = [f"file:     {path}"]
    metadata: dict[str, Any] | None = None
    heading = "layers:"
    height, width = next(iter(channels.values())).shape if channels else (0, 0)
    if "primal.R" in channels or (_written_by_gdpt(header) and not _image_hint(channels)):
        buffers = _buffers(path, header, channels, None)
        mode = "gradient-domain (dx, dy)" if buffers.has_gradients else "primal-only"
        lines += [
            f"kind:     gdpt buffers (gdpt render), written by gdpt {_writer(header)}",
            f"size:     {buffers.width} x {buffers.height} (W x H)",
            f"spp:      {buffers.spp}",
            f"mode:     {mode}",
        ]
        rows = [(name, list(channel_names(name))) for name in buffers.present()]
        metadata, heading = buffers.metadata, "buffers:"
    elif _written_by_gdpt(header):
        metadata = _metadata(path, header)
        method = metadata.get("method")
        made = f"method {method}" if method else "gdpt"
        lines += [
            f"kind:     reconstructed image ({made}), written by gdpt {_writer(header)}",
            f"size:     {width} x {height} (W x H)",
        ]
        if "spp" in metadata:
            lines.append(f"spp:      {metadata['spp']}")
        rows = [("image", ["R", "G", "B"])]
    else:
        try:
            recognised = mitsuba_aov.recognise(channels)
            mitsuba_aov.aov_arrays(channels, recognised)
        except ValueError as error:
            recognised = {}
            kind = f"EXR that gdpt does not read as buffers ({error})"
        else:
            by = header.get("generatedBy")
            made = f"{by}; " if isinstance(by, str) else ""
            kind = f"Mitsuba AOV EXR ({made}gdpt.load_buffers reads {', '.join(recognised)})"
            heading = "buffers:"
        lines += [f"kind:     {kind}", f"size:     {width} x {height} (W x H)"]
        rows = [(name, list(names)) for name, names in recognised.items()]
        read = {n for _, names in rows for n in names}
        rows += [
            ("(unread)", names)
            for names in mitsuba_aov.layers(channels).values()
            if not read & set(names)
        ]
    lines.append(heading)
    lines.append(f"  {'name':<11} {'channels':<32} {'NaN':>8} {'Inf':>8}")
    for name, names in rows:
        values = [channels[n] for n in names]
        nan = sum(int(np.isnan(v).sum()) for v in values if v.dtype.kind == "f")
        inf = sum(int(np.isinf(v).sum()) for v in values if v.dtype.kind == "f")
        lines.append(f"  {name:<11} {','.join(names):<32} {nan:>8} {inf:>8}")
    if metadata is not None:
        lines.append(f"metadata: {json.dumps(metadata, indent=2, sort_keys=True)}")
    return "\n".join(lines)


def _writer(header: dict[str, Any]) -> str:
    """The gdpt version (and format version) that wrote a file, from its header."""
    return f"{header.get(_KEY_VERSION, '(unknown)')}, format {header.get(_KEY_FORMAT, 0)}"
