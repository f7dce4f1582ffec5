"""Reader and writer of Intel Open Image Denoise's TZA weight container, and the built-in OIDN
weights.

OIDN (https://github.com/RenderKit/oidn, Apache-2.0) stores the weights of its U-Nets in
*Tensor Archive* (TZA) blobs. The format, as written by ``training/tza.py`` and parsed by
``core/tza.cpp`` (version 2.0), all integers little-endian::

    uint16 magic = 0x41D7 | uint8 major = 2 | uint8 minor | uint64 table_offset
    ... tensor data, each tensor 64-byte aligned relative to the blob start ...
    table (at table_offset): uint32 count, then per tensor:
        uint16 name_len | name (UTF-8) | uint8 ndims | uint32 dims[ndims]
        | layout: ndims ASCII chars ("oihw" for conv weights, "x" for biases)
        | dtype: 1 char ("f" float32, "h" float16) | uint64 data_offset

Names are PyTorch state-dict keys (``enc_conv0.weight``, ``enc_conv0.bias``, ...).
:func:`write_tza` writes this format (tensors in the given order, float32 or float16), which
OIDN's filters accept as user weights (``Filter.set_data("weights", blob)``).

The ``mitsuba-oidn`` wheel ships ``libmitsuba_oidn_core``, OIDN's core library, into which
OIDN's build embeds every built-in weight file verbatim as a byte array
``oidn::blobs::weights::<name>`` (e.g. ``rt_hdr_alb_nrm``). :func:`builtin_weights` finds them
without running OIDN:

1. it scans the library for the TZA header (magic + version 2.x) and keeps the candidates whose
   tables parse, are in bounds and name the layers of one of OIDN's U-Nets;
2. it names them from the library's ELF dynamic symbol table (the blobs are exported symbols;
   a symbol's address and size locate its blob exactly);
3. without usable symbols (a stripped or non-ELF build) it falls back to the order in which
   OIDN 2.x's build links the blobs (:data:`BUILTIN_ORDER`, checked on OIDN 2.5.1) and accepts
   it only if every blob's structure (U-Net size, input channels) matches its name.

Every named blob is checked against its name (input channels: 9 for ``*_alb_nrm`` /
``*_calb_cnrm``, 6 for ``*_alb``, 3 otherwise; ``*_small``: the small U-Net, ``*_large``: the
large one). Anything that does not fit raises :class:`OIDNWeightsError`.

Only numpy is needed here; tensors are returned as float32 numpy arrays (float16 blobs are
converted) in OIDN's ``oihw`` / ``x`` layouts, which are PyTorch's ``Conv2d`` layouts.
"""

from __future__ import annotations

import importlib.util
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "BUILTIN_ORDER",
    "TZA_MAGIC",
    "OIDNWeightsError",
    "TZAError",
    "WeightBlob",
    "builtin_weights",
    "find_oidn_library",
    "load_weights",
    "parse_tza",
    "read_tza",
    "OIDN_PACKAGE",
    "unet_kind",
    "write_tza",
]

TZA_MAGIC = 0x41D7
_HEADER = b"\xd7\x41\x02"  # magic (little-endian uint16) + major version 2
_DTYPES = {"f": np.dtype("<f4"), "h": np.dtype("<f2")}
_DTYPE_CHARS = {np.dtype("float32"): "f", np.dtype("float16"): "h"}
_ALIGNMENT = 64
_LAYOUTS = {1: "x", 4: "oihw"}

_HINT = (
    "pass the weights explicitly as a .tza file (weights='/path/to/rt_hdr_alb_nrm.tza'; the "
    "files are in https://github.com/RenderKit/oidn-weights)"
)

# Layer names of the two U-Nets of OIDN (training/model.py: UNet / UNet(small=True), UNetLarge).
_UNET_LAYERS = (
    "enc_conv0", "enc_conv1", "enc_conv2", "enc_conv3", "enc_conv4", "enc_conv5a", "enc_conv5b",
    "dec_conv4a", "dec_conv4b", "dec_conv3a", "dec_conv3b", "dec_conv2a", "dec_conv2b",
    "dec_conv1a", "dec_conv1b", "dec_conv0",
)  # fmt: skip
_UNET_LARGE_LAYERS = (
    "enc_conv1a", "enc_conv1b", "enc_conv2a", "enc_conv2b", "enc_conv3a", "enc_conv3b",
    "enc_conv4a", "enc_conv4b", "enc_conv5a", "enc_conv5b", "dec_conv4a", "dec_conv4b",
    "dec_conv3a", "dec_conv3b", "dec_conv2a", "dec_conv2b", "dec_conv1a", "dec_conv1b",
    "dec_conv1c",
)  # fmt: skip

