"""Per-pixel unbiasedness of ``gdpt`` and ``gdpt_rr`` on built-in and shared real scenes.

Oracles: Mitsuba's ``path`` for the primal, and forward differences of ``path`` for ``dx``/``dy``
(the quantity both gradient integrators estimate); ``gdpt_rr`` (random replay, no vertex
classification, no failed shifts) as a second gradient oracle for ``gdpt``.

Statistic (:mod:`pixel_stats`): per pixel and channel, z of the difference of the means of
``RUNS`` test renders and ``REF_RUNS`` oracle renders, with the run-to-run variances. ``gdpt``
and ``gdpt_rr`` rendered with the same seeds trace the same base paths (their per-pixel runs
correlate at about 0.65 on veach-mis), so that comparison uses the paired z of the per-run
differences (:func:`pixel_stats.paired_z`); the unpaired z would treat the two sides as
independent and overstate the standard error: with ``gdpt_rr``'s gradients 1% too large it gave
0.00% / max 2.7 on veach-mis at max depth 2, the paired z 7.5% / 66
(``test_paired_z_catches_a_bias_the_unpaired_z_missed``).

Decision rule, per buffer: the share of pixel-channels with ``|z| > 3.29`` is at most
``MAX_SHARE`` (1%) and the largest ``|z|`` is at most ``MAX_Z`` (6). Under the null hypothesis
a pixel-channel exceeds 3.29 with probability ~0.1% (normal) to ~0.2% (t with 31-47 degrees of
freedom), and the largest of ~1000 pixel-channels stays near 4-4.5; the three channels of a
pixel share their paths, so outliers come in groups of up to three. Heavy-tailed estimates make
a few runs' variance an underestimate, so the rule is calibrated by ``test_oracle_self_test``:
``path`` against itself (independent seeds, same counts) on the same scenes passes it.
A bias confined to a cluster of pixels, which image-wide aggregates do not see, fails it: the
hybrid shift before the NEE pair rule gave, on staircase at max depth 6,
dx 0.99% / max 6.6 and dy 1.39% / max 6.5 at 32 x 256 against 16 x 1024 samples (now
0.00% / 3.2 and 0.00% / 2.8), on matpreview-dof dx 3.01% / 6.9 and dy 2.16% / 4.7.

``primal="mis"`` (the primal from every base and offset path, MIS-weighted per pixel pair) is
checked on its own cases (:data:`MIS_CASES`, masked and pooled renders too): dropping the pair's
MIS weight from the base's share fails them (sphere-light: 100% of pixel-channels beyond 3.29).

Sample counts: ``RUNS x SPP`` = 48 x 192 test samples per pixel on the real scenes (48 x 96 on
the built-in ones) and ``REF_RUNS x REF_SPP`` = 32 x 512 oracle samples, at 24 px on the long
side. A fast subset runs in CI; ``slow`` adds every shared scene at max depth 2 and 6, every
built-in scene for both integrators and more half-vector thresholds.
"""

from __future__ import annotations

import gc
from functools import cache

import numpy as np
import pytest
from pixel_stats import Oracle, PixelZ, paired_z, pixel_z, render_runs
from shared_scenes import SHARED_SCENES

#: Test renders x spp (real scenes; the built-in scenes, simpler, take BUILTIN_SPP), oracle
#: renders x spp. 32 or more runs per side keep the t tails of the run variance near normal.
RUNS, SPP, BUILTIN_SPP = 48, 192, 96
REF_RUNS, REF_SPP = 32, 512
#: Marker of the cases that read the shared real scenes (see ``tests/conftest.py``).
SHARED = pytest.mark.shared_scenes
MAX_SHARE = 0.01
MAX_Z = 6.0
REAL_RES = BUILTIN_RES = 24

REAL = ["cornell-box", "veach-mis", "matpreview-dof", "sponza", "staircase", "torus", "veach-bidir"]
#: (scene, max depth) of the real scenes checked in CI; every other pair is ``slow``.
REAL_FAST = {("staircase", 6), ("matpreview-dof", 6), ("veach-mis", 2)}

