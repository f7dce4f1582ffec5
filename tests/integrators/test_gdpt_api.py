"""Registration, properties, outputs and numerical robustness of ``gdpt`` / ``gdpt_rr``."""

from __future__ import annotations

import numpy as np
import pytest

HARD_CASES = ["grazing", "tiny-bright-light", "tir-glass", "degenerate", "envmap", "sphere-light"]


def _xml(integrator: str, rfilter: str = "box", extra: str = "") -> str:
    return f"""<scene version="3.0.0">
        <integrator type="{integrator}"><integer name="max_depth" value="3"/>{extra}</integrator>
        <sensor type="perspective">
            <transform name="to_world">
                <lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
            <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="6"/>
                <rfilter type="{rfilter}"/></film>
        </sensor>
        <shape type="sphere"><bsdf type="diffuse"/></shape>
        <emitter type="constant"/>
    </scene>"""


@pytest.mark.parametrize("name", ["gdpt", "gdpt_rr"])
def test_usable_from_xml(variant, name):
    import mitsuba as mi

    scene = mi.load_string(_xml(name, extra='<float name="shift_threshold" value="0.001"/>'))
    assert scene.integrator().max_depth == 3
    image = mi.render(scene, spp=4)
    assert image.shape == (6, 8, 16)  # primal, dx, dy, albedo, normal, depth
    assert np.isfinite(np.array(image)).all()


def test_non_box_filter_is_refused(variant):
    import mitsuba as mi

    import gdpt

    scene = mi.load_string(_xml("gdpt", rfilter="gaussian"))
    with pytest.raises(ValueError, match="box pixel filter.*GaussianFilter"):
        gdpt.render(scene, spp=1)
    with pytest.raises(RuntimeError) as info:  # mi.render wraps it, the cause says why
        mi.render(scene, spp=1)
    assert "box pixel filter" in str(info.value.__cause__)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ('<boolean name="hide_emitters" value="true"/>', "hide_emitters"),
        ('<integer name="rr_depth" value="0"/>', "rr_depth"),
        ('<integer name="max_depth" value="-3"/>', "max_depth"),
        ('<float name="shift_threshold" value="-0.1"/>', "shift_threshold"),
        ('<string name="primal" value="offsets"/>', "'primal' must be one of 'base', 'mis'"),
    ],
)
def test_invalid_properties(variant, extra, message):
    import mitsuba as mi

    xml = _xml("gdpt", extra=extra).replace('<integer name="max_depth" value="3"/>', "", 1)
    with pytest.raises(Exception, match=message):
        mi.load_string(xml)


@pytest.mark.parametrize("name", ["gdpt", "gdpt_rr"])
def test_samples_per_pass_is_ours_without_a_deprecation_warning(variant, name, capfd):
    """``samples_per_pass`` sets the samples per kernel launch; Mitsuba's base class, which
    deprecates a property of the same name, does not see it."""
    import mitsuba as mi

    integrator = mi.load_dict({"type": name, "samples_per_pass": 4096})
    assert integrator.samples_per_pass == 4096
    assert "deprecated" not in capfd.readouterr().out


def test_shift_threshold_selects_the_half_vector_shift(variant):
    """A threshold above the scene's lobe roughness changes the gradients (the half-vector branch
    runs), never the primal (the base path does not depend on the shift)."""
    import gdpt
    from gdpt.scenes import builtin_scene

    scene = builtin_scene("near-specular", resolution=(12, 12))
    low, high = (
        gdpt.render(scene, spp=16, seed=4, max_depth=4, features=False, shift_threshold=t)
        for t in (0.001, 0.05)
    )
    # equal up to float32 rounding: where the offsets reconnect moves the split of the path into
    # the two loop phases, and with it the order of the sums
    np.testing.assert_allclose(low.primal.numpy(), high.primal.numpy(), rtol=1e-5, atol=1e-7)
    assert np.abs(low.dx.numpy() - high.dx.numpy()).max() > 1e-3
    assert np.isfinite(high.dx.numpy()).all() and np.isfinite(high.dy.numpy()).all()


