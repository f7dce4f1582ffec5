"""Tests for gdpt.metrics: hand-computed values, FLIP wrappers, registry and skipping."""

from __future__ import annotations

import sys

import flip_evaluator
import numpy as np
import pytest
import torch
from gdpt.reconstruct import elpips as E
from gdpt.reconstruct.flip import hdr_flip
from gdpt.reconstruct.registry import Registry
from scipy.ndimage import gaussian_filter

from gdpt import metrics as M

pytestmark = pytest.mark.usefixtures("single_thread")


def const(*rgb: float, size: int = 16) -> np.ndarray:
    return np.broadcast_to(np.asarray(rgb, np.float32), (size, size, 3)).copy()


def hdr_pair(size: int = 48, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    ref = (rng.random((size, size, 3)) ** 2 * 4).astype(np.float32)
    ref = gaussian_filter(ref, (1.5, 1.5, 0))
    test = np.clip(ref * (1 + 0.3 * rng.normal(size=ref.shape)), 0, None)
    return test.astype(np.float32), ref


def display(image: np.ndarray) -> np.ndarray:
    """Reference display transform: sRGB(clamp(x / (1 + mean_c |x|), 0, 1))."""
    tonemapped = np.clip(image / (1 + np.abs(image).mean(-1, keepdims=True)), 0, 1)
    return np.where(
        tonemapped <= 0.0031308, 12.92 * tonemapped, 1.055 * tonemapped ** (1 / 2.4) - 0.055
    )


# ---------------------------------------------------------------------------------------------
# Values on known inputs
# ---------------------------------------------------------------------------------------------


def test_pointwise_metrics_on_constant_images() -> None:
    ref, test = const(1.0, 2.0, 3.0), const(2.0, 3.0, 4.0)  # shifted by 1; mean_c(ref) = 2
    assert M.mse(test, ref) == pytest.approx(1.0)
    assert M.relmse(test, ref) == pytest.approx(1.0 / (1e-3 + 4.0))
    assert M.relmse(test, ref, eps=0.0) == pytest.approx(0.25)
    # Error in one channel only: the greyscale denominator is shared by all channels.
    assert M.relmse(const(2.0, 2.0, 3.0), ref) == pytest.approx(1.0 / 3.0 / (1e-3 + 4.0))
    expected = np.mean([1 / (3 + 0.01), 1 / (5 + 0.01), 1 / (7 + 0.01)])
    assert M.smape(test, ref) == pytest.approx(expected)
    assert M.smape(ref, ref) == 0.0 and M.mse(ref, ref) == 0.0 and M.relmse(ref, ref) == 0.0


def test_relmse_per_pixel_denominator() -> None:
    ref = np.concatenate([const(1.0, 1.0, 1.0, size=4), const(3.0, 3.0, 3.0, size=4)], 0)
    test = ref + 1.0
    by_hand = np.mean([1 / (1e-3 + 1.0), 1 / (1e-3 + 9.0)])
    assert M.relmse(test[:, :4], ref[:, :4]) == pytest.approx(by_hand)


def test_ssim_constant_images_closed_form() -> None:
    a, b = display(np.array([0.2, 0.2, 0.2]))[0], display(np.array([0.5, 0.5, 0.5]))[0]
    c1 = 0.01**2  # zero variance: SSIM = luminance term only
    expected = 1 - (2 * a * b + c1) / (a * a + b * b + c1)
    assert M.one_minus_ssim(const(0.2, 0.2, 0.2), const(0.5, 0.5, 0.5)) == pytest.approx(expected)
    assert M.one_minus_ssim(const(0.5, 0.5, 0.5), const(0.5, 0.5, 0.5)) == pytest.approx(0.0)


def test_ssim_matches_scipy_reference() -> None:
    test, ref = hdr_pair(32)
    x, y = display(test.astype(np.float64)), display(ref.astype(np.float64))

    def blur(t: np.ndarray) -> np.ndarray:  # 11-tap Gaussian (truncate 3.5), per channel
        return gaussian_filter(t, (1.5, 1.5, 0), truncate=3.5)

    mu_x, mu_y = blur(x), blur(y)
    var_x, var_y, cov = blur(x * x) - mu_x**2, blur(y * y) - mu_y**2, blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    ssim = (
        (2 * mu_x * mu_y + c1) * (2 * cov + c2) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))
    )
    assert M.one_minus_ssim(test, ref) == pytest.approx(1 - ssim[5:-5, 5:-5].mean(), rel=1e-9)