#: Built-in scenes whose primal is heavy-tailed (rough glass alpha 0.03 and a mirror of alpha
#: 0.02): twice the runs keep the run-variance estimate honest. Measured on near-specular at 48
#: runs: primal 1.04% |z| > 3.29 with the suite's seeds (the same base paths for gdpt, gdpt_rr
#: and every shift_threshold), 0.87% and 0.81% with two other seed sets; 0.46% at 96 runs.
HEAVY_TAILED = {"near-specular"}

#: Built-in scenes and their max depth.
BUILTIN = [
    ("alpha-mask", 5),
    ("bump-map", 4),
    ("spot-directional", 3),
    ("glass", 5),
    ("sphere-light", 3),
    ("envmap", 3),
    ("diffuse-box", 4),
    ("rough-conductor", 4),
    ("point-light", 3),
    ("mirror", 5),
    ("constant-env", 3),
    ("thin-lens", 3),
    ("plastic", 4),
    ("thin-dielectric", 4),
    ("tir-glass", 6),
    ("principled", 4),
    ("near-specular", 5),
    ("textured-roughness", 4),
]
#: (integrator, built-in scene) pairs checked in CI; every other pair is ``slow``.
BUILTIN_FAST = {
    ("gdpt", "alpha-mask"),
    ("gdpt", "bump-map"),
    ("gdpt", "spot-directional"),
    ("gdpt", "glass"),
    ("gdpt", "sphere-light"),
    ("gdpt_rr", "glass"),
    ("gdpt_rr", "envmap"),
}


def _load(name: str):
    """A real scene (``tests/conftest.py`` skips or fails a ``shared_scenes`` test without the
    folder; a scene missing from it fails) or a built-in one."""
    from gdpt.scenes.loading import load_scene

    if name in REAL:
        return load_scene(SHARED_SCENES / name / "scene.xml", box_filter=True, long_side=REAL_RES)
    return load_scene(f"builtin:{name}", long_side=BUILTIN_RES)


_LOADED: dict = {}


def _scene(name: str):
    """The last scene loaded; the one before is freed first (with another scene's objects
    alive Dr.Jit may refuse to record a frozen pass, which the integrators then trace, much
    slower: torus before veach-bidir)."""
    if name not in _LOADED:
        _LOADED.clear()
        gc.collect()
        _LOADED[name] = _load(name)
    return _LOADED[name]


@cache
def _oracle(name: str, max_depth: int, seed: int = 100_000) -> Oracle:
    import mitsuba as mi

    path = mi.load_dict({"type": "path", "max_depth": max_depth})
    return Oracle(render_runs(_scene(name), path, REF_RUNS, REF_SPP, seed)["primal"])


def _runs(
    name: str, integrator: str, max_depth: int, runs: int = RUNS, **props
) -> dict[str, np.ndarray]:
    import mitsuba as mi

    plugin = mi.load_dict({"type": integrator, "max_depth": max_depth, "features": False, **props})
    spp = SPP if name in REAL else BUILTIN_SPP
    result = render_runs(_scene(name), plugin, runs, spp, seed=1)
    counts = {k: v for k, v in plugin.guard_counts.items() if v}
    assert not counts, f"{integrator} on {name}: numerical guards fired {counts}"
    return result


def _assert_passes(results: dict, label: str) -> None:
    failed = {
        name: f"{z} at {z.where(3)}"
        for name, z in results.items()
        if z.share > MAX_SHARE or z.max_abs > MAX_Z
    }
    summary = ", ".join(f"{name} {z}" for name, z in results.items())
    assert not failed, f"{label}: {summary}; failing: {failed}"


def _real_cases():
    for name in REAL:
        for depth in (2, 6):
            marks = () if (name, depth) in REAL_FAST else (pytest.mark.slow,)
            yield pytest.param(name, depth, marks=(*marks, SHARED), id=f"{name}-{depth}")