def test_features_pass_near_specular_glossy_vertices(variant):
    """Features follow the path through lobes at or below shift_threshold (the rough glass
    sphere and mirror): farther first rough vertex, in primal-only mode too."""
    import gdpt
    from gdpt.scenes import builtin_scene

    scene = builtin_scene("near-specular", resolution=(12, 12))
    for gradients in (True, False):
        low, high = (
            gdpt.render(scene, spp=8, seed=4, max_depth=4, gradients=gradients, shift_threshold=t)
            for t in (0.001, 0.05)
        )
        deeper = high.depth.numpy() > low.depth.numpy() + 0.1
        assert deeper.mean() > 0.1, f"gradients={gradients}: {deeper.mean():.2f} of pixels"


def test_compute_only_what_is_requested(variant):
    import gdpt
    from gdpt.scenes import builtin_scene

    scene = builtin_scene("diffuse-box", resolution=(8, 8))
    plain = gdpt.render(scene, spp=2, gradients=False, features=False)
    assert plain.present() == ["primal"]
    full = gdpt.render(scene, spp=2, variance=True)
    assert full.present() == [
        "primal",
        "dx",
        "dy",
        "albedo",
        "normal",
        "depth",
        "var_primal",
        "var_dx",
        "var_dy",
    ]
    # All buffers are views of the integrator's one output tensor (no copies).
    storage = full.primal.untyped_storage().data_ptr()
    assert all(t.untyped_storage().data_ptr() == storage for _, t in full.items())


def test_gradient_buffer_borders_are_zero(variant):
    import gdpt
    from gdpt.scenes import builtin_scene

    b = gdpt.render(builtin_scene("diffuse-box", resolution=(9, 7)), spp=4)
    assert b.dx.shape == (7, 9, 3)
    assert (b.dx[:, -1] == 0).all() and (b.dy[-1] == 0).all()
    assert b.dx[:, :-1].abs().sum() > 0 and b.dy[:-1].abs().sum() > 0


def test_features(variant):
    import gdpt
    from gdpt.scenes import builtin_scene

    b = gdpt.render(builtin_scene("diffuse-box", resolution=(16, 16)), spp=8)
    normal, albedo, depth = b.normal.numpy(), b.albedo.numpy(), b.depth.numpy()
    hit = depth[..., 0] > 0
    assert hit.mean() > 0.9  # the camera looks into a closed box
    length = np.linalg.norm(normal[hit], axis=-1)
    assert (length > 0.5).all() and (length < 1.0001).all()
    assert (normal[hit][:, 2] > -1e-4).all()  # view space: normals face the viewer (+z)
    assert (albedo >= 0).all() and (albedo <= 1).all()
    # The back wall faces the camera: its normal is close to +z in the image centre.
    assert normal[8, 8, 2] > 0.9


@pytest.mark.parametrize("name", ["rough-conductor", "plastic", "principled", "cbox-demo"])
def test_albedo_is_bounded_on_glossy_surfaces(variant, name):
    """Mitsuba's eval_diffuse_reflectance of a narrow glossy lobe is far above 1 (seen: 40 on
    a rough conductor); the albedo feature must stay in [0, 1] for the denoisers."""
    import gdpt
    from gdpt.scenes import builtin_scene

    albedo = gdpt.render(builtin_scene(name, resolution=(16, 16)), spp=8).albedo
    assert albedo.min() >= 0 and albedo.max() <= 1
    assert albedo.max() > 0.05  # some rough surface is seen


#: Share of samples whose outputs may be dropped as non-finite, per hard case: only
#: ``degenerate``, whose flattened cube has zero-area faces with NaN shading frames in Mitsuba's
#: intersection code (Mitsuba's ``path`` yields NaN there too and its image block drops them).
GUARD_BOUNDS = {"degenerate": 0.02}


@pytest.mark.parametrize("integrator", ["gdpt", "gdpt_rr"])
@pytest.mark.parametrize("name", HARD_CASES)
def test_hard_cases_stay_finite(variant, name, integrator):
    """Finite buffers, and the numerical guards inside the loop never fire (counted): a
    non-finite throughput, MIS ratio or gradient term would be a failure, not a fix."""
    import gdpt
    from gdpt.scenes import builtin_scene

    spp, res = 16, 16
    b = gdpt.render(
        builtin_scene(name, resolution=(res, res)),
        spp=spp,
        integrator=integrator,
        max_depth=64,
        variance=True,
    )
    assert b.nonfinite_counts() == {n: 0 for n in b.present()}, name
    assert float(b.primal.sum()) > 0
    counts = b.metadata["guard_counts"]
    dropped = counts.pop("sample_nonfinite")
    assert dropped <= GUARD_BOUNDS.get(name, 0.0) * res * res * spp, (name, dropped)
    assert all(v == 0 for v in counts.values()), (name, counts)


