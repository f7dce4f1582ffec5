"""Tests of gdpt.reconstruct.elpips: the ensemble, the distance, backbones, weight files."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from gdpt.reconstruct import elpips as E

pytestmark = pytest.mark.usefixtures("single_thread")

#: E-LPIPS without any randomness: no dropout, no ensemble transform (plain LPIPS).
PLAIN = E.ELPIPSConfig(
    enable_dropout=False,
    enable_offset=False,
    enable_flip=False,
    enable_swap=False,
    enable_color_permutation=False,
    enable_color_multiplication=False,
    enable_scale=False,
)


def test_ensemble_sampling_is_stratified() -> None:
    gen = torch.Generator().manual_seed(0)
    config = E.ELPIPSConfig()
    sample = E.sample_ensemble(6, config, generator=gen)
    assert sorted(map(tuple, sample.permutations.tolist())) == sorted(
        [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]
    )
    sample = E.sample_ensemble(4, config, generator=gen)
    assert sorted(sample.flips.tolist()) == [0, 1, 2, 3]
    u = (sample.color_factors - 0.2) / 0.8  # stratified: one value in each [k/N, (k+1)/N)
    for channel in range(3):
        assert sorted((u[:, channel] * 4).floor().long().tolist()) == [0, 1, 2, 3]
    assert ((sample.offsets >= 0) & (sample.offsets <= 7)).all()
    scales = [
        E.sample_ensemble(1, E.ELPIPSConfig(num_scales=2), generator=gen).scale for _ in range(2000)
    ]
    assert np.mean(np.array(scales) == 1) == pytest.approx(0.8, abs=0.04)  # P(s) ~ 1/s^2
    brightness = E.sample_ensemble(3, E.ELPIPSConfig(color_multiplication_mode="brightness"))
    assert torch.equal(brightness.color_factors[:, :1].expand(3, 3), brightness.color_factors)


def test_apply_ensemble_transforms() -> None:
    x = torch.rand(4, 3, 16, 12)
    sample = E.EnsembleSample(
        scale=1,
        scale_offset=(0, 0),
        offsets=torch.tensor([[0, 0], [7, 7], [3, 2], [0, 5]]),
        flips=torch.tensor([0, 1, 2, 3]),
        swap=True,
        permutations=torch.tensor([[2, 1, 0], [0, 1, 2], [1, 2, 0], [0, 2, 1]]),
        color_factors=torch.tensor([[1.0, 0.5, 0.2]] * 4),
    )
    only = E.ELPIPSConfig(enable_offset=False, enable_scale=False)
    out = E.apply_ensemble(x, sample, only)
    expected = torch.stack([x[0].flip(-1), x[1].flip(-2), x[2].flip(-1, -2), x[3]])
    expected = expected.transpose(-1, -2)
    expected = torch.stack([e[p] for e, p in zip(expected, sample.permutations, strict=False)])
    expected = expected * torch.tensor([1.0, 0.5, 0.2]).view(1, 3, 1, 1)
    assert torch.equal(out, expected)
    offsets_only = replace(PLAIN, enable_dropout=True, enable_offset=True)
    padded = E.apply_ensemble(x, sample, offsets_only)
    assert padded.shape == (4, 3, 23, 19)
    assert torch.equal(padded[1, :, :16, :12], x[1])  # offset 7: all padding after the image
    assert torch.equal(padded[0, :, 7:, 7:], x[0])  # offset 0: all padding before
    fast = E.apply_ensemble(x, sample, replace(offsets_only, fast_and_approximate=True))
    assert fast.shape == (4, 3, 9, 5) and torch.equal(fast[2], x[2, :, 3:12, 2:7])
    scale_only = replace(offsets_only, enable_offset=False, enable_scale=True)
    scaled = E.apply_ensemble(x, replace(sample, scale=2), scale_only)
    assert scaled.shape == (4, 3, 9, 7)  # reflect-padded by one block
    assert torch.allclose(scaled[..., :8, :6], F.avg_pool2d(x, 2))
    shifted = E.apply_ensemble(x, replace(sample, scale=2, scale_offset=(1, 1)), scale_only)
    assert torch.allclose(shifted[..., 1:8, 1:6], F.avg_pool2d(x[..., 1:15, 1:11], 2))


def test_elpips_invariances_and_determinism(image_pair, tiny_elpips) -> None:
    a, b = image_pair()
    metric = tiny_elpips()
    assert torch.allclose(metric(a, a), torch.zeros(2), atol=1e-7)
    d_ab = tiny_elpips(seed=5)(a, b)
    assert (d_ab > 0).all()
    assert torch.allclose(d_ab, tiny_elpips(seed=5)(b, a), rtol=1e-5)  # same draws: symmetric
    assert torch.equal(d_ab, tiny_elpips(seed=5)(a, b))  # deterministic under a seed
    assert not torch.equal(d_ab, tiny_elpips(seed=6)(a, b))  # and actually random
    torch.manual_seed(1)
    global_rng = tiny_elpips(seed=None)(a, b)
    torch.manual_seed(1)
    assert torch.equal(global_rng, tiny_elpips(seed=None)(a, b))


def test_elpips_average_over_and_dropout(image_pair, tiny_elpips) -> None:
    a, b = image_pair()
    single = tiny_elpips(seed=3)
    mean_of_three = sum(single(a, b) for _ in range(3)) / 3
    averaged = tiny_elpips(E.ELPIPSConfig(num_scales=2, average_over=3), seed=3)(a, b)
    assert torch.allclose(averaged, mean_of_three, rtol=1e-5)
    # Without any randomness it is plain LPIPS (on the tiny net), independent of the seed.
    assert torch.equal(tiny_elpips(PLAIN, seed=1)(a, b), tiny_elpips(PLAIN, seed=2)(a, b))
    dropout_only = replace(PLAIN, enable_dropout=True, dropout_keep_prob=0.5)
    assert not torch.equal(
        tiny_elpips(dropout_only, seed=1)(a, b), tiny_elpips(dropout_only, seed=2)(a, b)
    )
    assert torch.allclose(tiny_elpips(dropout_only, seed=1)(a, a), torch.zeros(2), atol=1e-7)


def test_elpips_head_mismatch(tiny_elpips) -> None:
    with pytest.raises(ValueError, match="do not match backbone channels"):
        tiny_elpips(heads=[torch.ones(3), torch.ones(4)])


def test_elpips_missing_weights(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.delenv(E.ELPIPS_WEIGHTS_ENV, raising=False)
    with pytest.raises(E.ELPIPSWeightsError, match="GDPT_ELPIPS_WEIGHTS") as info:
        E.load_elpips_weights()
    assert "No download is attempted" in str(info.value)
    with pytest.raises(E.ELPIPSWeightsError, match="does not exist"):
        E.load_elpips_weights(tmp_path / "missing.pt")
    bad = tmp_path / "bad.npz"
    np.savez(bad, something=np.zeros(3))
    with pytest.raises(E.ELPIPSWeightsError, match="no SqueezeNet/VGG16"):
        E.load_elpips_weights(bad)


@pytest.mark.parametrize("suffix", [".pt", ".npz", ".safetensors"])
def test_elpips_loads_squeezenet_file(
    suffix: str, squeezenet_state, image_pair, tmp_path, monkeypatch
) -> None:
    state = squeezenet_state
    path = tmp_path / f"elpips_squeeze{suffix}"
    if suffix == ".pt":
        torch.save(state, path)
    elif suffix == ".npz":
        np.savez(path, **{k: v.numpy() for k, v in state.items()})
    else:
        from safetensors.torch import save_file

        save_file(state, str(path))
    monkeypatch.setenv(E.ELPIPS_WEIGHTS_ENV, str(path))
    loaded = E.load_elpips_weights(config=E.ELPIPSConfig(num_scales=1), seed=0)
    assert isinstance(loaded.backbone, E.SqueezeNetFeatures)
    for key, value in loaded.backbone.state_dict().items():
        assert torch.equal(value, state[key])
    a, b = image_pair(n=1, size=64)
    assert loaded(a, b).item() > 0 and loaded(a, a).item() == pytest.approx(0, abs=1e-7)


def test_backbones_feature_channels() -> None:
    x = torch.rand(1, 3, 48, 48)
    for net in (E.SqueezeNetFeatures(), E.VGG16Features()):
        feats = net(x, lambda t: t)
        assert tuple(f.shape[1] for f in feats) == net.channels
    assert {"features.0.weight", "features.12.expand3x3.bias"} <= set(
        E.SqueezeNetFeatures().state_dict()
    )