@pytest.mark.parametrize(
    ("name", "max_depth"),
    [
        pytest.param("staircase", 6, marks=SHARED, id="staircase-6"),
        pytest.param("alpha-mask", 5, id="alpha-mask-5"),
        pytest.param("veach-mis", 6, marks=(pytest.mark.slow, SHARED), id="veach-mis-6"),
        pytest.param("glass", 5, marks=pytest.mark.slow, id="glass-5"),
    ],
)
def test_oracle_self_test(variant, name, max_depth):
    """Calibration: ``path`` against the oracle (independent seeds, the test's run and sample
    counts) passes the decision rule, on the primal and on its forward differences."""
    import mitsuba as mi

    path = mi.load_dict({"type": "path", "max_depth": max_depth})
    spp = SPP if name in REAL else BUILTIN_SPP
    primal = Oracle(render_runs(_scene(name), path, RUNS, spp, seed=7)["primal"])
    oracle = _oracle(name, max_depth)
    results = {b: pixel_z(getattr(primal, b), getattr(oracle, b)) for b in ("primal", "dx", "dy")}
    _assert_passes(results, f"path vs path on {name}, max depth {max_depth}")


@pytest.mark.parametrize(("name", "max_depth"), list(_real_cases()))
def test_gdpt_unbiased_on_real_scenes(variant, name, max_depth):
    """Primal, dx and dy of ``gdpt`` against ``path`` on the shared real scenes."""
    results = _oracle(name, max_depth).compare(_runs(name, "gdpt", max_depth))
    _assert_passes(results, f"gdpt on {name}, max depth {max_depth}")


def _builtin_cases():
    for integrator in ("gdpt", "gdpt_rr"):
        for name, depth in BUILTIN:
            marks = () if (integrator, name) in BUILTIN_FAST else (pytest.mark.slow,)
            yield pytest.param(integrator, name, depth, marks=marks, id=f"{integrator}-{name}")


@pytest.mark.parametrize(("integrator", "name", "max_depth"), list(_builtin_cases()))
def test_unbiased_on_builtin_scenes(variant, integrator, name, max_depth):
    runs = 2 * RUNS if name in HEAVY_TAILED else RUNS
    results = _oracle(name, max_depth).compare(_runs(name, integrator, max_depth, runs=runs))
    _assert_passes(results, f"{integrator} on builtin:{name}, max depth {max_depth}")


#: ``primal="mis"`` (every base and offset path adds to the pixel it lands in with its pixel pair's
#: MIS weight): (integrator, scene, max depth); CI runs the first, ``slow`` the others: failed
#: shifts (glass, mirror, caustics on torus and veach-bidir), half-vector copies (near-specular at
#: shift_threshold 0.05), escaping offsets (envmap), opacity masks, random replay.
MIS_CASES = [
    ("gdpt", "sphere-light", 3, {}),
    ("gdpt", "glass", 5, {}),
    ("gdpt", "mirror", 5, {}),
    ("gdpt", "envmap", 3, {}),
    ("gdpt", "alpha-mask", 5, {}),
    ("gdpt", "near-specular", 5, {"shift_threshold": 0.05}),
    ("gdpt_rr", "glass", 5, {}),
    ("gdpt", "staircase", 6, {}),
    ("gdpt", "veach-mis", 2, {}),
    ("gdpt", "cornell-box", 6, {}),
    ("gdpt", "torus", 6, {}),
    ("gdpt", "veach-bidir", 6, {}),
]


def _mis_cases():
    for i, (integrator, name, depth, props) in enumerate(MIS_CASES):
        marks = (() if i == 0 else (pytest.mark.slow,)) + ((SHARED,) if name in REAL else ())
        yield pytest.param(integrator, name, depth, props, marks=marks, id=f"{integrator}-{name}")


@pytest.mark.parametrize(("integrator", "name", "max_depth", "props"), list(_mis_cases()))
def test_mis_primal_is_unbiased(variant, integrator, name, max_depth, props):
    """``primal="mis"``: the primal (and the gradients, unchanged) per pixel against ``path``,
    film border included (a pixel's pair with a neighbour off the film keeps the base path)."""
    runs = 2 * RUNS if name in HEAVY_TAILED else RUNS
    results = _oracle(name, max_depth).compare(
        _runs(name, integrator, max_depth, runs=runs, primal="mis", **props)
    )
    _assert_passes(results, f"{integrator} primal='mis' on {name}, max depth {max_depth}")


@cache
def _hybrid_and_replay(name: str, max_depth: int) -> tuple[dict, dict]:
    """``gdpt`` and ``gdpt_rr`` runs of a scene, pairwise with the same seeds."""
    return _runs(name, "gdpt", max_depth), _runs(name, "gdpt_rr", max_depth)