@pytest.mark.parametrize(
    "name", ["near-specular", "principled", "plastic", "tiny-bright-light", "grazing"]
)
def test_half_vector_shift_everywhere_stays_finite(variant, name):
    """shift_threshold 1 sends every glossy vertex through the half-vector copy."""
    import gdpt
    from gdpt.scenes import builtin_scene

    b = gdpt.render(
        builtin_scene(name, resolution=(16, 16)),
        spp=16,
        max_depth=64,
        variance=True,
        shift_threshold=1.0,
    )
    assert b.nonfinite_counts() == {n: 0 for n in b.present()}, name
    assert float(b.primal.sum()) > 0


def test_passes_split_the_work(variant):
    """Rendering in several passes gives a statistically equivalent image."""
    import gdpt
    from gdpt.scenes import builtin_scene

    scene = builtin_scene("diffuse-box", resolution=(8, 8))
    one = gdpt.render(scene, spp=256, seed=3, samples_per_pass=1 << 20)
    many = gdpt.render(scene, spp=256, seed=3, samples_per_pass=8 * 8 * 16)
    assert many.metadata["render_seconds"] > 0
    rel = float((one.primal.mean() - many.primal.mean()).abs() / one.primal.mean())
    assert rel < 0.05
    assert not np.array_equal(one.primal.numpy(), many.primal.numpy())  # different seeds


@pytest.mark.parametrize("name", ["gdpt", "gdpt_rr"])
def test_frozen_passes_equal_traced_passes(variant, name):
    """The frozen pass (the default) replays exactly what tracing gives: across spp per pass,
    film sizes, settings, a thin-lens camera (whose rays are traced outside the frozen pass)
    a scene parameter changed in place and ``primal``."""
    import mitsuba as mi

    from gdpt.scenes import builtin_scene

    def render(scene, freeze, spp, **props):
        integrator = mi.load_dict({"type": name, "max_depth": 4, "freeze": freeze, **props})
        return np.array(mi.render(scene, integrator=integrator, spp=spp, seed=5))

    small = mi.load_dict(builtin_scene("rough-conductor", resolution=(8, 6)))
    large = mi.load_dict(builtin_scene("rough-conductor", resolution=(12, 10)))
    lens = mi.load_dict(builtin_scene("thin-lens", resolution=(8, 6)))
    frozen = mi.load_dict({"type": name, "max_depth": 4})
    cases = [
        (small, 4, 4),
        (small, 3, 4),
        (large, 4, 4),
        (small, 4, 2),
        (small, 4, 4),
        (lens, 4, 4),
    ]
    for scene, spp, max_depth in cases:
        frozen.max_depth = max_depth  # a setting changed on the same integrator
        for _ in range(2):  # records (or finds its recording), then replays
            replayed = np.array(mi.render(scene, integrator=frozen, spp=spp, seed=5))
        traced = render(scene, False, spp, max_depth=max_depth)
        np.testing.assert_array_equal(replayed, traced)
    frozen.primal = "mis"  # part of the pass's key: records anew, then replays
    for _ in range(2):
        replayed = np.array(mi.render(small, integrator=frozen, spp=4, seed=5))
    np.testing.assert_array_equal(replayed, render(small, False, 4, primal="mis"))
    frozen.primal = "base"

    params = mi.traverse(small)
    key = next(k for k in params.keys() if k.endswith("radiance.value"))
    params[key] = params[key] * 3
    params.update()
    replayed = np.array(mi.render(small, integrator=frozen, spp=4, seed=5))
    np.testing.assert_array_equal(replayed, render(small, False, 4))


