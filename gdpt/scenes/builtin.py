"""Built-in test and demo scenes by name: :func:`builtin_scene` (``cbox-demo``, tiny
statistical test scenes). The scene contract is stated in :mod:`gdpt.scenes`."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import mitsuba as mi
import numpy as np

from gdpt.scenes.elements import (
    CBOX_GREEN,
    CBOX_RED,
    CBOX_WHITE,
    TEST_RESOLUTION,
    SceneDict,
    Vec3,
    area_emitter,
    camera,
    check_resolution,
    checker,
    cube,
    diffuse,
    envmap,
    rectangle,
    rgb,
    scene,
    shape,
    sky_image,
    sphere,
    twosided,
)

# --------------------------------------------------------------------------------------------

_BUILTINS: dict[str, tuple[Callable[[tuple[int, int]], SceneDict], tuple[int, int]]] = {}


def _builtin(name: str, default_resolution: tuple[int, int] = TEST_RESOLUTION) -> Callable:
    """Registers a builder ``f(resolution) -> dict`` under ``name``."""

    def decorate(builder: Callable[[tuple[int, int]], SceneDict]):
        _BUILTINS[name] = (builder, default_resolution)
        return builder

    return decorate


def builtin_names() -> tuple[str, ...]:
    """Returns the names accepted by :func:`builtin_scene`, in registration order."""
    return tuple(_BUILTINS)


def builtin_scene(name: str, *, resolution: Sequence[int] | None = None) -> SceneDict:
    """Returns a built-in scene dictionary.

    ``cbox-demo`` is the 256x256 demo scene; all other names are tiny scenes for statistical
    integrator tests (default 24x24, each exercising one feature, converging at a few thousand
    spp). See the module docstring for the dictionary contract (box filter, no integrator).

    Args:
        name (str): one of :func:`builtin_names`.
        resolution (tuple[int, int] | None): film ``(width, height)``; ``None`` uses the
            scene's default (``(256, 256)`` for ``cbox-demo``, :data:`TEST_RESOLUTION` else).

    Returns:
        dict: a fresh scene dictionary for :func:`mitsuba.load_dict`.

    Raises:
        ValueError: unknown ``name`` (the message lists the valid ones) or bad ``resolution``.
    """
    if name not in _BUILTINS:
        raise ValueError(f"unknown builtin scene {name!r}; valid names: {', '.join(_BUILTINS)}")
    builder, default = _BUILTINS[name]
    return builder(check_resolution(default if resolution is None else resolution))


def _box_walls(
    *, light: float | Vec3 | None = (12.0, 10.5, 8.0), light_size: float = 0.5
) -> SceneDict:
    """Cornell-box shell spanning [-1, 1]^3, open towards +z, optional ceiling light."""
    walls = {
        "floor": rectangle([0, -1, 0], [0, 1, 0], [2, 2], diffuse(CBOX_WHITE)),
        "ceiling": rectangle([0, 1, 0], [0, -1, 0], [2, 2], diffuse(CBOX_WHITE)),
        "back": rectangle([0, 0, -1], [0, 0, 1], [2, 2], diffuse(CBOX_WHITE)),
        "left": rectangle([-1, 0, 0], [1, 0, 0], [2, 2], diffuse(CBOX_RED)),
        "right": rectangle([1, 0, 0], [-1, 0, 0], [2, 2], diffuse(CBOX_GREEN)),
    }
    if light is not None:
        size = [light_size, light_size * 0.8]
        walls["light"] = rectangle([0, 0.995, 0], [0, -1, 0], size, emitter=area_emitter(light))
    return walls


def _box_camera(resolution: tuple[int, int], **lens) -> dict:
    return camera([0, 0, 3.9], [0, 0, 0], resolution, fov=39.3, **lens)


@_builtin("cbox-demo", default_resolution=(256, 256))
def _cbox_demo(res: tuple[int, int]) -> SceneDict:
    """Demo Cornell box: red/green walls, small ceiling light (hard-ish shadows), white
    box with a rough gold sphere (alpha 0.1) on top, a glass sphere and a mirror sphere."""
    return scene(
        _box_camera(res),
        **_box_walls(light=(20.0, 15.5, 10.0), light_size=0.45),
        tall_box=cube([-0.36, -0.6, -0.32], [0.56, 0.8, 0.56], diffuse(CBOX_WHITE), angle=18),
        gold=sphere(
            [-0.36, 0.03, -0.32],
            0.23,
            {
                "type": "roughconductor",
                "material": "Au",
                "alpha": 0.1,
            },
        ),
        glass=sphere([0.42, -0.66, 0.25], 0.34, {"type": "dielectric", "int_ior": 1.5}),
        mirror=sphere([-0.45, -0.8, 0.5], 0.2, {"type": "conductor"}),
    )


@_builtin("diffuse-box")
def _diffuse_box(res: tuple[int, int]) -> SceneDict:
    """Diffuse only: Cornell shell, ceiling area light, one rotated diffuse box."""
    return scene(
        _box_camera(res),
        **_box_walls(),
        block=cube([0.2, -0.55, -0.1], [0.8, 0.9, 0.8], diffuse(CBOX_WHITE), angle=-20),
    )


@_builtin("rough-conductor")
def _rough_conductor(res: tuple[int, int]) -> SceneDict:
    """Glossy reflection: a roughconductor sphere (alpha 0.1) lit by the ceiling area light."""
    bsdf = {"type": "roughconductor", "material": "Cu", "alpha": 0.1}
    return scene(_box_camera(res), **_box_walls(), ball=sphere([0, -0.45, 0], 0.55, bsdf))


@_builtin("mirror")
def _mirror(res: tuple[int, int]) -> SceneDict:
    """Perfect specular reflection: a mirror panel on the green wall and a mirror sphere, both
    reflecting the lit diffuse box and a blue diffuse cube."""
    mirror = {"type": "conductor"}
    return scene(
        _box_camera(res),
        **_box_walls(),
        panel=rectangle([0.99, 0.0, -0.3], [-1, 0, 0], [1.2, 1.0], mirror),
        ball=sphere([0.4, -0.65, 0.2], 0.35, mirror),
        block=cube([-0.45, -0.7, -0.2], [0.5, 0.6, 0.5], diffuse((0.2, 0.3, 0.7)), angle=25),
    )


@_builtin("glass")
def _glass(res: tuple[int, int]) -> SceneDict:
    """Refraction: a dielectric sphere (IOR 1.5) over a checkerboard floor, area light."""
    walls = _box_walls()
    walls["floor"]["bsdf"] = checker((0.8, 0.8, 0.8), (0.15, 0.15, 0.2), 6)
    return scene(
        _box_camera(res),
        **walls,
        ball=sphere([0, -0.5, 0.1], 0.5, {"type": "dielectric", "int_ior": 1.5}),
    )


@_builtin("near-specular")
def _near_specular(res: tuple[int, int]) -> SceneDict:
    """Narrow glossy lobes for the half-vector shift at ``shift_threshold`` >= 0.03: a rough
    glass sphere (roughdielectric, alpha 0.03) over a checkerboard floor and a rough mirror
    panel (roughconductor, alpha 0.02) on the green wall, area light."""
    walls = _box_walls()
    walls["floor"]["bsdf"] = checker((0.8, 0.8, 0.8), (0.15, 0.15, 0.2), 6)
    return scene(
        _box_camera(res),
        **walls,
        ball=sphere(
            [-0.2, -0.5, 0.1], 0.45, {"type": "roughdielectric", "int_ior": 1.5, "alpha": 0.03}
        ),
        panel=rectangle(
            [0.99, 0.0, -0.3],
            [-1, 0, 0],
            [1.2, 1.0],
            {"type": "roughconductor", "material": "Al", "alpha": 0.02},
        ),
    )


def _ground_with_objects(bsdf: dict | None = None) -> SceneDict:
    """Ground plane at y=0 (10 x 10) with a few diffuse objects for the environment scenes."""
    return {
        "ground": rectangle(
            [0, 0, 0], [0, 1, 0], [10, 10], bsdf or checker((0.6, 0.6, 0.55), (0.3, 0.3, 0.3), 10)
        ),
        "ball": sphere([-0.6, 0.5, 0], 0.5, diffuse((0.7, 0.3, 0.2))),
        "block": cube([0.7, 0.4, -0.3], [0.8, 0.8, 0.8], diffuse((0.3, 0.5, 0.7)), angle=30),
    }


@_builtin("envmap")
def _envmap_scene(res: tuple[int, int]) -> SceneDict:
    """Image-based lighting: a 16x32 procedural sky+sun ``envmap`` (built with ``mi.Bitmap``)
    over a checkerboard ground with a diffuse sphere and cube; the sky is visible."""
    sky = sky_image(16, 32, [0.5, 0.8, 0.4], sun=40.0, overcast=0.2)
    return scene(
        camera([0.5, 1.3, 3.5], [0, 0.4, 0], res, fov=50),
        **_ground_with_objects(),
        env=envmap(sky),
    )


@_builtin("constant-env")
def _constant_env(res: tuple[int, int]) -> SceneDict:
    """Uniform ``constant`` environment (ambient-occlusion look) over diffuse objects."""
    return scene(
        camera([0.5, 1.3, 3.5], [0, 0.4, 0], res, fov=50),
        **_ground_with_objects(diffuse(0.6)),
        env={"type": "constant", "radiance": rgb(1.0)},
    )


@_builtin("point-light")
def _point_light(res: tuple[int, int]) -> SceneDict:
    """Delta-position light: a ``point`` emitter (intensity 3) inside the unlit Cornell shell,
    casting a sharp shadow of a cube."""
    return scene(
        _box_camera(res),
        **_box_walls(light=None),
        block=cube([0.1, -0.7, -0.1], [0.5, 0.6, 0.5], diffuse(CBOX_WHITE), angle=30),
        lamp={"type": "point", "position": [-0.2, 0.6, 0.3], "intensity": rgb(3.0)},
    )


@_builtin("sphere-light")
def _sphere_light(res: tuple[int, int]) -> SceneDict:
    """Spherical area light (radius 0.08, radiance 80): an ``area`` emitter on a small sphere
    (cone sampling, so no plain reconnection) above a diffuse cube."""
    return scene(
        _box_camera(res),
        **_box_walls(light=None),
        block=cube([0.1, -0.7, -0.1], [0.5, 0.6, 0.5], diffuse(CBOX_WHITE), angle=30),
        bulb=sphere([-0.3, 0.5, 0.2], 0.08, emitter=area_emitter(80.0)),
    )


@_builtin("thin-lens")
def _thin_lens(res: tuple[int, int]) -> SceneDict:
    """Depth of field: ``thinlens`` camera (aperture 0.12) focused on the middle of three
    spheres at different depths, so the near and far ones are visibly blurred."""
    return scene(
        _box_camera(res, aperture=0.12, focus=3.9),
        **_box_walls(),
        near=sphere([-0.5, -0.75, 0.7], 0.25, diffuse((0.8, 0.7, 0.2))),
        middle=sphere([0.0, -0.7, 0.0], 0.3, diffuse((0.2, 0.4, 0.8))),
        far=sphere([0.5, -0.65, -0.7], 0.35, diffuse((0.8, 0.3, 0.6))),
    )


@_builtin("tir-glass")
def _tir_glass(res: tuple[int, int]) -> SceneDict:
    """Total internal reflection: a thick IOR-1.7 glass block and sphere seen obliquely from
    above on a checkerboard floor before a white backdrop, lit by a large area light; many
    paths bounce inside the block."""
    glass = {"type": "dielectric", "int_ior": 1.7}
    return scene(
        camera([1.3, 1.5, 2.4], [0, 0.25, 0], res, fov=50),
        floor=rectangle(
            [0, 0, 0], [0, 1, 0], [6, 6], checker((0.85, 0.85, 0.8), (0.1, 0.1, 0.15), 12)
        ),
        backdrop=rectangle([0, 1.5, -1.5], [0, 0, 1], [6, 3], diffuse(CBOX_WHITE)),
        light=rectangle([0.5, 3, 0.5], [0, -1, 0], [2, 2], emitter=area_emitter(6.0)),
        block=cube([-0.2, 0.35, 0], [1.0, 0.7, 0.7], glass, angle=35),
        ball=sphere([0.65, 0.3, 0.6], 0.3, glass),
    )


@_builtin("tiny-bright-light")
def _tiny_bright_light(res: tuple[int, int]) -> SceneDict:
    """Extreme emitter: a 1 cm x 1 cm ceiling light with radiance 1e5 (about the power of
    the usual one), firefly-prone for any strategy that hits it by BSDF sampling."""
    walls = _box_walls(light=None)
    walls["light"] = rectangle([0, 0.995, 0], [0, -1, 0], [0.01, 0.01], emitter=area_emitter(1e5))
    return scene(
        _box_camera(res),
        **walls,
        block=cube([0.2, -0.6, -0.1], [0.6, 0.8, 0.6], diffuse(CBOX_WHITE), angle=-20),
    )


@_builtin("grazing")
def _grazing(res: tuple[int, int]) -> SceneDict:
    """Grazing angles: camera 8 cm above a large checkerboard plane looking almost
    horizontally (about 2 degrees down) under a large overhead area light."""
    return scene(
        camera([0, 0.08, 4], [0, -0.06, 0], res, fov=40),
        ground=rectangle(
            [0, 0, -2], [0, 1, 0], [20, 20], checker((0.8, 0.8, 0.8), (0.2, 0.2, 0.25), 40)
        ),
        light=rectangle([0, 3, 1], [0, -1, 0], [4, 4], emitter=area_emitter(10.0)),
    )


@_builtin("degenerate")
def _degenerate(res: tuple[int, int]) -> SceneDict:
    """Degenerate geometry: a rectangle with a zero scale axis (zero area), a zero-area
    emitter, a cube flattened to zero height lying on the floor (coincident faces), and two
    coplanar overlapping quads of different colours on the back wall (z-fighting)."""

    def zero(y: float) -> mi.ScalarTransform4f:
        return mi.ScalarTransform4f().translate([0, y, 0]).scale([0.5, 0.0, 0.5])

    return scene(
        _box_camera(res),
        **_box_walls(),
        zero_area=shape("rectangle", diffuse(0.5), to_world=zero(0.0)),
        zero_light=shape("rectangle", None, to_world=zero(0.5), emitter=area_emitter(10.0)),
        flat_cube=cube([0.3, -1.0, 0.2], [0.6, 0.0, 0.6], diffuse((0.2, 0.2, 0.7))),
        quad_a=rectangle([-0.2, 0.0, -1], [0, 0, 1], [0.8, 0.8], diffuse((0.8, 0.8, 0.1))),
        quad_b=rectangle([0.2, -0.2, -1], [0, 0, 1], [0.8, 0.8], diffuse((0.1, 0.7, 0.8))),
    )


@_builtin("thin-dielectric")
def _thin_dielectric(res: tuple[int, int]) -> SceneDict:
    """Thin glass: a ``thindielectric`` pane (IOR 1.5) between the camera and a diffuse cube,
    tilted so the pane also reflects the red wall."""
    return scene(
        _box_camera(res),
        **_box_walls(),
        pane=rectangle(
            [0, -0.3, 0.3], [0.35, 0, 1], [1.2, 1.3], {"type": "thindielectric", "int_ior": 1.5}
        ),
        block=cube([0.1, -0.7, -0.4], [0.5, 0.6, 0.5], diffuse((0.2, 0.3, 0.7)), angle=30),
    )


@_builtin("plastic")
def _plastic(res: tuple[int, int]) -> SceneDict:
    """Coated materials: a smooth ``plastic`` sphere and a ``roughplastic`` (alpha 0.15) cube."""
    return scene(
        _box_camera(res),
        **_box_walls(),
        ball=sphere(
            [-0.4, -0.6, 0.1],
            0.4,
            {
                "type": "plastic",
                "diffuse_reflectance": rgb((0.1, 0.3, 0.7)),
            },
        ),
        block=cube(
            [0.45, -0.6, -0.2],
            [0.6, 0.8, 0.6],
            {
                "type": "roughplastic",
                "alpha": 0.15,
                "diffuse_reflectance": rgb((0.7, 0.6, 0.2)),
            },
            angle=-25,
        ),
    )


@_builtin("principled")
def _principled(res: tuple[int, int]) -> SceneDict:
    """Multi-lobe BSDF: a ``principled`` sphere (half metallic, roughness 0.3, clearcoat) and a
    fully dielectric-coated principled cube (roughness 0.5)."""
    return scene(
        _box_camera(res),
        **_box_walls(),
        ball=sphere(
            [-0.4, -0.6, 0.1],
            0.4,
            {
                "type": "principled",
                "base_color": rgb((0.8, 0.4, 0.2)),
                "metallic": 0.5,
                "roughness": 0.3,
                "clearcoat": 0.5,
            },
        ),
        block=cube(
            [0.45, -0.6, -0.2],
            [0.6, 0.8, 0.6],
            {
                "type": "principled",
                "base_color": rgb((0.2, 0.5, 0.3)),
                "roughness": 0.5,
            },
            angle=-25,
        ),
    )


def _height_field(size: int = 32, waves: float = 3.0) -> mi.Bitmap:
    """A smooth, tileable height field (sum of two sines) for ``bumpmap`` scenes."""
    u = (np.arange(size) + 0.5) / size
    h = (
        0.5
        + 0.25 * np.sin(2 * np.pi * waves * u)[None, :]
        + 0.25 * np.sin(2 * np.pi * waves * u)[:, None]
    )
    return mi.Bitmap(h[..., None].astype(np.float32))


def _normal_field(size: int = 32, waves: float = 2.0, tilt: float = 0.4) -> mi.Bitmap:
    """A tangent-space normal map (encoded as n * 0.5 + 0.5) of rolling bumps."""
    u = (np.arange(size) + 0.5) / size
    nx = tilt * np.sin(2 * np.pi * waves * u)[None, :].repeat(size, 0)
    ny = tilt * np.cos(2 * np.pi * waves * u)[:, None].repeat(size, 1)
    n = np.stack([nx, ny, np.ones_like(nx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return mi.Bitmap((n * 0.5 + 0.5).astype(np.float32))


@_builtin("alpha-mask")
def _alpha_mask(res: tuple[int, int]) -> SceneDict:
    """Opacity masks (``mask``, the null lobe): a checkerboard-cut screen (opacity 1 / 0.15)
    in front of the back wall, and a horizontal cut-out under the ceiling light casting a
    patterned shadow, in the Cornell shell."""

    def masked(color: Vec3, cells: int) -> dict:
        opacity = {
            "type": "checkerboard",
            "color0": 1.0,
            "color1": 0.15,
            "to_uv": mi.ScalarTransform4f().scale([float(cells), float(cells), 1.0]),
        }
        return {"type": "mask", "opacity": opacity, "nested": twosided(diffuse(color))}

    return scene(
        _box_camera(res),
        **_box_walls(light_size=0.7),
        screen=rectangle([0.15, -0.35, 0.1], [0.2, 0, 1], [1.1, 1.2], masked((0.8, 0.7, 0.3), 4)),
        lattice=rectangle([0, 0.6, 0], [0, -1, 0], [1.2, 1.2], masked((0.6, 0.6, 0.7), 5)),
    )


@_builtin("bump-map")
def _bump_map(res: tuple[int, int]) -> SceneDict:
    """Perturbed shading frames: a ``bumpmap`` (sine height field) over rough plastic on a
    sphere, a ``normalmap`` over rough conductor on the floor, a blend (``blendbsdf``) of
    diffuse and rough conductor on the back wall, in the Cornell shell."""
    bump = {
        "type": "bumpmap",
        "arbitrary": {"type": "bitmap", "bitmap": _height_field(), "raw": True},
        "scale": 0.5,
        "bsdf": {"type": "roughplastic", "alpha": 0.15, "diffuse_reflectance": rgb(0.5)},
    }
    normal = {
        "type": "normalmap",
        "normalmap": {"type": "bitmap", "bitmap": _normal_field(), "raw": True},
        "bsdf": {"type": "roughconductor", "material": "Al", "alpha": 0.2},
    }
    blend = {
        "type": "blendbsdf",
        "weight": {
            "type": "checkerboard",
            "color0": 0.2,
            "color1": 0.8,
            "to_uv": mi.ScalarTransform4f().scale([3.0, 3.0, 1.0]),
        },
        "bsdf_0": diffuse(CBOX_WHITE),
        "bsdf_1": {"type": "roughconductor", "material": "Cu", "alpha": 0.25},
    }
    walls = _box_walls()
    walls["floor"] = rectangle([0, -1, 0], [0, 1, 0], [2, 2], normal)
    walls["back"] = rectangle([0, 0, -1], [0, 0, 1], [2, 2], blend)
    return scene(_box_camera(res), **walls, ball=sphere([0, -0.5, 0], 0.45, bump))


@_builtin("spot-directional")
def _spot_directional(res: tuple[int, int]) -> SceneDict:
    """Delta lights other than points: a ``spot`` (cutoff 25 deg, soft falloff) and a low
    ``directional`` light over the ground with objects."""
    return scene(
        camera([0.5, 1.3, 3.5], [0, 0.4, 0], res, fov=50),
        **_ground_with_objects(),
        spot={
            "type": "spot",
            "to_world": mi.ScalarTransform4f().look_at(
                origin=[-1.5, 3.0, 1.0], target=[0, 0, 0], up=[0, 1, 0]
            ),
            "cutoff_angle": 25.0,
            "beam_width": 15.0,
            "intensity": rgb(25.0),
        },
        sun={"type": "directional", "direction": [0.6, -0.5, -0.4], "irradiance": rgb(1.5)},
    )


@_builtin("textured-roughness")
def _textured_roughness(res: tuple[int, int]) -> SceneDict:
    """Roughness from a texture: a roughconductor sphere and a roughdielectric slab whose
    ``alpha`` is a checkerboard of 0.02 and 0.3 (near-specular and rough cells side by side
    at a ``shift_threshold`` between them), in the Cornell shell."""

    def alpha(cells: float) -> dict:
        return {
            "type": "checkerboard",
            "color0": 0.02,
            "color1": 0.3,
            "to_uv": mi.ScalarTransform4f().scale([cells, cells, 1.0]),
        }

    metal = {"type": "roughconductor", "material": "Au", "alpha": alpha(4.0)}
    glass = {"type": "roughdielectric", "int_ior": 1.5, "alpha": alpha(3.0)}
    return scene(
        _box_camera(res),
        **_box_walls(),
        ball=sphere([-0.4, -0.55, -0.2], 0.45, metal),
        slab=cube([0.45, -0.6, 0.3], [0.5, 0.8, 0.15], glass, angle=20),
    )
