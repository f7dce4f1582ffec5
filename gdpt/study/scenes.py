"""The study's scenes: :func:`resolve_scenes` (``gdpt evaluate --scenes`` arguments, folders of
``*/scene.xml`` included -> named :class:`SceneSpec`) and :func:`load_eval_scene` (the study's
policy on top of :func:`gdpt.scenes.loading.read_scene`: box filter forced, the study's
resolution and path length, every change recorded for the report).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gdpt.scenes.loading import BOX_FILTER, GENERATED_PREFIXES, choose_max_depth, read_scene


# ------------------------------------------------------------------------------------ scenes
@dataclass(frozen=True)
class SceneSpec:
    """Where a scene comes from.

    Attributes:
        name: short name used in the report and in file names.
        source: an XML path, ``builtin:NAME`` or ``random:SEED[:VIEW]``.
    """

    name: str
    source: str


@dataclass
class EvalScene:
    """A loaded scene, ready for the methods.

    Attributes:
        name: short name.
        scene: the ``mi.Scene``.
        max_depth: longest path used by every method and the reference.
        resolution: film ``(width, height)``.
        notes: changes made to the scene when loading it (e.g. the filter override).
        film_filter: ``{"original": ..., "used": "box"}``.
        warm: ``(method, spp, render_only)`` renders done on this scene object, whose kernels
            and frozen passes a later render of the same replays
            (:func:`gdpt.study.calibration.timed_run`).
    """

    name: str
    scene: Any
    max_depth: int
    resolution: tuple[int, int]
    notes: list[str] = field(default_factory=list)
    film_filter: dict[str, str | None] = field(default_factory=dict)
    warm: set[tuple[str, int, bool]] = field(default_factory=set, repr=False, compare=False)


def _scene_name(path: Path) -> str:
    return path.parent.name if path.name == "scene.xml" else path.stem


def resolve_scenes(items: Iterable[str | os.PathLike[str]]) -> list[SceneSpec]:
    """Expand scene arguments into :class:`SceneSpec` objects.

    Each item is a Mitsuba XML file; a folder holding ``scene.xml``; a folder of such folders
    (every ``*/scene.xml``, sorted); ``builtin:NAME`` (:func:`gdpt.scenes.builtin_scene`);
    ``random:SEED[:VIEW]`` (a procedural scene from :func:`gdpt.scenes.random_scene`); or a
    comma-separated list of those. A path that does not exist is kept: loading it fails and
    the failure is reported with the results.

    Args:
        items: scene arguments.

    Returns:
        The scenes, in argument order, without duplicates (same name and source).

    Raises:
        ValueError: two different scenes would get the same name.
    """
    specs: list[SceneSpec] = []
    for item in items:
        for part in str(item).split(","):
            part = part.strip()
            if not part:
                continue
            if part.startswith("builtin:"):
                specs.append(SceneSpec(part.split(":", 1)[1], part))
            elif part.startswith("random:"):
                specs.append(SceneSpec("random-" + part.split(":", 1)[1].replace(":", "-"), part))
            else:
                path = Path(part)
                if path.is_dir() and (path / "scene.xml").is_file():
                    path = path / "scene.xml"
                if path.is_dir():
                    subs = sorted(path.glob("*/scene.xml"))
                    specs += [SceneSpec(_scene_name(p), str(p)) for p in subs]
                    if not subs:
                        specs.append(SceneSpec(path.name, str(path)))
                else:
                    specs.append(SceneSpec(_scene_name(path), str(path)))
    unique: dict[str, SceneSpec] = {}
    for spec in specs:
        if spec.name in unique and unique[spec.name] != spec:
            raise ValueError(
                f"two scenes are named {spec.name!r}: {unique[spec.name].source} and {spec.source}"
            )
        unique[spec.name] = spec
    return list(unique.values())


def load_eval_scene(spec: SceneSpec, *, resolution: int, max_depth: int | None = None) -> EvalScene:
    """Load a scene for evaluation at ``resolution`` pixels on the long side.

    Args:
        spec: the scene.
        resolution: long side of the film in pixels.
        max_depth: longest path; ``None`` uses the scene's integrator setting (else 6).

    Returns:
        The loaded scene with the notes describing every change made to it.

    Raises:
        FileNotFoundError: the XML file does not exist.
        ValueError: Mitsuba cannot load it, or an unknown builtin/random specification.
    """
    generated = spec.source.startswith(GENERATED_PREFIXES)
    loaded = read_scene(
        spec.source if generated else Path(spec.source), box_filter=True, long_side=resolution
    )
    notes = list(loaded.notes)
    depth, note = choose_max_depth(max_depth, loaded.max_depth)
    notes.append(note)
    return EvalScene(
        spec.name,
        loaded.scene,
        depth,
        loaded.resolution,
        notes,
        {"original": loaded.original_filter, "used": BOX_FILTER},
    )
