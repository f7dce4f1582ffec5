"""Building blocks of scene dictionaries: film, sensor, shapes, materials, emitters, sky.

The scene contract shared by every scene of :mod:`gdpt.scenes` (box filter, ``independent``
sampler, no integrator, deterministic) is stated in the package docstring. A Mitsuba variant
must be set before calling these (transforms and bitmaps are variant types).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import mitsuba as mi
import numpy as np

SceneDict = dict[str, Any]
Vec3 = Sequence[float]

#: Default resolution of the tiny statistical test scenes.
TEST_RESOLUTION = (24, 24)

#: Classic Cornell-box reflectances (diffuse albedo in linear RGB).
CBOX_WHITE = (0.725, 0.71, 0.68)
CBOX_RED = (0.63, 0.065, 0.05)
CBOX_GREEN = (0.14, 0.45, 0.091)


# --------------------------------------------------------------------------------------------
#  Small dictionary builders
# --------------------------------------------------------------------------------------------


def check_resolution(resolution: Sequence[int]) -> tuple[int, int]:
    """Returns ``resolution`` as ``(width, height)`` or raises ``ValueError``."""
    try:
        width, height = resolution
    except (TypeError, ValueError):
        raise ValueError(f"resolution must be a (width, height) pair, got {resolution!r}") from None
    for v in (width, height):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"resolution must hold two positive ints, got {resolution!r}")
    return int(width), int(height)


def _floats(v: Vec3) -> list[float]:
    return [float(x) for x in v]


def rgb(value: float | Vec3) -> dict:
    """An ``rgb`` value (a scalar is grey)."""
    values = [value] * 3 if np.isscalar(value) else value
    return {"type": "rgb", "value": _floats(values)}


def _film(resolution: tuple[int, int]) -> dict:
    return {
        "type": "hdrfilm",
        "width": resolution[0],
        "height": resolution[1],
        "rfilter": {"type": "box"},
        "pixel_format": "rgb",
    }


def camera(
    origin: Vec3,
    target: Vec3,
    resolution: tuple[int, int],
    *,
    fov: float,
    aperture: float = 0.0,
    focus: float | None = None,
) -> dict:
    """A perspective camera, or a thin-lens camera if ``aperture > 0`` (focused on ``focus``)."""
    sensor = {
        "type": "perspective",
        "fov": float(fov),
        "fov_axis": "x",
        "near_clip": 0.01,
        "to_world": mi.ScalarTransform4f().look_at(
            origin=_floats(origin), target=_floats(target), up=[0.0, 1.0, 0.0]
        ),
        "film": _film(resolution),
        "sampler": {"type": "independent", "sample_count": 16},
    }
    if aperture > 0.0:
        sensor["type"] = "thinlens"
        sensor["aperture_radius"] = float(aperture)
        sensor["focus_distance"] = float(focus)
    return sensor


def _frame(center: Vec3, normal: Vec3) -> mi.ScalarTransform4f:
    """Maps local +z to ``normal`` and the origin to ``center``."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    up = [0.0, 0.0, 1.0] if abs(n[1]) > 0.9 else [0.0, 1.0, 0.0]
    c = np.asarray(center, dtype=np.float64)
    return mi.ScalarTransform4f().look_at(origin=_floats(c), target=_floats(c + n), up=up)


def rectangle(center: Vec3, normal: Vec3, size: Vec3, bsdf: dict | None = None, **extra) -> dict:
    """A ``size[0] x size[1]`` rectangle facing ``normal`` (one-sided for emitters)."""
    to_world = _frame(center, normal).scale([size[0] / 2, size[1] / 2, 1.0])
    return shape("rectangle", bsdf, to_world=to_world, **extra)


def disk(center: Vec3, normal: Vec3, radius: float, bsdf: dict | None = None, **extra) -> dict:
    """A disk of ``radius`` facing ``normal``."""
    to_world = _frame(center, normal).scale([radius, radius, 1.0])
    return shape("disk", bsdf, to_world=to_world, **extra)


def cube(center: Vec3, size: Vec3, bsdf: dict, angle: float = 0.0) -> dict:
    """An axis-aligned (then rotated by ``angle`` degrees about +y) box of extent ``size``."""
    to_world = (
        mi.ScalarTransform4f()
        .translate(_floats(center))
        .rotate([0.0, 1.0, 0.0], float(angle))
        .scale([s / 2 for s in _floats(size)])
    )
    return shape("cube", bsdf, to_world=to_world)


