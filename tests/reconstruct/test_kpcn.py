"""gdpt.reconstruct.kpcn: kernels that sum to one, a delta kernel that gives back its input,
the paper's preprocessing on known buffers, row bands equal to the whole image, checkpoints,
missing and non-finite buffers."""

from __future__ import annotations

import json

import pytest
import torch
import torch.nn.functional as F
from gdpt.reconstruct.kpcn import (
    ALBEDO_EPS,
    FEATURES,
    IN_CHANNELS,
    KPCN_DESIGNS,
    KPCNDesign,
    KPCNNet,
    KPCNReconstructor,
    encode_kpcn,
    kpcn_filter,
    kpcn_input,
    kpcn_loss,
    load_kpcn,
)

from gdpt.buffers import GradientBuffers

pytestmark = pytest.mark.usefixtures("single_thread")

#: A small design: 3 layers of 8 channels, 3x3, 5x5 kernels.
SMALL = KPCNDesign(3, 8, 3, 5, "test")


def buffers(h: int = 14, w: int = 19, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "primal": torch.rand(h, w, 3, generator=g) * 3,
        "albedo": torch.rand(h, w, 3, generator=g),
        "normal": F.normalize(torch.randn(h, w, 3, generator=g), dim=-1),
        "depth": torch.rand(h, w, 1, generator=g) * 5 + 1,
        "var_primal": torch.rand(h, w, 1, generator=g) * 0.1,
    }


def net_of(design: KPCNDesign = SMALL, seed: int = 0) -> KPCNNet:
    torch.manual_seed(seed)
    return KPCNNet(design).eval()