def test_unsupported_plugins_are_named(variant, tmp_path):
    """Unsupported plugins, also nested ones, are refused by name with their shape; a blend
    with a delta component has no invertible shift and says so."""
    import mitsuba as mi

    import gdpt

    for old, new, expected in [
        ('<bsdf type="diffuse"/>', '<bsdf type="hair"/>', "BSDF 'Hair' on shape"),
        (
            '<bsdf type="diffuse"/>',
            '<bsdf type="mask"><bsdf type="pplastic"/></bsdf>',
            "BSDF 'PolarizedPlastic' on shape",
        ),
        (
            '<bsdf type="diffuse"/>',
            '<bsdf type="blendbsdf"><float name="weight" value="0.5"/>'
            '<bsdf type="diffuse"/><bsdf type="conductor"/></bsdf>',
            "blends a delta",
        ),
        (
            '<emitter type="constant"/>',
            '<emitter type="projector"><texture type="bitmap" '
            'name="irradiance"><string name="filename" value="{png}"/></texture></emitter>',
            "emitter 'Projector'",
        ),
    ]:
        if "{png}" in new:
            image = tmp_path / "white.exr"
            mi.Bitmap(np.ones((4, 4, 3), dtype=np.float32)).write(str(image))
            new = new.replace("{png}", str(image))
        scene = mi.load_string(_xml("gdpt").replace(old, new))
        with pytest.raises(ValueError, match=expected):
            gdpt.render(scene, spp=1)


def test_render_and_denoise_renders_only_what_the_method_reads(variant):
    import torch

    import gdpt
    from gdpt.scenes import builtin_scene

    scene = builtin_scene("diffuse-box", resolution=(16, 12))
    res = gdpt.render_and_denoise(scene, spp=4, method="l1", seed=3)
    assert res.image.shape == (12, 16, 3) and torch.isfinite(res.image).all()
    assert res.buffers.dx is not None and res.buffers.albedo is None  # no features for Poisson
    torch.testing.assert_close(res.image, gdpt.reconstruct_image(res.buffers, method="l1"))
    assert set(res.timings) == {"render", "reconstruct", "total", "compile"}

    res = gdpt.render_and_denoise(scene, spp=2, method="l2", features=True)  # explicit wins
    assert res.buffers.albedo is not None

    with pytest.raises(ValueError, match="unknown reconstruction method 'l3'"):
        gdpt.render_and_denoise(scene, spp=1, method="l3")
    with pytest.raises(ValueError, match="needs dx and dy"):
        gdpt.render_and_denoise(scene, spp=1, method="l1", gradients=False)


@pytest.mark.shared_scenes
def test_a_pass_dr_jit_will_not_record_is_traced(variant):
    """With torus's objects alive, Dr.Jit refuses to record veach-bidir's frozen pass (its
    virtual calls reach instances outside the pass's inputs): the integrator warns once, traces
    those passes, counts them in ``recordings`` and gives what tracing gives."""
    import mitsuba as mi
    from shared_scenes import SHARED_SCENES

    from gdpt.scenes.loading import load_scene

    def load(name):
        return load_scene(SHARED_SCENES / name / "scene.xml", box_filter=True, long_side=16)

    torus = load("torus")
    mi.render(torus, integrator=mi.load_dict({"type": "gdpt", "max_depth": 2}), spp=2)
    scene = load("veach-bidir")
    frozen = mi.load_dict({"type": "gdpt", "max_depth": 2})
    with pytest.warns(RuntimeWarning, match="could not record a frozen pass"):
        first = np.array(mi.render(scene, integrator=frozen, spp=2, seed=3))
    again = np.array(mi.render(scene, integrator=frozen, spp=2, seed=3))  # no second warning
    traced = mi.render(
        scene,
        integrator=mi.load_dict({"type": "gdpt", "max_depth": 2, "freeze": False}),
        spp=2,
        seed=3,
    )
    np.testing.assert_array_equal(first, np.array(traced))
    np.testing.assert_array_equal(again, first)
    assert frozen.recordings == 3  # the refused recording, then both renders' pass traced
    del torus


