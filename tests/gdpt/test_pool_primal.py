"""Pooling plain path samples into a gradient render: gdpt.buffers.pool_primal,
gdpt.render(..., primal_spp=N) and the methods that ask for it (gdpt.methods.Method.sampling)."""

from __future__ import annotations

import json
import warnings

import pytest
import torch
from safetensors.torch import save_file

from gdpt.buffers import pool_primal
from gdpt.methods import METHODS

GRADIENT = ("primal", "dx", "dy", "albedo", "normal", "depth", "var_primal")
PRIMAL_ONLY = ("primal", "albedo", "normal", "depth", "var_primal")


def test_pooled_buffers_are_sample_weighted_means(random_buffers):
    g = random_buffers(names=GRADIENT, spp=3, seed=1, metadata={"render_seconds": 0.5})
    p = random_buffers(names=PRIMAL_ONLY, spp=9, seed=2, metadata={"render_seconds": 0.25})
    pooled = pool_primal(g, p)
    assert pooled.metadata["render_seconds"] == 0.75
    for name in ("primal", "albedo", "normal", "depth"):
        expected = (3 * getattr(g, name) + 9 * getattr(p, name)) / 12
        torch.testing.assert_close(getattr(pooled, name), expected)
    torch.testing.assert_close(pooled.var_primal, (9 * g.var_primal + 81 * p.var_primal) / 144)
    assert pooled.dx is g.dx and pooled.dy is g.dy
    assert pooled.spp == 3 and pooled.metadata["primal_spp"] == 12


def test_features_of_the_plain_render_alone_are_taken_as_they_are(random_buffers):
    g = random_buffers(names=("primal", "dx", "dy", "var_primal"), spp=3, seed=1)
    p = random_buffers(names=PRIMAL_ONLY, spp=9, seed=2)
    pooled = pool_primal(g, p)
    for name in ("albedo", "normal", "depth"):
        assert getattr(pooled, name) is getattr(p, name)
    torch.testing.assert_close(pooled.primal, (3 * g.primal + 9 * p.primal) / 12)


@pytest.mark.parametrize(
    ("first", "second", "match"),
    [
        (("primal",), ("primal",), "first render has no dx/dy"),
        (GRADIENT, GRADIENT, "primal-only render has dx/dy"),
        (GRADIENT, ("primal",), "albedo, normal, depth, var_primal present in one render only"),
        (("primal", "dx", "dy", "var_primal"), ("primal",), "var_primal present in one render"),
    ],
)
def test_unpoolable_renders_are_named(random_buffers, first, second, match):
    with pytest.raises(ValueError, match=match):
        pool_primal(random_buffers(names=first), random_buffers(names=second))


def test_other_sizes_and_empty_renders_are_refused(random_buffers):
    g = random_buffers(names=("primal", "dx", "dy"))
    with pytest.raises(ValueError, match="10x12 and 10x13 px"):
        pool_primal(g, random_buffers(13, 10, names=("primal",)))
    with pytest.raises(ValueError, match="spp >= 1, got 16 and 0"):
        pool_primal(g, random_buffers(names=("primal",), spp=0))


def test_pooled_render_has_independent_primal_samples(variant):
    """Across seeds, the pooled primal's variance is the gradient render's times
    ``spp / (spp + primal_spp)`` (the plain samples are independent of the base paths: with a
    shared seed stream they would repeat them and the variance would not drop)."""
    import gdpt
    from gdpt.scenes import builtin_scene

    scene = builtin_scene("cbox-demo", resolution=(16, 16))
    spp, extra, runs = 2, 6, 24
    alone, pooled = [], []
    for seed in range(runs):
        props = dict(spp=spp, seed=seed, max_depth=3, features=False)
        alone.append(gdpt.render(scene, **props).primal.clone())
        both = gdpt.render(scene, primal_spp=extra, **props)
        assert both.spp == spp and both.metadata["primal_spp"] == spp + extra
        assert both.metadata["primal_only"]["integrator"] == "gdpt"
        assert both.albedo is None
        pooled.append(both.primal.clone())
    var_alone = torch.stack(alone).var(0).mean()
    var_pooled = torch.stack(pooled).var(0).mean()
    ratio = float(var_pooled / var_alone)
    # expected spp / (spp + extra) = 0.25; a shared stream gives about 1
    assert 0.15 < ratio < 0.4, ratio


