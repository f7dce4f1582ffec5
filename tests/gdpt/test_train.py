"""gdpt.training (augment, schedule, batches, step, config, run_dir, loop, train, dense):
gradient-correct augmentations, schedule, learning, the family dispatch, exact resume, DDP, run
dirs."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import subprocess
import sys
from collections.abc import Callable
from functools import partial
from pathlib import Path

import pytest
import torch
from gdpt.reconstruct.dense_unet import build_model
from gdpt.reconstruct.losses import get_loss

from gdpt.cli import main
from gdpt.training.augment import AugmentParams, augment, sample_augmentation
from gdpt.training.batches import make_batch
from gdpt.training.config import ConfigMismatchError, TrainConfig
from gdpt.training.dataset import CropDataset
from gdpt.training.run_dir import checkpoint_base, prune_checkpoints, read_jsonl
from gdpt.training.schedule import learning_rate
from gdpt.training.step import compute_loss, make_optimizer, update
from gdpt.training.train import PLANS, train

H = W = 8


@pytest.fixture
def data(tiny_dataset: Path) -> Path:
    """Two rendered 16x16 crops of a one-object scene (the shared ``tiny_dataset``)."""
    return tiny_dataset


@pytest.fixture
def tiny(tiny_run_config) -> Callable[..., TrainConfig]:
    """``tiny_run_config(data, out, **changes)`` of ``fast_xs`` (l1 loss, padding +-2)."""
    return partial(tiny_run_config, model="fast_xs", loss="l1", vary_padding=2)


# ------------------------------------------------------------------------------- augmentation
def buffers_of(
    image: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor
) -> dict[str, torch.Tensor]:
    """The exact G-PT buffers of an image: forward differences, unused last column/row 0."""
    dx = torch.zeros_like(image)
    dy = torch.zeros_like(image)
    dx[:, :-1] = image[:, 1:] - image[:, :-1]
    dy[:-1] = image[1:] - image[:-1]
    return {
        "primal": image,
        "dx": dx,
        "dy": dy,
        "albedo": albedo,
        "normal": normal,
        "depth": depth,
        "target": image,
    }


def augment_scene(scene: dict[str, torch.Tensor], p: AugmentParams) -> dict[str, torch.Tensor]:
    """Augment the *scene* (image, albedo, normal, depth) directly, in :func:`augment`'s order."""
    image, albedo, normal, depth = (scene[k] for k in ("image", "albedo", "normal", "depth"))
    if p.size is not None:
        (y, x), (h, w) = p.origin, p.size
        image, albedo, normal, depth = (
            t[y : y + h, x : x + w] for t in (image, albedo, normal, depth)
        )
    sign = torch.ones(3)
    if p.flip_x:
        image, albedo, normal, depth = (t.flip(1) for t in (image, albedo, normal, depth))
        sign[0] = -sign[0]
        normal = normal * torch.tensor([-1.0, 1.0, 1.0])
    if p.flip_y:
        image, albedo, normal, depth = (t.flip(0) for t in (image, albedo, normal, depth))
        normal = normal * torch.tensor([1.0, -1.0, 1.0])
    if p.transpose:
        image, albedo, normal, depth = (t.transpose(0, 1) for t in (image, albedo, normal, depth))
        normal = normal[..., [1, 0, 2]]
    colour = torch.tensor(p.colour)
    image = image[..., list(p.permutation)] * colour * p.brightness
    albedo = albedo[..., list(p.permutation)] * colour
    return buffers_of(image, albedo, normal, depth)


CASES = {
    "flip_x": AugmentParams(flip_x=True),
    "flip_y": AugmentParams(flip_y=True),
    "transpose": AugmentParams(transpose=True),
    "permutation": AugmentParams(permutation=(2, 0, 1)),
    "colour": AugmentParams(colour=(0.5, 2.0, 0.5)),
    "brightness": AugmentParams(brightness=3.7),
    "sub-crop": AugmentParams(origin=(1, 2), size=(5, 5)),
    "all": AugmentParams(
        origin=(2, 1),
        size=(6, 6),
        flip_x=True,
        flip_y=True,
        transpose=True,
        permutation=(1, 2, 0),
        colour=(1.2, 0.3, 1.5),
        brightness=0.4,
    ),
}


