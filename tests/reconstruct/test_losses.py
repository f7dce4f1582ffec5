"""Tests of gdpt.reconstruct.losses: NGPT L1 terms, FLIP and E-LPIPS losses, the registry."""

from __future__ import annotations

import math

import pytest
import torch
from gdpt.reconstruct import losses as L
from gdpt.reconstruct.colour import reinhard
from gdpt.reconstruct.elpips import ELPIPS_WEIGHTS_ENV, ELPIPSConfig, ELPIPSWeightsError
from gdpt.reconstruct.flip import ldr_flip

pytestmark = pytest.mark.usefixtures("single_thread")


def test_forward_differences_convention() -> None:
    image = torch.arange(12.0).view(1, 1, 3, 4)  # I[y, x] = 4y + x
    dx, dy = L.forward_differences(image)
    assert torch.equal(dx[..., :, :3], torch.ones(1, 1, 3, 3))
    assert torch.equal(dx[..., :, 3], torch.zeros(1, 1, 3))
    assert torch.equal(dy[..., :2, :], torch.full((1, 1, 2, 4), 4.0))
    assert torch.equal(dy[..., 2, :], torch.zeros(1, 1, 4))


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


def test_registry_weights_and_errors(image_pair) -> None:
    pred, target = image_pair(size=16)
    l1 = L.get_loss("l1")
    expected = L.l1_tonemapped(pred, target) + 0.01 * L.gradient_l1_tonemapped(pred, target)
    assert torch.allclose(l1(pred, target), expected)
    flip = L.get_loss("flip")
    expected = (
        ldr_flip(reinhard(pred), reinhard(target), inputs_srgb=False)
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


def test_flip_losses_gradient_flow(image_pair) -> None:
    pred, target = image_pair(size=24)
    pred = (4 * pred - 0.5).requires_grad_()  # HDR with some negative values
    for name in ("flip", "flip_hdr"):
        pred.grad = None
        loss = L.get_loss(name)(pred, 4 * target)
        loss.backward()
        assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0, name


def test_elpips_gradient_flow(image_pair, tiny_elpips) -> None:
    a, b = image_pair()
    a = a.requires_grad_()
    loss = L.DenseUNetLoss(L.ELPIPSLoss(tiny_elpips(ELPIPSConfig.for_training())))
    loss(4 * a, 4 * b).backward()
    assert torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0
    assert all(p.grad is None for p in loss.parameters())  # the backbone is frozen


def test_flip_loss_rejects_unknown_mode() -> None:
    with pytest.raises(ValueError, match="mode"):
        L.FLIPLoss("sdr")


def test_elpips_loss_needs_a_weight_file(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.delenv(ELPIPS_WEIGHTS_ENV, raising=False)
    with pytest.raises(ELPIPSWeightsError, match="does not exist"):
        L.get_loss("elpips", weights=tmp_path / "missing.pt")


def test_elpips_loss_reads_weights_from_the_environment(
    squeezenet_state, image_pair, tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "elpips_squeeze.pt"
    torch.save(squeezenet_state, path)
    monkeypatch.setenv(ELPIPS_WEIGHTS_ENV, str(path))
    training = L.get_loss("elpips", seed=0)
    assert torch.isfinite(training(*image_pair(n=1, size=96)))
