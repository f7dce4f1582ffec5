"""The render's own statistics: variances of the means against the spread of 64 independent
renders (per-pixel z), half-buffers independent of each other, and the bad inputs of the
methods that read them (``fuse``, ``auto``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import gdpt
from gdpt.scenes import builtin_scene

pytestmark = pytest.mark.usefixtures("variant", "single_thread")

RUNS, SPP, SIZE = 64, 8, 12
#: Share of pixels beyond |z| = 3.29 accepted: twice what the self-test allows for right
#: variances (the z of a variance is skewed).
OUTLIERS = 0.04


@pytest.fixture(scope="module", params=["base", "mis"])
def runs(request):
    """``RUNS`` independent ``cbox-demo`` renders (variances and halves on) of each primal
    estimator (``mis``: its variance and halves sum every sample's contributions to the pixel,
    its own base path's and its neighbours' offset paths'), as numpy arrays ``(runs, H, W, C)``
    per buffer."""
    gdpt.set_variant("llvm_ad_rgb")
    scene = gdpt.load_scene(builtin_scene("cbox-demo"), long_side=SIZE)
    out: dict[str, list[np.ndarray]] = {}
    for seed in range(RUNS):
        b = gdpt.render(
            scene,
            spp=SPP,
            seed=seed,
            variance=True,
            halves=True,
            features=False,
            primal=request.param,
        )
        for name, t in b.items():
            out.setdefault(name, []).append(t.numpy().copy())
    return {k: np.stack(v) for k, v in out.items()}


def variance_z(estimates: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Per-pixel z of ``mean(v_i) - var(x)``: ``estimates`` (runs, H, W, 1) per-run variance
    estimates of the mean of ``values`` (runs, H, W) (the luminance of each run). Per run,
    ``d_i = v_i - n/(n-1) (x_i - mean x)^2`` has expectation 0 when the estimates are right."""
    n = values.shape[0]
    sq = (values - values.mean(0)) ** 2 * n / (n - 1)
    d = estimates[..., 0] - sq
    se = d.std(0, ddof=1) / np.sqrt(n)
    return np.where(se > 0, d.mean(0) / np.where(se > 0, se, 1), 0.0)


def luminance(x: np.ndarray) -> np.ndarray:
    return x.mean(-1)


def test_variance_z_self_test():
    """The z of :func:`variance_z` is calibrated on synthetic data with known variances (and
    detects a 30% error in them)."""
    rng = np.random.default_rng(0)
    sd = rng.uniform(0.1, 2.0, (1, 40, 40))
    values = rng.normal(0, 1, (RUNS, 40, 40)) * sd
    # unbiased per-run estimates of sd^2 from 8 samples each (scaled chi-square)
    est = sd**2 * rng.chisquare(SPP - 1, (RUNS, 40, 40)) / (SPP - 1)
    z = variance_z(est[..., None], values)
    # skewed (squares of normals): about 1% beyond 3.29 instead of a normal's 0.1%; the
    # render tests allow OUTLIERS
    assert np.mean(np.abs(z) > 3.29) < OUTLIERS / 2
    z_wrong = variance_z(1.3 * est[..., None], values)
    assert np.mean(np.abs(z_wrong) > 3.29) > 0.1


@pytest.mark.slow  # 64 renders: about 2.5 min on 2 loaded cores
def test_primal_variance_matches_the_spread_of_independent_renders(runs):
    z = variance_z(runs["var_primal"], luminance(runs["primal"]))
    assert np.mean(np.abs(z) > 3.29) < OUTLIERS, (np.mean(np.abs(z) > 3.29), np.abs(z).max())


@pytest.mark.slow  # 64 renders: about 2.5 min on 2 loaded cores
@pytest.mark.parametrize("name", ["dx", "dy"])
def test_gradient_variance_matches_the_spread_of_independent_renders(runs, name):
    values = luminance(runs[name])
    inner = (
        (slice(None), slice(None), slice(0, -1)) if name == "dx" else (slice(None), slice(0, -1))
    )
    z = variance_z(runs[f"var_{name}"][inner], values[inner])
    assert np.mean(np.abs(z) > 3.29) < OUTLIERS, (np.mean(np.abs(z) > 3.29), np.abs(z).max())


@pytest.mark.slow  # 64 renders: about 2.5 min on 2 loaded cores
def test_halves_are_independent_and_average_to_the_primal(runs):
    a, b = luminance(runs["primal_a"]), luminance(runs["primal_b"])
    # Fisher z of the per-pixel correlation of the two halves across runs
    ca, cb = a - a.mean(0), b - b.mean(0)
    denom = np.sqrt((ca**2).sum(0) * (cb**2).sum(0))
    ok = denom > 0
    r = (ca * cb).sum(0)[ok] / denom[ok]
    z = np.arctanh(np.clip(r, -0.999999, 0.999999)) * np.sqrt(RUNS - 3)
    assert ok.mean() > 0.9 and np.mean(np.abs(z) > 3.29) < 0.02
    # their difference has the variance of both: var(a - b) = var(a) + var(b)
    diff = (a - b).var(0, ddof=1)[ok]
    assert abs(diff.sum() / (a.var(0, ddof=1) + b.var(0, ddof=1))[ok].sum() - 1) < 0.1
    # equal halves (even/odd samples of SPP): their mean is the primal
    np.testing.assert_allclose((runs["primal_a"] + runs["primal_b"]) / 2, runs["primal"], atol=1e-5)


def test_a_half_without_samples_is_refused_by_name_and_pooling_fills_it():
    scene = gdpt.load_scene(builtin_scene("cbox-demo"), long_side=8)
    one = gdpt.render(scene, spp=1, halves=True)
    assert one.metadata["half_spp"] == [1, 0]
    torch.testing.assert_close(one.half("a").primal, one.primal)
    with pytest.raises(ValueError, match="half 'b' of these buffers has no samples"):
        one.half("b")
    pooled = gdpt.render(scene, spp=1, primal_spp=3, halves=True)  # 1 + 2 and 0 + 1 samples
    assert pooled.metadata["half_spp"] == [3, 1]
    assert torch.isfinite(pooled.half("b").primal).all()


def test_fuse_names_the_missing_buffers_and_their_render_options():
    scene = gdpt.load_scene(builtin_scene("cbox-demo"), long_side=8)
    plain = gdpt.render(scene, spp=2)
    with pytest.raises(ValueError, match=r"'var_dx' \(render with variance=True\)"):
        gdpt.reconstruct_image(plain, "fuse")
    with pytest.raises(ValueError, match=r"'primal_a' \(render with halves=True\)"):
        gdpt.reconstruct_image(plain.replace(var_dx=plain.primal[..., :1]), "fuse")


def test_fuse_on_a_render_is_finite_and_reports_what_it_did():
    scene = gdpt.load_scene(builtin_scene("cbox-demo"), long_side=16)
    b = gdpt.render(scene, spp=4, primal_spp=4, variance=True, halves=True)
    image = gdpt.reconstruct_image(b, "fuse")
    assert image.shape == b.primal.shape and torch.isfinite(image).all()
    info = b.metadata["fuse"]
    assert 0.0 < info["trusted"] <= 1.0 and info["denoiser"] in ("oidn-tuned", "oidn")


@pytest.mark.parametrize("spp, per_pass", [(5, 1), (5, 2), (4, 3)])
def test_halves_split_by_the_render_wide_sample_index_whatever_the_passes(spp, per_pass):
    """One sample per pass (a large film) still fills both halves, in proportion."""
    from gdpt.rendering import make_integrator

    scene = gdpt.load_scene(builtin_scene("cbox-demo"), long_side=16)
    integrator = make_integrator("gdpt", halves=True, samples_per_pass=per_pass * 256)
    b = gdpt.render(scene, spp=spp, integrator=integrator)
    n_a, n_b = b.metadata["half_spp"]
    assert (n_a, n_b) == ((spp + 1) // 2, spp // 2)
    pooled = (n_a * b.primal_a + n_b * b.primal_b) / spp
    torch.testing.assert_close(pooled, b.primal, atol=1e-5, rtol=1e-5)


def test_gradient_halves_average_to_the_gradients_and_fuse_reports_its_held_out_choice():
    scene = gdpt.load_scene(builtin_scene("cbox-demo"), long_side=16)
    b = gdpt.render(scene, spp=4, primal_spp=4, variance=True, halves=True)
    assert b.metadata["gradient_half_spp"] == [2, 2] and b.metadata["half_spp"] == [4, 4]
    torch.testing.assert_close(0.5 * (b.dx_a + b.dx_b), b.dx, atol=1e-6, rtol=0)
    torch.testing.assert_close(0.5 * (b.dy_a + b.dy_b), b.dy, atol=1e-6, rtol=0)
    assert not torch.equal(b.dx_a, b.dx_b)  # two independent halves
    gdpt.reconstruct_image(b, "fuse")
    held_out = b.metadata["fuse"]["held_out"]
    keys = {"kept", "tile", "margin", "image_margin", "statistic", "difference", "nonfinite"}
    assert set(held_out) == keys
    assert 0.0 <= held_out["kept"] <= 1.0 and held_out["nonfinite"] == 0
    without = b.replace(dx_a=None, dx_b=None, dy_a=None, dy_b=None)
    with pytest.raises(ValueError, match=r"'dx_a' \(render with gradients=True, halves=True\)"):
        gdpt.reconstruct_image(without, "fuse")


def fisher_z(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Fisher z of the per-pixel correlation of ``a`` and ``b`` ``(runs, H, W)`` across runs
    (pixels where either is constant left out)."""
    ca, cb = a - a.mean(0), b - b.mean(0)
    denom = np.sqrt((ca**2).sum(0) * (cb**2).sum(0))
    ok = denom > 0
    r = (ca * cb).sum(0)[ok] / denom[ok]
    return np.arctanh(np.clip(r, -0.999999, 0.999999)) * np.sqrt(RUNS - 3)


@pytest.mark.slow  # 64 renders: about 2.5 min on 2 loaded cores
@pytest.mark.parametrize("name", ["dx", "dy"])
def test_gradient_halves_are_independent_of_the_other_half(runs, name):
    """``fuse``'s held-out check needs half ``a``'s gradients independent of half ``b``'s
    primal (and gradients); the same half's primal shares its paths, which the test sees."""
    inner = (
        (slice(None), slice(None), slice(0, -1)) if name == "dx" else (slice(None), slice(0, -1))
    )
    g_a, g_b = (luminance(runs[f"{name}_{h}"])[inner] for h in "ab")
    p_a, p_b = (luminance(runs[f"primal_{h}"])[inner] for h in "ab")
    for other in (p_b, g_b):
        assert np.mean(np.abs(fisher_z(g_a, other)) > 3.29) < 0.02
    assert np.mean(np.abs(fisher_z(g_a, p_a)) > 3.29) > 0.1  # same paths: correlated
    np.testing.assert_allclose((runs[f"{name}_a"] + runs[f"{name}_b"]) / 2, runs[name], atol=1e-5)
