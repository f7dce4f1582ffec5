"""Tests of :mod:`gdpt.scenes`: dictionary contract, renderability, coverage, determinism.

Renders are 16x16 at 4 spp with Mitsuba's ``path`` integrator; the kernel compile dominates,
so the random-scene renders use a small set of seeds chosen to cover every feature.
"""

from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

from gdpt import scenes

#: Scene dictionaries hold Mitsuba transforms and bitmaps: every test needs the variant.
pytestmark = pytest.mark.usefixtures("variant")

#: Seeds scanned (as dictionaries only) for generator coverage.
COVERAGE_SEEDS = range(40)

#: Plugin types the generator must produce over COVERAGE_SEEDS.
GENERATOR_TYPES = {
    "rectangle",
    "cube",
    "sphere",
    "cylinder",
    "disk",
    "diffuse",
    "checkerboard",
    "roughconductor",
    "conductor",
    "plastic",
    "roughplastic",
    "dielectric",
    "thindielectric",
    "twosided",
    "area",
    "point",
    "constant",
    "envmap",
    "perspective",
    "thinlens",
}
ALLOWED_TYPES = GENERATOR_TYPES | {
    "scene",
    "hdrfilm",
    "box",
    "independent",
    "rgb",
    "principled",
    "roughdielectric",
    # the plugin coverage of the built-in integrator test scenes
    "mask",
    "bumpmap",
    "normalmap",
    "blendbsdf",
    "bitmap",
    "spot",
    "directional",
}


def _types(node, found: set[str] | None = None) -> set[str]:
    """All plugin ``type`` values in a (nested) scene dictionary."""
    found = set() if found is None else found
    if isinstance(node, dict):
        if "type" in node:
            found.add(node["type"])
        for value in node.values():
            _types(value, found)
    return found


def _features(scene: dict) -> set[str]:
    """Plugin types plus derived features (which shape carries an area light, layout)."""
    found = _types(scene)
    for value in scene.values():
        if isinstance(value, dict) and "emitter" in value:
            found.add(f"area-{value['type']}")
    found.add("room" if any(k.startswith("ceiling") for k in scene) else "open")
    found |= {k.rsplit("_", 1)[0] for k in scene if k.startswith(("tabletop", "shelf"))}
    return found


def _canonical(node):
    """A comparable form of a scene dictionary (transforms and bitmaps as tuples)."""
    if isinstance(node, dict):
        return {k: _canonical(v) for k, v in node.items()}
    if isinstance(node, (list, tuple)):
        return [_canonical(v) for v in node]
    if isinstance(node, mi.ScalarTransform4f):
        return tuple(np.array(node.matrix).ravel().tolist())
    if isinstance(node, mi.Bitmap):
        return np.array(node).tobytes()
    return node


def _render(scene: dict, spp: int = 4) -> np.ndarray:
    loaded = mi.load_dict({**scene, "integrator": {"type": "path", "max_depth": 6}})
    return np.array(mi.render(loaded, spp=spp, seed=0))


def _check_contract(scene: dict, resolution: tuple[int, int]) -> None:
    assert scene["type"] == "scene" and "integrator" not in scene
    film = scene["sensor"]["film"]
    assert film["rfilter"] == {"type": "box"}
    assert film["pixel_format"] == "rgb"
    assert (film["width"], film["height"]) == resolution
    assert scene["sensor"]["sampler"]["type"] == "independent"
    assert _types(scene) <= ALLOWED_TYPES


def _covering_seeds() -> list[int]:
    """A few seeds of COVERAGE_SEEDS whose scenes together show every generator feature."""
    features = {s: _features(scenes.random_scene(s, resolution=(16, 16))) for s in COVERAGE_SEEDS}
    missing, chosen = set().union(*features.values()), []
    while missing:
        best = max(features, key=lambda s: len(features[s] & missing))
        chosen.append(best)
        missing -= features[best]
    return chosen


# --------------------------------------------------------------------------------------------


def test_builtin_registry():
    names = scenes.builtin_names()
    assert "cbox-demo" in names and "principled" in names and len(names) == len(set(names))
    with pytest.raises(ValueError, match="diffuse-box"):
        scenes.builtin_scene("no-such-scene")


@pytest.mark.parametrize("name", scenes.builtin_names())
def test_builtin_renders_finite_and_lit(name):
    scene = scenes.builtin_scene(name, resolution=(16, 12))
    _check_contract(scene, (16, 12))
    image = _render(scene)
    assert image.shape == (12, 16, 3)
    assert np.isfinite(image).all()
    assert image.mean() > 1e-3


def test_builtin_defaults_and_features():
    assert scenes.builtin_scene("cbox-demo")["sensor"]["film"]["width"] == 256
    assert scenes.builtin_scene("glass")["sensor"]["film"]["width"] == scenes.TEST_RESOLUTION[0]
    assert scenes.builtin_scene("thin-lens")["sensor"]["type"] == "thinlens"
    assert "envmap" in _types(scenes.builtin_scene("envmap"))
    assert "constant" in _types(scenes.builtin_scene("constant-env"))
    assert {"plastic", "roughplastic"} <= _types(scenes.builtin_scene("plastic"))
    bright = scenes.builtin_scene("tiny-bright-light")["light"]["emitter"]["radiance"]["value"]
    assert min(bright) >= 1e5