def sphere(center: Vec3, radius: float, bsdf: dict | None = None, **extra) -> dict:
    """A sphere (``extra``: e.g. ``emitter=``)."""
    return shape("sphere", bsdf, center=_floats(center), radius=float(radius), **extra)


def cylinder(p0: Vec3, p1: Vec3, radius: float, bsdf: dict) -> dict:
    """An open tube (no caps) from ``p0`` to ``p1``."""
    return shape("cylinder", bsdf, p0=_floats(p0), p1=_floats(p1), radius=float(radius))


def shape(kind: str, bsdf: dict | None, **props) -> dict:
    """A shape of plugin type ``kind`` with ``props`` and, unless ``None``, ``bsdf``."""
    shape = {"type": kind, **props}
    if bsdf is not None:
        shape["bsdf"] = bsdf
    return shape


def area_emitter(radiance: float | Vec3) -> dict:
    """An ``area`` emitter of constant ``radiance``."""
    return {"type": "area", "radiance": rgb(radiance)}


def diffuse(color: float | Vec3) -> dict:
    """A ``diffuse`` BSDF of reflectance ``color``."""
    return {"type": "diffuse", "reflectance": rgb(color)}


def checker(color0: Vec3, color1: Vec3, scale: float) -> dict:
    """Diffuse BSDF with a ``scale x scale`` checkerboard over the shape's UV square."""
    texture = {
        "type": "checkerboard",
        "color0": rgb(color0),
        "color1": rgb(color1),
        "to_uv": mi.ScalarTransform4f().scale([float(scale), float(scale), 1.0]),
    }
    return {"type": "diffuse", "reflectance": texture}


def twosided(bsdf: dict) -> dict:
    """``bsdf`` on both sides of a surface."""
    return {"type": "twosided", "bsdf": bsdf}


def envmap(image: np.ndarray, scale: float = 1.0) -> dict:
    """An ``envmap`` emitter from an in-memory ``(H, W, 3)`` float32 lat-long image."""
    bitmap = mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32))
    return {"type": "envmap", "bitmap": bitmap, "scale": float(scale)}


def scene(sensor: dict, **objects: dict) -> SceneDict:
    """A scene dictionary of ``sensor`` and ``objects`` (no integrator)."""
    return {"type": "scene", "sensor": sensor, **objects}


# --------------------------------------------------------------------------------------------
#  Procedural sky


def sky_image(
    height: int,
    width: int,
    sun_dir: Vec3,
    *,
    sun: float,
    overcast: float,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Procedural lat-long sky, ``(height, width, 3)`` float32, +y up, mean radiance ~1.

    Blue zenith to pale horizon, darker brown ground, optional gaussian sun of relative
    strength ``sun`` around ``sun_dir``, ``overcast`` in [0, 1] greys the sky, ``rng`` adds
    smooth clouds.
    """
    theta = (np.arange(height) + 0.5) / height * np.pi
    phi = (np.arange(width) + 0.5) / width * 2 * np.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    # Mitsuba's envmap direction for (u, v) = (phi / 2pi, theta / pi).
    d = np.stack([np.sin(ph) * np.sin(th), np.cos(th), -np.cos(ph) * np.sin(th)], axis=-1)
    elevation = np.clip(d[..., 1], 0.0, 1.0)[..., None]
    zenith = np.array([0.25, 0.45, 1.0]) * (1 - overcast) + 0.8 * overcast
    horizon = np.array([0.85, 0.9, 1.0])
    sky = horizon + (zenith - horizon) * np.sqrt(elevation)
    if rng is not None:
        clouds = sum(
            np.sin(f * ph + rng.uniform(0, 2 * np.pi)) * np.sin(f * th + rng.uniform(0, 2 * np.pi))
            for f in rng.integers(1, 6, size=3)
        )
        sky = sky + 0.25 * np.clip(clouds, 0, None)[..., None] * elevation
    ground = (
        np.array([0.3, 0.26, 0.21]) * (0.6 + 0.4 * np.exp(8 * np.minimum(d[..., 1], 0)))[..., None]
    )
    image = np.where(d[..., 1:2] >= 0, sky, ground)
    s = np.asarray(sun_dir, dtype=np.float64)
    cos_sun = d @ (s / np.linalg.norm(s))
    image = image + sun * np.exp((cos_sun - 1) / 0.004)[..., None] * np.array([1.0, 0.9, 0.75])
    # Normalise the solid-angle-weighted mean to 1.
    weights = np.sin(th)[..., None]
    image /= (image * weights).sum() / (3 * weights.sum())
    return image.astype(np.float32)
