"""gdpt.buffers_from_aovs: ``mi.render`` with the gdpt plugin, cut into the buffers gdpt.render
returns at the same seed and spp."""

from __future__ import annotations

import pytest
import torch

import gdpt


@pytest.fixture(scope="module")
def scene():
    from gdpt.scenes import builtin_scene

    gdpt.set_variant()
    return gdpt.load_scene(builtin_scene("cbox-demo", resolution=(16, 12)))


@pytest.mark.parametrize(
    "props", [{}, {"variance": True, "halves": True}, {"gradients": False, "features": False}]
)
def test_mi_render_tensor_equals_gdpt_render(scene, props):
    import mitsuba as mi

    integrator = mi.load_dict({"type": "gdpt", **props})
    tensor = mi.render(scene, integrator=integrator, spp=4, seed=3)
    buffers = gdpt.buffers_from_aovs(tensor, integrator, seed=3)
    expected = gdpt.render(scene, spp=4, seed=3, **props)
    assert buffers.present() == expected.present()
    for name, t in expected.items():
        assert torch.equal(getattr(buffers, name), t), name
    assert buffers.spp == expected.spp == 4
    timing = {"render_seconds", "recorded_passes"}  # of the run, not of the buffers
    assert {k: v for k, v in expected.metadata.items() if k not in timing} == buffers.metadata


def test_scene_integrator_and_torch_tensor(scene):
    """``integrator.render`` called directly, its tensor as torch, the spp given."""
    import mitsuba as mi

    integrator = mi.load_dict({"type": "gdpt_rr"})
    tensor = integrator.render(scene, seed=5, spp=2).torch()
    buffers = gdpt.buffers_from_aovs(tensor, integrator, spp=2)
    assert buffers.present() == ["primal", "dx", "dy", "albedo", "normal", "depth"]
    assert buffers.primal.data_ptr() == tensor.data_ptr()  # a view, no copy
    assert buffers.spp == 2 and buffers.metadata["integrator"] == "gdpt_rr"
    assert "seed" not in buffers.metadata


def test_wrong_integrator_or_tensor(scene):
    import mitsuba as mi

    path = mi.load_dict({"type": "path"})
    with pytest.raises(TypeError, match=r"gdpt or gdpt_rr.*got .*Integrator"):
        gdpt.buffers_from_aovs(mi.render(scene, integrator=path, spp=1), path)
    integrator = mi.load_dict({"type": "gdpt"})
    with pytest.raises(ValueError, match=r"\(H, W, 16\) tensor .*primal\.R.*got \(12, 16, 3\)"):
        gdpt.buffers_from_aovs(torch.zeros(12, 16, 3), integrator)