@pytest.mark.shared_scenes
@pytest.mark.parametrize(
    ("name", "max_depth"),
    [
        pytest.param("veach-mis", 2, id="veach-mis-2"),
        pytest.param("staircase", 6, marks=pytest.mark.slow, id="staircase-6"),
        pytest.param("matpreview-dof", 6, marks=pytest.mark.slow, id="matpreview-dof-6"),
    ],
)
def test_gdpt_agrees_with_random_replay(variant, name, max_depth):
    """The second oracle: ``gdpt``'s gradients against ``gdpt_rr``'s (same quantity, another
    shift; its estimate is unbiased where the hybrid once was not), paired run by run."""
    hybrid, replay = _hybrid_and_replay(name, max_depth)
    results = {b: paired_z(hybrid[b], replay[b]) for b in ("dx", "dy")}
    _assert_passes(results, f"gdpt vs gdpt_rr on {name}, max depth {max_depth}")


@pytest.mark.shared_scenes
def test_paired_z_catches_a_bias_the_unpaired_z_missed(variant):
    """``gdpt_rr`` broken slightly: its gradients 1% too large (a multiplicative bias, as a
    wrong Jacobian or MIS weight gives). The unpaired z of the same runs, which the comparison
    used before, passes the decision rule (0.00% / max 2.7-2.8 when measured); the paired z
    fails it (dx 7.5% / max 66, dy 4.4% / max 59)."""
    hybrid, replay = _hybrid_and_replay("veach-mis", 2)
    for b in ("dx", "dy"):
        broken = replay[b] * 1.01
        unpaired, paired = pixel_z(hybrid[b], broken), paired_z(hybrid[b], broken)
        assert unpaired.share <= MAX_SHARE and unpaired.max_abs <= MAX_Z, (b, str(unpaired))
        assert paired.share > MAX_SHARE and paired.max_abs > MAX_Z, (b, str(paired))


@pytest.mark.parametrize(
    ("name", "threshold", "runs"),
    [
        ("near-specular", 0.05, 2 * RUNS),
        pytest.param("textured-roughness", 0.05, 2 * RUNS, marks=pytest.mark.slow),
        pytest.param("near-specular", 0.025, 2 * RUNS, marks=pytest.mark.slow),
        pytest.param("rough-conductor", 0.5, 2 * RUNS, marks=pytest.mark.slow),
    ],
)
def test_unbiased_with_the_half_vector_shift(variant, name, threshold, runs):
    """shift_threshold above some roughness of the scene: those vertices take the half-vector
    copy and their light samples leave the gradient's MIS (near-specular at 0.05: glass alpha
    0.03 and mirror 0.02, reflection and refraction; textured-roughness: alpha 0.02 and 0.3
    cells side by side; rough-conductor: the copy on a genuinely rough lobe; principled: see
    :func:`test_unbiased_with_the_half_vector_copy_on_rough_principled_lobes`).

    All cases are heavy-tailed (narrow glossy lobes; the copy on lobes it does not suit,
    textured 0.3 cells): twice the runs keep the run-variance estimate honest there (measured
    at 48 runs: textured-roughness's primal, which the threshold does not change, 1.1%; at 96
    runs 0.06%; near-specular: see ``HEAVY_TAILED``)."""
    results = _oracle(name, 5).compare(_runs(name, "gdpt", 5, runs=runs, shift_threshold=threshold))
    _assert_passes(results, f"gdpt on builtin:{name}, shift_threshold {threshold}")


#: Film (long side), runs x spp of the test and oracle spp of the principled case below: 16x
#: the samples per pixel of the built-in cases' 96 x 96 at a quarter of the pixels.
PRINCIPLED_RES, PRINCIPLED_RUNS, PRINCIPLED_SPP, PRINCIPLED_REF_SPP = 12, 4 * RUNS, 768, 2048