def test_pooled_features_come_from_the_plain_pass_alone(variant):
    """The gradient pass skips the features; the pooled ones are the plain pass's, equal to a
    plain render with its seed, and the gradients equal a featureless gradient render's."""
    import gdpt
    from gdpt.rendering import PRIMAL_SEED_SALT
    from gdpt.scenes import builtin_scene

    scene = builtin_scene("cbox-demo", resolution=(16, 16))
    pooled = gdpt.render(scene, spp=2, seed=5, primal_spp=3, max_depth=3)
    plain = gdpt.render(scene, spp=3, seed=5 ^ PRIMAL_SEED_SALT, max_depth=3, gradients=False)
    gradient = gdpt.render(scene, spp=2, seed=5, max_depth=3, features=False)
    for name in ("albedo", "normal", "depth"):
        assert torch.equal(getattr(pooled, name), getattr(plain, name)), name
    assert torch.equal(pooled.dx, gradient.dx) and torch.equal(pooled.dy, gradient.dy)
    torch.testing.assert_close(pooled.primal, (2 * gradient.primal + 3 * plain.primal) / 5)


def test_primal_spp_needs_gradients(variant):
    import gdpt
    from gdpt.scenes import builtin_scene

    scene = builtin_scene("cbox-demo", resolution=(8, 8))
    with pytest.raises(ValueError, match="gradients=false"):
        gdpt.render(scene, spp=1, primal_spp=2, gradients=False)
    with pytest.raises(ValueError, match="primal_spp must be >= 0"):
        gdpt.render(scene, spp=1, primal_spp=-1)


def test_methods_ask_for_the_primal_samples_of_their_card(tmp_path):
    card = {"format": "gdpt-oidn-delta/1", "sampling": {"primal_spp_factor": 2.5}}
    (tmp_path / "pooled.json").write_text(json.dumps(card))
    save_file({}, tmp_path / "pooled.safetensors")  # a readable, empty checkpoint
    network = METHODS["oidn-grad"]
    model = str(tmp_path / "pooled.safetensors")
    expected = {"gradients": True, "features": True, "primal_spp": 20}
    assert network.sampling(8, model=model) == expected
    (tmp_path / "pooled.json").write_text(json.dumps({**card, "sampling": {}}))
    assert network.sampling(8, model=model) == {"gradients": True, "features": True}
    assert METHODS["l1"].sampling(8) == {"gradients": True, "features": False}


def test_pooled_model_on_unpooled_buffers_warns(tmp_path, monkeypatch, random_buffers):
    from gdpt import checkpoints, methods

    card = {"format": "gdpt-oidn-delta/1", "sampling": {"primal_spp_factor": 2.5}}
    (tmp_path / "pooled.json").write_text(json.dumps(card))
    save_file({}, tmp_path / "pooled.safetensors")  # a readable, empty checkpoint
    monkeypatch.setattr(checkpoints, "oidn_weights_missing", lambda name, path: None)
    monkeypatch.setattr(checkpoints, "load_reconstructor", lambda path: lambda b: b.primal)
    model = str(tmp_path / "pooled.safetensors")
    buffers = random_buffers(names=("primal", "dx", "dy"))
    with pytest.warns(UserWarning, match=r"pooled.safetensors .* primal_spp=2.5 x spp"):
        methods.reconstruct_image(buffers, "oidn-grad", model=model)
    pooled = buffers.replace(metadata={"primal_spp": 40})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        methods.reconstruct_image(pooled, "oidn-grad", model=model)
