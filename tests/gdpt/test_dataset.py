"""gdpt.training.preprocess, .manifest and .dataset: deterministic plans, resumable rendering,
manifest safety, corrupt shards, Ray."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
import torch

import gdpt.training.preprocess as dataset_module
from gdpt.cli import main
from gdpt.io.exr import load_buffers
from gdpt.training.dataset import CropDataset
from gdpt.training.manifest import MANIFEST_FILE, DatasetWarning, append_manifest, read_manifest
from gdpt.training.preprocess import DatasetConfig, build_dataset, plan_crop

#: Manifest fields that depend on timing (and thus on file headers), not on the content.
TIMING_FIELDS = ("render_seconds", "bytes")


def content_of(root: Path) -> dict[str, dict]:
    records, problems = read_manifest(root)
    assert not problems
    return {r["crop"]: {k: v for k, v in r.items() if k not in TIMING_FIELDS} for r in records}


def assert_same_pixels(root_a: Path, root_b: Path, crop: str) -> None:
    for name in ("in0", "in4", "pt2", "target"):
        a = load_buffers(root_a / "crops" / crop / f"{name}.exr")
        b = load_buffers(root_b / "crops" / crop / f"{name}.exr")
        assert a.present() == b.present()
        for (_, ta), (_, tb) in zip(a.items(), b.items(), strict=True):
            torch.testing.assert_close(ta, tb, rtol=1e-5, atol=1e-6)


@pytest.fixture
def copy_of(tiny_dataset, tmp_path) -> Path:
    return Path(shutil.copytree(tiny_dataset, tmp_path / "copy"))


def test_plan_is_deterministic_stratified_log_uniform():
    config = DatasetConfig(spp_min=2, spp_max=1024, levels=5, seed=3)
    plan = plan_crop(config, 7, 2)
    assert plan == plan_crop(config, 7, 2)
    assert plan.crop_id == "s00007-v002"
    assert plan.scene_seed == plan_crop(config, 7, 0).scene_seed  # one scene, several views
    assert plan.input_seeds != plan_crop(config, 7, 0).input_seeds
    assert plan.scene_seed != plan_crop(DatasetConfig(seed=4), 7, 2).scene_seed
    assert list(plan.spp) == sorted(plan.spp) and 2 <= plan.spp[0] and plan.spp[-1] <= 1024
    assert plan.pt_spp == tuple(round(2.5 * s) for s in plan.spp)
    seeds = [*plan.input_seeds, *plan.pt_seeds, plan.target_seed]
    assert len(set(seeds)) == len(seeds)
    # Stratified: draw k lies in the k-th fifth of the log range (up to rounding).
    log_range = torch.tensor([2.0, 1024.0]).log()
    for k in range(5):
        fraction = torch.tensor([k, k + 1]) / 5
        edges = torch.exp(log_range[0] + (log_range[1] - log_range[0]) * fraction)
        assert edges[0].floor() <= plan.spp[k] <= edges[1].ceil()


def test_dataset_layout_and_reader(tiny_dataset):
    records, _ = read_manifest(tiny_dataset)
    assert [r["crop"] for r in records] == ["s00000-v000", "s00000-v001"]
    record = records[0]
    assert set(record["files"]) == {
        *(f"in{k}" for k in range(5)),
        *(f"pt{k}" for k in range(5)),
        "target",
    }
    assert record["resolution"] == [16, 16] and record["target_spp"] == 8
    target = load_buffers(tiny_dataset / record["files"]["target"])
    assert target.metadata["primal"] == "l1_poisson" and target.spp == 8 and target.has_gradients
    pt = load_buffers(tiny_dataset / record["files"]["pt3"])
    assert not pt.has_gradients and pt.spp == record["pt_spp"][3]

    gdpt_set = CropDataset(tiny_dataset)
    pt_set = CropDataset(tiny_dataset, kind="pt")
    assert len(gdpt_set) == len(pt_set) == 10
    item = gdpt_set[7]
    assert (item["crop"], item["level"], item["spp"]) == ("s00000-v001", 2, records[1]["spp"][2])
    assert {k: tuple(v.shape) for k, v in item["inputs"].items()} == {
        "primal": (16, 16, 3),
        "dx": (16, 16, 3),
        "dy": (16, 16, 3),
        "albedo": (16, 16, 3),
        "normal": (16, 16, 3),
        "depth": (16, 16, 1),
    }
    assert set(pt_set[0]["inputs"]) == {"primal", "albedo", "normal", "depth"}
    assert item["target"].shape == (16, 16, 3) and torch.isfinite(item["target"]).all()


def test_resume_after_kill_gives_the_same_dataset(
    tiny_dataset, tiny_dataset_config, tmp_path, monkeypatch
):
    root = tmp_path / "resumed"
    real = dataset_module.render_crop
    calls = []

    def killed_on_second_crop(plan, out, content, variant=None):
        calls.append(plan.crop_id)
        if len(calls) == 2:  # the kill hits while crop 2 is half written
            (Path(out) / "crops" / plan.crop_id).mkdir(parents=True)
            (Path(out) / "crops" / plan.crop_id / "in0.exr").write_bytes(b"partial")
            raise KeyboardInterrupt
        return real(plan, out, content, variant)

    monkeypatch.setattr(dataset_module, "render_crop", killed_on_second_crop)
    with pytest.raises(KeyboardInterrupt):
        build_dataset(tiny_dataset_config(), root, progress=False)
    monkeypatch.undo()
    # Out of disk while appending the next line: a torn line without newline.
    with (root / MANIFEST_FILE).open("ab") as f:
        f.write(b'{"crop": "s00000-v001", "fil')
    with pytest.warns(DatasetWarning, match="invalid line"):
        assert len(CropDataset(root)) == 5

    with pytest.warns(DatasetWarning, match="repairing"):
        summary = build_dataset(tiny_dataset_config(), root, progress=False)
    assert (summary.rendered, summary.skipped) == (1, 1)
    assert content_of(root) == content_of(tiny_dataset)
    assert_same_pixels(root, tiny_dataset, "s00000-v001")
    assert len(CropDataset(root)) == 10
    assert build_dataset(tiny_dataset_config(), root, progress=False).rendered == 0


def test_corrupt_and_partial_shards_are_skipped_with_warning(copy_of):
    partial = copy_of / "crops" / "s00000-v001" / "pt2.exr"
    partial.write_bytes(partial.read_bytes()[:-100])
    assert len(CropDataset(copy_of)) == 10  # the gdpt inputs do not use pt2
    with pytest.warns(DatasetWarning, match=r"s00000-v001/pt2.exr has \d+ bytes"):
        pt_set = CropDataset(copy_of, kind="pt")
    assert len(pt_set) == 5 and {r["crop"] for r in pt_set.crops} == {"s00000-v000"}

    # Same size, garbage inside: found only when loaded; the next element is returned.
    corrupt = copy_of / "crops" / "s00000-v000" / "in1.exr"
    data = bytearray(corrupt.read_bytes())
    data[400:] = b"\xff" * (len(data) - 400)
    corrupt.write_bytes(bytes(data))
    gdpt_set = CropDataset(copy_of)
    with pytest.warns(DatasetWarning, match="unreadable element 1"):
        item = gdpt_set[1]
    assert (item["crop"], item["level"]) == ("s00000-v000", 2)


def test_empty_missing_and_mismatched_datasets(copy_of, tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        CropDataset(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="empty dataset"):
        CropDataset(tmp_path / "empty")
    with pytest.raises(ValueError, match="no crop of the selected scenes"):
        CropDataset(copy_of, scenes=lambda s: s > 0)
    lines = (copy_of / MANIFEST_FILE).read_text().splitlines()
    record = json.loads(lines[1])
    record["resolution"] = [32, 32]
    (copy_of / MANIFEST_FILE).write_text(lines[0] + "\n" + json.dumps(record) + "\n")
    with pytest.raises(ValueError, match="different sizes.*16x16.*32x32"):
        CropDataset(copy_of)


def test_rerun_with_other_settings_is_refused(copy_of, tiny_dataset_config, capsys):
    with pytest.raises(ValueError, match="target_spp: 8 .* vs 16 requested"):
        build_dataset(tiny_dataset_config(target_spp=16), copy_of, progress=False)
    status = main(["dataset", "--out", str(copy_of), "--scenes", "1", "--views", "1"])
    assert status == 2
    assert "gdpt dataset: error:" in capsys.readouterr().err


def test_ray_local_mode(tiny_dataset, tiny_dataset_config, tmp_path):
    root = tmp_path / "ray"
    summary = build_dataset(tiny_dataset_config(views=1), root, ray_address="local", progress=False)
    assert summary.rendered == 1
    expected = content_of(tiny_dataset)
    assert content_of(root) == {"s00000-v000": expected["s00000-v000"]}
    assert_same_pixels(root, tiny_dataset, "s00000-v000")


def test_local_worker_processes(tiny_dataset, tiny_dataset_config, tmp_path):
    root = tmp_path / "workers"
    summary = build_dataset(tiny_dataset_config(), root, workers=2, progress=False)
    assert summary.rendered == 2
    assert content_of(root) == content_of(tiny_dataset)
    assert_same_pixels(root, tiny_dataset, "s00000-v001")


def test_out_of_disk_while_appending_leaves_a_valid_manifest(tmp_path, monkeypatch):
    append_manifest(tmp_path, {"crop": "a", "files": {}, "resolution": [8, 8]})
    real_write = os.write

    def disk_full(fd, data):  # the disk fills up half way through the line
        return real_write(fd, data[: len(data) // 2])

    monkeypatch.setattr(os, "write", disk_full)
    with pytest.raises(OSError, match="short write"):
        append_manifest(tmp_path, {"crop": "b", "files": {}, "resolution": [8, 8]})
    monkeypatch.undo()
    records, problems = read_manifest(tmp_path)
    assert [r["crop"] for r in records] == ["a"] and len(problems) == 1
    append_manifest(tmp_path, {"crop": "b", "files": {}, "resolution": [8, 8]})
    records, problems = read_manifest(tmp_path)
    assert [r["crop"] for r in records] == ["a", "b"] and len(problems) == 1


def test_pool_kind_pools_the_path_traced_input(pt_dataset):
    """``pool`` elements: the G-PT input with the path-traced input of the same crop and level
    averaged in by sample count, features those of the path-traced input; gradients unchanged."""
    sets = {kind: CropDataset(pt_dataset, kind=kind) for kind in ("gdpt", "pt", "pool")}
    assert len(sets["pool"]) == len(sets["gdpt"])
    for index in range(len(sets["pool"])):
        g, p, pooled = (sets[kind].load(index) for kind in ("gdpt", "pt", "pool"))
        assert pooled["spp"] == g["spp"] and (pooled["crop"], pooled["level"]) == (
            g["crop"],
            g["level"],
        )
        n_g, n_p = g["spp"], p["spp"]
        expected = (n_g * g["inputs"]["primal"] + n_p * p["inputs"]["primal"]) / (n_g + n_p)
        torch.testing.assert_close(pooled["inputs"]["primal"], expected)
        for name in ("albedo", "normal", "depth"):
            assert torch.equal(pooled["inputs"][name], p["inputs"][name])
        assert torch.equal(pooled["inputs"]["dx"], g["inputs"]["dx"])
        assert torch.equal(pooled["target"], g["target"])


def test_mis_primal_renders_only_the_gdpt_inputs_with_it(
    tiny_dataset, tiny_dataset_config, tmp_path
):
    """``primal="mis"`` reaches the integrator of the G-PT inputs (their primal differs from the
    base dataset's at the same seeds) and nothing else (path-traced inputs and target equal)."""
    root = tmp_path / "mis"
    build_dataset(tiny_dataset_config(views=1, primal="mis"), root, progress=False)
    assert json.loads((root / "dataset.json").read_text())["config"]["primal"] == "mis"
    assert "primal" not in json.loads((tiny_dataset / "dataset.json").read_text())["config"]
    crop = root / "crops" / "s00000-v000"
    base = tiny_dataset / "crops" / "s00000-v000"
    for name in ("pt0", "pt4", "target"):
        torch.testing.assert_close(
            load_buffers(crop / f"{name}.exr").primal, load_buffers(base / f"{name}.exr").primal
        )
    for k in range(5):
        mis, plain = load_buffers(crop / f"in{k}.exr"), load_buffers(base / f"in{k}.exr")
        assert (mis.primal - plain.primal).abs().max() > 1e-3, f"in{k}: the base primal"
    with pytest.raises(ValueError, match="primal"):
        build_dataset(tiny_dataset_config(views=1), root, progress=False)  # never mixed


def test_unknown_primal_is_refused_before_rendering(tmp_path, capsys):
    out = tmp_path / "never"
    with pytest.raises(SystemExit) as exit_info:
        main(["dataset", "--out", str(out), "--scenes", "1", "--views", "1", "--primal", "all"])
    assert exit_info.value.code == 2 and not out.exists()
    assert "invalid choice: 'all'" in capsys.readouterr().err