@pytest.mark.slow
def test_unbiased_with_the_half_vector_copy_on_rough_principled_lobes(variant):
    """``shift_threshold`` 1.0 on builtin:principled (roughness 0.3 and 0.5): every principled
    vertex takes the half-vector copy, and there the gradient's light segment comes from BSDF
    sampling alone (its light technique leaves the gradient's MIS; the primal keeps NEE).
    On these rough lobes a BSDF-sampled hit of the light is rare and large, and the gradient's
    expectation depends on it: runs without a hit sit off the mean by the hits' share.

    Measured at the suite's 24 px and 96 spp: at pixel (18, 5) (blue) three of 384 runs of
    seed 20000 held a hit (dx -0.056 per run against a typical 0.001) and with them the 384
    runs pass against an 8x larger independent ``path`` oracle (dx/dy max |z| 3.5/3.8); the
    384 runs of seed 1 held none and failed (14.7/19.1), as did 96 runs of seeds 1, 1000 and
    5000 against the suite's oracle (max |z| 6.6-10.5); ``shift_threshold`` 0 and ``gdpt_rr``
    on the same seeds pass (3.9 and 3.9). ~8e-5 hits per sample there: 96 x 96 samples per
    pixel expect fewer than one, so the rule cannot decide. Hence 12 px on the long side and
    16x the samples per pixel (~12 hits expected): seeds 1 and 5000 pass (max |z| 3.9/4.1)."""
    import mitsuba as mi

    from gdpt.scenes.loading import load_scene

    scene = load_scene("builtin:principled", long_side=PRINCIPLED_RES)
    path = mi.load_dict({"type": "path", "max_depth": 5})
    oracle = Oracle(render_runs(scene, path, REF_RUNS, PRINCIPLED_REF_SPP, seed=100_000)["primal"])
    plugin = mi.load_dict(
        {"type": "gdpt", "max_depth": 5, "features": False, "shift_threshold": 1.0}
    )
    runs = render_runs(scene, plugin, PRINCIPLED_RUNS, PRINCIPLED_SPP, seed=1)
    counts = {k: v for k, v in plugin.guard_counts.items() if v}
    assert not counts, f"gdpt on builtin:principled: numerical guards fired {counts}"
    _assert_passes(oracle.compare(runs), "gdpt on builtin:principled, shift_threshold 1.0")


@pytest.mark.parametrize(
    ("name", "max_depth", "primal"),
    [
        ("glass", 5, "base"),
        ("sphere-light", 3, "base"),
        pytest.param("glass", 5, "mis", marks=pytest.mark.slow),
    ],
)
def test_pooled_render_is_unbiased(variant, name, max_depth, primal):
    """``gdpt.render(..., primal_spp=N)`` (what ``oidn-grad`` reads): the pooled primal and the
    gradients per pixel against ``path``, 48 runs of 32 gradient + 64 plain path samples."""
    from gdpt.rendering import render

    runs: dict[str, list[np.ndarray]] = {}
    for i in range(RUNS):
        buffers = render(
            _scene(name),
            spp=32,
            primal_spp=64,
            seed=1 + i,
            max_depth=max_depth,
            features=False,
            primal=primal,
        )
        assert buffers.metadata["primal_spp"] == 96
        for key in ("primal", "dx", "dy"):
            runs.setdefault(key, []).append(getattr(buffers, key).cpu().numpy())
    results = _oracle(name, max_depth).compare({k: np.stack(v) for k, v in runs.items()})
    _assert_passes(results, f"pooled gdpt ({primal}) on builtin:{name}, max depth {max_depth}")


