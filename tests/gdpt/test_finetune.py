"""gdpt.training.oidn_finetune: OIDN fine-tuning (the ``oidn-finetune`` family's plan) learns,
writes its run directory, resumes exactly."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from functools import partial
from pathlib import Path

import pytest
import torch
from gdpt.reconstruct.oidn_finetune import DESIGNS, base_model, finetune_loss, load_model

from gdpt.training.config import TrainConfig
from gdpt.training.dataset import CropDataset
from gdpt.training.oidn_finetune import make_finetune_batch
from gdpt.training.run_dir import read_jsonl
from gdpt.training.step import make_optimizer
from gdpt.training.train import train


@pytest.fixture
def data(pt_dataset) -> Path:
    """The session's path-traced dataset (``pt_dataset``)."""
    return pt_dataset


@pytest.fixture
def tiny(tiny_run_config) -> Callable[..., TrainConfig]:
    """``tiny_run_config(data, out, **changes)`` of ``oidn-grad`` (l1_rel, 16 px, lr 1e-4)."""
    return partial(tiny_run_config, model="oidn-grad", loss="l1_rel", crop=16, lr=1e-4)


def test_path_traced_targets_are_written(data):
    record = json.loads((data / "manifest.jsonl").read_text().splitlines()[0])
    assert len(record["spp"]) == 2 and record["target_spp"] == 16
    assert json.loads((data / "dataset.json").read_text())["config"]["target"] == "pt"


@pytest.mark.parametrize("name", ["oidn-grad", "oidn-grad-l1", "oidn-grad-pool"])
def test_three_steps_on_a_fixed_batch_reduce_the_loss(data, tiny, tmp_path, name):
    """Small steps (Adam moves every weight by about ``lr`` at first: 1e-5 keeps each step in
    the loss's descent region, whichever crops the dataset holds) lower the loss every step."""
    config = tiny(data, tmp_path, model=name, lr=1e-5)
    design = DESIGNS[name]
    dataset = CropDataset(data, kind=design.input_kind)
    batch = make_finetune_batch(dataset, config, design, step=0)
    assert batch.x.shape == (2, 9 + design.extra_channels, 16, 16)
    net = base_model(design).train()
    optimizer = make_optimizer(net, config)
    losses = []
    for _ in range(4):
        optimizer.zero_grad()
        loss = finetune_loss(net(batch.x), batch.target, batch.scale)
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert losses[3] < losses[2] < losses[1] < losses[0], losses


def test_run_directory_and_exact_resume(
    data, tiny, tmp_path, resume_after_a_lost_checkpoint, assert_same_state
):
    run = tmp_path / "run"
    config = tiny(data, run)
    train(config, progress=False)
    log = read_jsonl(run / "log.jsonl")
    assert [r["step"] for r in log] == [1, 2, 3]
    val = read_jsonl(run / "val.jsonl")
    assert [r["step"] for r in val] == [2, 3]
    assert set(val[0]) >= {"relmse", "flip", "oidn_relmse", "pt_oidn_relmse", "l1_relmse"}
    net, design, card = load_model(run / "model.safetensors")
    assert design == DESIGNS["oidn-grad"] and card["steps"] == 3 and card["validation"]

    resumed, before, after = resume_after_a_lost_checkpoint(run, config, train)
    assert [r["step"] for r in resumed] == [1, 2, 3]
    assert resumed[2]["loss"] == log[2]["loss"]
    assert_same_state(before, after)  # weights and Adam state, bit for bit
    again, _, _ = load_model(run / "model.safetensors")
    for k, v in net.state_dict().items():
        assert torch.equal(again.state_dict()[k], v), k


def test_nograd_design_trains_on_path_traced_inputs(data, tiny, tmp_path):
    train(tiny(data, tmp_path / "run", model="oidn-nograd", steps=1, val_every=0), progress=False)
    _, design, card = load_model(tmp_path / "run" / "model.json")
    assert not design.gradients and card["steps"] == 1