@pytest.mark.parametrize("name", list(CASES))
def test_augmenting_buffers_equals_buffers_of_augmented_image(name):
    g = torch.Generator().manual_seed(1)
    scene = {
        "image": torch.rand(H, W, 3, generator=g) * 4,
        "albedo": torch.rand(H, W, 3, generator=g),
        "normal": torch.randn(H, W, 3, generator=g),
        "depth": torch.rand(H, W, 1, generator=g),
    }
    buffers = buffers_of(scene["image"], scene["albedo"], scene["normal"], scene["depth"])
    got = augment(buffers, CASES[name])
    expected = augment_scene(scene, CASES[name])
    assert set(got) == set(expected)
    for key in expected:
        torch.testing.assert_close(got[key], expected[key], msg=f"{name}: buffer {key}")


def test_sampled_augmentations_have_the_reference_distributions():
    g = torch.Generator().manual_seed(0)
    config = TrainConfig(data="d", out="o", crop=12)
    draws = [sample_augmentation(g, config, (16, 16)) for _ in range(2000)]
    colours = torch.tensor([d.colour for d in draws])
    torch.testing.assert_close(colours.sum(1), torch.full((2000,), 3.0, dtype=colours.dtype))
    assert (colours > 0).all() and (colours.mean(0) - 1).abs().max() < 0.06
    brightness = torch.tensor([d.brightness for d in draws])
    assert abs(float(brightness.mean()) - 1) < 0.15 and float(brightness.log().std()) > 0.9
    assert {d.offset[0] for d in draws} == set(range(-7, 8))
    assert all(0 <= d.origin[0] <= 4 and d.size == (12, 12) for d in draws)
    assert all(0.1 <= d.depth_scale <= 1.1 for d in draws)
    assert len({d.permutation for d in draws}) == 6
    for flag in ("flip_x", "flip_y", "transpose"):
        assert 900 < sum(getattr(d, flag) for d in draws) < 1100
    plain = sample_augmentation(g, dataclasses.replace(config, augment=False), (16, 16))
    assert dataclasses.replace(plain, origin=(0, 0)) == AugmentParams(size=(12, 12))


def test_learning_rate_warms_up_geometrically_and_decays_exponentially():
    config = TrainConfig(data="d", out="o", steps=1000).resolved()
    assert (config.warmup_steps, config.decay_start, config.half_life) == (20, 250, 250)
    assert math.isclose(learning_rate(0, config), 5e-4 * 1e-4 * 1e4 ** (1 / 20))
    assert math.isclose(
        learning_rate(9, config) ** 2, learning_rate(4, config) * learning_rate(14, config)
    )
    assert learning_rate(19, config) == learning_rate(250, config) == 5e-4
    assert math.isclose(learning_rate(500, config), 2.5e-4)
    assert math.isclose(learning_rate(999, config), 5e-4 * 0.5 ** (749 / 250))


# ------------------------------------------------------------------------------------ training
def test_three_steps_on_a_fixed_batch_reduce_the_loss(data, tiny, tmp_path):
    config = tiny(data, tmp_path)
    dataset = CropDataset(data)
    x, target = make_batch(dataset, config, step=0)
    assert x.shape == (2, 16, 32, 32) and target.shape == (2, 3, 32, 32)
    torch.manual_seed(0)
    model = build_model("fast_xs").to(memory_format=torch.channels_last)
    optimizer = make_optimizer(model, config)
    loss_fn = get_loss("l1")
    losses = [
        update(model, optimizer, lambda: compute_loss(model, loss_fn, x, target, 10), lr=1e-3)[0]
        for _ in range(4)
    ]
    assert losses[3] < losses[2] < losses[1] < losses[0], losses


def test_an_update_with_non_finite_gradients_is_skipped():
    net = torch.nn.Linear(2, 1)
    optimizer = torch.optim.Adam(net.parameters())
    before = {k: v.clone() for k, v in net.state_dict().items()}
    loss, updated = update(net, optimizer, lambda: net(torch.tensor([[math.inf, 1.0]])).sum(), 1.0)
    assert not updated and not math.isfinite(loss)
    assert all(torch.equal(v, before[k]) for k, v in net.state_dict().items())
    assert not optimizer.state  # Adam has not counted the update


def test_update_scale_multiplies_the_change_of_a_parameter():
    torch.manual_seed(0)
    plain, scaled = torch.nn.Linear(3, 1), torch.nn.Linear(3, 1)
    scaled.load_state_dict(plain.state_dict())
    x, multiplier = torch.rand(4, 3), torch.tensor([[2.0, 0.0, 1.0]])
    changes = []
    for net, scale in ((plain, ()), (scaled, [(scaled.weight, multiplier)])):
        start = net.weight.detach().clone()
        optimizer = torch.optim.SGD(net.parameters())
        update(net, optimizer, lambda n=net: n(x).square().sum(), 0.1, scale)
        changes.append(net.weight.detach() - start)
    assert (changes[0] != 0).all()
    torch.testing.assert_close(changes[1], changes[0] * multiplier)


