"""Buffers from an EXR written by Mitsuba 3's ``aov`` integrator around a renderer (``path``).

Mitsuba names the channels of ``<integrator type="aov">`` after the AOV names the user chose
(``aovs="dd.y:depth,nn:sh_normal,albedo:albedo"``) and the AOV's type, e.g.::

    R G B                      the image (the nested integrator's estimate; A with an RGBA film)
    integrator.R/G/B/A         the nested integrator's own layer (named after its id)
    albedo.R/G/B   dd.y.T   nn.X/Y/Z

The kind of a layer is recognised from its channels: ``R/G/B`` without ``A`` is the albedo,
``X/Y/Z`` the normal, ``T`` the depth; a layer with an ``A`` channel is a nested integrator's
image and is not read. Where several layers fit one kind (``position`` and ``geo_normal`` also
write ``X/Y/Z``), ``aov_kinds`` says which is which: ``{"normal": "nn"}``; it can also name the
layer of the image (``{"primal": "integrator"}``) when the file has no ``R/G/B`` channels.

Mitsuba's ``sh_normal`` is a world-space shading normal and its ``depth`` the distance to the
first intersection; gdpt's own renders store a camera-space normal facing the viewer and the
distance to the first rough vertex (:class:`~gdpt.buffers.GradientBuffers`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: Buffer kinds an AOV EXR can supply -> number of channels.
AOV_KINDS: dict[str, int] = {"primal": 3, "albedo": 3, "normal": 3, "depth": 1}

#: Channel suffixes that identify a layer's kind when ``aov_kinds`` does not name it.
_SIGNATURES: dict[str, tuple[str, ...]] = {
    "albedo": ("R", "G", "B"),
    "normal": ("X", "Y", "Z"),
    "depth": ("T",),
}
#: Orders in which an explicitly named layer's channels are read.
_ORDERS = (("R", "G", "B"), ("X", "Y", "Z"))

#: ``GradientBuffers.metadata["source"]`` of buffers read from a Mitsuba AOV EXR.
SOURCE = "mitsuba-aov-exr"


def layers(channels: dict[str, Any]) -> dict[str, list[str]]:
    """``{layer: [channel names]}``, the layer being the name before the last ``.`` (``""``
    for the channels without one), channels in the file's (sorted) order."""
    out: dict[str, list[str]] = {}
    for name in sorted(channels):
        out.setdefault(name.rpartition(".")[0], []).append(name)
    return out


def recognise(
    channels: dict[str, Any], aov_kinds: dict[str, str] | None = None
) -> dict[str, tuple[str, ...]]:
    """Which channels hold the image, the albedo, the normal and the depth.

    Args:
        channels: ``{channel name: pixels}`` of an EXR (only the names are read).
        aov_kinds: ``{kind: layer}`` for kinds whose layer is ambiguous or named otherwise
            (kinds: :data:`AOV_KINDS`; layer ``""`` is the file's ``R/G/B`` channels).

    Returns:
        ``{kind: channel names in buffer order}`` for every kind found (``primal`` always).

    Raises:
        ValueError: an unknown kind or layer in ``aov_kinds``, a named layer with the wrong
            channels, several layers fitting one kind, no image channels, or no AOV layer at
            all (a plain RGB image); the message lists the layers found.
    """
    aov_kinds = dict(aov_kinds or {})
    by_layer = layers(channels)
    found = "; ".join(
        f"{layer or '(image)'}: {', '.join(names)}" for layer, names in by_layer.items()
    )
    if unknown := sorted(set(aov_kinds) - set(AOV_KINDS)):
        raise ValueError(f"unknown AOV kind {', '.join(unknown)}; kinds: {', '.join(AOV_KINDS)}")
    out: dict[str, tuple[str, ...]] = {}
    for kind, layer in aov_kinds.items():
        if layer not in by_layer:
            raise ValueError(f"no layer {layer!r} for the {kind}; layers found: {found}")
        out[kind] = _named_channels(kind, layer, by_layer[layer], found)
    used = {n for names in out.values() for n in names}
    if "primal" not in out:
        if not {"R", "G", "B"} <= set(by_layer.get("", [])):
            raise ValueError(
                "no image channels R, G, B (nor gdpt's primal.R/G/B): name the image's layer "
                f"(aov_kinds={{'primal': LAYER}}, --aov primal=LAYER); channels found: {found}"
            )
        out["primal"] = ("R", "G", "B")
    for kind, suffixes in _SIGNATURES.items():
        if kind in out:
            continue
        fits = [
            layer
            for layer, names in by_layer.items()
            if layer
            and sorted(n.rpartition(".")[2] for n in names) == sorted(suffixes)
            and not used & set(names)
        ]
        if len(fits) > 1:
            raise ValueError(
                f"layers {', '.join(fits)} all have {'/'.join(suffixes)} channels: say which "
                f"is the {kind} (aov_kinds={{'{kind}': LAYER}}, --aov {kind}=LAYER); "
                f"channels found: {found}"
            )
        if fits:
            out[kind] = tuple(f"{fits[0]}.{s}" for s in suffixes)
    if len(out) == 1:
        raise ValueError(
            "an RGB image without AOV layers: no albedo (R/G/B), normal (X/Y/Z) or depth (T) "
            "layer, as Mitsuba's aov integrator writes (aovs=\"albedo:albedo,nn:sh_normal,"
            f'dd:depth"); channels found: {found}'
        )
    return out