#: Order of the built-in blobs in OIDN 2.x's core library (link order of its weight files),
#: used only when the library has no usable symbol table.
BUILTIN_ORDER = (
    "rt_alb", "rt_alb_large",
    "rt_hdr", "rt_hdr_small", "rt_hdr_alb", "rt_hdr_alb_small", "rt_hdr_alb_nrm",
    "rt_hdr_alb_nrm_small", "rt_hdr_calb_cnrm", "rt_hdr_calb_cnrm_small", "rt_hdr_calb_cnrm_large",
    "rt_ldr", "rt_ldr_small", "rt_ldr_alb", "rt_ldr_alb_small", "rt_ldr_alb_nrm",
    "rt_ldr_alb_nrm_small", "rt_ldr_calb_cnrm", "rt_ldr_calb_cnrm_small",
    "rt_nrm", "rt_nrm_large", "rtlightmap_hdr", "rtlightmap_dir",
)  # fmt: skip

_SYMBOL = re.compile(rb"_ZN4oidn5blobs7weights(\d+)([A-Za-z0-9_]+)E")


class TZAError(ValueError):
    """A TZA blob or file is malformed (bad magic/version, table out of bounds, bad layout)."""


class OIDNWeightsError(RuntimeError):
    """OIDN's built-in weights cannot be found or are not recognised."""


@dataclass(frozen=True)
class WeightBlob:
    """One built-in weight blob: ``name`` (e.g. ``rt_hdr_alb_nrm``), byte ``offset`` and
    ``size`` in ``library``, and its ``tensors`` (name -> read-only numpy view of the library's
    bytes, in the stored dtype: float16 in OIDN 2.5.1; :func:`load_weights` gives float32)."""

    name: str
    library: Path
    offset: int
    size: int
    tensors: dict[str, np.ndarray]


# ----------------------------------------------------------------------------------------------
# TZA parsing
# ----------------------------------------------------------------------------------------------


def _parse(buf: memoryview, start: int, end: int) -> tuple[dict[str, np.ndarray], int]:
    """Parse the TZA blob at ``buf[start:]`` (nothing past ``end`` may be touched).

    Returns the tensors and the blob's byte size (its table's end). Raises :class:`TZAError`.
    """
    pos = start

    def take(fmt: str) -> tuple:
        nonlocal pos
        size = struct.calcsize(fmt)
        if pos + size > end:
            raise TZAError("truncated TZA table")
        vals = struct.unpack_from(fmt, buf, pos)
        pos += size
        return vals

    magic, major, _minor, table = take("<HBBQ")
    if magic != TZA_MAGIC:
        raise TZAError(f"bad TZA magic 0x{magic:04X} (expected 0x{TZA_MAGIC:04X})")
    if major != 2:
        raise TZAError(f"unsupported TZA version {major} (expected 2)")
    if table < 12 or start + table >= end:
        raise TZAError(f"TZA table offset {table} is out of bounds")
    pos = start + table
    (count,) = take("<I")
    if not 0 < count <= 4096:
        raise TZAError(f"implausible TZA tensor count {count}")
    tensors: dict[str, np.ndarray] = {}
    for _ in range(count):
        (name_len,) = take("<H")
        if pos + name_len > end:
            raise TZAError("truncated TZA tensor name")
        try:
            name = bytes(buf[pos : pos + name_len]).decode("utf-8")
        except UnicodeDecodeError as exc:
            raise TZAError("TZA tensor name is not UTF-8") from exc
        pos += name_len
        (ndims,) = take("<B")
        dims = take(f"<{ndims}I") if ndims else ()
        if pos + ndims + 1 > end:
            raise TZAError("truncated TZA tensor layout")
        layout = bytes(buf[pos : pos + ndims]).decode("ascii", errors="replace")
        dtype_char = chr(buf[pos + ndims])
        pos += ndims + 1
        (offset,) = take("<Q")
        if _LAYOUTS.get(ndims) != layout:
            raise TZAError(f"tensor {name!r}: unsupported layout {layout!r} ({ndims} dims)")
        if dtype_char not in _DTYPES:
            raise TZAError(f"tensor {name!r}: unsupported data type {dtype_char!r}")
        dtype = _DTYPES[dtype_char]
        nbytes = int(np.prod(dims, dtype=np.int64)) * dtype.itemsize
        if offset % 64 or offset < 12 or start + offset + nbytes > start + table:
            raise TZAError(
                f"tensor {name!r}: data at offset {offset} is misaligned or out of bounds"
            )
        data = np.frombuffer(
            buf, dtype=dtype, count=nbytes // dtype.itemsize, offset=start + offset
        )
        if name in tensors:
            raise TZAError(f"duplicate TZA tensor {name!r}")
        tensors[name] = data.reshape(dims)
    return tensors, pos - start


