"""gdpt.reconstruct.combiner: kernels on known images, step 0, checkpoints, bad input."""

from __future__ import annotations

import json

import pytest
import torch
import torch.nn.functional as F
from gdpt.reconstruct.combiner import (
    COMBINER_DESIGNS,
    CombinerNet,
    CombinerReconstructor,
    candidates,
    combine,
    combiner_input,
    encode_combiner,
    load_combiner,
)
from gdpt.reconstruct.oidn_finetune import DESIGNS, OIDNReconstructor, base_model, encode_delta
from gdpt.reconstruct.poisson import NonFiniteInputWarning


def buffers(h: int = 20, w: int = 27, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "primal": torch.rand(h, w, 3, generator=g) * 2,
        "albedo": torch.rand(h, w, 3, generator=g),
        "normal": F.normalize(torch.randn(h, w, 3, generator=g), dim=-1),
        "dx": torch.randn(h, w, 3, generator=g) * 0.1,
        "dy": torch.randn(h, w, 3, generator=g) * 0.1,
    }


@pytest.mark.parametrize("name", list(COMBINER_DESIGNS))
def test_step_zero_gives_the_base_image_nearly_all_the_weight(name):
    design = COMBINER_DESIGNS[name]
    net = CombinerNet(design.in_channels, len(design.candidate_names)).eval()
    b = {k: v[None] for k, v in buffers(16, 20).items()}
    cands = torch.rand(1, len(design.candidate_names), 16, 20, 3)
    x, scale = combiner_input(b, cands, design)
    assert x.shape == (1, design.in_channels, 16, 20)
    with torch.no_grad():
        weights = torch.softmax(net(x), 1)
        out = combine(net, x, scale)
    assert float(weights[:, 4].min()) > 0.99
    assert out.shape == (1, 16, 20, 3) and (out >= 0).all()


@pytest.fixture
def checkpoint(tmp_path):
    """A ``combiner-grad`` checkpoint (perturbed head) next to an untrained ``oidn-grad`` base."""
    base = base_model(DESIGNS["oidn-grad"])
    weights, text = encode_delta(base, "oidn-grad", {"steps": 0})
    (tmp_path / "base.safetensors").write_bytes(weights)
    (tmp_path / "base.json").write_text(text)
    design = COMBINER_DESIGNS["combiner-grad"]
    net = CombinerNet(design.in_channels, len(design.candidate_names))
    with torch.no_grad():
        net.head.weight.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(4))
    weights, text = encode_combiner(net, "combiner-grad", {"base_model": "base", "steps": 7})
    (tmp_path / "m.safetensors").write_bytes(weights)
    (tmp_path / "m.json").write_text(text)
    return tmp_path / "m.safetensors", net


def test_checkpoint_round_trips_and_reconstructs_an_odd_size(checkpoint):
    path, net = checkpoint
    loaded, design, card, base_path = load_combiner(path)
    assert card["steps"] == 7 and design == COMBINER_DESIGNS["combiner-grad"]
    assert base_path == path.parent / "base"
    for k, v in net.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v), k
    rec = CombinerReconstructor.from_checkpoint(path)
    b = buffers()
    out = rec(b)
    base_image = OIDNReconstructor.from_checkpoint(base_path)(b)
    assert out.shape == (20, 27, 3) and torch.isfinite(out).all()
    assert not torch.allclose(out, base_image)  # the perturbed head mixes in the L1 candidate
    cands = candidates(b, base_image, design)
    assert (out <= cands.amax((0, 1, 2)) * 1.0001 + 1e-6).all()


def test_a_missing_base_network_is_named(checkpoint):
    path, _ = checkpoint
    (path.parent / "base.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match="base network"):
        load_combiner(path)


def test_a_card_of_another_format_is_refused(checkpoint):
    path, _ = checkpoint
    card = path.with_suffix(".json")
    card.write_text(json.dumps({**json.loads(card.read_text()), "format": "other/1"}))
    with pytest.raises(ValueError, match="expected 'gdpt-combiner/1'"):
        load_combiner(path)


def test_missing_gradient_buffer_is_named(checkpoint):
    b = buffers()
    del b["dx"]
    with pytest.raises(KeyError, match="dx"):
        CombinerReconstructor.from_checkpoint(checkpoint[0])(b)


def test_non_finite_inputs_give_a_finite_output(checkpoint):
    b = buffers()
    for name in ("primal", "dx", "dy", "albedo"):
        b[name][3, 4] = float("nan")
        b[name][5, 6] = float("inf")
    rec = CombinerReconstructor.from_checkpoint(checkpoint[0])
    with pytest.warns(NonFiniteInputWarning, match="2 dx, 2 dy"):  # the L1 candidate's count
        out = rec(b)
    assert torch.isfinite(out).all() and (out >= 0).all()
