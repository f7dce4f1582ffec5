"""gdpt.training.kpcn: KPCN learns on its batches, writes a complete run directory, resumes
exactly, ships, and refuses a dataset without variances; the variance follows the
augmentations."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from functools import partial

import pytest
import torch
from gdpt.reconstruct.kpcn import (
    KPCN_DESIGNS,
    KPCNDesign,
    KPCNNet,
    KPCNReconstructor,
    kpcn_filter,
    kpcn_input,
    kpcn_loss,
    load_kpcn,
)

from gdpt.training.augment import AugmentParams, augment
from gdpt.training.config import TrainConfig
from gdpt.training.dataset import CropDataset
from gdpt.training.kpcn import INPUT_KIND, make_kpcn_batch
from gdpt.training.model_report import ship_model
from gdpt.training.run_dir import read_jsonl
from gdpt.training.step import make_optimizer
from gdpt.training.train import train

pytestmark = pytest.mark.usefixtures("single_thread")


@pytest.fixture
def tiny(tiny_run_config) -> Callable[..., TrainConfig]:
    """``tiny_run_config(data, out, **changes)`` of ``kpcn`` (16 px crops, lr 1e-3)."""
    return partial(tiny_run_config, model="kpcn", loss="l1", crop=16, lr=1e-3)


def test_three_steps_on_a_fixed_batch_reduce_the_loss(pt_dataset, tiny, tmp_path):
    config = tiny(pt_dataset, tmp_path)
    buffers, target = make_kpcn_batch(CropDataset(pt_dataset, kind=INPUT_KIND), config, 0)
    assert buffers["var_primal"].shape == (2, 16, 16, 1) and target.shape == (2, 16, 16, 3)
    torch.manual_seed(0)
    net = KPCNNet(KPCNDesign(3, 8, 3, 5, "test")).train()
    optimizer = make_optimizer(net, config)
    x, y, scale = kpcn_input(buffers)
    losses = []
    for _ in range(4):
        optimizer.zero_grad()
        loss = kpcn_loss(kpcn_filter(net, x, y), target.permute(0, 3, 1, 2), scale)
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert losses[3] < losses[2] < losses[1] < losses[0], losses


def test_run_directory_resumes_exactly_and_ships(
    pt_dataset, tiny, tmp_path, resume_after_a_lost_checkpoint, assert_same_state
):
    run = tmp_path / "run"
    config = tiny(pt_dataset, run)
    train(config, progress=False)
    log = read_jsonl(run / "log.jsonl")
    assert [r["step"] for r in log] == [1, 2, 3]
    val = read_jsonl(run / "val.jsonl")
    assert [r["step"] for r in val] == [2, 3]
    assert set(val[0]) >= {"relmse", "flip", "input_relmse", "input_flip", "oidn_relmse"}
    net, card = load_kpcn(run / "model.safetensors")
    assert net.design == KPCN_DESIGNS["kpcn"] and card["steps"] == 3 and card["validation"]
    assert card["training"]["crop"] == 16

    resumed, before, after = resume_after_a_lost_checkpoint(run, config, train)
    assert [r["step"] for r in resumed] == [1, 2, 3]
    assert resumed[2]["loss"] == log[2]["loss"]
    assert_same_state(before, after)  # weights and Adam state, bit for bit

    path = ship_model(run, "kpcn", dest=tmp_path / "models")
    item = CropDataset(pt_dataset, kind=INPUT_KIND)[0]["inputs"]
    shipped = KPCNReconstructor.from_checkpoint(path)
    assert shipped.card["name"] == "kpcn"
    assert torch.equal(shipped(item), KPCNReconstructor(net)(item))


def test_a_dataset_without_variances_is_refused_by_name(pt_dataset, tiny, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(pt_dataset, data)
    settings = json.loads((data / "dataset.json").read_text())
    del settings["config"]["variance"]  # as a dataset rendered with --no-variance
    (data / "dataset.json").write_text(json.dumps(settings))
    with pytest.raises(ValueError, match="without variances.*var_primal"):
        train(tiny(data, tmp_path / "run"), progress=False)
    assert not (tmp_path / "run").exists()


def test_the_variance_follows_the_augmentations():
    g = torch.Generator().manual_seed(0)
    variance = torch.rand(5, 6, 1, generator=g)
    params = AugmentParams(flip_x=True, transpose=True, colour=(0.5, 2.0, 0.5), brightness=3.0)
    out = augment({"var_primal": variance}, params)["var_primal"]
    torch.testing.assert_close(out, 9.0 * variance.flip(1).transpose(0, 1))