def test_every_family_has_a_training_plan():
    from gdpt.reconstruct.families import FAMILIES

    assert list(PLANS) == list(FAMILIES)


def test_an_unknown_design_or_a_loss_of_another_family_is_refused_before_any_file(
    data, tiny, tmp_path
):
    with pytest.raises(ValueError, match="unknown network design 'no-such'.*dense-unet: paper"):
        train(tiny(data, tmp_path / "a", model="no-such"), progress=False)
    with pytest.raises(ValueError, match="loss 'l1_rel' does not apply to fast_xs.*dense-unet"):
        train(tiny(data, tmp_path / "b", loss="l1_rel"), progress=False)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_run_directory_and_exact_resume(
    data, tiny, tmp_path, resume_after_a_lost_checkpoint, assert_same_state
):
    run = tmp_path / "run"
    config = tiny(data, run)
    train(config, progress=False)
    assert json.loads((run / "config.json").read_text()) == config.to_dict()
    log = read_jsonl(run / "log.jsonl")
    assert [r["step"] for r in log] == [1, 2, 3]
    assert all(set(r) >= {"step", "loss", "lr", "time"} for r in log)
    val = read_jsonl(run / "val.jsonl")
    assert [r["step"] for r in val] == [2, 3]
    assert set(val[0]) >= {"relmse", "flip", "l1_relmse", "l1_flip", "count"}
    assert (run / "model.safetensors").is_file()
    card = json.loads((run / "model.json").read_text())
    assert card["config_name"] == "fast_xs" and card["steps"] == 3 and card["validation"]

    resumed, before, after = resume_after_a_lost_checkpoint(run, config, train)
    assert [r["step"] for r in resumed] == [1, 2, 3]
    assert resumed[2]["loss"] == log[2]["loss"] and resumed[2]["lr"] == log[2]["lr"]
    assert_same_state(before, after)  # weights and Adam state, bit for bit


def test_prune_checkpoints_keeps_the_newest_complete_ones(tmp_path):
    """All three files of every checkpoint but the newest ``keep`` are deleted; files of other
    names stay."""
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    for step in (1, 2, 10, 100, 1000):
        for suffix in (".pt", ".safetensors", ".json"):
            checkpoint_base(run, step).with_suffix(suffix).write_text("x")
    (run / "checkpoints" / "notes.txt").write_text("kept")
    prune_checkpoints(run, 2)
    left = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert left == [
        *(
            f"ckpt-{step:07d}{suffix}"
            for step in (100, 1000)
            for suffix in (".json", ".pt", ".safetensors")
        ),
        "notes.txt",
    ]
    prune_checkpoints(run, 2)  # nothing more to delete
    assert len(list((run / "checkpoints").iterdir())) == 7


def test_training_keeps_keep_checkpoints_and_resumes_from_the_last(data, tiny, tmp_path):
    run = tmp_path / "run"
    train(tiny(data, run, keep_checkpoints=1, val_every=0), progress=False)
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == [
        f"ckpt-0000003{suffix}" for suffix in (".json", ".pt", ".safetensors")
    ]
    train(tiny(data, run, keep_checkpoints=1, val_every=0, steps=4), resume=True, progress=False)
    assert [r["step"] for r in read_jsonl(run / "log.jsonl")] == [1, 2, 3, 4]
    assert sorted(p.name for p in (run / "checkpoints").iterdir())[0] == "ckpt-0000004.json"


def test_a_truncated_newest_checkpoint_falls_back_to_the_one_before(
    data, tiny, tmp_path, capfd, assert_same_state
):
    """A damaged newest ``.pt`` is skipped, said in one line; the resumed run is the same run."""
    run = tmp_path / "run"
    config = tiny(data, run, val_every=0, ckpt_every=1, keep_checkpoints=3)
    train(config, progress=False)
    newest = run / "checkpoints" / "ckpt-0000003.pt"
    before = torch.load(newest, weights_only=True)
    newest.write_bytes(newest.read_bytes()[:100])
    capfd.readouterr()
    train(config, resume=True, progress=False)
    said = [line for line in capfd.readouterr().err.splitlines() if "gdpt train:" in line]
    assert len(said) == 1
    assert "ckpt-0000003.pt is unreadable" in said[0] and "from step 2" in said[0]
    after = torch.load(newest, weights_only=True)
    assert_same_state(
        {k: before[k] for k in ("step", "model", "optimizer")},
        {k: after[k] for k in ("step", "model", "optimizer")},
    )


