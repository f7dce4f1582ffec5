"""gdpt.training.combiner: the combiner learns, writes a complete run directory, resumes
exactly, and refuses a base network that does not fit."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from gdpt.reconstruct.combiner import (
    COMBINER_DESIGNS,
    CombinerNet,
    CombinerReconstructor,
    combine,
    combiner_input,
    combiner_loss,
    load_combiner,
)
from gdpt.reconstruct.oidn_finetune import DESIGNS, OIDNReconstructor, base_model, encode_delta

from gdpt.training.checkpoint import write_checkpoint
from gdpt.training.combiner import CandidateCache, make_combiner_batch
from gdpt.training.config import TrainConfig
from gdpt.training.dataset import CropDataset
from gdpt.training.model_report import ship_model
from gdpt.training.run_dir import read_jsonl
from gdpt.training.step import make_optimizer
from gdpt.training.train import train


@pytest.fixture(scope="module")
def bases(tmp_path_factory) -> dict[str, Path]:
    """Untrained ``oidn-grad`` and ``oidn-nograd`` delta checkpoints (OIDN itself)."""
    root = tmp_path_factory.mktemp("bases")
    out = {}
    for name in ("oidn-grad", "oidn-nograd"):
        write_checkpoint(root / name, *encode_delta(base_model(DESIGNS[name]), name, {}))
        out[name] = root / f"{name}.safetensors"
    return out


@pytest.fixture
def tiny(tiny_run_config, bases) -> Callable[..., TrainConfig]:
    """``tiny(out, **changes)``: a 3-step ``combiner-grad`` run (lr 1e-3, PU-L1) on
    ``pt_dataset`` over the untrained ``oidn-grad`` base."""

    def make(data: Path, out: Path, **changes) -> TrainConfig:
        settings = dict(model="combiner-grad", loss="l1", lr=1e-3, crop=16)
        settings["base_model"] = str(bases["oidn-grad"])
        return tiny_run_config(data, out, **{**settings, **changes})

    return make


def test_four_steps_on_a_fixed_batch_reduce_the_loss(pt_dataset, tiny, tmp_path, bases):
    config = tiny(pt_dataset, tmp_path)
    design = COMBINER_DESIGNS["combiner-grad"]
    cache = CandidateCache(design, OIDNReconstructor.from_checkpoint(bases["oidn-grad"]))
    buffers, cands, target = make_combiner_batch(CropDataset(pt_dataset), config, design, 0, cache)
    assert cands.shape == (2, 2, 16, 16, 3) and target.shape == (2, 16, 16, 3)
    torch.manual_seed(0)
    net = CombinerNet(design.in_channels, 2).train()
    optimizer = make_optimizer(net, config)
    x, scale = combiner_input(buffers, cands, design)
    losses = []
    for _ in range(4):
        optimizer.zero_grad()
        loss = combiner_loss(combine(net, x, scale), target, cands[:, 0], scale, relative=None)
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert losses[3] < losses[2] < losses[1] < losses[0], losses


@pytest.mark.parametrize("relative", ["abs", "huber"])
def test_relative_term_charges_a_firefly_linearly(relative):
    target = torch.full((1, 4, 4, 3), 0.5)
    scale = torch.ones(1)
    firefly = target.clone()
    firefly[0, 1, 1] = 1e3
    pu_only = float(combiner_loss(firefly, target, target, scale, relative=None))
    small = float(combiner_loss(target, target, target, scale, relative=relative))
    big = float(combiner_loss(firefly, target, target, scale, relative=relative))
    assert small < 1e-6 and pu_only < 0.05
    # one pixel's 3 channels of 48, |r| = 999.5 / 0.51: about 120 (abs) or 120 - 0.5 / 16 (huber)
    assert 100 < big < 130


def test_an_unknown_relative_term_is_refused():
    t = torch.ones(1, 2, 2, 3)
    with pytest.raises(ValueError, match="unknown relative term"):
        combiner_loss(t, t, t, torch.ones(1), relative="square")


def test_run_directory_is_a_complete_model_and_resumes_exactly(
    pt_dataset, tiny, tmp_path, resume_after_a_lost_checkpoint, assert_same_state
):
    run = tmp_path / "run"
    config = tiny(pt_dataset, run)
    train(config, progress=False)
    log = read_jsonl(run / "log.jsonl")
    assert [r["step"] for r in log] == [1, 2, 3]
    val = read_jsonl(run / "val.jsonl")
    assert [r["step"] for r in val] == [2, 3]
    assert set(val[0]) >= {"relmse", "flip", "candidate_base_relmse", "candidate_l1_relmse"}
    net, design, card, base_path = load_combiner(run / "model.safetensors")
    assert design == COMBINER_DESIGNS["combiner-grad"] and card["steps"] == 3
    assert base_path == run / "base" and base_path.with_suffix(".json").is_file()
    item = CropDataset(pt_dataset)[0]["inputs"]
    assert torch.isfinite(CombinerReconstructor.from_checkpoint(run / "model.json")(item)).all()

    resumed, before, after = resume_after_a_lost_checkpoint(run, config, train)
    assert [r["step"] for r in resumed] == [1, 2, 3]
    assert resumed[2]["loss"] == log[2]["loss"]
    assert_same_state(before, after)  # weights and Adam state, bit for bit
    again, _, _, _ = load_combiner(run / "model.safetensors")
    for k, v in net.state_dict().items():
        assert torch.equal(again.state_dict()[k], v), k


def test_resuming_with_a_changed_copy_of_the_base_is_refused(pt_dataset, tiny, tmp_path):
    run = tmp_path / "run"
    train(tiny(pt_dataset, run, steps=1, val_every=0), progress=False)
    (run / "base.json").write_text("{}")
    with pytest.raises(ValueError, match="base.json differs from the one this run needs"):
        train(tiny(pt_dataset, run, steps=2, val_every=0), resume=True, progress=False)


def test_a_shipped_combiner_carries_its_base_network(pt_dataset, tiny, tmp_path):
    run = tmp_path / "run"
    train(tiny(pt_dataset, run, steps=1, val_every=0), progress=False)
    path = ship_model(run, "combiner", dest=tmp_path / "models")
    assert (tmp_path / "models" / "combiner-base.safetensors").is_file()
    rec = CombinerReconstructor.from_checkpoint(path)
    assert rec.card["name"] == "combiner" and rec.card["base_model"] == "combiner-base"
    item = CropDataset(pt_dataset)[0]["inputs"]
    trained = CombinerReconstructor.from_checkpoint(run / "model.safetensors")(item)
    assert torch.equal(rec(item), trained)


def test_nograd_design_trains_on_path_traced_inputs(pt_dataset, tiny, tmp_path, bases):
    config = tiny(pt_dataset, tmp_path / "run", model="combiner-nograd", steps=1, val_every=0)
    config = TrainConfig(**{**config.to_dict(), "base_model": str(bases["oidn-nograd"])})
    train(config, progress=False)
    _, design, card, _ = load_combiner(tmp_path / "run" / "model.json")
    assert not design.gradients and card["steps"] == 1


def test_a_base_network_of_the_other_kind_is_refused(pt_dataset, tiny, tmp_path, bases):
    config = tiny(pt_dataset, tmp_path / "run", base_model=str(bases["oidn-nograd"]))
    with pytest.raises(ValueError, match="must both read gradients or both not"):
        train(config, progress=False)


def test_a_missing_base_network_is_an_error(pt_dataset, tiny, tmp_path):
    with pytest.raises(ValueError, match="--base-model"):
        train(tiny(pt_dataset, tmp_path / "run", base_model=None), progress=False)
