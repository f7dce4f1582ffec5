"""Tests of gdpt.reconstruct.flip: LDR- and HDR-FLIP against NVIDIA's ``flip_evaluator``."""

from __future__ import annotations

import flip_evaluator
import numpy as np
import pytest
import torch
from gdpt.reconstruct.flip import flip_exposures, hdr_flip, ldr_flip
from scipy.ndimage import gaussian_filter

pytestmark = pytest.mark.usefixtures("single_thread")


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


def assert_matches_flip_evaluator(mode: str, name: str) -> dict:
    """Our ``mode`` FLIP map of pair ``name`` against flip_evaluator's: mean within 1 %, every
    pixel within 1e-3. Returns flip_evaluator's parameters."""
    reference, pairs, flip = {
        "LDR": (BASE_LDR, LDR_PAIRS, ldr_flip),
        "HDR": (BASE_HDR, HDR_PAIRS, hdr_flip),
    }[mode]
    test = pairs[name].astype(np.float32)
    error_map, mean, params = flip_evaluator.evaluate(reference, test, mode, applyMagma=False)
    ours = flip(nchw(test), nchw(reference), reduction="none")[0].numpy()
    assert ours.mean() == pytest.approx(mean, rel=0.01)
    assert np.abs(ours - error_map[..., 0]).max() < 1e-3
    return params


@pytest.mark.parametrize("name", sorted(LDR_PAIRS))
def test_ldr_flip_matches_flip_evaluator(name: str) -> None:
    assert_matches_flip_evaluator("LDR", name)


def test_ldr_flip_linear_inputs_and_batching() -> None:
    test = LDR_PAIRS["noise"].astype(np.float32)
    _, mean, _ = flip_evaluator.evaluate(BASE_LDR, test, "LDR", inputsRGB=False, applyMagma=False)
    ours = ldr_flip(nchw(test), nchw(BASE_LDR), inputs_srgb=False)
    assert ours.item() == pytest.approx(mean, rel=0.01)
    batch = ldr_flip(
        torch.cat([nchw(test), nchw(BASE_LDR)]),
        torch.cat([nchw(BASE_LDR), nchw(BASE_LDR)]),
        reduction="none",
    )
    assert batch[1].abs().max() == 0.0  # identical images
    assert torch.allclose(batch[0], ldr_flip(nchw(test), nchw(BASE_LDR), reduction="none")[0])


@pytest.mark.parametrize("name", sorted(HDR_PAIRS))
def test_hdr_flip_matches_flip_evaluator(name: str) -> None:
    params = assert_matches_flip_evaluator("HDR", name)
    start, stop = flip_exposures(nchw(BASE_HDR))
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
    ours = hdr_flip(
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
    ours = hdr_flip(
        torch.cat([nchw(test), nchw(noisy)]),
        torch.cat([nchw(dark), nchw(BASE_HDR[:32, :32])]),
        reduction="none",
    ).mean((1, 2))
    assert ours[0].item() == pytest.approx(mean_dark, rel=0.01)
    assert ours[1].item() == pytest.approx(mean_noise, rel=0.01)
    black = torch.zeros(1, 3, 8, 8)  # the tool aborts here; we return a finite value
    assert torch.isfinite(hdr_flip(black + 0.1, black))


def test_flip_argument_errors() -> None:
    image = torch.rand(1, 3, 8, 8)
    with pytest.raises(ValueError, match="unknown tone mapper"):
        hdr_flip(image, image, tonemapper="filmic")
    with pytest.raises(ValueError, match="start exposure"):
        hdr_flip(image, image, start_exposure=3.0, stop_exposure=1.0)
    with pytest.raises(ValueError, match="reduction"):
        ldr_flip(image, image, reduction="sum")


def test_ldr_flip_gradcheck() -> None:
    gen = torch.Generator().manual_seed(3)
    ref = 0.2 + 0.6 * torch.rand(1, 3, 6, 6, generator=gen, dtype=torch.float64)
    test = ref + 0.1 * torch.randn(1, 3, 6, 6, generator=gen, dtype=torch.float64)
    test = test.clamp(0.05, 0.95).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda t: ldr_flip(t, ref, inputs_srgb=False), (test,), atol=1e-5
    )
