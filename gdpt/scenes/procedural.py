"""The procedural training-scene generator: :func:`random_scene`, :func:`random_views`
(rooms and open set-ups, random materials, lights and cameras; deterministic in the seed)."""

from __future__ import annotations

import colorsys
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from gdpt.scenes.elements import (
    SceneDict,
    Vec3,
    _area,
    _check_resolution,
    _checker,
    _cube,
    _cylinder,
    _diffuse,
    _disk,
    _envmap,
    _rectangle,
    _rgb,
    _scene,
    _sensor,
    _sky_image,
    _sphere,
    _twosided,
)

# --------------------------------------------------------------------------------------------
#  Procedural training scenes
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RandomSceneConfig:
    """Knobs of :func:`random_scene`. Probabilities are per scene unless stated otherwise.

    Attributes:
        p_room: probability of a room (else an open set-up on a ground plane).
        p_open_side: probability that a room has one wall missing (the camera may look in).
        p_window: probability that a room is lit by an environment through a wall opening.
        p_env_open: probability that an open set-up is lit by an environment (sky).
        p_bitmap_env: probability that an environment is a procedural sky ``envmap`` rather
            than a ``constant`` emitter.
        p_extra_light: probability of adding a second kind of light.
        num_objects: inclusive range of the number of top-level objects.
        p_thinlens: probability, per view, of a thin-lens camera with visible defocus.
        target_radiance: rough radiance of lit diffuse surfaces, which sets the light power
            (image means, shadows and dark backgrounds included, typically land between 0.1x
            and 2.5x this value).
        env_shape: ``(height, width)`` of the procedural sky bitmap.
    """

    p_room: float = 0.6
    p_open_side: float = 0.35
    p_window: float = 0.4
    p_env_open: float = 0.7
    p_bitmap_env: float = 0.65
    p_extra_light: float = 0.4
    num_objects: tuple[int, int] = (3, 7)
    p_thinlens: float = 0.25
    target_radiance: float = 0.5
    env_shape: tuple[int, int] = (32, 64)

    def __post_init__(self) -> None:
        for name in (
            "p_room",
            "p_open_side",
            "p_window",
            "p_env_open",
            "p_bitmap_env",
            "p_extra_light",
            "p_thinlens",
        ):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must lie in [0, 1], got {getattr(self, name)}")
        lo, hi = self.num_objects
        if not 1 <= lo <= hi:
            raise ValueError("num_objects must be a range (lo, hi) with 1 <= lo <= hi")
        if self.target_radiance <= 0:
            raise ValueError("target_radiance must be positive")
        _check_resolution(self.env_shape)


@dataclass
class _Item:
    """Footprint and point of interest of a placed object (for placement and cameras)."""

    x: float
    z: float
    radius: float
    top: float


@dataclass
class _Layout:
    """Where content may go: a room ``[-hx, hx] x [0, height] x [-hz, hz]`` or open ground."""

    room: bool
    half: tuple[float, float]  # half extents in x and z (content region for open set-ups)
    height: float
    albedo: float  # mean albedo of the room surfaces, or of the ground
    open_side: str | None = None  # missing wall: '+x', '-x', '+z' or '-z'
    window: str | None = None  # wall with the window opening
    window_area: float = 0.0  # area of the openings an environment shines through
    items: list[_Item] = field(default_factory=list)