def test_no_readable_checkpoint_is_refused_naming_them(data, tiny, tmp_path):
    run = tmp_path / "run"
    config = tiny(data, run, steps=1, val_every=0)
    train(config, progress=False)
    state = run / "checkpoints" / "ckpt-0000001.pt"
    state.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="no readable checkpoint: ckpt-0000001.pt is unreadable"):
        train(config, resume=True, progress=False)


def test_resume_from_a_state_without_the_network_is_refused(data, tiny, tmp_path):
    """A ``.pt`` without the exact weights (written by an older gdpt) cannot resume exactly."""
    run = tmp_path / "run"
    train(tiny(data, run, steps=1, val_every=0), progress=False)
    state = run / "checkpoints" / "ckpt-0000001.pt"
    payload = torch.load(state, weights_only=True)
    del payload["model"]
    torch.save(payload, state)
    with pytest.raises(ValueError, match=re.escape(f"{state}: no network state")):
        train(tiny(data, run, steps=2, val_every=0), resume=True, progress=False)


def test_resume_with_another_config_is_refused(data, tiny, tmp_path, capsys):
    run = tmp_path / "run"
    train(tiny(data, run, steps=1, val_every=0), progress=False)
    with pytest.raises(FileExistsError, match="--resume"):
        train(tiny(data, run, steps=1, val_every=0), progress=False)
    with pytest.raises(ConfigMismatchError, match="model: 'fast_xs' .* 'fast'"):
        train(tiny(data, run, steps=2, model="fast"), resume=True, progress=False)
    status = main(
        [
            "train",
            "--config",
            "fast_xs",
            "--data",
            str(data),
            "--out",
            str(run),
            "--loss",
            "flip",
            "--resume",
        ]
    )
    assert status == 2
    err = capsys.readouterr().err
    assert "gdpt train: error: cannot resume" in err and "loss: 'l1'" in err


def test_nograd_model_trains_on_path_traced_inputs(data, tiny, tmp_path):
    config = tiny(data, tmp_path / "nograd", model="nograd", steps=1, batch=1, val_every=1)
    train(config, progress=False)
    val = read_jsonl(tmp_path / "nograd" / "val.jsonl")[0]
    assert val["count"] == 2 and math.isfinite(val["relmse"])


#: Family -> ``(dataset fixture, gdpt train options)`` of a 2-step torchrun run.
DDP_RUNS = {
    "dense-unet": ("tiny_dataset", ["--config", "fast_xs", "--loss", "l1"]),
    "oidn-finetune": ("pt_dataset", ["--config", "oidn-grad", "--loss", "l1_rel", "--crop", "16"]),
}


@pytest.mark.parametrize(
    "family", ["dense-unet", pytest.param("oidn-finetune", marks=pytest.mark.slow)]
)
def test_torchrun_ddp_two_processes(family, request, tmp_path):
    """The one training loop runs any family's plan under torchrun (gloo on the CPU)."""
    fixture, options = DDP_RUNS[family]
    data = request.getfixturevalue(fixture)
    run = tmp_path / "ddp"
    command = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc_per_node",
        "2",
        "--master-port",
        str(29500 + os.getpid() % 1000),
        "-m",
        "gdpt",
        "train",
        *options,
        "--data",
        str(data),
        "--val-data",
        str(data),
        "--out",
        str(run),
        "--steps",
        "2",
        "--batch",
        "1",
        "--val-every",
        "2",
        "--val-crops",
        "2",
        "--ckpt-every",
        "1",
    ]
    result = subprocess.run(command, check=False, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert [r["step"] for r in read_jsonl(run / "log.jsonl")] == [1, 2]
    assert len(read_jsonl(run / "val.jsonl")) == 1
    assert (run / "checkpoints" / "ckpt-0000002.pt").is_file()
    assert torch.load(run / "checkpoints" / "ckpt-0000002.pt", weights_only=True)["world_size"] == 2


def test_validation_skips_an_unreadable_element_with_a_warning(data, tmp_path):
    """A held-out element whose render cannot be read is named in a warning and left out; the
    others are still validated (the fine-tuning validation uses the same element loader)."""
    import shutil

    from gdpt.training.manifest import DatasetWarning
    from gdpt.training.validation import load_validation

    root = tmp_path / "data"
    shutil.copytree(data, root)
    dataset = CropDataset(root)
    record, level = dataset.element(0)
    (root / record["files"][f"in{level}"]).write_bytes(b"not an EXR file")
    with pytest.warns(DatasetWarning, match="validation element 0 skipped"):
        elements = load_validation(dataset, 2, torch.device("cpu"))  # picks the first and last
    assert len(elements) == 1