def delta_net(design: KPCNDesign = SMALL) -> KPCNNet:
    """A network whose kernels are the centre tap alone (softmax weight exactly 1)."""
    net = net_of(design)
    last = net.body[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.fill_(-1e4)
        last.bias[design.kernel**2 // 2] = 0.0
    return net


@pytest.fixture
def checkpoint(tmp_path):
    net = net_of(KPCN_DESIGNS["kpcn"])
    weights, text = encode_kpcn(net, "kpcn", {"training": {"note": "test"}})
    path = tmp_path / "kpcn.safetensors"
    path.write_bytes(weights)
    path.with_suffix(".json").write_text(text)
    return path, net


def test_the_kernels_sum_to_one():
    """A constant buffer stays constant under any predicted kernels (also at the border)."""
    x, _, _ = kpcn_input({k: v[None] for k, v in buffers().items()})
    y = torch.full((1, 3, 14, 19), 0.7)
    out = kpcn_filter(net_of(), x * 5, y)
    torch.testing.assert_close(out, y)


def test_a_delta_kernel_reproduces_its_input():
    b = buffers()
    out = KPCNReconstructor(delta_net())(b)
    torch.testing.assert_close(out, b["primal"], rtol=1e-5, atol=1e-6)


def test_the_input_follows_the_papers_preprocessing():
    b = buffers(6, 7)
    x, y, scale = kpcn_input({k: v[None] for k, v in b.items()})
    assert x.shape == (1, IN_CHANNELS, 6, 7) and y.shape == scale.shape == (1, 3, 6, 7)
    radiance, albedo = b["primal"].permute(2, 0, 1), b["albedo"].permute(2, 0, 1)
    torch.testing.assert_close(scale[0], albedo + ALBEDO_EPS)
    torch.testing.assert_close(y[0], torch.log1p(radiance / (albedo + ALBEDO_EPS)))
    torch.testing.assert_close(x[0, :3], y[0])
    variance = b["var_primal"][..., 0] / (radiance + albedo + ALBEDO_EPS).square().mean(0)
    torch.testing.assert_close(x[0, 3], variance)
    torch.testing.assert_close(x[0, 4:7], b["normal"].permute(2, 0, 1))
    depth = x[0, 7]
    torch.testing.assert_close(depth, b["depth"][..., 0] / b["depth"].max())
    torch.testing.assert_close(x[0, 8:11], albedo)
    dx_y, dy_y = x[0, 11:14], x[0, 14:17]  # forward differences of y, zero at the far edge
    torch.testing.assert_close(dx_y[:, :, :-1], y[0, :, :, 1:] - y[0, :, :, :-1])
    torch.testing.assert_close(dy_y[:, :-1], y[0, :, 1:] - y[0, :, :-1])
    assert not dx_y[:, :, -1].any() and not dy_y[:, -1].any()
    torch.testing.assert_close(x[0, 23, :, :-1], depth[:, 1:] - depth[:, :-1])  # depth's dx


def test_row_bands_give_the_whole_image_result():
    b = buffers(40, 9)
    net = net_of()
    whole = KPCNReconstructor(net, band_pixels=1 << 20)(b)
    banded = KPCNReconstructor(net, band_pixels=9 * (16 + 2 * SMALL.halo))(b)  # 3 bands
    torch.testing.assert_close(banded, whole, rtol=1e-5, atol=1e-6)


def test_the_loss_is_zero_on_the_transformed_target():
    b = buffers()
    _, y, scale = kpcn_input({k: v[None] for k, v in b.items()})
    target = b["primal"].permute(2, 0, 1)[None]
    assert float(kpcn_loss(y, target, scale)) < 1e-6
    assert float(kpcn_loss(y + 0.25, target, scale)) == pytest.approx(0.25, rel=1e-5)


def test_a_checkpoint_round_trip_gives_the_same_output(checkpoint):
    path, net = checkpoint
    loaded, card = load_kpcn(path.with_suffix(".json"))
    assert card["design"] == "kpcn" and card["features"] == list(FEATURES)
    assert (card["kernel"], card["layers"], card["width"], card["conv"]) == (11, 5, 32, 3)
    assert card["parameter_count"] == sum(p.numel() for p in net.parameters())
    b = buffers()
    rec = KPCNReconstructor.from_checkpoint(path)
    assert torch.equal(rec(b), KPCNReconstructor(net)(b)) and rec.card == card
    for key, value in net.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key


def test_a_card_of_another_format_or_design_is_refused(checkpoint):
    path, _ = checkpoint
    card_path = path.with_suffix(".json")
    card = json.loads(card_path.read_text())
    card_path.write_text(json.dumps({**card, "format": "other/1"}))
    with pytest.raises(ValueError, match="expected 'gdpt-kpcn/1'"):
        load_kpcn(path)
    card_path.write_text(json.dumps({**card, "design": "kpcn-paper"}))
    with pytest.raises(ValueError, match="does not fit design 'kpcn-paper'"):
        load_kpcn(path)


def test_a_network_of_another_design_is_not_encoded():
    with pytest.raises(ValueError, match="'kpcn-paper' checkpoint needs"):
        encode_kpcn(net_of(), "kpcn-paper", {})


@pytest.mark.parametrize("missing", ["var_primal", "depth"])
def test_a_missing_buffer_is_named(missing):
    b = buffers()
    del b[missing]
    with pytest.raises(KeyError, match=f"lack {missing}"):
        KPCNReconstructor(net_of())(b)
    as_render = GradientBuffers(**b, spp=4)  # an object with the buffers as attributes
    with pytest.raises(KeyError, match=f"lack {missing}"):
        KPCNReconstructor(net_of())(as_render)


@pytest.mark.parametrize("make_net", [net_of, delta_net], ids=["predicted", "delta"])
def test_non_finite_inputs_give_a_finite_output(make_net):
    b = buffers()
    for name in FEATURES:
        b[name][3, 4] = float("nan")
        b[name][5, 6] = float("inf")
        b[name][7, 8] = -float("inf")
    b["primal"][9, 10] = 3e38  # finite, but exp of its demodulated log overflows float32
    out = KPCNReconstructor(make_net())(b)
    assert torch.isfinite(out).all() and (out >= 0).all()


@pytest.mark.parametrize("shape", [(0, 8, 3, 5), (3, 8, 4, 5), (3, 8, 3, 6)])
def test_designs_need_layers_and_odd_sides(shape):
    with pytest.raises(ValueError, match="must be"):
        KPCNDesign(*shape, "bad")
