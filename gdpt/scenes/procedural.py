"""The procedural training-scene generator: :func:`random_scene`, :func:`random_views`
(rooms and open set-ups, random materials, lights and cameras; deterministic in the seed).

Its lights and cameras live here; its knobs (:class:`~.procedural_config.RandomSceneConfig`) in
:mod:`.procedural_config`, the rooms and objects in :mod:`.procedural_layout`, the colours and
materials in :mod:`.procedural_materials`."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from gdpt.scenes.elements import (
    SceneDict,
    area_emitter,
    camera,
    check_resolution,
    envmap,
    rectangle,
    rgb,
    scene,
    sky_image,
    sphere,
)
from gdpt.scenes.procedural_config import RandomSceneConfig
from gdpt.scenes.procedural_layout import (
    Layout,
    SceneBuilder,
    build_open_layout,
    build_room,
    place_objects,
)
from gdpt.scenes.procedural_materials import light_tint

# -- Lights ----------------------------------------------------------------------------------


def _free_spot(rng: np.random.Generator, layout: Layout, y: float) -> list[float]:
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


def _lights(b: SceneBuilder, cfg: RandomSceneConfig, layout: Layout, window: bool) -> None:
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
        tint = light_tint(rng)
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
                image = sky_image(
                    *cfg.env_shape,
                    sun_dir,
                    sun=rng.choice([0.0, 10.0, 30.0]),
                    overcast=rng.uniform(0, 1),
                    rng=rng,
                )
                b.add("env", envmap(image, radiance))
            else:
                b.add("env", {"type": "constant", "radiance": rgb(radiance * tint)})
        elif kind == "area_large":
            w, d = rng.uniform(0.3, 0.6) * 2 * hx, rng.uniform(0.3, 0.6) * 2 * hz
            radiance = p / (np.pi * w * d)
            if layout.room:
                b.add(
                    "light",
                    rectangle(
                        [rng.uniform(-0.3, 0.3) * hx, ceiling, rng.uniform(-0.3, 0.3) * hz],
                        [0, -1, 0],
                        [w, d],
                        emitter=area_emitter(radiance * tint),
                    ),
                )
            else:  # a tilted soft box above the content
                pos = np.array([rng.uniform(-3, 3), rng.uniform(3, 5), rng.uniform(-3, 3)])
                b.add(
                    "light",
                    rectangle(
                        pos, -pos + [0, 0.5, 0], [w, d], emitter=area_emitter(radiance * tint)
                    ),
                )
        elif kind == "area_small":
            count = rng.integers(1, 5)
            for _ in range(count):
                s = rng.uniform(0.1, 0.4)
                radiance = p / count / (np.pi * s * s)
                y = ceiling if layout.room else rng.uniform(2.5, 4.0)
                b.add(
                    "light",
                    rectangle(
                        _free_spot(rng, layout, y),
                        [0, -1, 0],
                        [s, s],
                        emitter=area_emitter(radiance * tint),
                    ),
                )
        elif kind == "sphere":
            count = rng.integers(1, 4)
            for _ in range(count):
                r = rng.uniform(0.04, 0.15)
                radiance = p / count / (np.pi * 4 * np.pi * r * r)
                y = layout.height - rng.uniform(0.3, 0.7) if layout.room else rng.uniform(1.5, 3.5)
                b.add(
                    "bulb",
                    sphere(_free_spot(rng, layout, y), r, emitter=area_emitter(radiance * tint)),
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
                        "intensity": rgb(p / count / (4 * np.pi) * tint),
                    },
                )


# -- Cameras ---------------------------------------------------------------------------------


def _camera(
    rng: np.random.Generator, cfg: RandomSceneConfig, layout: Layout, resolution: tuple[int, int]
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
        return camera(
            origin,
            target,
            resolution,
            fov=fov,
            aperture=rng.uniform(0.02, 0.1) * min(dist, 3.0),
            focus=dist,
        )
    return camera(origin, target, resolution, fov=fov)


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
    resolution = check_resolution(resolution)
    for name, value in (("seed", seed), ("view", view)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
            raise ValueError(f"{name} must be a non-negative int, got {value!r}")
    cfg = config or RandomSceneConfig()
    b = SceneBuilder(np.random.Generator(np.random.PCG64(seed)))
    if b.rng.uniform() < cfg.p_room:
        window = b.rng.uniform() < cfg.p_window
        layout = build_room(b, cfg, window)
    else:
        window = False
        layout = build_open_layout(b)
    place_objects(b, cfg, layout)
    _lights(b, cfg, layout, window)
    view_rng = np.random.Generator(np.random.PCG64([int(seed), _VIEW_SALT, int(view)]))
    return scene(_camera(view_rng, cfg, layout, resolution), **b.entries)


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