def test_torch_and_numpy_inputs_agree() -> None:
    test, ref = hdr_pair(24)
    for name in ("mse", "relmse", "smape", "one_minus_ssim"):
        metric = M.METRICS[name]
        from_numpy = metric(test, ref)
        assert metric(torch.from_numpy(test), torch.from_numpy(ref)) == pytest.approx(from_numpy)
        assert metric(torch.from_numpy(test), ref) == pytest.approx(from_numpy)


# ---------------------------------------------------------------------------------------------
# FLIP wrappers
# ---------------------------------------------------------------------------------------------


def test_flip_metrics_match_tool_and_torch_flip() -> None:
    test, ref = hdr_pair()
    _, expected, _ = flip_evaluator.evaluate(ref, test, "HDR", applyMagma=False)
    assert M.flip_hdr(test, ref) == pytest.approx(expected, rel=1e-6)
    torch_flip = hdr_flip(
        torch.from_numpy(test).permute(2, 0, 1)[None], torch.from_numpy(ref).permute(2, 0, 1)[None]
    )
    assert torch_flip.item() == pytest.approx(expected, rel=0.01)
    srgb_ref = display(ref).astype(np.float32)
    srgb_test = display(test).astype(np.float32)
    _, expected, _ = flip_evaluator.evaluate(srgb_ref, srgb_test, "LDR", applyMagma=False)
    assert M.flip_ldr(test, ref) == pytest.approx(expected, rel=1e-5)
    assert M.flip_ldr(ref, ref) == 0.0


def test_flip_hdr_tonemapper_case_and_errors() -> None:
    test, ref = hdr_pair(32)
    _, reinhard, _ = flip_evaluator.evaluate(
        ref, test, "HDR", applyMagma=False, parameters={"tonemapper": "reinhard"}
    )
    assert M.flip_hdr(test, ref, tonemapper="Reinhard") == pytest.approx(reinhard, rel=1e-6)
    assert M.flip_hdr(test, ref, tonemapper="Reinhard") != pytest.approx(M.flip_hdr(test, ref))
    with pytest.raises(ValueError, match="black"):
        M.flip_hdr(test, np.zeros_like(ref))
    with pytest.raises(ValueError, match="tonemapper"):
        M.flip_hdr(test, ref, tonemapper="filmic")
    with pytest.raises(ValueError, match="ppd"):
        M.flip_ldr(test, ref, ppd=0.0)


# ---------------------------------------------------------------------------------------------
# Validation, registry, skipping
# ---------------------------------------------------------------------------------------------


def test_shape_and_type_errors_name_the_metric_and_shapes() -> None:
    with pytest.raises(
        ValueError,
        match=r"relmse: .*image_test \(4, 4, 3\) and image_ref "
        r"\(4, 5, 3\)",
    ):
        M.relmse(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))
    with pytest.raises(ValueError, match=r"mse: expected two \(H, W, C\)"):
        M.mse(np.zeros((1, 4, 4, 3)), np.zeros((1, 4, 4, 3)))
    with pytest.raises(ValueError, match=r"flip_ldr: expected \(H, W, 3\) RGB"):
        M.flip_ldr(np.zeros((4, 4, 1)), np.zeros((4, 4, 1)))
    with pytest.raises(TypeError, match="smape: image_ref must be a float"):
        M.smape(np.zeros((4, 4, 3)), np.zeros((4, 4, 3), dtype=np.int32))
    with pytest.raises(ValueError, match="at least 11x11"):
        M.one_minus_ssim(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)))


