"""gdpt.reconstruct.families: every family recognises, loads, re-encodes and reconstructs its own
checkpoints; designs name one family; unknown formats and designs are refused by name."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from gdpt.reconstruct.combiner import COMBINER_DESIGNS, CombinerNet, encode_combiner
from gdpt.reconstruct.dense_unet import build_model
from gdpt.reconstruct.dense_unet_reconstructor import encode_checkpoint
from gdpt.reconstruct.families import FAMILIES, family_of, family_of_design
from gdpt.reconstruct.kpcn import KPCN_DESIGNS, KPCNNet, encode_kpcn
from gdpt.reconstruct.oidn_finetune import DESIGNS, base_model, encode_delta


def write(path: Path, encoded: tuple[bytes, str]) -> Path:
    """Write an encoded checkpoint as ``path.safetensors`` + ``path.json``; return the former."""
    weights, text = encoded
    path.with_suffix(".safetensors").write_bytes(weights)
    path.with_suffix(".json").write_text(text)
    return path.with_suffix(".safetensors")


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory) -> dict[str, Path]:
    """One small checkpoint per family (random or OIDN's weights, each with a training note)."""
    root = tmp_path_factory.mktemp("families")
    torch.manual_seed(0)
    oidn = base_model(DESIGNS["oidn-grad"])
    with torch.no_grad():  # a fine-tuned network: not OIDN itself
        for p in oidn.parameters():
            p.add_(1e-3 * torch.randn_like(p))
    design = COMBINER_DESIGNS["combiner-grad"]
    combiner = CombinerNet(design.in_channels, len(design.candidate_names))
    note = {"training": {"note": "test"}}
    return {
        "dense-unet": write(root / "dense", encode_checkpoint(build_model("fast_xs"), note)),
        "oidn-finetune": write(root / "base", encode_delta(oidn, "oidn-grad", note)),
        "combiner": write(
            root / "comb", encode_combiner(combiner, "combiner-grad", {"base_model": "base"})
        ),
        "kpcn": write(root / "kpcn", encode_kpcn(KPCNNet(KPCN_DESIGNS["kpcn"]), "kpcn", note)),
    }


def buffers(h: int = 16, w: int = 20) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    out = {n: torch.rand(h, w, 3, generator=g) for n in ("primal", "albedo", "dx", "dy")}
    out["normal"] = F.normalize(torch.randn(h, w, 3, generator=g), dim=-1)
    out["depth"] = torch.rand(h, w, 1, generator=g)
    out["var_primal"] = torch.rand(h, w, 1, generator=g) * 0.01
    return out


def test_the_families_and_their_formats_are_distinct():
    assert list(FAMILIES) == ["dense-unet", "oidn-finetune", "combiner", "kpcn"]
    assert len({f.card_format for f in FAMILIES.values()}) == len(FAMILIES)


def test_every_design_names_exactly_one_family():
    for family in FAMILIES.values():
        assert family.designs and family.losses, family.name
        for design in family.designs:
            assert family_of_design(design) is family
            owners = [f.name for f in FAMILIES.values() if design in f.designs]
            assert owners == [family.name], design


@pytest.mark.parametrize("name", list(FAMILIES))
def test_a_checkpoint_is_recognised_by_either_file(checkpoints, name):
    path = checkpoints[name]
    assert family_of(path) is FAMILIES[name]
    assert family_of(path.with_suffix(".json")) is FAMILIES[name]


@pytest.mark.parametrize("name", list(FAMILIES))
def test_load_and_encode_round_trip(checkpoints, name, tmp_path):
    """Loading, re-encoding the card without the family's own keys and loading again gives the
    same network (the delta family adds to OIDN's weights: one float32 rounding) and card."""
    family = FAMILIES[name]
    net, design, card = family.load(checkpoints[name])
    assert design in family.designs and not net.training
    info = {k: v for k, v in card.items() if k not in family.card_keys}
    assert set(info) <= {"training", "base_model"}
    copy = tmp_path / checkpoints[name].name
    if name == "combiner":  # its base sits next to its card
        for suffix in (".safetensors", ".json"):
            base = checkpoints["oidn-finetune"].with_suffix(suffix)
            (tmp_path / base.name).write_bytes(base.read_bytes())
    write(copy, family.encode(net, design, info))
    again, design_again, card_again = family.load(copy)
    assert design_again == design and card_again == card
    exact = name != "oidn-finetune"
    for key, value in net.state_dict().items():
        tol = {"rtol": 0, "atol": 0} if exact else {"rtol": 1e-6, "atol": 1e-7}
        torch.testing.assert_close(again.state_dict()[key], value, **tol, msg=key)


@pytest.mark.parametrize("name", list(FAMILIES))
def test_the_reconstructor_reads_its_features(checkpoints, name):
    rec = FAMILIES[name].reconstructor(checkpoints[name])
    b = buffers()
    image = rec({n: b[n] for n in rec.features})
    assert image.shape == (16, 20, 3) and torch.isfinite(image).all() and (image >= 0).all()
    assert rec.card["format"] == FAMILIES[name].card_format


def test_only_a_combiner_builds_on_another_checkpoint(checkpoints):
    for name, path in checkpoints.items():
        card = json.loads(path.with_suffix(".json").read_text())
        expected = path.parent / "base" if name == "combiner" else None
        assert FAMILIES[name].base(path.with_suffix(".json"), card) == expected
    assert [n for n, f in FAMILIES.items() if f.oidn_weights] == ["oidn-finetune", "combiner"]


def test_a_checkpoint_of_an_unknown_family_is_named_with_the_known_ones(checkpoints, tmp_path):
    source = checkpoints["dense-unet"]
    path = tmp_path / "odd.safetensors"
    path.write_bytes(source.read_bytes())
    card = json.loads(source.with_suffix(".json").read_text())
    path.with_suffix(".json").write_text(json.dumps({**card, "format": "someone-else/3"}))
    with pytest.raises(ValueError) as error:
        family_of(path)
    message = str(error.value)
    assert str(path.with_suffix(".json")) in message and "'someone-else/3'" in message
    for family in FAMILIES.values():
        assert family.name in message and family.card_format in message


def test_an_unknown_design_lists_every_family(checkpoints):
    with pytest.raises(ValueError, match="unknown network design 'nope'") as error:
        family_of_design("nope")
    assert all(f"{name}: " in str(error.value) for name in FAMILIES)


def test_a_missing_card_is_named(checkpoints, tmp_path):
    path = tmp_path / "lonely.safetensors"
    path.write_bytes(checkpoints["dense-unet"].read_bytes())
    with pytest.raises(FileNotFoundError, match="lonely.json"):
        family_of(path)


def test_a_dense_checkpoint_refuses_another_design(checkpoints):
    net, _, _ = FAMILIES["dense-unet"].load(checkpoints["dense-unet"])
    with pytest.raises(ValueError, match="'paper' needs that DenseUNet"):
        FAMILIES["dense-unet"].encode(net, "paper", {})


def test_a_combiner_card_needs_its_base(checkpoints):
    net, design, _ = FAMILIES["combiner"].load(checkpoints["combiner"])
    with pytest.raises(ValueError, match="base_model"):
        encode_combiner(net, design, {"training": {}})
