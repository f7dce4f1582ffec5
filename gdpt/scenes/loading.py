"""The scene loader: every part of gdpt (render, CLI, dataset, study) loads scenes here.

A scene source is one of:

* a ``mi.Scene`` (returned as is) or a scene dict (:func:`mitsuba.load_dict`);
* a path to a Mitsuba XML file (relative meshes and textures resolve next to it);
* ``builtin:NAME``, a built-in test scene (:func:`gdpt.scenes.builtin_scene`);
* ``random:SEED[:VIEW]``, a procedural scene (:func:`gdpt.scenes.random_scene`).

Gradient-domain rendering needs a box pixel filter; Mitsuba XML scenes usually use the default
Gaussian one. ``box_filter=True`` replaces it explicitly and ``long_side`` resizes the film; every
change made is listed in :attr:`LoadedScene.notes` for the caller to report. The path length
to render with is the caller's, else the scene's own integrator ``max_depth``, else
:data:`DEFAULT_MAX_DEPTH` (:func:`choose_max_depth`).

Scenes load with Mitsuba's object merging off (:data:`MERGE_MESHES`): merged, the meshes that
share a BSDF come out in an order that changes from process to process, and so does the image
of a seed.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

#: The pixel filter gradient-domain rendering needs.
BOX_FILTER = "box"
#: Mitsuba's ``hdrfilm`` size when the XML sets none.
_DEFAULT_FILM = {"width": 768, "height": 576}
#: Source prefixes of the generated scenes.
GENERATED_PREFIXES = ("builtin:", "random:")
#: Longest path when neither the caller nor the scene's integrator sets one.
DEFAULT_MAX_DEPTH = 6
#: Mitsuba's ``optimize`` of :func:`mitsuba.load_string` / :func:`mitsuba.load_dict`, which
#: merges the meshes that share a BSDF into one shape. Off: merged, the triangles' order changes
#: between processes, and one seed of one file renders to other bits (living-room-2 of
#: ``../shared/scenes``, 179 meshes merged into 54 shapes: three fresh processes, three images
#: with two threads, two with one); unmerged, four processes gave one image, and a 64-spp
#: render at 128 px took 0.64 s against 0.65 s merged (sponza, 38 shapes against 13: 0.50
#: against 0.52 s).
MERGE_MESHES = False


@dataclass
class LoadedScene:
    """A loaded scene and what loading it changed.

    Attributes:
        scene: the ``mi.Scene``.
        resolution: film ``(width, height)`` in pixels (``None`` for a given ``mi.Scene``).
        max_depth: the ``max_depth`` of the scene's own integrator, ``None`` if it sets none.
        original_filter: the film's pixel filter before loading (``"gaussian"``, Mitsuba's
            default, when the XML has none).
        notes: changes made to the scene (resize, filter override), one sentence each.
    """

    scene: Any
    resolution: tuple[int, int] | None = None
    max_depth: int | None = None
    original_filter: str | None = BOX_FILTER
    notes: list[str] = field(default_factory=list)


def load_scene(
    source: Any, *, box_filter: bool = False, long_side: int | None = None, check: bool = True
):
    """A ``mi.Scene`` from any scene source (see the module docstring); variant set if needed.

    Args:
        source: ``mi.Scene``, scene dict, XML path, ``builtin:NAME`` or ``random:SEED[:VIEW]``.
        box_filter (bool): XML only: replace the film's pixel filter by a box filter.
        long_side (int | None): rescale the film to this many pixels on its long side (XML
            and dicts: aspect ratio kept; ``builtin:``/``random:``: a square film of this
            size); not for a loaded ``mi.Scene``.
        check (bool): refuse a scene it loads with plugins the ``gdpt`` integrators do not
            render (participating media, unsupported BSDFs and emitters:
            :func:`gdpt.integrators.common.check_scene`, which the integrators also run before
            every render); off for scenes rendered with Mitsuba's own integrators.

    Raises:
        FileNotFoundError: the XML file does not exist.
        ValueError: Mitsuba cannot load the scene (the message names the file), an unknown
            ``builtin:``/``random:`` specification, ``box_filter``/``long_side`` for a
            source they cannot change, or (with ``check``) a plugin the integrators do not
            support, named with where it is.
    """
    return read_scene(source, box_filter=box_filter, long_side=long_side, check=check).scene


def choose_max_depth(
    requested: int | None, scene_depth: int | None, *, option: str = "configured"
) -> tuple[int, str]:
    """The ``max_depth`` to render with and where it comes from.

    Args:
        requested: the caller's choice (``None``: none).
        scene_depth: :attr:`LoadedScene.max_depth`, the scene's own integrator setting.
        option: how to name the caller's choice in the note (e.g. ``"--max-depth"``).

    Returns:
        ``(depth, note)``: ``requested`` if given, else ``scene_depth`` if the scene sets one,
        else :data:`DEFAULT_MAX_DEPTH`; ``note`` says which, e.g. ``"max_depth 8 (from the
        scene's integrator)"``.
    """
    if requested is not None:
        return requested, f"max_depth {requested} ({option})"
    if scene_depth is not None:
        return scene_depth, f"max_depth {scene_depth} (from the scene's integrator)"
    return DEFAULT_MAX_DEPTH, f"max_depth {DEFAULT_MAX_DEPTH} (default; the scene sets none)"


def read_scene(
    source: Any, *, box_filter: bool = False, long_side: int | None = None, check: bool = True
) -> LoadedScene:
    """Like :func:`load_scene`, with the film size, integrator depth and changes made."""
    from gdpt.backend import ensure_variant

    ensure_variant()
    loaded = _read_scene(source, box_filter=box_filter, long_side=long_side)
    if check and loaded.scene is not source:  # (a given mi.Scene: the integrator checks it)
        from gdpt.integrators.common import check_scene

        check_scene(loaded.scene, "gdpt")
    return loaded


def _read_scene(source: Any, *, box_filter: bool, long_side: int | None) -> LoadedScene:
    import mitsuba as mi

    if isinstance(source, mi.Scene):
        if box_filter or long_side:
            raise ValueError(
                "box_filter and long_side change a scene before it loads; pass the scene's "
                "dict or XML path instead of a loaded mi.Scene"
            )
        return LoadedScene(source)
    if isinstance(source, dict):
        if box_filter:
            raise ValueError("box_filter is for XML scenes; set the dict's film rfilter instead")
        return _from_dict(_resized(source, long_side) if long_side else source)
    if isinstance(source, str) and source.startswith(GENERATED_PREFIXES):
        return _from_dict(generated_scene(source, long_side), source)
    return _from_xml(Path(os.fspath(source)), box_filter=box_filter, long_side=long_side)


def generated_scene(source: str, long_side: int | None = None) -> dict[str, Any]:
    """The scene dict of ``builtin:NAME`` or ``random:SEED[:VIEW]`` (square film of
    ``long_side`` pixels, else the scene's default size).

    Raises:
        ValueError: not such a source, an unknown built-in name or a malformed seed.
    """
    from gdpt.scenes import builtin_scene, random_scene

    kind, _, arg = source.partition(":")
    size = {} if long_side is None else {"resolution": (long_side, long_side)}
    if kind == "builtin":
        return builtin_scene(arg, **size)
    if kind == "random":
        seed, _, view = arg.partition(":")
        try:
            return random_scene(int(seed), view=int(view or 0), **size)
        except ValueError as err:
            raise ValueError(f"{source}: expected random:SEED[:VIEW] ({err})") from err
    raise ValueError(f"{source}: expected builtin:NAME or random:SEED[:VIEW]")


def _from_dict(scene_dict: dict[str, Any], label: str = "scene dict") -> LoadedScene:
    import mitsuba as mi

    film = scene_dict.get("sensor", {}).get("film", {})
    rfilter = film.get("rfilter", {}).get("type")
    if label != "scene dict" and rfilter != BOX_FILTER:
        raise ValueError(f"{label}: film filter is {rfilter!r}, expected box")
    size = (film["width"], film["height"]) if "width" in film and "height" in film else None
    depth = scene_dict.get("integrator", {}).get("max_depth")
    return LoadedScene(mi.load_dict(scene_dict, optimize=MERGE_MESHES), size, depth, rfilter)


def _resized(scene_dict: dict[str, Any], long_side: int) -> dict[str, Any]:
    """A copy of ``scene_dict`` whose film has ``long_side`` pixels on its long side (aspect
    kept); the film must give ``width`` and ``height``."""
    film = scene_dict.get("sensor", {}).get("film", {})
    if "width" not in film or "height" not in film:
        raise ValueError(
            "long_side needs the scene dict's sensor film to give 'width' and 'height'"
        )
    width, height = int(film["width"]), int(film["height"])
    scale = long_side / max(width, height)
    size = {"width": max(1, round(width * scale)), "height": max(1, round(height * scale))}
    sensor = {**scene_dict["sensor"], "film": {**film, **size}}
    return {**scene_dict, "sensor": sensor}


def _xml_value(element: ET.Element | None, defaults: dict[str, str]) -> str | None:
    """The ``value`` attribute of ``element`` with ``$name`` resolved from ``<default>``."""
    if element is None:
        return None
    value = element.get("value")
    if value is not None and value.startswith("$"):
        value = defaults.get(value[1:], value)
    return value


def _from_xml(path: Path, *, box_filter: bool, long_side: int | None) -> LoadedScene:
    """Load an XML scene, resizing the film and overriding its filter as requested."""
    import mitsuba as mi

    if not path.is_file():
        raise FileNotFoundError(f"scene file not found: {path}")
    root = ET.parse(path).getroot()
    defaults = {d.get("name", ""): d.get("value", "") for d in root.iter("default")}
    film = root.find("sensor/film")
    if film is None and (box_filter or long_side):
        raise ValueError(f"{path}: no <sensor><film> element (included films are not handled)")
    notes: list[str] = []
    size = None
    original = None
    if film is not None:
        elements = {}
        for key, fallback in _DEFAULT_FILM.items():
            element = film.find(f"*[@name='{key}']")
            value = _xml_value(element, defaults)
            elements[key] = (element, int(value) if value is not None else fallback)
        (w_el, width), (h_el, height) = elements["width"], elements["height"]
        size = (width, height)
        if long_side:
            scale = long_side / max(width, height)
            size = (max(1, round(width * scale)), max(1, round(height * scale)))
            for key, element, value in (("width", w_el, size[0]), ("height", h_el, size[1])):
                if element is None:
                    element = ET.SubElement(film, "integer", {"name": key})
                element.set("value", str(value))
            notes.append(f"film resized from {width}x{height} to {size[0]}x{size[1]}")
        rfilter = film.find("rfilter")
        original = "gaussian" if rfilter is None else rfilter.get("type")  # Mitsuba's default
        if box_filter and original != BOX_FILTER:
            for old in film.findall("rfilter"):
                film.remove(old)
            ET.SubElement(film, "rfilter", {"type": BOX_FILTER})
            notes.append(
                f"pixel filter overridden: '{original}' -> 'box' (the gradient-domain "
                "integrators need a box filter; the reference and every method use the same "
                "box-filtered film)"
            )
    integrator = root.find("integrator")
    depth = _xml_value(
        None if integrator is None else integrator.find("*[@name='max_depth']"), defaults
    )

    resolver = mi.file_resolver()
    saved = mi.FileResolver(resolver)
    resolver.prepend(str(path.parent.resolve()))  # relative meshes and textures
    try:
        scene = mi.load_string(ET.tostring(root, encoding="unicode"), optimize=MERGE_MESHES)
    except Exception as err:  # Mitsuba raises RuntimeError with its parser message
        raise ValueError(f"cannot load scene {path}: {' '.join(str(err).split())}") from err
    finally:
        mi.set_file_resolver(saved)
    return LoadedScene(scene, size, int(depth) if depth is not None else None, original, notes)
