"""Random colours and BSDFs of the procedural training-scene generator
(:mod:`gdpt.scenes.procedural`): object materials, floor/wall materials, light tints."""

from __future__ import annotations

import colorsys

import numpy as np

from gdpt.scenes.elements import Vec3, checker, diffuse, rgb, twosided


def random_color(
    rng: np.random.Generator, sat: tuple[float, float], val: tuple[float, float]
) -> tuple[float, float, float]:
    """A random linear-RGB colour with hue uniform, saturation and value in the ranges."""
    h = rng.uniform()
    return colorsys.hsv_to_rgb(h, rng.uniform(*sat), rng.uniform(*val))


def light_tint(rng: np.random.Generator) -> np.ndarray:
    """Warm-to-cool white with unit luminance."""
    t = rng.uniform()
    c = (1 - t) * np.array([1.0, 0.8, 0.6]) + t * np.array([0.85, 0.92, 1.0])
    return c / (0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2])


_CONDUCTORS = ("Au", "Ag", "Cu", "Al", "Cr", "none")

#: Material kind -> weight, for closed shapes (sphere, cube) and open ones (everything else).
SOLID_MATERIALS = {
    "diffuse": 0.26,
    "checker": 0.1,
    "roughplastic": 0.15,
    "plastic": 0.08,
    "roughconductor": 0.15,
    "conductor": 0.08,
    "dielectric": 0.18,
}
SURFACE_MATERIALS = {
    "diffuse": 0.35,
    "checker": 0.15,
    "roughplastic": 0.2,
    "plastic": 0.08,
    "roughconductor": 0.15,
    "conductor": 0.07,
}


def random_material(rng: np.random.Generator, weights: dict[str, float]) -> dict:
    """A random BSDF; non-transmissive ones are wrapped in ``twosided``."""
    kinds = list(weights)
    p = np.array([weights[k] for k in kinds])
    kind = kinds[rng.choice(len(kinds), p=p / p.sum())]
    if kind == "dielectric":
        return {"type": "dielectric", "int_ior": float(rng.uniform(1.33, 1.8))}
    if kind == "diffuse":
        bsdf = diffuse(random_color(rng, (0.0, 0.8), (0.15, 0.85)))
    elif kind == "checker":
        bsdf = checker(
            random_color(rng, (0.0, 0.9), (0.4, 0.9)),
            random_color(rng, (0.0, 0.9), (0.05, 0.5)),
            rng.choice([2, 4, 6, 8, 12]),
        )
    elif kind in ("plastic", "roughplastic"):
        bsdf = {
            "type": kind,
            "diffuse_reflectance": rgb(random_color(rng, (0.2, 0.9), (0.1, 0.8))),
            "int_ior": float(rng.uniform(1.4, 1.6)),
        }
        if kind == "roughplastic":
            bsdf["alpha"] = float(np.exp(rng.uniform(np.log(0.03), np.log(0.4))))
    else:
        bsdf = {"type": kind, "material": str(rng.choice(_CONDUCTORS))}
        if kind == "roughconductor":
            bsdf["alpha"] = float(np.exp(rng.uniform(np.log(0.02), np.log(0.4))))
    return twosided(bsdf)


def luminance(color: Vec3) -> float:
    return float(np.dot([0.2126, 0.7152, 0.0722], color))


def wall_material(rng: np.random.Generator, floor: bool) -> tuple[dict, float]:
    """A random floor/wall/ceiling BSDF and its approximate albedo."""
    if floor and rng.uniform() < 0.4:
        c0 = np.array(random_color(rng, (0.0, 0.4), (0.5, 0.85)))
        c1 = c0 * rng.uniform(0.2, 0.6)
        return twosided(checker(c0, c1, rng.integers(4, 16))), luminance((c0 + c1) / 2)
    if floor and rng.uniform() < 0.3:
        c = random_color(rng, (0.3, 0.7), (0.2, 0.5))
        bsdf = {
            "type": "roughplastic",
            "alpha": float(rng.uniform(0.1, 0.4)),
            "diffuse_reflectance": rgb(c),
        }
        return twosided(bsdf), luminance(c) + 0.05
    c = random_color(rng, (0.0, 0.35), (0.45, 0.85))
    return twosided(diffuse(c)), luminance(c)
