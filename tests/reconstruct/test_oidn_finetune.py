"""gdpt.reconstruct.oidn_finetune: step 0 is OIDN, delta checkpoints round-trip, bad input."""

from __future__ import annotations

import pytest
import torch
from gdpt.reconstruct.oidn_finetune import (
    DESIGNS,
    OIDNReconstructor,
    assemble,
    base_model,
    encode_delta,
    finetune_loss,
    load_model,
    neighbour_estimate,
    predict,
)
from gdpt.reconstruct.oidn_unet import denoise


def buffers(h: int = 20, w: int = 27, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    primal = torch.rand(h, w, 3, generator=g) * 2
    normal = torch.nn.functional.normalize(torch.randn(h, w, 3, generator=g), dim=-1)
    return {
        "primal": primal,
        "albedo": torch.rand(h, w, 3, generator=g),
        "normal": normal,
        "dx": torch.randn(h, w, 3, generator=g),
        "dy": torch.randn(h, w, 3, generator=g),
    }


@pytest.mark.parametrize("name", list(DESIGNS))
def test_untrained_design_is_oidn_on_an_odd_size(name):
    b = buffers()
    net = base_model(DESIGNS[name])
    with torch.no_grad():
        x, scale = assemble(b, DESIGNS[name])
        out = predict(net, x, 20, 27, scale)
        oidn = denoise(b["primal"], b["albedo"], b["normal"])
    assert out.shape == (20, 27, 3)
    assert torch.equal(out, oidn)


def test_delta_checkpoint_round_trips_and_stores_no_oidn_weights(tmp_path):
    design = DESIGNS["oidn-grad"]
    net = base_model(design)
    with torch.no_grad():
        net.enc_conv0.weight[:, 9:] += 0.01  # a "fine-tuned" gradient input
        net.dec_conv0.bias += 0.001
    weights, text = encode_delta(net, "oidn-grad", {"steps": 1})
    (tmp_path / "m.safetensors").write_bytes(weights)
    (tmp_path / "m.json").write_text(text)
    from safetensors.torch import load_file

    delta = load_file(str(tmp_path / "m.safetensors"))
    assert float(delta["enc_conv1.weight"].abs().max()) == 0.0  # untouched layers: zero delta
    loaded, loaded_design, card = load_model(tmp_path / "m.json")
    assert loaded_design == design and card["steps"] == 1
    for k, v in net.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[k], v, rtol=1e-6, atol=1e-7)
    rec = OIDNReconstructor(loaded, design)
    b = buffers(seed=1)
    with torch.no_grad():
        ref = denoise(b["primal"], b["albedo"], b["normal"])
    assert not torch.allclose(rec(b), ref)  # the gradient inputs now matter


def test_neighbour_estimate_is_exact_for_consistent_gradients_and_drops_a_firefly():
    yy, xx = torch.meshgrid(torch.arange(6.0), torch.arange(9.0), indexing="ij")
    image = torch.stack([0.3 * xx + 0.1 * yy, xx * xx, torch.sin(xx + 2 * yy)], -1)
    dx = torch.zeros_like(image)
    dy = torch.zeros_like(image)
    dx[:, :-1] = image[:, 1:] - image[:, :-1]
    dy[:-1] = image[1:] - image[:-1]
    torch.testing.assert_close(neighbour_estimate(image, dx, dy), image)
    flat = torch.ones(5, 5, 1)
    spike = flat.clone()
    spike[2, 2] = 100.0  # primal noise the zero gradients do not support
    estimate = neighbour_estimate(spike, torch.zeros_like(spike), torch.zeros_like(spike))
    assert float(estimate[2, 2]) == 1.0
    assert float(estimate[1, 2]) == pytest.approx((100.0 + 3.0) / 4)  # a neighbour of it
    assert float(estimate[0, 0]) == 1.0  # corner: two neighbours
    assert torch.equal(neighbour_estimate(flat[:1, :1], flat[:1, :1], flat[:1, :1]), flat[:1, :1])


def test_missing_gradient_buffer_is_named():
    b = buffers()
    del b["dy"]
    with pytest.raises(KeyError, match="dy"):
        assemble(b, DESIGNS["oidn-grad"])


def test_non_finite_inputs_give_a_finite_output():
    b = buffers()
    for name in ("primal", "dx", "albedo"):
        b[name][3, 4] = float("nan")
        b[name][5, 6] = float("inf")
    rec = OIDNReconstructor(base_model(DESIGNS["oidn-grad-l1"]), DESIGNS["oidn-grad-l1"])
    out = rec(b)
    assert torch.isfinite(out).all() and (out >= 0).all()


def test_refined_reconstruction_passes_gradients_to_every_buffer_it_reads():
    """With the gated L1 refinement, ``dx``/``dy`` reach the image through the network and the
    L1 solve (its last IRLS weights); the weights stay frozen."""
    design = DESIGNS["oidn-grad"]
    rec = OIDNReconstructor(base_model(design), design, {"refine": {"tau": 0.5}})
    b = {k: v.requires_grad_(True) for k, v in buffers(16, 16).items()}
    rec(b).square().mean().backward()
    for name in design.features:
        assert torch.isfinite(b[name].grad).all() and b[name].grad.abs().sum() > 0, name
    assert all(p.grad is None for net in rec._per_device.values() for p in net.parameters())


def test_finetune_loss_is_zero_at_the_target_and_grows_away_from_it():
    from gdpt.reconstruct.oidn_unet import pu_forward

    target = torch.rand(2, 3, 8, 8) + 0.1
    scale = torch.tensor([1.0, 0.5])
    y = pu_forward(scale.reshape(-1, 1, 1, 1) * target)
    assert float(finetune_loss(y, target, scale)) < 1e-5
    assert float(finetune_loss(y + 0.05, target, scale)) > 0.05


def test_finetune_loss_difference_term_sees_texture_not_a_constant_offset():
    from gdpt.reconstruct.oidn_unet import pu_forward

    target = torch.rand(2, 3, 8, 8) + 0.1
    scale = torch.tensor([1.0, 0.5])
    y = pu_forward(scale.reshape(-1, 1, 1, 1) * target)
    offset = y + 0.05
    plain = float(finetune_loss(offset, target, scale, relative=0.0))
    with_term = float(finetune_loss(offset, target, scale, relative=0.0, gradient=1.0))
    assert with_term == pytest.approx(plain, abs=1e-6)
    checker = (torch.arange(8).reshape(1, 1, 1, 8) + torch.arange(8).reshape(1, 1, 8, 1)) % 2
    textured = y + 0.05 * (2 * checker - 1)  # the same PU-L1 as the offset, wrong edges
    plain = float(finetune_loss(textured, target, scale, relative=0.0))
    with_term = float(finetune_loss(textured, target, scale, relative=0.0, gradient=1.0))
    assert with_term - plain == pytest.approx(2 * 0.1 * 7 / 8, rel=1e-4)
