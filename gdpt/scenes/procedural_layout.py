"""Rooms, open set-ups and the objects placed in them, for the procedural training-scene
generator (:mod:`gdpt.scenes.procedural`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from gdpt.scenes.elements import SceneDict, Vec3, cube, cylinder, disk, rectangle, sphere
from gdpt.scenes.procedural_config import RandomSceneConfig
from gdpt.scenes.procedural_materials import (
    SOLID_MATERIALS,
    SURFACE_MATERIALS,
    random_material,
    wall_material,
)


@dataclass
class PlacedItem:
    """Footprint and point of interest of a placed object (for placement and cameras)."""

    x: float
    z: float
    radius: float
    top: float


@dataclass
class Layout:
    """Where content may go: a room ``[-hx, hx] x [0, height] x [-hz, hz]`` or open ground."""

    room: bool
    half: tuple[float, float]  # half extents in x and z (content region for open set-ups)
    height: float
    albedo: float  # mean albedo of the room surfaces, or of the ground
    open_side: str | None = None  # missing wall: '+x', '-x', '+z' or '-z'
    window: str | None = None  # wall with the window opening
    window_area: float = 0.0  # area of the openings an environment shines through
    items: list[PlacedItem] = field(default_factory=list)


class SceneBuilder:
    """Accumulates uniquely named scene entries."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.entries: SceneDict = {}

    def add(self, prefix: str, entry: dict) -> None:
        self.entries[f"{prefix}_{len(self.entries):03d}"] = entry


# -- Layouts ---------------------------------------------------------------------------------


def _wall_with_window(
    b: SceneBuilder,
    center: Vec3,
    normal: Vec3,
    along: Vec3,
    width: float,
    height: float,
    window: tuple[float, float, float, float] | None,
    bsdf: dict,
) -> None:
    """A vertical wall of ``width x height`` (bottom at y=0) with an optional rectangular hole
    ``window = (offset along the wall, bottom, window width, window height)``."""
    c = np.asarray(center, dtype=np.float64)
    a = np.asarray(along, dtype=np.float64)
    if window is None:
        b.add("wall", rectangle(c + [0, height / 2, 0], normal, [width, height], bsdf))
        return
    off, y0, ww, wh = window
    lo, hi = off - ww / 2, off + ww / 2
    pieces = [  # (start, end along the wall, bottom, top)
        (-width / 2, lo, 0.0, height),
        (hi, width / 2, 0.0, height),
        (lo, hi, 0.0, y0),
        (lo, hi, y0 + wh, height),
    ]
    for s0, s1, t0, t1 in pieces:
        mid = c + a * (s0 + s1) / 2 + [0, (t0 + t1) / 2, 0]
        b.add("wall", rectangle(mid, normal, [s1 - s0, t1 - t0], bsdf))


def build_room(b: SceneBuilder, cfg: RandomSceneConfig, window: bool) -> Layout:
    rng = b.rng
    hx, hz = rng.uniform(1.5, 3.5, size=2)
    height = rng.uniform(2.4, 3.4)
    open_side = (
        str(rng.choice(["+x", "-x", "+z", "-z"])) if rng.uniform() < cfg.p_open_side else None
    )
    floor, floor_albedo = wall_material(rng, True)
    ceiling, ceiling_albedo = wall_material(rng, False)
    b.add("floor", rectangle([0, 0, 0], [0, 1, 0], [2 * hx, 2 * hz], floor))
    b.add("ceiling", rectangle([0, height, 0], [0, -1, 0], [2 * hx, 2 * hz], ceiling))
    sides = {  # side -> (center, inward normal, direction along the wall, wall length)
        "+x": ([hx, 0, 0], [-1, 0, 0], [0, 0, 1], 2 * hz),
        "-x": ([-hx, 0, 0], [1, 0, 0], [0, 0, 1], 2 * hz),
        "+z": ([0, 0, hz], [0, 0, -1], [1, 0, 0], 2 * hx),
        "-z": ([0, 0, -hz], [0, 0, 1], [1, 0, 0], 2 * hx),
    }
    closed = [s for s in sides if s != open_side]
    window_side = str(rng.choice(closed)) if window else None
    window_area = 0.0
    wall = wall_material(rng, False)
    total_area = 8 * hx * hz
    albedo_sum = total_area / 2 * (floor_albedo + ceiling_albedo)
    for side in closed:
        center, normal, along, length = sides[side]
        hole = None
        if side == window_side:
            ww = rng.uniform(1.0, min(3.0, length - 0.8))
            wh = rng.uniform(1.0, height - 0.8)
            off = rng.uniform(-(length - ww) / 2 + 0.3, (length - ww) / 2 - 0.3)
            hole = (off, rng.uniform(0.3, height - wh - 0.3), ww, wh)
            window_area = ww * wh
        bsdf, albedo = wall_material(rng, False) if rng.uniform() < 0.3 else wall
        _wall_with_window(b, center, normal, along, length, height, hole, bsdf)
        albedo_sum += length * height * albedo
        total_area += length * height
    albedo = albedo_sum / total_area
    if window and open_side is not None:  # the environment also shines through the open side
        window_area += sides[open_side][3] * height
    return Layout(True, (hx, hz), height, albedo, open_side, window_side, window_area)