def _named_channels(kind: str, layer: str, names: list[str], found: str) -> tuple[str, ...]:
    """The channels of ``layer`` (named for ``kind`` in ``aov_kinds``) in buffer order."""
    suffixes = {n.rpartition(".")[2]: n for n in names}
    if AOV_KINDS[kind] == 1:
        if len(names) == 1:
            return (names[0],)
    else:
        for order in _ORDERS:
            if set(order) <= set(suffixes):
                return tuple(suffixes[s] for s in order)
    want = "one channel" if AOV_KINDS[kind] == 1 else "R/G/B or X/Y/Z channels"
    raise ValueError(
        f"layer {layer or '(image)'!r} given for the {kind} has {', '.join(names)}, not {want}; "
        f"channels found: {found}"
    )


def aov_arrays(
    channels: dict[str, np.ndarray], recognised: dict[str, tuple[str, ...]]
) -> dict[str, np.ndarray]:
    """``{kind: (H, W, C) float32 array}`` of the channels :func:`recognise` found.

    Raises:
        ValueError: the file's channels have different sizes, or a channel read is not
            half/float (the message lists the channels with their sizes).
    """
    shapes = {name: pixels.shape for name, pixels in channels.items()}
    if len(set(shapes.values())) > 1:
        sizes = ", ".join(f"{n} {s[1]}x{s[0]}" for n, s in sorted(shapes.items()))
        raise ValueError(f"channels of different sizes (W x H): {sizes}")
    out = {}
    for kind, names in recognised.items():
        for name in names:
            if channels[name].dtype not in (np.float16, np.float32):
                raise ValueError(
                    f"channel '{name}' has type {channels[name].dtype}, not half/float"
                )
        out[kind] = np.stack([channels[n] for n in names], axis=-1).astype(np.float32)
    return out


def parse_aov_kinds(items: list[str] | None) -> dict[str, str]:
    """``["normal=nn", "depth=dd.y"]`` (the ``--aov KIND=LAYER`` options) -> ``aov_kinds``.

    Raises:
        ValueError: an item without ``=``, an unknown kind, or a kind given twice.
    """
    out: dict[str, str] = {}
    for item in items or []:
        kind, sep, layer = item.partition("=")
        if not sep:
            raise ValueError(f"--aov {item!r}: expected KIND=LAYER, e.g. normal=nn")
        if kind not in AOV_KINDS:
            raise ValueError(
                f"--aov {item!r}: unknown kind {kind!r}; kinds: {', '.join(AOV_KINDS)}"
            )
        if kind in out:
            raise ValueError(f"--aov: the {kind} is given twice ({out[kind]!r}, {layer!r})")
        out[kind] = layer
    return out