@pytest.mark.slow
def test_no_garbage_collection_inside_a_recording():
    """The interrupt tests, then this file, in one process (the abort was found so:
    ``Fatal Python error: Aborted`` with ``Garbage-collecting`` on top of a frozen recording in
    ``test_shift_threshold_selects_the_half_vector_shift``; the integrators now pause the
    collector while a pass records)."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    files = ["tests/gdpt/test_interrupt.py", "tests/integrators/test_gdpt_api.py"]
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *files, "-m", "not slow"],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    assert "Fatal Python error" not in run.stderr + run.stdout, run.stderr[-2000:]


_FOG = '<medium type="homogeneous" id="fog"><float name="scale" value="0.5"/></medium>'


@pytest.mark.parametrize(
    ("old", "new", "where"),
    [
        ('<sensor type="perspective">', '<sensor type="perspective"><ref id="fog"/>', "on sensor"),
        (
            '<bsdf type="diffuse"/></shape>',
            '<bsdf type="dielectric"/><ref name="interior" id="fog"/></shape>',
            "inside shape",
        ),
        (
            '<bsdf type="diffuse"/></shape>',
            '<bsdf type="diffuse"/><ref name="exterior" id="fog"/></shape>',
            "outside shape",
        ),
        (
            '<emitter type="constant"/>',
            '<emitter type="point"><point name="position" value="0,3,0"/><ref id="fog"/></emitter>',
            "on emitter",
        ),
    ],
)
def test_participating_media_are_refused_everywhere(variant, old, new, where):
    """A medium on a sensor, an emitter or either side of a shape is named with where it is,
    by the loader, ``gdpt.render`` and ``mi.render`` (the paths are traced in vacuum)."""
    import mitsuba as mi

    import gdpt

    xml = _xml("gdpt").replace("<sensor", _FOG + "<sensor", 1).replace(old, new, 1)
    expected = f"participating media are not supported: medium 'fog' .*{where}"
    scene = mi.load_string(xml)
    with pytest.raises(ValueError, match=expected):
        gdpt.render(scene, spp=1)
    with pytest.raises(RuntimeError) as info:  # mi.render wraps it, the cause says why
        mi.render(scene, spp=1)
    assert where in str(info.value.__cause__)


def test_the_loader_refuses_before_rendering(variant, tmp_path):
    """``gdpt.load_scene`` refuses what the integrators cannot render, except where the scene
    is for Mitsuba's own integrators (``check=False``)."""
    import gdpt

    path = tmp_path / "fog.xml"
    path.write_text(
        _xml("path")
        .replace("<sensor", _FOG + "<sensor", 1)
        .replace('<sensor type="perspective">', '<sensor type="perspective"><ref id="fog"/>')
    )
    with pytest.raises(ValueError, match="medium 'fog' \\(HomogeneousMedium\\) on sensor"):
        gdpt.load_scene(path)
    assert gdpt.load_scene(path, check=False).sensors()[0].get_medium() is not None


@pytest.mark.parametrize("sampler", ["stratified", "ldsampler"])
def test_statistics_need_independent_samples(variant, sampler):
    """The variance and half-buffers are statistics of independent samples: a sampler that
    correlates them is refused for those, not for a plain render."""
    import mitsuba as mi

    import gdpt

    xml = _xml("gdpt").replace("</film>", f'</film><sampler type="{sampler}"/>')
    scene = mi.load_string(xml)
    for props in ({"variance": True}, {"halves": True}):
        with pytest.raises(ValueError, match="independent samples.*Sampler"):
            gdpt.render(scene, spp=4, **props)
    assert gdpt.render(scene, spp=4).primal.shape == (6, 8, 3)


def test_unsupported_variants_are_refused():
    """Spectral, mono and polarized variants are refused in one line by the bridge and by the
    plugin itself (set with ``mi.set_variant`` after gdpt registered the plugins)."""
    import subprocess
    import sys

    code = (
        "import gdpt, mitsuba as mi\n"
        "gdpt.set_variant('llvm_ad_rgb')\n"
        "for v in ('llvm_ad_spectral', 'llvm_ad_mono', 'llvm_ad_mono_polarized'):\n"
        "    mi.set_variant(v)\n"
        "    for f in (lambda: gdpt.render('builtin:diffuse-box', spp=1),\n"
        "              lambda: mi.load_dict({'type': 'gdpt'})):\n"
        "        try:\n"
        "            f()\n"
        "            print(v, 'not refused')\n"
        "        except Exception as e:\n"
        "            print(type(e).__name__ + ':', str(e).splitlines()[-1])\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.splitlines()
    assert len(out) == 6, out
    for line, variant_name in zip(out[::2], ("spectral", "mono", "mono_polarized"), strict=True):
        assert line.startswith("ValueError: the Mitsuba variant 'llvm_ad_" + variant_name), line
    for line in out[1::2]:  # Mitsuba wraps the plugin's error, whose last line says why
        assert "is not supported; the integrators render RGB buffers" in line, line
