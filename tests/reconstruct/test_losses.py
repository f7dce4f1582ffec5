"""Tests for gdpt.reconstruct.losses: tone mapping, NGPT L1 terms, FLIP, E-LPIPS, registry."""

from __future__ import annotations

import math
from dataclasses import replace

import colour
import flip_evaluator
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from gdpt.reconstruct import losses as L
from scipy.ndimage import gaussian_filter
from torch import nn

# ---------------------------------------------------------------------------------------------
# Fixtures and helpers
# ---------------------------------------------------------------------------------------------


@pytest.fixture(autouse=True)
def _single_thread():
    """Tiny workloads: avoid intra-op thread oversubscription on shared CPUs (restored after)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def nchw(image: np.ndarray) -> torch.Tensor:
    """HWC numpy image -> (1, 3, H, W) float32 tensor."""
    return torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]


def _base_ldr(size: int = 64) -> np.ndarray:
    yy, xx = np.mgrid[0:size, 0:size] / size
    image = np.stack(
        [0.5 + 0.4 * np.sin(6 * xx), 0.5 + 0.4 * np.cos(5 * yy), 0.3 + 0.3 * xx * yy], -1
    )
    image[20:40, 10:30] = [0.9, 0.2, 0.1]
    return image.astype(np.float32)


BASE_LDR = _base_ldr()
_RNG = np.random.default_rng(1)
BASE_HDR = (BASE_LDR**2.2 * np.exp(_RNG.normal(0.0, 0.7, (64, 64, 1)))).astype(np.float32)
BASE_HDR[5:15, 40:60] = 12.0  # a light source; 5 exposures

LDR_PAIRS = {
    "noise": np.clip(BASE_LDR + _RNG.normal(0.0, 0.05, BASE_LDR.shape), 0, 1),
    "blur": gaussian_filter(BASE_LDR, (1.5, 1.5, 0)),
    "colour_shift": np.clip(BASE_LDR * [1.1, 0.9, 1.0], 0, 1),
    "translation": np.roll(BASE_LDR, 2, 1),
}
HDR_PAIRS = {
    "noise": np.clip(BASE_HDR * (1 + _RNG.normal(0.0, 0.3, BASE_HDR.shape)), 0, None),
    "blur": gaussian_filter(BASE_HDR, (1.0, 1.0, 0)),
    "exposure": BASE_HDR * 1.3,
    "colour_shift": BASE_HDR * [1.0, 0.8, 1.2],
}


class TinyBackbone(nn.Module):
    """Small random backbone with the E-LPIPS backbone interface."""

    channels = (3, 4, 6)

    def __init__(self) -> None:
        super().__init__()
        gen = torch.Generator().manual_seed(0)
        self.conv1 = nn.Conv2d(3, 4, 3, padding=1)
        self.conv2 = nn.Conv2d(4, 6, 3, stride=2, padding=1)
        for p in self.parameters():
            p.data = torch.randn(p.shape, generator=gen) * 0.5

    def forward(self, x: torch.Tensor, drop: L.Dropout) -> list[torch.Tensor]:
        h1 = F.relu(self.conv1(drop(x)))
        return [x, h1, F.relu(self.conv2(drop(h1)))]


def tiny_elpips(config: L.ELPIPSConfig | None = None, seed: int | None = 0) -> L.ELPIPS:
    heads = [torch.rand(c, generator=torch.Generator().manual_seed(c)) for c in (3, 4, 6)]
    return L.ELPIPS(TinyBackbone(), heads, config or L.ELPIPSConfig(num_scales=2), seed=seed)


def random_images(n: int = 2, size: int = 32, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    a = torch.rand(n, 3, size, size, generator=gen)
    return a, (a + 0.2 * torch.rand(n, 3, size, size, generator=gen)).clamp(0, 1)


# ---------------------------------------------------------------------------------------------
# Tone mapping, sRGB, forward differences
# ---------------------------------------------------------------------------------------------


def test_srgb_matches_colour_science() -> None:
    x = np.concatenate([np.linspace(-0.1, 2.0, 1001), [0.0031308, 0.04045, 1.0]])
    encoded = L.srgb_encode(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(encoded, colour.cctf_encoding(x, function="sRGB"), atol=1e-12)
    y = np.linspace(-0.1, 1.5, 1001)
    decoded = L.srgb_decode(torch.from_numpy(y)).numpy()
    np.testing.assert_allclose(decoded, colour.cctf_decoding(y, function="sRGB"), atol=1e-12)
    np.testing.assert_allclose(
        L.srgb_decode(L.srgb_encode(torch.from_numpy(x))).numpy(), x, atol=1e-12
    )


def test_srgb_and_reinhard_gradcheck() -> None:
    x = torch.linspace(-0.5, 2.0, 24, dtype=torch.float64).view(2, 3, 2, 2).requires_grad_()
    assert torch.autograd.gradcheck(L.srgb_encode, (x,))
    assert torch.autograd.gradcheck(L.srgb_decode, (x,))
    assert torch.autograd.gradcheck(L.reinhard, (x,))
    zero = torch.zeros(3, requires_grad=True)
    L.srgb_encode(zero).sum().backward()
    assert torch.isfinite(zero.grad).all()


def test_reinhard_values_oddness_and_layouts() -> None:
    x = torch.tensor([1.0, 1.0, 1.0]).view(1, 3, 1, 1)
    assert torch.allclose(L.reinhard(x), torch.full_like(x, 0.5))
    x = torch.tensor([3.0, -1.0, 2.0]).view(1, 3, 1, 1)  # mean |x| = 2
    assert torch.allclose(L.reinhard(x), x / 3.0)
    assert torch.equal(L.reinhard(-x), -L.reinhard(x))
    hwc = torch.randn(4, 5, 3)
    assert torch.allclose(
        L.reinhard(hwc, channel_dim=-1), L.reinhard(hwc.permute(2, 0, 1)).permute(1, 2, 0)
    )


def test_forward_differences_convention() -> None:
    image = torch.arange(12.0).view(1, 1, 3, 4)  # I[y, x] = 4y + x
    dx, dy = L.forward_differences(image)
    assert torch.equal(dx[..., :, :3], torch.ones(1, 1, 3, 3))
    assert torch.equal(dx[..., :, 3], torch.zeros(1, 1, 3))
    assert torch.equal(dy[..., :2, :], torch.full((1, 1, 2, 4), 4.0))
    assert torch.equal(dy[..., 2, :], torch.zeros(1, 1, 4))


# ---------------------------------------------------------------------------------------------
# NGPT L1 terms and combined losses
# ---------------------------------------------------------------------------------------------


def test_l1_terms_known_values() -> None:
    zeros, ones = torch.zeros(2, 3, 4, 4), torch.ones(2, 3, 4, 4)
    assert L.l1_tonemapped(zeros, ones).item() == pytest.approx(0.5)
    assert L.gradient_l1_tonemapped(zeros, 5 * ones).item() == 0.0  # constant: no gradients
    # Horizontal ramp I = x: dx = 1 except the zero last column, R(1) = 0.5, dy = 0.
    ramp = torch.arange(4.0).expand(1, 3, 4, 4)
    assert L.gradient_l1_tonemapped(ramp, zeros[:1]).item() == pytest.approx(0.5 * 3 / 4)
    # log1p does not saturate: 1e4 vs 1e2 differs by log(10001/101), Reinhard by < 0.01
    big, small = torch.full((1, 3, 2, 2), 1e4), torch.full((1, 3, 2, 2), 1e2)
    assert L.l1_log(big, small).item() == pytest.approx(math.log(10001 / 101), rel=1e-5)
    assert L.l1_tonemapped(big, small).item() < 0.01
    assert L.l1_log(zeros, ones).item() == pytest.approx(math.log(2.0))
    # relative L1 divides by eps + the reference's channel mean, per pixel
    dark = torch.tensor([0.01, 0.02, 0.03]).view(1, 3, 1, 1).expand(1, 3, 2, 2)
    assert L.l1_relative(dark * 2, dark).item() == pytest.approx(0.02 / 0.03, rel=1e-5)
    assert L.l1_relative(big, small).item() == pytest.approx(9900 / 100.01, rel=1e-5)


def test_l1_terms_gradcheck() -> None:
    gen = torch.Generator().manual_seed(0)
    pred = torch.rand(1, 3, 4, 5, generator=gen, dtype=torch.float64).requires_grad_()
    target = torch.rand(1, 3, 4, 5, generator=gen, dtype=torch.float64) + 0.1
    assert torch.autograd.gradcheck(lambda p: L.l1_tonemapped(p, target), (pred,))
    assert torch.autograd.gradcheck(lambda p: L.gradient_l1_tonemapped(p, target), (pred,))
    assert torch.autograd.gradcheck(lambda p: L.l1_log(p, target), (pred,))
    assert torch.autograd.gradcheck(lambda p: L.l1_relative(p, target), (pred,))


def test_l1_terms_shape_errors() -> None:
    with pytest.raises(ValueError, match=r"pred \(1, 3, 4, 4\) and target \(1, 3, 4, 5\)"):
        L.l1_tonemapped(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 5))
    with pytest.raises(ValueError, match="N, 3, H, W"):
        L.gradient_l1_tonemapped(torch.zeros(3, 4, 4), torch.zeros(3, 4, 4))


def test_registry_weights_and_errors() -> None:
    pred, target = random_images(size=16)
    l1 = L.get_loss("l1")
    expected = L.l1_tonemapped(pred, target) + 0.01 * L.gradient_l1_tonemapped(pred, target)
    assert torch.allclose(l1(pred, target), expected)
    flip = L.get_loss("flip")
    expected = (
        L.ldr_flip(L.reinhard(pred), L.reinhard(target), inputs_srgb=False)
        + 0.01 * L.l1_tonemapped(pred, target)
        + 0.01 * L.gradient_l1_tonemapped(pred, target)
    )
    assert torch.allclose(flip(pred, target), expected)
    flip_log = L.get_loss("flip_log")
    assert torch.allclose(flip_log(pred, target), expected + 0.1 * L.l1_log(pred, target))
    flip_rel = L.get_loss("flip_rel")
    assert torch.allclose(flip_rel(pred, target), expected + L.l1_relative(pred, target))
    with pytest.raises(
        KeyError, match="valid names: flip, flip_hdr, flip_log, flip_rel, elpips, l1"
    ):
        L.get_loss("lpips")


def test_flip_losses_gradient_flow() -> None:
    pred, target = random_images(size=24)
    pred = (4 * pred - 0.5).requires_grad_()  # HDR with some negative values
    for name in ("flip", "flip_hdr"):
        pred.grad = None
        loss = L.get_loss(name)(pred, 4 * target)
        loss.backward()
        assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0, name


# ---------------------------------------------------------------------------------------------
# FLIP against flip_evaluator
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(LDR_PAIRS))
def test_ldr_flip_matches_flip_evaluator(name: str) -> None:
    test = LDR_PAIRS[name].astype(np.float32)
    error_map, mean, _ = flip_evaluator.evaluate(BASE_LDR, test, "LDR", applyMagma=False)
    ours = L.ldr_flip(nchw(test), nchw(BASE_LDR), reduction="none")[0].numpy()
    assert ours.mean() == pytest.approx(mean, rel=0.01)
    assert np.abs(ours - error_map[..., 0]).max() < 1e-3


def test_ldr_flip_linear_inputs_and_batching() -> None:
    test = LDR_PAIRS["noise"].astype(np.float32)
    _, mean, _ = flip_evaluator.evaluate(BASE_LDR, test, "LDR", inputsRGB=False, applyMagma=False)
    ours = L.ldr_flip(nchw(test), nchw(BASE_LDR), inputs_srgb=False)
    assert ours.item() == pytest.approx(mean, rel=0.01)
    batch = L.ldr_flip(
        torch.cat([nchw(test), nchw(BASE_LDR)]),
        torch.cat([nchw(BASE_LDR), nchw(BASE_LDR)]),
        reduction="none",
    )
    assert batch[1].abs().max() == 0.0  # identical images
    assert torch.allclose(batch[0], L.ldr_flip(nchw(test), nchw(BASE_LDR), reduction="none")[0])


@pytest.mark.parametrize("name", sorted(HDR_PAIRS))
def test_hdr_flip_matches_flip_evaluator(name: str) -> None:
    test = HDR_PAIRS[name].astype(np.float32)
    error_map, mean, params = flip_evaluator.evaluate(BASE_HDR, test, "HDR", applyMagma=False)
    ours = L.hdr_flip(nchw(test), nchw(BASE_HDR), reduction="none")[0].numpy()
    assert ours.mean() == pytest.approx(mean, rel=0.01)
    assert np.abs(ours - error_map[..., 0]).max() < 1e-3
    start, stop = L.flip_exposures(nchw(BASE_HDR))
    assert start.item() == pytest.approx(params["startExposure"], abs=1e-5)
    assert stop.item() == pytest.approx(params["stopExposure"], abs=1e-5)


@pytest.mark.parametrize("tonemapper", ["reinhard", "hable"])
def test_hdr_flip_other_tonemappers_and_explicit_exposures(tonemapper: str) -> None:
    # flip_evaluator compares names case-sensitively: "Reinhard" silently falls back to ACES.
    test = HDR_PAIRS["noise"].astype(np.float32)
    params = {
        "tonemapper": tonemapper,
        "startExposure": -2.0,
        "stopExposure": 1.0,
        "numExposures": 3,
    }
    _, mean, _ = flip_evaluator.evaluate(BASE_HDR, test, "HDR", applyMagma=False, parameters=params)
    ours = L.hdr_flip(
        nchw(test),
        nchw(BASE_HDR),
        tonemapper=tonemapper,
        start_exposure=-2.0,
        stop_exposure=1.0,
        num_exposures=3,
    )
    assert ours.item() == pytest.approx(mean, rel=0.01)


def test_hdr_flip_batch_and_median_zero() -> None:
    dark = BASE_HDR[:32, :32].copy()
    dark[:20] = 0.0  # median luminance 0: FLIP clamps it to FLT_EPSILON (many exposures)
    test = np.clip(dark + _RNG.normal(0, 0.3, dark.shape), 0, None).astype(np.float32)
    _, mean_dark, params = flip_evaluator.evaluate(dark, test, "HDR", applyMagma=False)
    assert params["numExposures"] > 20
    noisy = HDR_PAIRS["noise"][:32, :32].astype(np.float32)
    _, mean_noise, _ = flip_evaluator.evaluate(BASE_HDR[:32, :32], noisy, "HDR", applyMagma=False)
    ours = L.hdr_flip(
        torch.cat([nchw(test), nchw(noisy)]),
        torch.cat([nchw(dark), nchw(BASE_HDR[:32, :32])]),
        reduction="none",
    ).mean((1, 2))
    assert ours[0].item() == pytest.approx(mean_dark, rel=0.01)
    assert ours[1].item() == pytest.approx(mean_noise, rel=0.01)
    black = torch.zeros(1, 3, 8, 8)  # the tool aborts here; we return a finite value
    assert torch.isfinite(L.hdr_flip(black + 0.1, black))


def test_flip_argument_errors() -> None:
    image = torch.rand(1, 3, 8, 8)
    with pytest.raises(ValueError, match="unknown tone mapper"):
        L.hdr_flip(image, image, tonemapper="filmic")
    with pytest.raises(ValueError, match="start exposure"):
        L.hdr_flip(image, image, start_exposure=3.0, stop_exposure=1.0)
    with pytest.raises(ValueError, match="reduction"):
        L.ldr_flip(image, image, reduction="sum")
    with pytest.raises(ValueError, match="mode"):
        L.FLIPLoss("sdr")


def test_ldr_flip_gradcheck() -> None:
    gen = torch.Generator().manual_seed(3)
    ref = 0.2 + 0.6 * torch.rand(1, 3, 6, 6, generator=gen, dtype=torch.float64)
    test = ref + 0.1 * torch.randn(1, 3, 6, 6, generator=gen, dtype=torch.float64)
    test = test.clamp(0.05, 0.95).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda t: L.ldr_flip(t, ref, inputs_srgb=False), (test,), atol=1e-5
    )


# ---------------------------------------------------------------------------------------------
# E-LPIPS
# ---------------------------------------------------------------------------------------------


def test_ensemble_sampling_is_stratified() -> None:
    gen = torch.Generator().manual_seed(0)
    config = L.ELPIPSConfig()
    sample = L.sample_ensemble(6, config, generator=gen)
    assert sorted(map(tuple, sample.permutations.tolist())) == sorted(
        [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]
    )
    sample = L.sample_ensemble(4, config, generator=gen)
    assert sorted(sample.flips.tolist()) == [0, 1, 2, 3]
    u = (sample.color_factors - 0.2) / 0.8  # stratified: one value in each [k/N, (k+1)/N)
    for channel in range(3):
        assert sorted((u[:, channel] * 4).floor().long().tolist()) == [0, 1, 2, 3]
    assert ((sample.offsets >= 0) & (sample.offsets <= 7)).all()
    scales = [
        L.sample_ensemble(1, L.ELPIPSConfig(num_scales=2), generator=gen).scale for _ in range(2000)
    ]
    assert np.mean(np.array(scales) == 1) == pytest.approx(0.8, abs=0.04)  # P(s) ~ 1/s^2
    brightness = L.sample_ensemble(3, L.ELPIPSConfig(color_multiplication_mode="brightness"))
    assert torch.equal(brightness.color_factors[:, :1].expand(3, 3), brightness.color_factors)


def test_apply_ensemble_transforms() -> None:
    x = torch.rand(4, 3, 16, 12)
    sample = L.EnsembleSample(
        scale=1,
        scale_offset=(0, 0),
        offsets=torch.tensor([[0, 0], [7, 7], [3, 2], [0, 5]]),
        flips=torch.tensor([0, 1, 2, 3]),
        swap=True,
        permutations=torch.tensor([[2, 1, 0], [0, 1, 2], [1, 2, 0], [0, 2, 1]]),
        color_factors=torch.tensor([[1.0, 0.5, 0.2]] * 4),
    )
    only = L.ELPIPSConfig(enable_offset=False, enable_scale=False)
    out = L.apply_ensemble(x, sample, only)
    expected = torch.stack([x[0].flip(-1), x[1].flip(-2), x[2].flip(-1, -2), x[3]])
    expected = expected.transpose(-1, -2)
    expected = torch.stack([e[p] for e, p in zip(expected, sample.permutations, strict=False)])
    expected = expected * torch.tensor([1.0, 0.5, 0.2]).view(1, 3, 1, 1)
    assert torch.equal(out, expected)
    offsets_only = L.ELPIPSConfig(
        enable_flip=False,
        enable_swap=False,
        enable_scale=False,
        enable_color_permutation=False,
        enable_color_multiplication=False,
    )
    padded = L.apply_ensemble(x, sample, offsets_only)
    assert padded.shape == (4, 3, 23, 19)
    assert torch.equal(padded[1, :, :16, :12], x[1])  # offset 7: all padding after the image
    assert torch.equal(padded[0, :, 7:, 7:], x[0])  # offset 0: all padding before
    fast = L.apply_ensemble(x, sample, replace(offsets_only, fast_and_approximate=True))
    assert fast.shape == (4, 3, 9, 5) and torch.equal(fast[2], x[2, :, 3:12, 2:7])
    scale_only = replace(offsets_only, enable_offset=False, enable_scale=True)
    scaled = L.apply_ensemble(x, replace(sample, scale=2), scale_only)
    assert scaled.shape == (4, 3, 9, 7)  # reflect-padded by one block
    assert torch.allclose(scaled[..., :8, :6], F.avg_pool2d(x, 2))
    shifted = L.apply_ensemble(x, replace(sample, scale=2, scale_offset=(1, 1)), scale_only)
    assert torch.allclose(shifted[..., 1:8, 1:6], F.avg_pool2d(x[..., 1:15, 1:11], 2))


def test_elpips_invariances_and_determinism() -> None:
    a, b = random_images()
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


def test_elpips_average_over_and_dropout() -> None:
    a, b = random_images()
    single = tiny_elpips(seed=3)
    mean_of_three = sum(single(a, b) for _ in range(3)) / 3
    averaged = tiny_elpips(L.ELPIPSConfig(num_scales=2, average_over=3), seed=3)(a, b)
    assert torch.allclose(averaged, mean_of_three, rtol=1e-5)
    # Without any randomness it is plain LPIPS (on the tiny net), independent of the seed.
    plain = L.ELPIPSConfig(
        enable_dropout=False,
        enable_offset=False,
        enable_flip=False,
        enable_swap=False,
        enable_color_permutation=False,
        enable_color_multiplication=False,
        enable_scale=False,
    )
    assert torch.equal(tiny_elpips(plain, seed=1)(a, b), tiny_elpips(plain, seed=2)(a, b))
    dropout_only = replace(plain, enable_dropout=True, dropout_keep_prob=0.5)
    assert not torch.equal(
        tiny_elpips(dropout_only, seed=1)(a, b), tiny_elpips(dropout_only, seed=2)(a, b)
    )
    assert torch.allclose(tiny_elpips(dropout_only, seed=1)(a, a), torch.zeros(2), atol=1e-7)


def test_elpips_gradient_flow() -> None:
    a, b = random_images()
    a = a.requires_grad_()
    loss = L.NGPTLoss(L.ELPIPSLoss(tiny_elpips(L.ELPIPSConfig.ngpt_training())))
    loss(4 * a, 4 * b).backward()
    assert torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0
    assert all(p.grad is None for p in loss.parameters())  # the backbone is frozen


def test_elpips_head_mismatch() -> None:
    with pytest.raises(ValueError, match="do not match backbone channels"):
        L.ELPIPS(TinyBackbone(), [torch.ones(3), torch.ones(4)])


def test_elpips_missing_weights(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.delenv(L.ELPIPS_WEIGHTS_ENV, raising=False)
    with pytest.raises(L.ELPIPSWeightsError, match="GDPT_ELPIPS_WEIGHTS") as info:
        L.load_elpips_weights()
    assert "No download is attempted" in str(info.value)
    with pytest.raises(L.ELPIPSWeightsError, match="does not exist"):
        L.get_loss("elpips", weights=tmp_path / "missing.pt")
    bad = tmp_path / "bad.npz"
    np.savez(bad, something=np.zeros(3))
    with pytest.raises(L.ELPIPSWeightsError, match="no SqueezeNet/VGG16"):
        L.load_elpips_weights(bad)


def _squeeze_state() -> dict[str, torch.Tensor]:
    torch.manual_seed(0)
    state = dict(L.SqueezeNetFeatures().state_dict())
    for i, c in enumerate(L.SqueezeNetFeatures.channels):
        state[f"lin{i}.model.1.weight"] = torch.rand(1, c, 1, 1)
    return state


@pytest.mark.parametrize("suffix", [".pt", ".npz", ".safetensors"])
def test_elpips_loads_squeezenet_file(suffix: str, tmp_path, monkeypatch) -> None:
    state = _squeeze_state()
    path = tmp_path / f"elpips_squeeze{suffix}"
    if suffix == ".pt":
        torch.save(state, path)
    elif suffix == ".npz":
        np.savez(path, **{k: v.numpy() for k, v in state.items()})
    else:
        from safetensors.torch import save_file

        save_file(state, str(path))
    monkeypatch.setenv(L.ELPIPS_WEIGHTS_ENV, str(path))
    loaded = L.load_elpips_weights(config=L.ELPIPSConfig(num_scales=1), seed=0)
    assert isinstance(loaded.backbone, L.SqueezeNetFeatures)
    for key, value in loaded.backbone.state_dict().items():
        assert torch.equal(value, state[key])
    a, b = random_images(n=1, size=64)
    assert loaded(a, b).item() > 0 and loaded(a, a).item() == pytest.approx(0, abs=1e-7)
    training = L.get_loss("elpips", seed=0)  # weights from the environment variable
    assert torch.isfinite(training(*random_images(n=1, size=96)))


def test_backbones_feature_channels() -> None:
    x = torch.rand(1, 3, 48, 48)
    for net in (L.SqueezeNetFeatures(), L.VGG16Features()):
        feats = net(x, lambda t: t)
        assert tuple(f.shape[1] for f in feats) == net.channels
    assert {"features.0.weight", "features.12.expand3x3.bias"} <= set(
        L.SqueezeNetFeatures().state_dict()
    )