@pytest.mark.parametrize("resolution", [(0, 16), (16,), (16.0, 16), (-2, 8), (True, 8), "ab", None])
def test_bad_resolution(resolution):
    if resolution is not None:
        with pytest.raises(ValueError):
            scenes.builtin_scene("diffuse-box", resolution=resolution)
    with pytest.raises(ValueError):
        scenes.random_scene(0, resolution=resolution)


def test_bad_generator_arguments():
    for kwargs in ({"seed": -1}, {"seed": 1.5}, {"seed": 0, "view": -1}):
        with pytest.raises(ValueError):
            scenes.random_scene(**kwargs)
    with pytest.raises(ValueError):
        scenes.random_views(0, 0)
    with pytest.raises(ValueError):
        scenes.RandomSceneConfig(p_room=1.5)
    with pytest.raises(ValueError):
        scenes.RandomSceneConfig(num_objects=(4, 2))


def test_generator_coverage_and_contract():
    found = set()
    for seed in COVERAGE_SEEDS:
        scene = scenes.random_scene(seed, resolution=(20, 10), view=seed % 3)
        _check_contract(scene, (20, 10))
        found |= _features(scene)
    expected = GENERATOR_TYPES | {
        "area-rectangle",
        "area-sphere",
        "room",
        "open",
        "tabletop",
        "shelfside",
    }
    assert expected <= found, f"never generated: {expected - found}"


def test_random_scenes_render_finite():
    seeds = _covering_seeds()
    assert len(seeds) <= 8
    for seed in seeds:
        image = _render(scenes.random_scene(seed, resolution=(16, 16)))
        assert np.isfinite(image).all(), seed
        assert image.mean() > 1e-3, seed


def test_random_determinism():
    a = scenes.random_scene(7, resolution=(16, 16))
    b = scenes.random_scene(7, resolution=(16, 16))
    assert _canonical(a) == _canonical(b)
    assert np.array_equal(_render(a), _render(b))
    assert _canonical(scenes.random_scene(8, resolution=(16, 16))) != _canonical(a)


def test_random_views_share_content():
    views = scenes.random_views(3, 4, resolution=(16, 16))
    content = [_canonical({k: v for k, v in s.items() if k != "sensor"}) for s in views]
    assert all(c == content[0] for c in content)
    sensors = [_canonical(s["sensor"]) for s in views]
    assert len({repr(s) for s in sensors}) == 4
    assert _canonical(views[2]) == _canonical(scenes.random_scene(3, resolution=(16, 16), view=2))


def test_long_side_resizes_a_scene_dict_and_refuses_a_loaded_scene():
    """``load_scene(dict, long_side=N)`` resizes the dict's film (aspect kept) instead of
    ignoring the request; a loaded ``mi.Scene`` cannot be resized and says so."""
    import gdpt

    wide = scenes.builtin_scene("diffuse-box", resolution=(64, 32))
    film = gdpt.load_scene(wide, long_side=16).sensors()[0].film()
    assert list(film.crop_size()) == [16, 8]
    assert wide["sensor"]["film"]["width"] == 64  # the caller's dict is left alone
    with pytest.raises(ValueError, match="loaded mi.Scene"):
        gdpt.load_scene(gdpt.load_scene(wide), long_side=16)
    with pytest.raises(ValueError, match="'width' and 'height'"):
        gdpt.load_scene({"type": "scene", "sensor": {"type": "perspective"}}, long_side=16)


def test_meshes_that_share_a_bsdf_load_unmerged(tmp_path):
    """Every mesh of a scene file and of a scene dict stays its own shape (Mitsuba's merging,
    whose triangle order changes between processes, is off: ``MERGE_MESHES``)."""
    import gdpt

    triangle = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    for k in range(3):
        (tmp_path / f"m{k}.obj").write_text(triangle)
    meshes = "".join(
        f'<shape type="obj"><string name="filename" value="m{k}.obj"/><ref id="grey"/></shape>'
        for k in range(3)
    )
    (tmp_path / "scene.xml").write_text(
        '<scene version="3.0.0"><bsdf type="diffuse" id="grey"/>'
        '<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>'
        '<integer name="height" value="8"/><rfilter type="box"/></film></sensor>'
        f"{meshes}</scene>"
    )
    assert len(gdpt.load_scene(tmp_path / "scene.xml").shapes()) == 3
    grey = {"type": "diffuse"}
    shapes = {
        f"m{k}": {"type": "obj", "filename": str(tmp_path / f"m{k}.obj"), "bsdf": grey}
        for k in range(3)
    }
    assert len(gdpt.load_scene({"type": "scene", **shapes}).shapes()) == 3