def test_registry(monkeypatch: pytest.MonkeyPatch) -> None:
    registry = Registry("metric")
    registry.update(M.METRICS)
    monkeypatch.setattr(M, "METRICS", registry)

    @M.METRICS.register("max_abs")
    def max_abs(image_test: M.Image, image_ref: M.Image) -> float:
        return float(np.abs(np.asarray(image_test) - np.asarray(image_ref)).max())

    assert M.METRICS["max_abs"] is max_abs
    with pytest.raises(ValueError, match="already registered"):
        M.METRICS.register("mse")(max_abs)
    with pytest.raises(KeyError, match="valid names: .*relmse"):
        M.METRICS["psnr"]
    result = M.compute_metrics(const(1.0, 1.0, 1.0), const(0.0, 0.0, 0.0), ["max_abs", "mse"])
    assert result.values == {"max_abs": 1.0, "mse": 1.0} and result.skipped == {}


def test_compute_metrics_skips_unavailable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(E.ELPIPS_WEIGHTS_ENV, raising=False)
    monkeypatch.setitem(sys.modules, "flip_evaluator", None)  # import now raises ImportError
    test, ref = hdr_pair(16)
    result = M.compute_metrics(test, ref, options={"relmse": {"eps": 0.0}})
    assert set(result.values) == {"mse", "relmse", "smape", "one_minus_ssim"}
    assert set(result.skipped) == {"flip_hdr", "flip_ldr", "elpips"}
    assert "pip install flip-evaluator" in result.skipped["flip_hdr"]
    assert "GDPT_ELPIPS_WEIGHTS" in result.skipped["elpips"]
    assert result.values["relmse"] == pytest.approx(M.relmse(test, ref, eps=0.0))
    with pytest.raises(KeyError, match="not requested"):
        M.compute_metrics(test, ref, ["mse"], options={"relmse": {}})
    with pytest.raises(ValueError, match="compute_metrics"):
        M.compute_metrics(test, ref[:8])


def test_elpips_metric_with_local_weights(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    torch.manual_seed(0)
    state = dict(E.SqueezeNetFeatures().state_dict())
    state.update(
        {f"lin{i}.weight": torch.rand(c) for i, c in enumerate(E.SqueezeNetFeatures.channels)}
    )
    path = tmp_path / "elpips.pt"
    torch.save(state, path)
    monkeypatch.setenv(E.ELPIPS_WEIGHTS_ENV, str(path))
    test, ref = hdr_pair(64)
    value = M.elpips(test, ref, samples=2)
    assert value > 0 and value == M.elpips(test, ref, samples=2)  # seeded: reproducible
    assert M.elpips(ref, ref, samples=2) == pytest.approx(0.0, abs=1e-7)
    result = M.compute_metrics(test, ref, ["elpips"], options={"elpips": {"samples": 1}})
    assert result.skipped == {} and result.values["elpips"] > 0


def test_relmse_trimmed_leaves_out_the_largest_pixels() -> None:
    """One firefly in 10 000 pixels dominates relMSE; the trimmed companion leaves it out and
    otherwise equals relMSE."""
    ref = torch.full((100, 100, 3), 0.5)
    test = ref + 0.01
    assert M.relmse_trimmed(test, ref) == pytest.approx(M.relmse(test, ref))
    test[3, 4] = 500.0
    assert M.relmse(test, ref) > 100 * M.relmse_trimmed(test, ref)
    assert M.relmse_trimmed(test, ref) == pytest.approx(1e-4 / (1e-3 + 0.25), rel=1e-4)
    assert M.relmse_trimmed(test, ref, trim=0.0) == pytest.approx(M.relmse(test, ref))