def _float32(tensors: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: v.astype(np.float32) for k, v in tensors.items()}


def parse_tza(
    data: bytes | bytearray | memoryview, *, stored_dtype: bool = False
) -> dict[str, np.ndarray]:
    """Parse one TZA blob (OIDN ``core/tza.cpp`` format, version 2.x).

    Args:
        data: the blob's bytes (trailing bytes after the table are allowed).
        stored_dtype: keep each tensor's stored dtype (float16 or float32) instead of
            converting to float32.

    Returns:
        ``{name: array}``, numpy arrays (copies; float32, or as stored), conv weights
        ``(O, I, 3, 3)`` (``oihw``), biases ``(O,)`` (``x``).

    Raises:
        TZAError: malformed blob.
    """
    buf = memoryview(data).cast("B")
    tensors = _parse(buf, 0, len(buf))[0]
    if stored_dtype:
        return {k: v.astype(v.dtype.newbyteorder("=")) for k, v in tensors.items()}
    return _float32(tensors)


def write_tza(tensors: dict[str, np.ndarray]) -> bytes:
    """One TZA blob (version 2.0) holding ``tensors``, readable by :func:`parse_tza` and by OIDN.

    Args:
        tensors: name -> float32 or float16 array, 4-d (written as ``oihw``) or 1-d (``x``),
            in the order the table lists them; other arrays are converted with ``np.asarray``.

    Returns:
        The blob: header, each tensor's data and the table 64-byte aligned (zero padding), as
        OIDN's ``training/tza.py`` lays it out.
        Float32 and float16 tensors are stored as they are, so :func:`parse_tza` of the blob
        returns them exactly.

    Raises:
        TZAError: a tensor of another rank or dtype, or an empty ``tensors``.
    """
    if not tensors:
        raise TZAError("a TZA blob needs at least one tensor")
    data = bytearray(struct.pack("<HBBQ", TZA_MAGIC, 2, 0, 0))
    table = bytearray(struct.pack("<I", len(tensors)))
    for name, value in tensors.items():
        array = np.ascontiguousarray(_to_numpy(value))
        if array.ndim not in _LAYOUTS or array.dtype not in _DTYPE_CHARS:
            raise TZAError(
                f"tensor {name!r}: {array.ndim}-d {array.dtype} cannot be written "
                "(4-d oihw or 1-d, float32 or float16)"
            )
        data += bytes(-len(data) % _ALIGNMENT)
        offset = len(data)
        data += array.astype(array.dtype.newbyteorder("<"), copy=False).tobytes()
        encoded = name.encode("utf-8")
        table += struct.pack("<H", len(encoded)) + encoded
        table += struct.pack(f"<B{array.ndim}I", array.ndim, *array.shape)
        table += (_LAYOUTS[array.ndim] + _DTYPE_CHARS[array.dtype]).encode("ascii")
        table += struct.pack("<Q", offset)
    data += bytes(-len(data) % _ALIGNMENT)
    struct.pack_into("<Q", data, 4, len(data))
    return bytes(data + table)


