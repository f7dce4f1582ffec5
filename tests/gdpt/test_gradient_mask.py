"""``gdpt.render(..., gradient_mask=M)``: offsets only where the mask is set, on a compacted
wavefront; untraced gradients marked (``buffers.gradient_mask``, infinite variance, 0); the
border rule (a gradient is traced iff both of its pixels are masked); full and empty masks."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import torch

from gdpt.buffers import merge_renders, pool_primal
from gdpt.rendering import make_integrator, render, shared_integrator

SIZE = 16
PROPS = dict(max_depth=3, variance=True, halves=True)


@pytest.fixture(scope="module")
def scene(variant):
    from gdpt.scenes import builtin_scene
    from gdpt.scenes.loading import load_scene

    return load_scene(builtin_scene("cbox-demo", resolution=(SIZE, SIZE)))


def _mask() -> np.ndarray:
    """A block, a one-pixel-wide column and isolated pixels (every border case)."""
    mask = np.zeros((SIZE, SIZE), dtype=bool)
    mask[3:9, 4:12] = True
    mask[:, 14] = True
    mask[12, 1] = mask[13, 2] = True
    return mask


def _digests(buffers) -> dict[str, str]:
    return {
        n: hashlib.sha256(t.contiguous().cpu().numpy().tobytes()).hexdigest()
        for n, t in buffers.items()
    }


def _expected_traced(mask: np.ndarray) -> np.ndarray:
    """The border rule, pixel by pixel: dx at (y, x) iff (y, x) and (y, x + 1) are masked."""
    h, w = mask.shape
    out = np.zeros((h, w, 2), dtype=bool)
    for y in range(h):
        for x in range(w):
            out[y, x, 0] = x + 1 < w and mask[y, x] and mask[y, x + 1]
            out[y, x, 1] = y + 1 < h and mask[y, x] and mask[y + 1, x]
    return out


def test_full_mask_renders_exactly_the_render_without_one(scene):
    plain = _digests(render(scene, spp=4, seed=5, **PROPS))
    full = render(
        scene, spp=4, seed=5, gradient_mask=torch.ones(SIZE, SIZE, dtype=torch.bool), **PROPS
    )
    assert _digests(full) == plain
    assert full.gradient_mask is None
    assert full.metadata["gradient_mask"] == {"share": 1.0}


def test_empty_mask_is_a_plain_render_with_the_reason(scene):
    empty = render(scene, spp=4, seed=5, gradient_mask=np.zeros((SIZE, SIZE), bool), **PROPS)
    plain = render(scene, spp=4, seed=5, **{**PROPS, "gradients": False})
    assert not empty.has_gradients and empty.gradient_mask is None
    assert _digests(empty) == _digests(plain)
    assert empty.metadata["gradient_mask"]["share"] == 0.0
    assert "empty" in empty.metadata["gradient_mask"]["reason"]


@pytest.mark.parametrize(
    ("mask", "props", "message"),
    [
        (np.ones((SIZE, SIZE + 1), bool), {}, r"shape \(H, W\) = \(16, 16\).*got shape \(16, 17\)"),
        (torch.ones(SIZE, SIZE), {}, r"\(H, W\) = \(16, 16\).*torch.float32"),
        (np.ones((SIZE, SIZE), np.uint8), {}, r"\(H, W\) = \(16, 16\).*uint8"),
        ([[True] * SIZE] * SIZE, {}, r"\(H, W\) = \(16, 16\).*list"),
        (np.ones((SIZE, SIZE), bool), {"gradients": False}, r"\(16, 16\).*gradients=false"),
    ],
)
def test_bad_masks_are_refused_before_rendering(scene, monkeypatch, mask, props, message):
    import gdpt.rendering

    def no_render(*args, **kwargs):
        raise AssertionError("rendered before the mask was checked")

    monkeypatch.setattr(gdpt.rendering, "_render_one", no_render)
    with pytest.raises(ValueError, match=message):
        render(scene, spp=1, gradient_mask=mask, **props)


def test_untraced_gradients_are_marked_by_the_border_rule(scene):
    mask = _mask()
    buffers = render(scene, spp=4, seed=2, gradient_mask=torch.from_numpy(mask), **PROPS)
    traced = _expected_traced(mask)
    assert torch.equal(buffers.gradient_mask, torch.from_numpy(traced))
    assert buffers.metadata["gradient_mask"] == {"share": float(mask.mean())}
    inner = np.ones((SIZE, SIZE, 2), dtype=bool)  # gradients that exist (not the last col/row)
    inner[:, -1, 0] = inner[-1, :, 1] = False
    for k, axis in enumerate(("dx", "dy")):
        untraced = torch.from_numpy(~traced[..., k])
        for name in (axis, f"{axis}_a", f"{axis}_b"):
            assert (getattr(buffers, name)[untraced] == 0).all(), name
        var = getattr(buffers, f"var_{axis}")[..., 0]
        assert torch.isinf(var[torch.from_numpy(~traced[..., k] & inner[..., k])]).all()
        assert torch.isfinite(var[torch.from_numpy(traced[..., k])]).all()
        assert (getattr(buffers, axis)[torch.from_numpy(traced[..., k])] != 0).any()
    for name in ("primal", "albedo", "normal", "depth", "var_primal", "primal_a", "primal_b"):
        assert torch.isfinite(getattr(buffers, name)).all(), name
    assert (buffers.normal.abs().sum(-1) > 0).all()  # features at every pixel


def test_offsets_are_traced_on_a_compacted_wavefront(scene):
    """The masked pixels' samples run the path loop with the four offsets on a wavefront of
    their own; the other pixels' samples without offsets on another; each padded to a multiple
    of 1/16 of the film's pixels."""
    integrator = make_integrator("gdpt", freeze=False, **PROPS)
    launches = []
    trace = integrator.sample_paths

    def recorded(scene, sensor, sampler, rays, weights, active):
        import drjit as dr

        launches.append((len(rays), dr.width(rays[0].d)))
        return trace(scene, sensor, sampler, rays, weights, active)

    integrator.sample_paths = recorded
    mask = _mask()
    render(scene, spp=4, seed=1, integrator=integrator, gradient_mask=mask)  # one pass
    n = int(mask.sum())
    padded = lambda k: -(-k // 16) * 16  # noqa: E731
    assert n % 16 and padded(n) < SIZE * SIZE  # (the mask needs padding)
    assert sorted(launches) == [(1, padded(SIZE * SIZE - n) * 4), (5, padded(n) * 4)]


def test_masked_renders_replay_their_recording(scene):
    """A second render with a mask of the same pixel count, or of another count in the same
    1/16 of the film (the wavefronts' padded size), replays the first's recording and equals
    tracing without ``dr.freeze``; a count in another 1/16 records anew."""
    props = dict(max_depth=3, features=False)
    render(scene, spp=2, seed=3, gradient_mask=_mask(), **props)
    integrator = shared_integrator(scene, "gdpt", **props)
    recordings = integrator._frozen_pass.n_recordings
    moved = np.roll(_mask(), 1, axis=0)  # same count, other pixels
    replayed = render(scene, spp=2, seed=4, gradient_mask=moved, **props)
    assert integrator._frozen_pass.n_recordings == recordings
    traced = render(
        scene,
        spp=2,
        seed=4,
        gradient_mask=moved,
        integrator=make_integrator("gdpt", freeze=False, **props),
    )
    assert _digests(replayed) == _digests(traced)
    assert torch.equal(replayed.gradient_mask, traced.gradient_mask)
    other = _mask()
    other[0, 0] = True  # 67 pixels: padded to 80 as 66 (the rest: 189 and 190 to 192)
    render(scene, spp=2, seed=4, gradient_mask=other, **props)
    assert integrator._frozen_pass.n_recordings == recordings
    other[15] = True  # 82 pixels: padded to 96
    render(scene, spp=2, seed=4, gradient_mask=other, **props)
    assert integrator._frozen_pass.n_recordings > recordings


def test_the_mask_follows_pooling_merging_and_cropping(scene):
    mask = torch.from_numpy(_mask())
    pooled = render(scene, spp=2, seed=1, primal_spp=2, gradient_mask=mask, **PROPS)
    expected = torch.from_numpy(_expected_traced(_mask()))
    assert torch.equal(pooled.gradient_mask, expected)
    assert pooled.metadata["primal_spp"] == 4
    again = render(scene, spp=2, seed=2, gradient_mask=mask, **PROPS)
    assert torch.equal(merge_renders([pooled, again]).gradient_mask, expected)
    with pytest.raises(ValueError, match="different sample counts"):  # masked and unmasked
        merge_renders([again, render(scene, spp=2, seed=3, **PROPS)])
    crop = again.centre_crop(8)
    assert crop.gradient_mask.shape == (8, 8, 2)
    assert not crop.gradient_mask[:, -1, 0].any() and not crop.gradient_mask[-1, :, 1].any()
    assert torch.equal(crop.gradient_mask[:-1, :-1], expected[4:11, 4:11])
    assert torch.equal(again.to("cpu").gradient_mask, again.gradient_mask)
    plain = render(scene, spp=2, seed=4, **{**PROPS, "gradients": False})
    assert torch.equal(pool_primal(again, plain).gradient_mask, again.gradient_mask)


def test_a_gradient_mask_must_match_the_buffers(random_buffers):
    buffers = random_buffers(4, 5)
    with pytest.raises(ValueError, match=r"\(H, W, 2\) = \(4, 5, 2\)"):
        buffers.replace(gradient_mask=torch.ones(4, 5, 1, dtype=torch.bool))
    with pytest.raises(TypeError, match=r"\(H, W, 2\) = \(4, 5, 2\)"):
        buffers.replace(gradient_mask=torch.ones(4, 5, 2))
