"""Tests of the NGPT dense U-Net: published shapes, every registered config, both code paths."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from gdpt.reconstruct import dense_unet
from gdpt.reconstruct.dense_unet import CONFIGS, DenseUNet, ModelConfig, build_model

PAPER_PARAMETERS = 4_360_054  # W, s and b of every layer of the paper's network (~4.36 M)


def _perturbed(model: DenseUNet, seed: int = 0) -> DenseUNet:
    """Randomise gains and biases so that every code path is exercised non-trivially."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if not name.endswith("weight"):
                p.add_(0.1 * torch.randn(p.shape, generator=gen))
    return model


def test_paper_parameter_count_and_layer_shapes():
    model = build_model("paper")
    assert dense_unet.parameter_count(model) == PAPER_PARAMETERS
    assert model.alignment == 8
    e0 = [u.bottleneck.weight.shape[1] for u in model.encoders[0]]
    assert e0 == [16, 56, 96, 136]
    assert all(
        u.bottleneck.weight.shape[0] == 80 and u.conv.weight.shape[:2] == (40, 80)
        for u in model.encoders[0]
    )
    assert [u.bottleneck.weight.shape[1] for u in model.encoders[1]] == [160, 240, 320]
    assert [u.bottleneck.weight.shape[1] for u in model.encoders[2]] == [160, 240]
    assert [u.bottleneck.weight.shape[1] for u in model.encoders[3]] == [160, 240]
    assert [u.bottleneck.weight.shape[1] for u in model.decoders[3]] == [320, 400]
    assert [u.bottleneck.weight.shape[1] for u in model.decoders[2]] == [480, 560]
    assert [u.bottleneck.weight.shape[1] for u in model.decoders[1]] == [560, 640, 720]
    assert [u.bottleneck.weight.shape[1] for u in model.decoders[0]] == [256, 296, 336, 376]
    assert [tuple(p.weight.shape) for p in model.pools] == [
        (160, 176, 2, 2),
        (160, 400, 2, 2),
        (160, 320, 2, 2),
    ]
    # transposed convs: torch layout (C_in, C_out, kh, kw), gain per input channel
    assert [tuple(u.weight.shape) for u in model.unpools] == [
        (800, 80, 2, 2),
        (640, 160, 2, 2),
        (480, 160, 2, 2),
    ]
    assert tuple(model.head[0].weight.shape) == (3, 416, 1, 1)
    assert model.list_widths == [(176, 416), (400, 800), (320, 640), (320, 480)]


def test_nograd_shapes():
    model = build_model("nograd")
    assert model.decoders[0][0].bottleneck.weight.shape[1] == 250
    assert tuple(model.head[0].weight.shape) == (3, 410, 1, 1)


def test_plain_unet_has_equal_capacity():
    ratio = dense_unet.parameter_count(build_model("unet")) / PAPER_PARAMETERS
    assert abs(ratio - 1) < 0.05
    assert not CONFIGS["unet"].dense


def test_registry_error_lists_names():
    with pytest.raises(ValueError, match="paper.*nograd.*unet"):
        build_model("papper")


def test_weight_norm_formula():
    conv = dense_unet.Conv(7, 5, 3)
    with torch.no_grad():
        conv.gain.copy_(torch.arange(1.0, 6.0))
    w = conv.effective_weight()
    norms = w.square().sum(dim=(1, 2, 3)).sqrt()
    torch.testing.assert_close(norms, math.sqrt(2) * torch.arange(1.0, 6.0))
    tconv = dense_unet.Conv(7, 5, 2, stride=2, transposed=True)
    assert tconv.gain.shape == (7,)  # TF convention: normalised per input channel
    torch.testing.assert_close(
        tconv.effective_weight().square().sum(dim=(1, 2, 3)), torch.full((7,), 2.0)
    )
    assert torch.count_nonzero(conv.bias) == 0


@pytest.mark.parametrize("name", list(CONFIGS))
@pytest.mark.parametrize("size", [(20, 28), (9, 13)])
def test_forward_backward_every_config(name, size):
    from gdpt.reconstruct.transforms import padding_for

    model = _perturbed(build_model(name))
    pad = padding_for(*size, model.alignment, margin=0)
    h, w = size[0] + pad.top + pad.bottom, size[1] + pad.left + pad.right
    x = torch.randn(2, model.config.in_channels, h, w)
    y = model(x)
    assert y.shape == (2, 3, h, w)
    y[..., : size[0], : size[1]].square().mean().backward()
    for pname, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), pname
    assert any(p.grad.abs().sum() > 0 for p in model.parameters())


@pytest.mark.parametrize("name", list(CONFIGS))
def test_inference_path_and_fuse_match_autograd_path(name):
    model = _perturbed(build_model(name), seed=1)
    x = torch.randn(1, model.config.in_channels, 16, 24)
    reference = model(x)
    with torch.inference_mode():
        buffered = model(x.contiguous(memory_format=torch.channels_last))
        fused = model.fuse()(x)
    torch.testing.assert_close(buffered, reference.detach(), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(fused, reference.detach(), rtol=1e-4, atol=1e-4)


def test_residual_adds_the_input_primal():
    x = torch.randn(2, 16, 16, 24)
    residual = build_model("fast_xs_res")
    direct = _perturbed(build_model("fast_xs"), seed=2)
    residual.load_state_dict(direct.state_dict())  # same parameters, other output rule
    pre_activation = residual(x) - x[:, :3]
    torch.testing.assert_close(F.leaky_relu(pre_activation, 0.01), direct(x))
    assert (pre_activation < 0).any()  # no final activation clips the correction


def test_input_errors():
    model = build_model("fast_xs")
    with pytest.raises(ValueError, match="multiple of 8"):
        model(torch.zeros(1, 16, 12, 16))
    with pytest.raises(ValueError, match=r"\(N, 16, H, W\)"):
        model(torch.zeros(1, 10, 16, 16))


def test_config_round_trip_and_validation():
    for cfg in CONFIGS.values():
        assert ModelConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="unknown ModelConfig fields"):
        ModelConfig.from_dict({"growth": [1]})
    with pytest.raises(ValueError, match="pool_features"):
        ModelConfig(pool_features=(160,))


def test_receptive_radius_bounds_influence():
    model = _perturbed(build_model("fast_xs"))
    size, c = 160, 80
    x = torch.randn(1, 16, size, size, requires_grad=True)
    model(x)[0, :, c, c].sum().backward()
    influenced = x.grad.abs().sum(dim=(0, 1)).nonzero()
    reach = (influenced - c).abs().max().item()
    assert 0 < reach <= model.receptive_radius


def test_flops():
    conv = dense_unet.Conv(4, 6, 3, scale=2)
    assert conv.flops(16, 32) == 2 * 4 * 6 * 9 * 8 * 16
    assert math.isclose(build_model("paper").flops(720, 1280) / 1e9, 2052.7, rel_tol=1e-3)