def read_tza(path: str | Path) -> dict[str, np.ndarray]:
    """Read a ``.tza`` file (see :func:`parse_tza`).

    Raises:
        FileNotFoundError: no such file.
        TZAError: malformed file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"OIDN weights file not found: {path}")
    try:
        return parse_tza(path.read_bytes())
    except TZAError as exc:
        raise TZAError(f"{path}: {exc}") from None


def unet_kind(tensors: dict[str, np.ndarray]) -> tuple[str, int]:
    """``(kind, input_channels)`` of an OIDN state dict; ``kind`` is ``"small"``, ``"base"`` or
    ``"large"`` (training/model.py: ``UNet(small=True)``, ``UNet``, ``UNetLarge``).

    Raises:
        TZAError: the tensors are not exactly the layers of one of these U-Nets with 3x3 convs.
    """
    names = set(tensors)
    for layers in (_UNET_LAYERS, _UNET_LARGE_LAYERS):
        expected = {f"{n}.{p}" for n in layers for p in ("weight", "bias")}
        if names == expected:
            break
    else:
        raise TZAError("tensor names are not those of an OIDN U-Net (enc_conv0.weight, ...)")
    for n in layers:
        w, b = tensors[f"{n}.weight"], tensors[f"{n}.bias"]
        if w.ndim != 4 or w.shape[2:] != (3, 3) or b.shape != (w.shape[0],):
            raise TZAError(f"layer {n}: unexpected shapes {w.shape}, {b.shape}")
    first = tensors[f"{layers[0]}.weight"]
    if layers is _UNET_LARGE_LAYERS:
        return "large", int(first.shape[1])
    small = tensors["enc_conv2.weight"].shape[0] == tensors["enc_conv1.weight"].shape[0]
    return ("small" if small else "base"), int(first.shape[1])


# ----------------------------------------------------------------------------------------------
# Built-in weights in the OpenImageDenoise library installed by mitsuba-oidn
# ----------------------------------------------------------------------------------------------

#: The package whose OpenImageDenoise core library holds OIDN's built-in weights.
OIDN_PACKAGE = "mitsuba_oidn"


def find_oidn_library() -> Path:
    """Path of the OpenImageDenoise core library (which holds the weights) that the
    ``mitsuba-oidn`` wheel installs (``libmitsuba_oidn_core``); found with
    ``importlib.util.find_spec`` (no import).

    Raises:
        OIDNWeightsError: ``mitsuba-oidn`` is not installed or holds no such library.
    """
    spec = importlib.util.find_spec(OIDN_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise OIDNWeightsError(
            "OIDN's built-in weights are read from the mitsuba-oidn package, which is not "
            f"installed (pip install mitsuba-oidn), or {_HINT}"
        )
    roots = [Path(p) for p in spec.submodule_search_locations]
    found: list[Path] = []
    for root in roots:
        for pattern in ("*oidn_core*", "*OpenImageDenoise_core*"):
            found += sorted(
                p
                for p in root.rglob(pattern)
                if p.is_file() and p.suffix not in (".cmake", ".h", ".lib", ".py")
            )
            if found:
                break
        if found:
            break
    if not found:
        raise OIDNWeightsError(
            f"no OpenImageDenoise core library found in the mitsuba-oidn package ({roots[0]}); "
            f"{_HINT}"
        )
    return max(found, key=lambda p: p.stat().st_size)  # versioned copies are identical


def _elf_symbols(buf: memoryview) -> dict[str, tuple[int, int]]:
    """``{blob name: (file offset, size)}`` of the ``oidn::blobs::weights::*`` symbols of a
    64-bit little-endian ELF file's ``.dynsym`` / ``.symtab``; ``{}`` if not such a file."""
    if bytes(buf[:6]) != b"\x7fELF\x02\x01":
        return {}
    try:
        (shoff,) = struct.unpack_from("<Q", buf, 0x28)
        shentsize, shnum = struct.unpack_from("<HH", buf, 0x3A)
        sections = [
            struct.unpack_from("<IIQQQQIIQQ", buf, shoff + i * shentsize) for i in range(shnum)
        ]
        out: dict[str, tuple[int, int]] = {}
        for sec in sections:
            if sec[1] not in (2, 11):  # SHT_SYMTAB, SHT_DYNSYM
                continue
            strtab = sections[sec[6]]
            str_off, str_size = strtab[4], strtab[5]
            for k in range(sec[5] // 24):
                st_name, _i, _o, shndx, value, size = struct.unpack_from(
                    "<IBBHQQ", buf, sec[4] + 24 * k
                )
                if shndx == 0 or shndx >= shnum or st_name >= str_size:
                    continue
                s = str_off + st_name
                name_end = bytes(buf[s : min(s + 128, str_off + str_size)]).split(b"\0", 1)[0]
                m = _SYMBOL.fullmatch(name_end)
                if not m or int(m[1]) != len(m[2]):
                    continue
                home = sections[shndx]  # (addr, offset) of the section holding the symbol
                offset = home[4] + (value - home[3])
                if home[3] <= value and value + size <= home[3] + home[5]:
                    out[m[2].decode()] = (offset, size)
        return out
    except struct.error:
        return {}


def _expected(name: str) -> tuple[str, int]:
    """(kind, input channels) that OIDN's blob ``name`` must have."""
    kind = "small" if name.endswith("_small") else "large" if name.endswith("_large") else "base"
    body = name.split("_", 1)[1]  # "hdr_alb_nrm", "alb" (the albedo filter), ...
    channels = 9 if ("alb_nrm" in body or "calb_cnrm" in body) else 6 if "_alb" in body else 3
    return kind, channels


def _scan(buf: memoryview, raw: bytes) -> list[tuple[int, int, dict[str, np.ndarray]]]:
    """All valid OIDN U-Net TZA blobs in ``raw``: ``(offset, size, tensors)``."""
    blobs = []
    i = raw.find(_HEADER)
    while i >= 0:
        try:
            tensors, size = _parse(buf, i, len(buf))
            unet_kind(tensors)
        except TZAError:
            i = raw.find(_HEADER, i + 1)
            continue
        blobs.append((i, size, tensors))
        i = raw.find(_HEADER, i + size)
    return blobs


_CACHE: dict[tuple[str, int, int, bool], dict[str, WeightBlob]] = {}


def builtin_weights(
    library: str | Path | None = None, *, use_symbols: bool = True
) -> dict[str, WeightBlob]:
    """All built-in weight blobs of an OpenImageDenoise library, by OIDN's name.

    Args:
        library: the library file; default :func:`find_oidn_library` (mitsuba-oidn's).
        use_symbols: name the blobs from the ELF symbol table (``False`` forces the
            :data:`BUILTIN_ORDER` fallback; for tests).

    Returns:
        ``{"rt_hdr_alb_nrm": WeightBlob(...), ...}``; results are cached per file.

    Raises:
        OIDNWeightsError: no library, or its blobs do not parse or cannot be identified.
    """
    path = Path(library) if library is not None else find_oidn_library()
    if not path.is_file():
        raise OIDNWeightsError(f"OpenImageDenoise library not found: {path}; {_HINT}")
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns, use_symbols)
    if key in _CACHE:
        return _CACHE[key]
    raw = path.read_bytes()
    buf = memoryview(raw)
    unrecognised = (
        f"the weights in this OpenImageDenoise build ({path}) are not recognised; {_HINT}"
    )
    scanned = {off: (size, t) for off, size, t in _scan(buf, raw)}
    out: dict[str, WeightBlob] = {}
    symbols = _elf_symbols(buf) if use_symbols else {}
    if symbols:
        for name, (off, size) in symbols.items():
            if off not in scanned or scanned[off][0] > size:
                raise OIDNWeightsError(
                    f"blob {name!r}: not a valid OIDN U-Net TZA blob; {unrecognised}"
                )
            out[name] = WeightBlob(name, path, off, scanned[off][0], scanned[off][1])
    else:
        if len(scanned) != len(BUILTIN_ORDER):
            raise OIDNWeightsError(
                f"found {len(scanned)} weight blobs and no symbol table, "
                f"expected {len(BUILTIN_ORDER)}; {unrecognised}"
            )
        for name, off in zip(BUILTIN_ORDER, sorted(scanned), strict=True):
            out[name] = WeightBlob(name, path, off, scanned[off][0], scanned[off][1])
    if not out:
        raise OIDNWeightsError(f"no weight blobs found; {unrecognised}")
    for blob in out.values():
        got = unet_kind(blob.tensors)
        if got != _expected(blob.name):
            raise OIDNWeightsError(
                f"blob {blob.name!r} is a {got[0]} U-Net with {got[1]} input "
                f"channels, expected {_expected(blob.name)}; {unrecognised}"
            )
    _CACHE[key] = out
    return out


