"""gdpt.rendering: named integrators are shared between renders of one scene object (their
frozen passes replay), never across scene objects."""

from __future__ import annotations

import warnings

import pytest
import torch

from gdpt.rendering import make_integrator, render, shared_integrator


@pytest.fixture
def scene(variant):
    """A fresh 16 px scene, after the integrators other tests left were dropped: a scene freed
    while a test runs (the least recently used of :func:`shared_integrator`'s eight) leaves
    Dr.Jit's registry of BSDFs and emitters, whose contents the frozen passes' recordings
    depend on, so a replay would record again."""
    import gc

    from gdpt import rendering
    from gdpt.scenes import builtin_scene
    from gdpt.scenes.loading import load_scene

    rendering._SHARED.clear()
    gc.collect()
    return load_scene(builtin_scene("cbox-demo", resolution=(16, 16)))


def test_renders_of_one_scene_with_the_same_settings_share_one_integrator(scene):
    from gdpt.scenes import builtin_scene
    from gdpt.scenes.loading import load_scene

    first = shared_integrator(scene, "gdpt", max_depth=3, features=False)
    assert shared_integrator(scene, "gdpt", features=False, max_depth=3) is first
    assert shared_integrator(scene, "gdpt", max_depth=4, features=False) is not first
    assert shared_integrator(scene, "gdpt_rr", max_depth=3, features=False) is not first
    again = load_scene(builtin_scene("cbox-demo", resolution=(16, 16)))
    assert shared_integrator(again, "gdpt", max_depth=3, features=False) is not first


def test_second_render_of_one_scene_replays_and_equals_tracing(scene):
    """A second render of the same ``mi.Scene`` object with the same settings replays the
    recording of the first (the frozen pass records no more) and gives identical buffers, for
    the seed of the recording and for another; both equal tracing without ``dr.freeze``. A
    pooled render in between (two integrators of their own) does not disturb it. No warning."""
    props = dict(max_depth=3, features=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        first = _copy(render(scene, spp=2, seed=3, **props))
        integrator = shared_integrator(scene, "gdpt", **props)  # the one render() used
        recordings = integrator._frozen_pass.n_recordings
        assert recordings >= 1
        render(scene, spp=2, seed=1, primal_spp=4, **props)
        for seed in (3, 4):
            replayed = render(scene, spp=2, seed=seed, **props)
            assert shared_integrator(scene, "gdpt", **props) is integrator
            assert integrator._frozen_pass.n_recordings == recordings, f"seed {seed} recorded"
            tracer = make_integrator("gdpt", freeze=False, **props)
            traced = render(scene, spp=2, seed=seed, integrator=tracer)
            for name in ("primal", "dx", "dy"):
                assert torch.equal(getattr(replayed, name), getattr(traced, name)), (seed, name)
                if seed == 3:
                    assert torch.equal(getattr(replayed, name), first[name]), name
    assert [str(w.message) for w in caught] == []


def test_a_render_reports_the_passes_it_recorded(scene):
    """``metadata["recorded_passes"]``: a render at a pass size its integrator has not recorded
    says so (its time includes the tracing), a repeat replays and says 0."""
    props = dict(max_depth=2, features=False)
    first = render(scene, spp=3, seed=1, **props)  # passes of 2 and 1 spp
    again = render(scene, spp=3, seed=2, **props)
    assert first.metadata["recorded_passes"] >= 1
    assert again.metadata["recorded_passes"] == 0


def _copy(buffers) -> dict[str, torch.Tensor]:
    """Copies of the primal and gradients (the render's tensors are views that may be reused)."""
    return {name: getattr(buffers, name).clone() for name in ("primal", "dx", "dy")}


@pytest.mark.shared_scenes
def test_release_scene_frees_it_for_the_next_scene_s_frozen_passes(variant):
    """``gdpt.release_scene``: ``render`` keeps a scene's integrator (and the scene); released
    and dropped, the next scene records its frozen passes, where with the first one alive
    Dr.Jit refuses (torus before veach-bidir, tests/integrators/test_gdpt_api.py)."""
    from shared_scenes import SHARED_SCENES

    import gdpt
    from gdpt import rendering
    from gdpt.scenes.loading import load_scene

    def load(name):
        return load_scene(SHARED_SCENES / name / "scene.xml", box_filter=True, long_side=16)

    torus = load("torus")
    gdpt.render(torus, spp=2, max_depth=2)
    assert any(kept is torus for kept, _ in rendering._SHARED.values())
    gdpt.release_scene(torus)
    assert not any(kept is torus for kept, _ in rendering._SHARED.values())
    del torus
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # no traced fallback
        buffers = gdpt.render(load("veach-bidir"), spp=2, max_depth=2)
    assert buffers.metadata["recorded_passes"] >= 1


@pytest.mark.parametrize(
    ("props", "message"),
    [
        ({"max_dept": 3}, "unknown gdpt integrator property 'max_dept'; valid: max_depth"),
        ({"max_depth": 2.5}, "'max_depth' must be -1 \\(unbounded\\) or >= 0, got 2.5"),
        ({"features": "no"}, "'features' must be true or false, got 'no'"),
    ],
)
def test_bad_properties_are_one_line_before_mitsuba_loads_the_plugin(scene, props, message):
    """``gdpt.render``'s properties are checked against the plugins' table (a ValueError, not
    Mitsuba's wrapped multi-line error)."""
    with pytest.raises(ValueError, match=message) as info:
        render(scene, spp=1, **props)
    assert "\n" not in str(info.value)
