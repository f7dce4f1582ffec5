"""gdpt.training.model_report: training plot, held-out comparison, shipping, CLI errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from gdpt.reconstruct.dense_unet_reconstructor import DenseUNetReconstructor

from gdpt.cli import main
from gdpt.io.exr import load_buffers
from gdpt.metrics import relmse
from gdpt.training import model_report
from gdpt.training.config import TrainConfig
from gdpt.training.manifest import read_manifest
from gdpt.training.train import train


@pytest.fixture(scope="module")
def runs(tmp_path_factory, tiny_dataset) -> tuple[Path, dict[str, Path]]:
    """The shared 2-crop dataset and two 2-step runs (G-PT and no-gradient networks) on it."""
    root = tmp_path_factory.mktemp("report")
    data = tiny_dataset
    out = {}
    for name, config in (("dense", "fast_xs"), ("dense-nograd", "fast_xs_nograd")):
        out[name] = root / name
        train(
            TrainConfig(
                model=config,
                data=str(data),
                val_data=str(data),
                out=str(out[name]),
                loss="l1",
                steps=2,
                batch=1,
                vary_padding=2,
                val_every=1,
                val_crops=2,
            ),
            progress=False,
        )
    return data, out


def test_cli_writes_plot_and_comparison(runs, tmp_path):
    data, run_dirs = runs
    status = main(
        [
            "model-report",
            "--data",
            str(data),
            "--holdout-every",
            "1",
            "--out",
            str(tmp_path),
            *[f"--run={k}={v}" for k, v in run_dirs.items()],
        ]
    )
    assert status == 0
    assert (tmp_path / "training.png").stat().st_size > 10_000
    result = json.loads((tmp_path / "comparison.json").read_text())
    assert result["crops"] == 2 and len(result["levels"]) == 5
    assert {"dense", "dense-nograd", "gdpt+l1", "pt"} <= set(result["mean"])
    assert "| mean over levels |" in (tmp_path / "comparison.md").read_text()


def test_comparison_scores_the_right_inputs(runs):
    """The ``pt`` row must equal relMSE of each crop's own path-traced input at that level."""
    data, run_dirs = runs
    result = model_report.compare_models(
        data, {"dense": run_dirs["dense"] / "model.safetensors"}, holdout_every=1, progress=False
    )
    records, _ = read_manifest(data)
    for level, entry in enumerate(result["levels"]):
        expected = []
        for record in records:
            pt = load_buffers(data / record["files"][f"pt{level}"]).primal
            target = load_buffers(data / record["files"]["target"]).primal
            expected.append(relmse(pt, target))
        assert entry["methods"]["pt"]["relmse"] == pytest.approx(sum(expected) / 2, rel=1e-6)
        assert entry["spp"] == sum(r["spp"][level] for r in records) / 2


def test_ship_model_writes_a_loadable_card_and_enforces_the_size_limit(runs, tmp_path, monkeypatch):
    _, run_dirs = runs
    path = model_report.ship_model(run_dirs["dense"], "dense", comparison={"x": 1}, dest=tmp_path)
    card = DenseUNetReconstructor.from_checkpoint(path).card
    assert card["name"] == "dense" and card["heldout_comparison"] == {"x": 1}
    assert card["wall_clock_hours"] >= 0 and card["dataset"]["config"]["target_spp"] == 8
    assert card["train_config"]["model"] == "fast_xs"
    manifest = (Path(card["train_config"]["data"]) / "manifest.jsonl").read_text().splitlines()
    assert card["dataset_size"]["crops"] == len(manifest) > 0
    monkeypatch.setattr(model_report, "MAX_SHIPPED_MIB", 0.1)
    with pytest.raises(ValueError, match="exceeds the 0.1 MiB"):
        model_report.ship_model(run_dirs["dense"], "big", dest=tmp_path)
    assert not (tmp_path / "big.safetensors").exists()


@pytest.mark.parametrize(
    "run, message",
    [("dense", "expected NAME=RUN_DIR"), ("dense=/nonexistent", "model.safetensors not found")],
)
def test_cli_bad_run_argument(runs, tmp_path, capsys, run, message):
    data, _ = runs
    status = main(["model-report", "--data", str(data), "--out", str(tmp_path), "--run", run])
    assert status == 2
    assert message in capsys.readouterr().err


def test_cli_ships_only_the_named_runs(runs, tmp_path, monkeypatch, capsys):
    import gdpt.checkpoints

    data, run_dirs = runs
    monkeypatch.setattr(gdpt.checkpoints, "MODEL_DIR", tmp_path / "models")
    args = ["model-report", "--data", str(data), "--holdout-every", "1", "--out", str(tmp_path)]
    args += [f"--run={k}={v}" for k, v in run_dirs.items()]
    assert main([*args, "--ship", "dense-nograd"]) == 0
    assert sorted(p.name for p in (tmp_path / "models").iterdir()) == [
        "dense-nograd.json",
        "dense-nograd.safetensors",
    ]
    assert main([*args, "--ship", "nope"]) == 2
    assert "--ship nope: not among the --run names" in capsys.readouterr().err


def test_cli_compares_checkpoints_given_by_model(runs, tmp_path, capsys):
    data, run_dirs = runs
    args = ["model-report", "--data", str(data), "--holdout-every", "1", "--out", str(tmp_path)]
    args += [f"--run=dense={run_dirs['dense']}"]
    checkpoint = run_dirs["dense-nograd"] / "model.safetensors"
    assert main([*args, f"--model=other={checkpoint}"]) == 0
    result = json.loads((tmp_path / "comparison.json").read_text())
    assert {"dense", "other"} <= set(result["mean"])
    assert main([*args, f"--model=dense={checkpoint}"]) == 2
    assert "the name 'dense' is taken by a --run" in capsys.readouterr().err
    assert main([*args, "--model=x=/nonexistent.safetensors"]) == 2
    assert "/nonexistent.safetensors not found" in capsys.readouterr().err