def _tile_mask(height: int, width: int) -> np.ndarray:
    """Half of the 4 px tiles (seeded) and one column one pixel wide: borders of every kind."""
    rng = np.random.default_rng(5)
    tiles = rng.random((-(-height // 4), -(-width // 4))) < 0.5
    mask = tiles.repeat(4, 0).repeat(4, 1)[:height, :width].copy()
    mask[:, width // 2] = True
    mask[:, width // 2 - 1] = mask[:, width // 2 + 1] = False
    return mask


@pytest.mark.slow
@SHARED
@pytest.mark.parametrize(
    ("name", "max_depth", "primal"),
    [
        ("staircase", 6, "base"),
        ("veach-mis", 2, "base"),
        ("staircase", 6, "mis"),
        ("veach-mis", 2, "mis"),
    ],
)
def test_masked_render_is_unbiased(variant, name, max_depth, primal):
    """A render with a gradient mask (``gradient_mask``: half of the tiles and a one-pixel
    column): the primal at every pixel and the gradients it traced (both pixels masked) against
    ``path``, the others exactly 0 (the border rule: a gradient between a masked and an
    unmasked pixel is not traced). Measured: staircase-6 primal 0.10% / max 3.4, dx 0.00% /
    3.0, dy 0.00% / 2.9; veach-mis-2 0.00% / 3.2, 0.00% / 2.9, 0.58% / 3.8. With one MIS half
    dropped from the masked render's dx it fails (dx 84% / 123 and 55% / 110). With
    ``primal="mis"`` a pixel pair counts for the primal iff both pixels are masked too (the
    one-pixel column: no pair across it)."""
    import mitsuba as mi
    from gdpt.integrators.common import traced_gradients

    scene = _scene(name)
    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    mask = _tile_mask(height, width)
    plugin = mi.load_dict(
        {"type": "gdpt", "max_depth": max_depth, "features": False, "primal": primal}
    )
    plugin.gradient_mask = mask
    runs = render_runs(scene, plugin, RUNS, SPP, seed=1)
    assert not any(plugin.guard_counts.values()), plugin.guard_counts
    oracle = _oracle(name, max_depth)
    traced = traced_gradients(mask)
    results = {"primal": pixel_z(runs["primal"], oracle.primal)}
    for k, buffer in enumerate(("dx", "dy")):
        assert (runs[buffer][:, ~traced[..., k]] == 0).all(), buffer
        results[buffer] = PixelZ(pixel_z(runs[buffer], getattr(oracle, buffer)).z[traced[..., k]])
    border = mask & ~traced[..., 0]  # masked pixels whose dx is not traced
    assert border[:, :-1].any() and traced[..., 0].any()
    _assert_passes(results, f"masked gdpt ({primal}) on {name}, max depth {max_depth}")


@pytest.mark.slow
@pytest.mark.parametrize(("name", "max_depth"), [("sphere-light", 3), ("glass", 5)])
def test_auto_pilot_merged_with_its_main_render_is_unbiased(variant, name, max_depth):
    """``auto``'s gradient route (:func:`gdpt.auto_route.render_route`): a pilot with offsets
    in the tiles of :func:`_tile_mask` and pooled plain samples, merged gradient by gradient
    with the rest (offsets outside the tiles, then plain samples). The primal at every pixel and
    every gradient traced by either render against ``path``; a gradient between a tile and the
    rest, traced by neither, exactly 0."""
    import torch

    from gdpt.auto_route import Pilot, RouteChoice, render_route
    from gdpt.methods import METHODS
    from gdpt.rendering import render

    scene = _scene(name)
    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    mask = _tile_mask(height, width)
    g, pooled, rest = 16, 24, 24
    # a plain sample's cost so large that the measured render time buys none: ``rest`` exactly
    pilot_info = {"gradient_spp": g, "cost_spp": 0.0, "seconds_per_spp": 1e9, "share": 0.5}
    choice = RouteChoice("gradient", "fuse", "", pilot=pilot_info)
    sampling = {**METHODS["fuse"].sampling(g), "primal_spp": pooled, "max_depth": max_depth}
    runs: dict[str, list[np.ndarray]] = {}
    for i in range(RUNS):
        first = render(scene, spp=g, seed=1 + 2 * i, gradient_mask=mask, **sampling)
        pilot = Pilot(first, torch.from_numpy(mask).to(first.device))
        merged = render_route(scene, choice, pilot, spp=rest, seed=2 + 2 * i, max_depth=max_depth)
        assert merged.metadata["primal_spp"] == g + pooled + g + rest
        for key in ("primal", "dx", "dy"):
            runs.setdefault(key, []).append(getattr(merged, key).cpu().numpy())
    traced = merged.gradient_mask.cpu().numpy()
    oracle = _oracle(name, max_depth)
    results = {"primal": pixel_z(np.stack(runs["primal"]), oracle.primal)}
    for k, buffer in enumerate(("dx", "dy")):
        values = np.stack(runs[buffer])
        assert (values[:, ~traced[..., k]] == 0).all(), buffer
        results[buffer] = PixelZ(pixel_z(values, getattr(oracle, buffer)).z[traced[..., k]])
    assert traced[..., 0][:, :-1].mean() < 1.0 and traced[..., 0].any()  # border pairs untraced
    _assert_passes(results, f"auto's merged pilot + main render on {name}, max depth {max_depth}")