def test_pooled_design_trains_on_pooled_inputs_and_records_the_factor(data, tiny, tmp_path):
    train(tiny(data, tmp_path / "run", model="oidn-grad-pool", steps=1), progress=False)
    _, design, card = load_model(tmp_path / "run" / "model.json")
    factor = json.loads((data / "dataset.json").read_text())["config"]["pt_factor"]
    assert design.input_kind == "pool" and card["sampling"] == {"primal_spp_factor": factor}


def test_extra_lr_scale_multiplies_the_first_update_of_the_extra_inputs(data, tiny, tmp_path):
    # step 0 has the same gradients with any scale (the extra weights are still zero), so one
    # Adam update differs exactly by the scale on the extra inputs' weights and not elsewhere
    nets = {}
    for scale in (1.0, 4.0):
        run = tmp_path / f"scale{scale}"
        train(tiny(data, run, steps=1, val_every=0, extra_lr_scale=scale), progress=False)
        nets[scale], design, card = load_model(run / "model.json")
        assert card["training"]["extra_lr_scale"] == scale
    base = dict(base_model(design).named_parameters())
    masks = nets[1.0].extra_input_masks()
    assert set(masks) == {"enc_conv0.weight", "dec_conv1a.weight"}
    for name, plain in nets[1.0].named_parameters():
        scaled = dict(nets[4.0].named_parameters())[name]
        step_plain, step_scaled = (plain - base[name]).detach(), (scaled - base[name]).detach()
        if name in masks:
            extra = masks[name].bool()
            assert (step_plain[extra] != 0).float().mean() > 0.5
            torch.testing.assert_close(step_scaled[extra], 4.0 * step_plain[extra])
            torch.testing.assert_close(step_scaled[~extra], step_plain[~extra], rtol=0, atol=0)
        else:
            torch.testing.assert_close(step_scaled, step_plain, rtol=0, atol=0)


def test_extra_lr_scale_must_be_positive(data, tiny, tmp_path):
    with pytest.raises(ValueError, match="extra_lr_scale"):
        tiny(data, tmp_path, extra_lr_scale=0.0)


def test_nograd_design_trains_on_the_gdpt_input_when_asked(data, tiny, tmp_path):
    """``input="gdpt"``: the same batches read the G-PT input's primal, not ``pt<k>``'s."""
    losses = {}
    for kind in (None, "gdpt"):
        run = tmp_path / f"run-{kind}"
        config = tiny(data, run, model="oidn-nograd", steps=1, val_every=0, input=kind)
        train(config, progress=False)
        losses[kind] = read_jsonl(run / "log.jsonl")[0]["loss"]
        assert load_model(run / "model.json")[2]["training"]["input"] == (kind or "pt")
    assert losses[None] != losses["gdpt"]
    with pytest.raises(ValueError, match="reads gradients"):
        train(tiny(data, tmp_path / "grad", input="gdpt"), progress=False)


def test_base_model_is_the_start_of_a_finetune(data, tiny, tmp_path):
    """A fine-tune from ``base_model`` starts at its weights (a 1e-12 step stays there), and
    the checkpoint must be of the same design."""
    first = tmp_path / "first"
    train(tiny(data, first, model="oidn-nograd", steps=1, val_every=0), progress=False)
    start = first / "model.safetensors"
    again = tmp_path / "again"
    config = tiny(data, again, model="oidn-nograd", steps=1, val_every=0, lr=1e-12)
    train(dataclasses.replace(config, base_model=str(start)), progress=False)
    trained, _, card = load_model(again / "model.json")
    assert card["training"]["start"] == str(start)
    intel = dict(base_model(DESIGNS["oidn-nograd"]).named_parameters())
    moved = 0.0
    for name, weight in load_model(start)[0].named_parameters():
        torch.testing.assert_close(
            dict(trained.named_parameters())[name], weight, atol=1e-9, rtol=0
        )
        moved = max(moved, float((weight - intel[name]).detach().abs().max()))
    assert moved > 1e-6  # the start is not Intel's weights
    with pytest.raises(ValueError, match="not 'oidn-grad'"):
        train(tiny(data, tmp_path / "other", steps=1, base_model=str(start)), progress=False)