def test_input_kind_follows_the_card_and_the_features():
    from types import SimpleNamespace

    pooled = {"sampling": {"primal_spp_factor": 2.5}}
    grad = ("primal", "albedo", "normal", "dx", "dy")
    kind = model_report.input_kind
    assert kind(SimpleNamespace(features=grad, card=pooled)) == "pool"
    assert kind(SimpleNamespace(features=grad, card={})) == "gdpt"
    assert kind(SimpleNamespace(features=grad[:3])) == "pt"
    on_gdpt = {"training": {"input": "gdpt"}}  # fine-tuned on the G-PT primal, no gradients
    assert kind(SimpleNamespace(features=grad[:3], card=on_gdpt)) == "gdpt"


def test_a_model_of_an_unknown_family_is_refused_by_name(runs, tmp_path, capsys):
    """Shipping or comparing a checkpoint whose card has no known family's format fails with the
    card's path and the known families, before anything is written or scored."""
    from gdpt.reconstruct.families import FAMILIES

    data, run_dirs = runs
    run = tmp_path / "odd-run"
    shutil.copytree(run_dirs["dense"], run)
    card = json.loads((run / "model.json").read_text())
    (run / "model.json").write_text(json.dumps({**card, "format": "someone-else/3"}))
    with pytest.raises(ValueError, match="no known network family") as error:
        model_report.ship_model(run, "odd", dest=tmp_path / "models")
    assert str(run / "model.json") in str(error.value)
    assert all(name in str(error.value) for name in FAMILIES)
    assert not (tmp_path / "models").exists()
    args = ["model-report", "--data", str(data), "--holdout-every", "1", "--out", str(tmp_path)]
    args += [f"--run=dense={run_dirs['dense']}", f"--model=odd={run / 'model.safetensors'}"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "no known network family" in err and str(run / "model.json") in err
    assert not (tmp_path / "comparison.json").exists()


def _synthetic_result(a: list[float], b: list[float], levels: list[int]) -> dict:
    return {
        "mean": {"a": {}, "b": {}},
        "levels": [
            {"spp": 4.0 * (k + 1), "pt_spp": 10.0 * (k + 1)} for k in range(1 + max(levels))
        ],
        "elements": {"level": levels, "a": {"relmse": a}, "b": {"relmse": b}},
    }


def test_paired_comparison_is_the_geometric_mean_ratio_with_a_t_interval():
    import math

    ratios = [0.5, 0.8, 1.25, 0.4]
    b = [0.1, 2.0, 0.3, 5.0]
    result = _synthetic_result([r * y for r, y in zip(ratios, b, strict=True)], b, [0, 1, 0, 1])
    pair = model_report.paired_comparison(result, "a", "b")
    logs = [math.log(r) for r in ratios]
    mean = sum(logs) / 4
    sd = math.sqrt(sum((x - mean) ** 2 for x in logs) / 3)
    assert pair["all"]["ratio"] == pytest.approx(math.exp(mean))
    assert pair["all"]["high"] == pytest.approx(math.exp(mean + 3.182 * sd / 2))
    assert pair["all"]["a_lower"] == 0.75 and pair["all"]["n"] == 4
    assert pair["levels"][0]["ratio"] == pytest.approx(math.sqrt(0.5 * 1.25))
    assert pair["levels"][1]["a_lower"] == 1.0 and pair["levels"][1]["spp"] == 8.0
    assert "| all | 4 |" in model_report.paired_markdown(pair)


def test_paired_comparison_refuses_unknown_labels_and_non_positive_scores():
    result = _synthetic_result([1.0, 0.0], [1.0, 1.0], [0, 0])
    with pytest.raises(KeyError, match="'c' is not in the comparison"):
        model_report.paired_comparison(result, "c", "b")
    with pytest.raises(ValueError, match="not positive"):
        model_report.paired_comparison(result, "a", "b")


def test_cli_pairs_runs_element_by_element(runs, tmp_path, capsys):
    data, run_dirs = runs
    args = ["model-report", "--data", str(data), "--holdout-every", "1", "--out", str(tmp_path)]
    args += [f"--run={k}={v}" for k, v in run_dirs.items()]
    assert main([*args, "--pair", "dense", "dense-nograd", "--pair", "dense", "pt"]) == 0
    result = json.loads((tmp_path / "comparison.json").read_text())
    first, first_flip, second, second_flip = result["pairs"]
    assert (first["a"], first["b"], second["b"]) == ("dense", "dense-nograd", "pt")
    assert [p["metric"] for p in result["pairs"]] == ["relmse", "flip"] * 2
    for pair, metric in ((second, "relmse"), (second_flip, "flip")):
        dense = result["elements"]["dense"][metric]
        pt = result["elements"]["pt"][metric]
        assert len(dense) == 2 * 5 and pair["all"]["a_lower"] == sum(
            x < y for x, y in zip(dense, pt, strict=True)
        ) / len(dense)
    report = (tmp_path / "comparison.md").read_text()
    assert "relmse dense / dense-nograd" in report and "flip dense / dense-nograd" in report
    assert main([*args, "--pair", "dense", "nope"]) == 2
    assert "--pair dense nope: nope is neither" in capsys.readouterr().err