def build_open_layout(b: SceneBuilder) -> Layout:
    rng = b.rng
    ground, albedo = wall_material(rng, True)
    b.add("ground", rectangle([0, 0, 0], [0, 1, 0], [60, 60], ground))
    if rng.uniform() < 0.3:  # a backdrop wall behind the content
        angle = rng.uniform(0, 2 * np.pi)
        n = np.array([np.cos(angle), 0, np.sin(angle)])
        b.add("backdrop", rectangle(-4 * n + [0, 2, 0], n, [10, 4], wall_material(rng, False)[0]))
    half = rng.uniform(1.8, 3.0)
    return Layout(False, (half, half), 4.0, albedo)


# -- Objects ---------------------------------------------------------------------------------


def _rot(angle_deg: float, lx: float, lz: float) -> np.ndarray:
    """Rotates the local offset ``(lx, 0, lz)`` about +y like ``ScalarTransform4f.rotate``."""
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    return np.array([lx * c + lz * s, 0.0, -lx * s + lz * c])


def _small_object(b: SceneBuilder, base: np.ndarray, max_size: float) -> float:
    """A small box, sphere or capped cylinder standing at ``base``; returns its height."""
    rng = b.rng
    kind = rng.choice(["box", "sphere", "cylinder"])
    size = rng.uniform(0.4, 1.0) * max_size
    if kind == "sphere":
        bsdf = random_material(rng, SOLID_MATERIALS)
        b.add("sphere", sphere(base + [0, size / 2, 0], size / 2, bsdf))
    elif kind == "box":
        dims = size * rng.uniform(0.5, 1.0, size=3)
        b.add(
            "box",
            cube(
                base + [0, dims[1] / 2, 0],
                dims,
                random_material(rng, SOLID_MATERIALS),
                rng.uniform(0, 90),
            ),
        )
        size = dims[1]
    else:
        bsdf = random_material(rng, SURFACE_MATERIALS)
        r = size * rng.uniform(0.2, 0.45)
        b.add("cylinder", cylinder(base, base + [0, size, 0], r, bsdf))
        b.add("cap", disk(base + [0, size, 0], [0, 1, 0], r, bsdf))
    return size


def _table(b: SceneBuilder, x: float, z: float, angle: float, max_height: float) -> PlacedItem:
    rng = b.rng
    w, d = rng.uniform(0.8, 1.6), rng.uniform(0.6, 1.0)
    h, t = min(rng.uniform(0.65, 0.8), max_height), rng.uniform(0.03, 0.06)
    bsdf = random_material(rng, SURFACE_MATERIALS)
    base = np.array([x, 0.0, z])
    b.add("tabletop", cube(base + [0, h - t / 2, 0], [w, t, d], bsdf, angle))
    leg_r = rng.uniform(0.02, 0.04)
    for sx in (-1, 1):
        for sz in (-1, 1):
            p = base + _rot(angle, sx * (w / 2 - 2 * leg_r), sz * (d / 2 - 2 * leg_r))
            b.add("leg", cylinder(p, p + [0, h - t, 0], leg_r, bsdf))
    top = h
    for _ in range(rng.integers(0, 3)):
        offset = _rot(angle, rng.uniform(-0.3, 0.3) * w, rng.uniform(-0.3, 0.3) * d)
        top = max(top, h + _small_object(b, base + offset + [0, h, 0], 0.3))
    return PlacedItem(x, z, 0.5 * math.hypot(w, d), top)


def _shelf(b: SceneBuilder, x: float, z: float, angle: float, max_height: float) -> PlacedItem:
    """An open shelf (front towards local +z) with boards, back panel and a few items."""
    rng = b.rng
    w, d = rng.uniform(0.6, 1.4), rng.uniform(0.25, 0.4)
    h, t = min(rng.uniform(1.0, 2.0), max_height), 0.03
    bsdf = random_material(rng, SURFACE_MATERIALS)
    base = np.array([x, 0.0, z])
    for sx in (-1, 1):
        b.add(
            "shelfside",
            cube(base + _rot(angle, sx * (w - t) / 2, 0) + [0, h / 2, 0], [t, h, d], bsdf, angle),
        )
    b.add(
        "shelfback",
        cube(base + _rot(angle, 0, -(d - t) / 2) + [0, h / 2, 0], [w, h, t], bsdf, angle),
    )
    levels = np.linspace(t / 2, h - t / 2, rng.integers(3, 6))
    for y in levels:
        b.add("board", cube(base + [0, y, 0], [w - 2 * t, t, d - t], bsdf, angle))
    gap = levels[1] - levels[0]
    for y in levels[:-1]:
        if rng.uniform() < 0.6:
            offset = _rot(angle, rng.uniform(-0.3, 0.3) * w, 0.0)
            _small_object(b, base + offset + [0, y + t / 2, 0], min(0.8 * gap, 0.8 * d))
    return PlacedItem(x, z, 0.5 * math.hypot(w, d), h)