def load_weights(
    weights: str | Path | dict = "rt_hdr_alb_nrm", *, library: str | Path | None = None
) -> dict[str, np.ndarray]:
    """OIDN weights as a state dict of float32 numpy arrays.

    Args:
        weights: a built-in blob name (``"rt_hdr_alb_nrm"``, ``"rt_hdr_alb_nrm_small"``,
            ``"rt_ldr"``, ... see :data:`BUILTIN_ORDER`), a path to a ``.tza`` file (any string
            ending in ``.tza`` or containing a path separator is taken as a path), or a state dict
            (returned as float32 arrays).
        library: OpenImageDenoise library to read built-in blobs from (default: mitsuba-oidn's).

    Raises:
        FileNotFoundError: a ``.tza`` path that does not exist.
        TZAError: malformed ``.tza`` file.
        OIDNWeightsError: built-in weights unavailable / unrecognised, or an unknown name.
    """
    if isinstance(weights, dict):
        return {k: np.asarray(_to_numpy(v), dtype=np.float32) for k, v in weights.items()}
    text = str(weights)
    if isinstance(weights, Path) or text.endswith(".tza") or "/" in text or "\\" in text:
        tensors = read_tza(weights)
        unet_kind(tensors)
        return tensors
    blobs = builtin_weights(library)
    if text not in blobs:
        raise OIDNWeightsError(
            f"no built-in OIDN weights named {text!r}; available: "
            f"{', '.join(sorted(blobs))}; or {_HINT}"
        )
    return _float32(blobs[text].tensors)


def _to_numpy(v: object) -> np.ndarray:
    detach = getattr(v, "detach", None)
    return detach().cpu().numpy() if detach is not None else np.asarray(v)