class _Builder:
    """Accumulates uniquely named scene entries."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.entries: SceneDict = {}

    def add(self, prefix: str, entry: dict) -> None:
        self.entries[f"{prefix}_{len(self.entries):03d}"] = entry


def _color(
    rng: np.random.Generator, sat: tuple[float, float], val: tuple[float, float]
) -> tuple[float, float, float]:
    """A random linear-RGB colour with hue uniform, saturation and value in the ranges."""
    h = rng.uniform()
    return colorsys.hsv_to_rgb(h, rng.uniform(*sat), rng.uniform(*val))


def _light_tint(rng: np.random.Generator) -> np.ndarray:
    """Warm-to-cool white with unit luminance."""
    t = rng.uniform()
    c = (1 - t) * np.array([1.0, 0.8, 0.6]) + t * np.array([0.85, 0.92, 1.0])
    return c / (0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2])


_CONDUCTORS = ("Au", "Ag", "Cu", "Al", "Cr", "none")

#: Material kind -> weight, for closed shapes (sphere, cube) and open ones (everything else).
_SOLID_MATERIALS = {
    "diffuse": 0.26,
    "checker": 0.1,
    "roughplastic": 0.15,
    "plastic": 0.08,
    "roughconductor": 0.15,
    "conductor": 0.08,
    "dielectric": 0.18,
}
_SURFACE_MATERIALS = {
    "diffuse": 0.35,
    "checker": 0.15,
    "roughplastic": 0.2,
    "plastic": 0.08,
    "roughconductor": 0.15,
    "conductor": 0.07,
}


def _material(rng: np.random.Generator, weights: dict[str, float]) -> dict:
    """A random BSDF; non-transmissive ones are wrapped in ``twosided``."""
    kinds = list(weights)
    p = np.array([weights[k] for k in kinds])
    kind = kinds[rng.choice(len(kinds), p=p / p.sum())]
    if kind == "dielectric":
        return {"type": "dielectric", "int_ior": float(rng.uniform(1.33, 1.8))}
    if kind == "diffuse":
        bsdf = _diffuse(_color(rng, (0.0, 0.8), (0.15, 0.85)))
    elif kind == "checker":
        bsdf = _checker(
            _color(rng, (0.0, 0.9), (0.4, 0.9)),
            _color(rng, (0.0, 0.9), (0.05, 0.5)),
            rng.choice([2, 4, 6, 8, 12]),
        )
    elif kind in ("plastic", "roughplastic"):
        bsdf = {
            "type": kind,
            "diffuse_reflectance": _rgb(_color(rng, (0.2, 0.9), (0.1, 0.8))),
            "int_ior": float(rng.uniform(1.4, 1.6)),
        }
        if kind == "roughplastic":
            bsdf["alpha"] = float(np.exp(rng.uniform(np.log(0.03), np.log(0.4))))
    else:
        bsdf = {"type": kind, "material": str(rng.choice(_CONDUCTORS))}
        if kind == "roughconductor":
            bsdf["alpha"] = float(np.exp(rng.uniform(np.log(0.02), np.log(0.4))))
    return _twosided(bsdf)


def _luminance(color: Vec3) -> float:
    return float(np.dot([0.2126, 0.7152, 0.0722], color))


def _wall_material(rng: np.random.Generator, floor: bool) -> tuple[dict, float]:
    """A random floor/wall/ceiling BSDF and its approximate albedo."""
    if floor and rng.uniform() < 0.4:
        c0 = np.array(_color(rng, (0.0, 0.4), (0.5, 0.85)))
        c1 = c0 * rng.uniform(0.2, 0.6)
        return _twosided(_checker(c0, c1, rng.integers(4, 16))), _luminance((c0 + c1) / 2)
    if floor and rng.uniform() < 0.3:
        c = _color(rng, (0.3, 0.7), (0.2, 0.5))
        bsdf = {
            "type": "roughplastic",
            "alpha": float(rng.uniform(0.1, 0.4)),
            "diffuse_reflectance": _rgb(c),
        }
        return _twosided(bsdf), _luminance(c) + 0.05
    c = _color(rng, (0.0, 0.35), (0.45, 0.85))
    return _twosided(_diffuse(c)), _luminance(c)


# -- Layouts ---------------------------------------------------------------------------------


def _wall_with_window(
    b: _Builder,
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
        b.add("wall", _rectangle(c + [0, height / 2, 0], normal, [width, height], bsdf))
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
        b.add("wall", _rectangle(mid, normal, [s1 - s0, t1 - t0], bsdf))


def _room(b: _Builder, cfg: RandomSceneConfig, window: bool) -> _Layout:
    rng = b.rng
    hx, hz = rng.uniform(1.5, 3.5, size=2)
    height = rng.uniform(2.4, 3.4)
    open_side = (
        str(rng.choice(["+x", "-x", "+z", "-z"])) if rng.uniform() < cfg.p_open_side else None
    )
    floor, floor_albedo = _wall_material(rng, True)
    ceiling, ceiling_albedo = _wall_material(rng, False)
    b.add("floor", _rectangle([0, 0, 0], [0, 1, 0], [2 * hx, 2 * hz], floor))
    b.add("ceiling", _rectangle([0, height, 0], [0, -1, 0], [2 * hx, 2 * hz], ceiling))
    sides = {  # side -> (center, inward normal, direction along the wall, wall length)
        "+x": ([hx, 0, 0], [-1, 0, 0], [0, 0, 1], 2 * hz),
        "-x": ([-hx, 0, 0], [1, 0, 0], [0, 0, 1], 2 * hz),
        "+z": ([0, 0, hz], [0, 0, -1], [1, 0, 0], 2 * hx),
        "-z": ([0, 0, -hz], [0, 0, 1], [1, 0, 0], 2 * hx),
    }
    closed = [s for s in sides if s != open_side]
    window_side = str(rng.choice(closed)) if window else None
    window_area = 0.0
    wall = _wall_material(rng, False)
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
        bsdf, albedo = _wall_material(rng, False) if rng.uniform() < 0.3 else wall
        _wall_with_window(b, center, normal, along, length, height, hole, bsdf)
        albedo_sum += length * height * albedo
        total_area += length * height
    albedo = albedo_sum / total_area
    if window and open_side is not None:  # the environment also shines through the open side
        window_area += sides[open_side][3] * height
    return _Layout(True, (hx, hz), height, albedo, open_side, window_side, window_area)


def _open_layout(b: _Builder) -> _Layout:
    rng = b.rng
    ground, albedo = _wall_material(rng, True)
    b.add("ground", _rectangle([0, 0, 0], [0, 1, 0], [60, 60], ground))
    if rng.uniform() < 0.3:  # a backdrop wall behind the content
        angle = rng.uniform(0, 2 * np.pi)
        n = np.array([np.cos(angle), 0, np.sin(angle)])
        b.add("backdrop", _rectangle(-4 * n + [0, 2, 0], n, [10, 4], _wall_material(rng, False)[0]))
    half = rng.uniform(1.8, 3.0)
    return _Layout(False, (half, half), 4.0, albedo)


# -- Objects ---------------------------------------------------------------------------------


def _rot(angle_deg: float, lx: float, lz: float) -> np.ndarray:
    """Rotates the local offset ``(lx, 0, lz)`` about +y like ``ScalarTransform4f.rotate``."""
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    return np.array([lx * c + lz * s, 0.0, -lx * s + lz * c])


def _small_object(b: _Builder, base: np.ndarray, max_size: float) -> float:
    """A small box, sphere or capped cylinder standing at ``base``; returns its height."""
    rng = b.rng
    kind = rng.choice(["box", "sphere", "cylinder"])
    size = rng.uniform(0.4, 1.0) * max_size
    if kind == "sphere":
        bsdf = _material(rng, _SOLID_MATERIALS)
        b.add("sphere", _sphere(base + [0, size / 2, 0], size / 2, bsdf))
    elif kind == "box":
        dims = size * rng.uniform(0.5, 1.0, size=3)
        b.add(
            "box",
            _cube(
                base + [0, dims[1] / 2, 0],
                dims,
                _material(rng, _SOLID_MATERIALS),
                rng.uniform(0, 90),
            ),
        )
        size = dims[1]
    else:
        bsdf = _material(rng, _SURFACE_MATERIALS)
        r = size * rng.uniform(0.2, 0.45)
        b.add("cylinder", _cylinder(base, base + [0, size, 0], r, bsdf))
        b.add("cap", _disk(base + [0, size, 0], [0, 1, 0], r, bsdf))
    return size


def _table(b: _Builder, x: float, z: float, angle: float, max_height: float) -> _Item:
    rng = b.rng
    w, d = rng.uniform(0.8, 1.6), rng.uniform(0.6, 1.0)
    h, t = min(rng.uniform(0.65, 0.8), max_height), rng.uniform(0.03, 0.06)
    bsdf = _material(rng, _SURFACE_MATERIALS)
    base = np.array([x, 0.0, z])
    b.add("tabletop", _cube(base + [0, h - t / 2, 0], [w, t, d], bsdf, angle))
    leg_r = rng.uniform(0.02, 0.04)
    for sx in (-1, 1):
        for sz in (-1, 1):
            p = base + _rot(angle, sx * (w / 2 - 2 * leg_r), sz * (d / 2 - 2 * leg_r))
            b.add("leg", _cylinder(p, p + [0, h - t, 0], leg_r, bsdf))
    top = h
    for _ in range(rng.integers(0, 3)):
        offset = _rot(angle, rng.uniform(-0.3, 0.3) * w, rng.uniform(-0.3, 0.3) * d)
        top = max(top, h + _small_object(b, base + offset + [0, h, 0], 0.3))
    return _Item(x, z, 0.5 * math.hypot(w, d), top)


def _shelf(b: _Builder, x: float, z: float, angle: float, max_height: float) -> _Item:
    """An open shelf (front towards local +z) with boards, back panel and a few items."""
    rng = b.rng
    w, d = rng.uniform(0.6, 1.4), rng.uniform(0.25, 0.4)
    h, t = min(rng.uniform(1.0, 2.0), max_height), 0.03
    bsdf = _material(rng, _SURFACE_MATERIALS)
    base = np.array([x, 0.0, z])
    for sx in (-1, 1):
        b.add(
            "shelfside",
            _cube(base + _rot(angle, sx * (w - t) / 2, 0) + [0, h / 2, 0], [t, h, d], bsdf, angle),
        )
    b.add(
        "shelfback",
        _cube(base + _rot(angle, 0, -(d - t) / 2) + [0, h / 2, 0], [w, h, t], bsdf, angle),
    )
    levels = np.linspace(t / 2, h - t / 2, rng.integers(3, 6))
    for y in levels:
        b.add("board", _cube(base + [0, y, 0], [w - 2 * t, t, d - t], bsdf, angle))
    gap = levels[1] - levels[0]
    for y in levels[:-1]:
        if rng.uniform() < 0.6:
            offset = _rot(angle, rng.uniform(-0.3, 0.3) * w, 0.0)
            _small_object(b, base + offset + [0, y + t / 2, 0], min(0.8 * gap, 0.8 * d))
    return _Item(x, z, 0.5 * math.hypot(w, d), h)


def _floor_object(b: _Builder, layout: _Layout, x: float, z: float, radius: float) -> _Item:
    """A box, sphere, capped cylinder, rug disk or standing panel with footprint ``radius``."""
    rng = b.rng
    kind = rng.choice(["box", "sphere", "cylinder", "rug", "panel"], p=[0.3, 0.3, 0.2, 0.1, 0.1])
    base = np.array([x, 0.0, z])
    max_height = layout.height - 1.0
    if kind == "sphere":
        b.add("sphere", _sphere(base + [0, radius, 0], radius, _material(rng, _SOLID_MATERIALS)))
        return _Item(x, z, radius, 2 * radius)
    if kind == "box":
        side = radius * math.sqrt(2)
        dims = [
            side * rng.uniform(0.6, 1.0),
            min(rng.uniform(0.2, 1.6), max_height),
            side * rng.uniform(0.6, 1.0),
        ]
        b.add(
            "box",
            _cube(
                base + [0, dims[1] / 2, 0],
                dims,
                _material(rng, _SOLID_MATERIALS),
                rng.uniform(0, 90),
            ),
        )
        return _Item(x, z, radius, dims[1])
    if kind == "cylinder":
        h = min(rng.uniform(0.2, 1.5), max_height)
        bsdf = _material(rng, _SURFACE_MATERIALS)
        b.add("cylinder", _cylinder(base, base + [0, h, 0], radius, bsdf))
        b.add("cap", _disk(base + [0, h, 0], [0, 1, 0], radius, bsdf))
        return _Item(x, z, radius, h)
    if kind == "rug":
        b.add(
            "rug",
            _disk(
                base + [0, 0.005, 0],
                [0, 1, 0],
                radius,
                _material(rng, {"diffuse": 0.5, "checker": 0.5}),
            ),
        )
        return _Item(x, z, radius, 0.01)
    # A standing panel: thin glass pane, or an opaque screen.
    h = min(rng.uniform(0.6, 1.8), max_height)
    a = rng.uniform(0, 2 * np.pi)
    if rng.uniform() < 0.5:
        bsdf = {"type": "thindielectric", "int_ior": float(rng.uniform(1.4, 1.6))}
    else:
        bsdf = _material(rng, _SURFACE_MATERIALS)
    b.add(
        "panel", _rectangle(base + [0, h / 2, 0], [np.cos(a), 0, np.sin(a)], [2 * radius, h], bsdf)
    )
    return _Item(x, z, radius, h)


def _wall_decor(b: _Builder, layout: _Layout) -> None:
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
    bsdf = _material(rng, {"checker": 0.4, "diffuse": 0.3, "conductor": 0.3})
    if rng.uniform() < 0.5:
        b.add("picture", _rectangle(center, normal, [2 * size, size * rng.uniform(1.0, 1.6)], bsdf))
    else:
        b.add("plate", _disk(center, normal, size, bsdf))


def _objects(b: _Builder, cfg: RandomSceneConfig, layout: _Layout) -> None:
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


# -- Lights ----------------------------------------------------------------------------------


def _free_spot(rng: np.random.Generator, layout: _Layout, y: float) -> list[float]:
    """A random point at height ``y`` over the content region, away from objects reaching
    up to ``y`` (best effort)."""
    hx, hz = layout.half
    for _attempt in range(20):
        x, z = rng.uniform(-0.8, 0.8) * hx, rng.uniform(-0.8, 0.8) * hz
        if all(
            math.hypot(x - it.x, z - it.z) > it.radius + 0.2 or it.top < y - 0.3
            for it in layout.items
        ):
            break
    return [float(x), float(y), float(z)]


def _lights(b: _Builder, cfg: RandomSceneConfig, layout: _Layout, window: bool) -> None:
    """Adds emitters whose total power gives diffuse surfaces a mean radiance near
    ``cfg.target_radiance`` (a crude energy balance: closed rooms re-reflect about as much
    light as they receive, open set-ups lose it)."""
    rng = b.rng
    hx, hz = layout.half
    local = ["area_large", "area_small", "sphere", "point"]
    kinds: list[str] = []
    if window or (not layout.room and rng.uniform() < cfg.p_env_open):
        kinds.append("env")
        if rng.uniform() < cfg.p_extra_light:
            kinds.append(str(rng.choice(local)))
    else:
        kinds += [
            str(k)
            for k in rng.choice(local, size=1 + (rng.uniform() < cfg.p_extra_light), replace=False)
        ]
    shares = rng.dirichlet(np.full(len(kinds), 4.0))
    target = cfg.target_radiance * np.exp(rng.uniform(-0.4, 0.4))
    rho = layout.albedo
    if layout.room:  # radiosity of a closed room: B = rho / (1 - rho) * flux / (pi * area)
        area = 2 * (4 * hx * hz + 2 * (hx + hz) * layout.height)
        power = target * np.pi * area * (1 - rho) / rho
    else:  # a single bounce off the ground around the content
        area = np.pi * (max(hx, hz) + 1.5) ** 2
        power = target * np.pi * area / rho
    ceiling = layout.height - 0.005 if layout.room else None
    for kind, share in zip(kinds, shares, strict=True):
        p = share * power
        tint = _light_tint(rng)
        if kind == "env":
            bitmap = rng.uniform() < cfg.p_bitmap_env
            if layout.room:  # light through the window: flux ~ pi L A
                radiance = p / (np.pi * layout.window_area)
            else:  # unoccluded ground: B = rho L (a sky's upper half is ~1.5x its mean)
                radiance = share * target / rho / (1.5 if bitmap else 1.0)
            if bitmap:
                elev = rng.uniform(0.15, 1.2)
                az = rng.uniform(0, 2 * np.pi)
                sun_dir = [np.cos(elev) * np.cos(az), np.sin(elev), np.cos(elev) * np.sin(az)]
                image = _sky_image(
                    *cfg.env_shape,
                    sun_dir,
                    sun=rng.choice([0.0, 10.0, 30.0]),
                    overcast=rng.uniform(0, 1),
                    rng=rng,
                )
                b.add("env", _envmap(image, radiance))
            else:
                b.add("env", {"type": "constant", "radiance": _rgb(radiance * tint)})
        elif kind == "area_large":
            w, d = rng.uniform(0.3, 0.6) * 2 * hx, rng.uniform(0.3, 0.6) * 2 * hz
            radiance = p / (np.pi * w * d)
            if layout.room:
                b.add(
                    "light",
                    _rectangle(
                        [rng.uniform(-0.3, 0.3) * hx, ceiling, rng.uniform(-0.3, 0.3) * hz],
                        [0, -1, 0],
                        [w, d],
                        emitter=_area(radiance * tint),
                    ),
                )
            else:  # a tilted soft box above the content
                pos = np.array([rng.uniform(-3, 3), rng.uniform(3, 5), rng.uniform(-3, 3)])
                b.add(
                    "light",
                    _rectangle(pos, -pos + [0, 0.5, 0], [w, d], emitter=_area(radiance * tint)),
                )
        elif kind == "area_small":
            count = rng.integers(1, 5)
            for _ in range(count):
                s = rng.uniform(0.1, 0.4)
                radiance = p / count / (np.pi * s * s)
                y = ceiling if layout.room else rng.uniform(2.5, 4.0)
                b.add(
                    "light",
                    _rectangle(
                        _free_spot(rng, layout, y),
                        [0, -1, 0],
                        [s, s],
                        emitter=_area(radiance * tint),
                    ),
                )
        elif kind == "sphere":
            count = rng.integers(1, 4)
            for _ in range(count):
                r = rng.uniform(0.04, 0.15)
                radiance = p / count / (np.pi * 4 * np.pi * r * r)
                y = layout.height - rng.uniform(0.3, 0.7) if layout.room else rng.uniform(1.5, 3.5)
                b.add(
                    "bulb", _sphere(_free_spot(rng, layout, y), r, emitter=_area(radiance * tint))
                )
        else:
            count = rng.integers(1, 4)
            for _ in range(count):
                y = layout.height - rng.uniform(0.2, 0.6) if layout.room else rng.uniform(1.5, 3.5)
                b.add(
                    "point",
                    {
                        "type": "point",
                        "position": _free_spot(rng, layout, y),
                        "intensity": _rgb(p / count / (4 * np.pi) * tint),
                    },
                )


# -- Cameras ---------------------------------------------------------------------------------


def _camera(
    rng: np.random.Generator, cfg: RandomSceneConfig, layout: _Layout, resolution: tuple[int, int]
) -> dict:
    """A random camera inside (or, for open sides and open set-ups, around) the content,
    aimed at a random object or wall point; thin lens with probability ``cfg.p_thinlens``."""
    hx, hz = layout.half
    for _attempt in range(100):
        if layout.items and rng.uniform() < 0.85:
            it = layout.items[rng.integers(len(layout.items))]
            target = np.array([it.x, rng.uniform(0.3, 0.8) * max(it.top, 0.3), it.z])
        else:
            target = np.array([rng.uniform(-hx, hx), rng.uniform(0.3, 1.5), rng.uniform(-hz, hz)])
        target += rng.normal(0, 0.15, size=3)
        if not layout.room:
            a, r = rng.uniform(0, 2 * np.pi), rng.uniform(2.5, 7.0)
            origin = np.array([r * np.cos(a), rng.uniform(0.3, 3.5), r * np.sin(a)])
        elif layout.open_side is not None and rng.uniform() < 0.4:
            axis = 0 if layout.open_side[1] == "x" else 2
            sign = 1.0 if layout.open_side[0] == "+" else -1.0
            origin = np.array(
                [rng.uniform(-hx, hx) * 0.8, rng.uniform(0.5, 2.2), rng.uniform(-hz, hz) * 0.8]
            )
            origin[axis] = sign * (layout.half[axis // 2] + rng.uniform(0.3, 3.0))
        else:
            origin = np.array(
                [
                    rng.uniform(-hx + 0.3, hx - 0.3),
                    rng.uniform(0.4, min(2.0, layout.height - 0.3)),
                    rng.uniform(-hz + 0.3, hz - 0.3),
                ]
            )
        d = target - origin
        dist = float(np.linalg.norm(d))
        if dist < 1.2 or abs(d[1]) > 0.9 * dist:
            continue
        if any(
            math.hypot(origin[0] - it.x, origin[2] - it.z) < it.radius + 0.25
            and origin[1] < it.top + 0.25
            for it in layout.items
        ):
            continue
        break
    fov = rng.uniform(35.0, 75.0)
    if rng.uniform() < cfg.p_thinlens:
        return _sensor(
            origin,
            target,
            resolution,
            fov=fov,
            aperture=rng.uniform(0.02, 0.1) * min(dist, 3.0),
            focus=dist,
        )
    return _sensor(origin, target, resolution, fov=fov)


# -- Public API ------------------------------------------------------------------------------

#: Salt separating the camera streams from the content stream of a seed.
_VIEW_SALT = 0x5CE7E


def random_scene(
    seed: int,
    *,
    resolution: Sequence[int] = (128, 128),
    view: int = 0,
    config: RandomSceneConfig | None = None,
) -> SceneDict:
    """Returns a random procedural training scene.

    The content (room with walls, optional open side and window, or an open ground plane;
    boxes, spheres, capped cylinders, rugs, panels, tables with legs and items, shelves with
    items, wall pictures; diffuse/checkerboard, (rough) plastic, (rough) conductor, dielectric
    and thin-dielectric materials; large/small/multiple area lights, sphere lights, point
    lights, constant or procedural-sky environment) depends only on ``seed``. The camera
    depends on ``(seed, view)``, so one scene can be rendered from several views. Light power
    is set by a crude energy balance so that images are neither black nor blown out.

    Args:
        seed (int): non-negative scene seed (``numpy.random.PCG64(seed)`` drives the content).
        resolution (tuple[int, int]): film ``(width, height)``.
        view (int): non-negative camera index.
        config (RandomSceneConfig | None): generator knobs; ``None`` uses the defaults.

    Returns:
        dict: a scene dictionary following the module contract (box filter, no integrator).

    Raises:
        ValueError: negative ``seed``/``view`` or bad ``resolution``.
    """
    resolution = _check_resolution(resolution)
    for name, value in (("seed", seed), ("view", view)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
            raise ValueError(f"{name} must be a non-negative int, got {value!r}")
    cfg = config or RandomSceneConfig()
    b = _Builder(np.random.Generator(np.random.PCG64(seed)))
    if b.rng.uniform() < cfg.p_room:
        window = b.rng.uniform() < cfg.p_window
        layout = _room(b, cfg, window)
    else:
        window = False
        layout = _open_layout(b)
    _objects(b, cfg, layout)
    _lights(b, cfg, layout, window)
    view_rng = np.random.Generator(np.random.PCG64([int(seed), _VIEW_SALT, int(view)]))
    return _scene(_camera(view_rng, cfg, layout, resolution), **b.entries)


def random_views(
    seed: int,
    n: int,
    *,
    resolution: Sequence[int] = (128, 128),
    config: RandomSceneConfig | None = None,
) -> list[SceneDict]:
    """Returns scene ``seed`` seen from views ``0 .. n-1`` (see :func:`random_scene`).

    Raises:
        ValueError: ``n < 1`` or an invalid argument of :func:`random_scene`.
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    return [random_scene(seed, resolution=resolution, view=v, config=config) for v in range(n)]