def _floor_object(b: SceneBuilder, layout: Layout, x: float, z: float, radius: float) -> PlacedItem:
    """A box, sphere, capped cylinder, rug disk or standing panel with footprint ``radius``."""
    rng = b.rng
    kind = rng.choice(["box", "sphere", "cylinder", "rug", "panel"], p=[0.3, 0.3, 0.2, 0.1, 0.1])
    base = np.array([x, 0.0, z])
    max_height = layout.height - 1.0
    if kind == "sphere":
        b.add(
            "sphere", sphere(base + [0, radius, 0], radius, random_material(rng, SOLID_MATERIALS))
        )
        return PlacedItem(x, z, radius, 2 * radius)
    if kind == "box":
        side = radius * math.sqrt(2)
        dims = [
            side * rng.uniform(0.6, 1.0),
            min(rng.uniform(0.2, 1.6), max_height),
            side * rng.uniform(0.6, 1.0),
        ]
        b.add(
            "box",
            cube(
                base + [0, dims[1] / 2, 0],
                dims,
                random_material(rng, SOLID_MATERIALS),
                rng.uniform(0, 90),
            ),
        )
        return PlacedItem(x, z, radius, dims[1])
    if kind == "cylinder":
        h = min(rng.uniform(0.2, 1.5), max_height)
        bsdf = random_material(rng, SURFACE_MATERIALS)
        b.add("cylinder", cylinder(base, base + [0, h, 0], radius, bsdf))
        b.add("cap", disk(base + [0, h, 0], [0, 1, 0], radius, bsdf))
        return PlacedItem(x, z, radius, h)
    if kind == "rug":
        b.add(
            "rug",
            disk(
                base + [0, 0.005, 0],
                [0, 1, 0],
                radius,
                random_material(rng, {"diffuse": 0.5, "checker": 0.5}),
            ),
        )
        return PlacedItem(x, z, radius, 0.01)
    # A standing panel: thin glass pane, or an opaque screen.
    h = min(rng.uniform(0.6, 1.8), max_height)
    a = rng.uniform(0, 2 * np.pi)
    if rng.uniform() < 0.5:
        bsdf = {"type": "thindielectric", "int_ior": float(rng.uniform(1.4, 1.6))}
    else:
        bsdf = random_material(rng, SURFACE_MATERIALS)
    b.add(
        "panel", rectangle(base + [0, h / 2, 0], [np.cos(a), 0, np.sin(a)], [2 * radius, h], bsdf)
    )
    return PlacedItem(x, z, radius, h)


def _wall_decor(b: SceneBuilder, layout: Layout) -> None:
    """A picture (rectangle) or round plate (disk) hung on a closed, windowless room wall;
    sometimes a mirror."""
    rng = b.rng
    sides = [s for s in ("+x", "-x", "+z", "-z") if s not in (layout.open_side, layout.window)]
    side = str(rng.choice(sides))
    axis = 0 if side[1] == "x" else 2
    sign = 1.0 if side[0] == "+" else -1.0
    normal = np.zeros(3)
    normal[axis] = -sign
    center = np.array([0.0, rng.uniform(1.2, layout.height - 0.7), 0.0])
    center[axis] = sign * (layout.half[axis // 2] - 0.01)
    center[2 - axis] = rng.uniform(-0.6, 0.6) * layout.half[1 - axis // 2]
    size = rng.uniform(0.3, 0.6)
    bsdf = random_material(rng, {"checker": 0.4, "diffuse": 0.3, "conductor": 0.3})
    if rng.uniform() < 0.5:
        b.add("picture", rectangle(center, normal, [2 * size, size * rng.uniform(1.0, 1.6)], bsdf))
    else:
        b.add("plate", disk(center, normal, size, bsdf))


def place_objects(b: SceneBuilder, cfg: RandomSceneConfig, layout: Layout) -> None:
    rng = b.rng
    hx, hz = layout.half
    n = rng.integers(cfg.num_objects[0], cfg.num_objects[1] + 1)
    for _ in range(n):
        kind = rng.choice(["floor", "table", "shelf"], p=[0.7, 0.18, 0.12])
        radius = rng.uniform(0.15, 0.6) if kind == "floor" else 0.9
        for _attempt in range(30):
            x = rng.uniform(-hx + radius + 0.1, hx - radius - 0.1)
            z = rng.uniform(-hz + radius + 0.1, hz - radius - 0.1)
            if all(
                math.hypot(x - it.x, z - it.z) > radius + it.radius + 0.05 for it in layout.items
            ):
                break
        else:
            continue
        angle = rng.uniform(0, 360)
        if kind == "table":
            item = _table(b, x, z, angle, layout.height - 1.0)
        elif kind == "shelf":
            # Face the room centre (local +z of the shelf is its open front).
            item = _shelf(b, x, z, math.degrees(math.atan2(-x, -z)), layout.height - 1.0)
        else:
            item = _floor_object(b, layout, x, z, radius)
        layout.items.append(item)
    if layout.room and rng.uniform() < 0.5:
        _wall_decor(b, layout)
