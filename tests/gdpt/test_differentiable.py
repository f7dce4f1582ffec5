"""gdpt.render_differentiable: gradients of a loss on the reconstructed image w.r.t. scene
parameters, against central differences of the whole pipeline; refusals of what cannot be
differentiated; non-finite gradients reported."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
import torch

import gdpt
from gdpt.differentiable import NonFiniteGradientWarning
from gdpt.methods import METHODS

pytestmark = pytest.mark.usefixtures("variant", "single_thread")

KEY = "light.emitter.radiance.value"  # the features (albedo, normal, depth) do not depend on it
NETWORK = "oidn-tuned"


@pytest.fixture(scope="module")
def scene():
    return gdpt.load_scene("builtin:cbox-demo", long_side=16)


def _loss(scene, params, value, method, *, grad=False):
    params[KEY] = mi.Color3f(*[float(v) for v in value])
    if grad:
        dr.enable_grad(params[KEY])
    params.update()
    image = gdpt.render_differentiable(
        scene, params, spp=2, seed=7, seed_grad=7, method=method, max_depth=4
    )
    target = dr.linspace(mi.Float, 0.0, 0.3, dr.prod(image.shape))
    return dr.mean(dr.square(image - mi.TensorXf(target, image.shape)), axis=None)


@pytest.mark.parametrize("method", [None, NETWORK])
def test_gradient_matches_central_differences_of_the_whole_pipeline(scene, method):
    """d loss / d radiance along (1, 2, 3): autograd (the network in torch, then prb's adjoint
    pass replaying the primal's paths, ``seed_grad == seed``) against a central difference of
    render + reconstruction + loss at the same seeds, which differentiates the same estimator.
    The rendered image is linear in the radiance (one emitter; sampling does not depend on
    it), so the difference sees only the network's curvature and float32 rounding: measured
    0.2% at this step; 2% allowed."""
    if method is not None and (reason := METHODS[method].check()):
        pytest.skip(reason)
    params = mi.traverse(scene)
    value = np.array(params[KEY].numpy()).ravel()
    direction = np.array([1.0, 2.0, 3.0])
    try:
        dr.backward(_loss(scene, params, value, method, grad=True))
        autograd = float(np.dot(dr.grad(params[KEY]).numpy().ravel(), direction))
        dr.disable_grad(params[KEY])
        step = 1e-2
        up = _loss(scene, params, value + step * direction, method).array[0]
        down = _loss(scene, params, value - step * direction, method).array[0]
    finally:
        params[KEY] = mi.Color3f(*[float(v) for v in value])
        params.update()
    central = (up - down) / (2 * step)
    assert autograd == pytest.approx(central, rel=0.02)
    assert abs(autograd) > 0


def test_non_finite_gradients_are_counted(scene):
    """A NaN weight on one output pixel: through the network's input scale (a mean over the
    image) every entry of the gradient w.r.t. the rendered image becomes NaN, and the warning
    counts them. Mitsuba's adjoint pass then drops non-finite adjoint pixels (the parameter's
    gradient comes out 0 here), so this count is the only report of them."""
    if reason := METHODS[NETWORK].check():
        pytest.skip(reason)
    params = mi.traverse(scene)
    dr.enable_grad(params[KEY])
    params.update()
    try:
        image = gdpt.render_differentiable(scene, params, spp=1, seed=1, method=NETWORK)
        weight = np.ones(image.shape, dtype=np.float32)
        weight[5, 6, 1] = np.nan
        with pytest.warns(NonFiniteGradientWarning, match=r"768 of 768 entries .* 'oidn-tuned'"):
            dr.backward(dr.sum(image * mi.TensorXf(weight), axis=None))
    finally:
        dr.disable_grad(params[KEY])


def test_image_without_gradients_is_the_method_on_the_render(scene):
    if reason := METHODS[NETWORK].check():
        pytest.skip(reason)
    image = gdpt.render_differentiable(scene, spp=2, seed=3, method=NETWORK, max_depth=4)
    assert isinstance(image, mi.TensorXf) and image.shape == (16, 16, 3)
    assert not dr.grad_enabled(image)
    plain = gdpt.render_differentiable(scene, spp=2, seed=3, method=None, max_depth=4)
    features = gdpt.render(scene, spp=2, seed=3 ^ 0x5BD1E995, gradients=False, max_depth=4)
    expected = gdpt.reconstruct_image(features.replace(primal=plain.torch()), NETWORK)
    np.testing.assert_allclose(image.numpy(), expected.numpy(), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("method", list(METHODS))
def test_the_registry_says_truly_which_methods_pass_gradients(method, random_buffers):
    """``reconstruct_image`` on 16x16 buffers whose primal and gradients require gradients: a
    method marked differentiable gives finite, nonzero gradients to the buffers it reads; the
    others refuse by name."""
    if reason := METHODS[method].check():
        pytest.skip(reason)
    buffers = random_buffers(16, 16, metadata={"half_spp": [8, 8], "primal_spp": 40})
    read = ("primal", "dx", "dy") if METHODS[method].gradients else ("primal",)
    leaves = {n: getattr(buffers, n).clone().requires_grad_(True) for n in read}
    buffers = buffers.replace(**leaves)
    if not METHODS[method].differentiable:
        with pytest.raises(ValueError, match=rf"method '{method}' is not differentiable"):
            gdpt.reconstruct_image(buffers, method)
        return
    gdpt.reconstruct_image(buffers, method).square().mean().backward()
    for name, leaf in leaves.items():
        assert torch.isfinite(leaf.grad).all() and leaf.grad.abs().sum() > 0, name


@pytest.mark.parametrize("method", ["l1", "l2"])
def test_methods_reading_gradients_are_refused_as_forward_only(scene, method):
    with pytest.raises(ValueError, match=rf"method '{method}' reads the gradients.*forward-only"):
        gdpt.render_differentiable(scene, spp=1, method=method)


def test_a_method_without_gradients_is_refused_by_name(scene):
    undifferentiable = [n for n, m in METHODS.items() if not m.differentiable and not m.gradients]
    assert "oidn" in undifferentiable
    with pytest.raises(ValueError, match="method 'oidn' is not differentiable"):
        gdpt.render_differentiable(scene, spp=1, method="oidn")


def test_a_variant_without_autodiff_is_refused_with_the_ones_to_use(scene, monkeypatch):
    monkeypatch.setattr(mi, "variant", lambda: "llvm_rgb")
    with pytest.raises(ValueError, match="'llvm_rgb' has no automatic.*llvm_ad_rgb.*cuda_ad_rgb"):
        gdpt.render_differentiable(scene, spp=1)


def test_an_integrator_without_adjoint_is_refused(scene):
    with pytest.raises(ValueError, match="not differentiable; use a Mitsuba AD integrator"):
        gdpt.render_differentiable(scene, spp=1, integrator="path", method=None)


def _radiance_gradient(scene, **kwargs) -> np.ndarray:
    params = mi.traverse(scene)
    dr.enable_grad(params[KEY])
    params.update()
    try:
        image = gdpt.render_differentiable(scene, params, spp=1, seed=5, max_depth=3, **kwargs)
        dr.backward(dr.mean(image, axis=None))
        return dr.grad(params[KEY]).numpy().ravel()
    finally:
        dr.disable_grad(params[KEY])


def test_a_reconstruction_replays_the_primal_paths_unless_told_otherwise(scene):
    if reason := METHODS[NETWORK].check():
        pytest.skip(reason)
    default = _radiance_gradient(scene, method=NETWORK)
    np.testing.assert_array_equal(default, _radiance_gradient(scene, method=NETWORK, seed_grad=5))
    assert not np.array_equal(default, _radiance_gradient(scene, method=NETWORK, seed_grad=0))
    plain = _radiance_gradient(scene, method=None)  # Mitsuba's decorrelated adjoint pass
    assert not np.array_equal(plain, _radiance_gradient(scene, method=None, seed_grad=5))


def test_a_replay_needs_the_primal_sample_count(scene):
    with pytest.raises(ValueError, match="replay traces the primal's spp=2, not spp_grad=4"):
        gdpt.render_differentiable(scene, spp=2, seed=3, seed_grad=3, spp_grad=4, method=None)


def test_the_inverse_rendering_example_runs_tiny_and_descends(tmp_path):
    """``examples/inverse_denoised.py --tiny`` as written, in a fresh interpreter: every run's
    radiance error falls from the start, and the loss of the denoised run (a low-noise image)
    falls too; the undenoised runs' loss is dominated by the image's noise, which grows with
    the radiance, so it is not required to fall in six iterations."""
    if reason := METHODS[NETWORK].check():
        pytest.skip(reason)
    root = Path(__file__).resolve().parents[2]
    result = subprocess.run(
        [sys.executable, str(root / "examples" / "inverse_denoised.py"), "--tiny", "--out", "out"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    summary = json.loads((tmp_path / "out" / "results.json").read_text())
    start = np.sqrt(
        np.mean(((np.array(summary["start"]) - summary["truth"]) / summary["truth"]) ** 2)
    )
    for name, run in summary["runs"].items():
        assert run["records"][-1]["error"] < 0.9 * start, name
    denoised = summary["runs"][f"low+{NETWORK}"]["records"]
    assert denoised[-1]["loss"] < denoised[0]["loss"]
    assert (tmp_path / "out" / "curves.png").is_file()
