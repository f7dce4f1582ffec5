"""gdpt.training.refinement: the grid search picks its argmin, writes a shippable run, and
refuses what it cannot refine."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from gdpt.reconstruct.oidn_finetune import DESIGNS, OIDNReconstructor, base_model, encode_delta
from gdpt.reconstruct.refine import GatedRefinement

from gdpt.training.checkpoint import write_checkpoint
from gdpt.training.model_report import ship_model
from gdpt.training.refinement import select_refinement


def fake_run(root: Path, design: str, data: Path) -> Path:
    """A run directory holding OIDN itself as ``design`` (no training)."""
    root.mkdir(parents=True)
    write_checkpoint(root / "model", *encode_delta(base_model(DESIGNS[design]), design, {}))
    (root / "config.json").write_text(json.dumps({"data": str(data), "holdout_every": 1}))
    (root / "log.jsonl").write_text(json.dumps({"step": 1, "loss": 0.1, "time": 1.0}) + "\n")
    return root / "model.safetensors"


def test_the_lowest_mean_relmse_is_chosen_and_the_run_ships(pt_dataset, tmp_path):
    model = fake_run(tmp_path / "run", "oidn-grad", pt_dataset)
    out = tmp_path / "refined"
    path = select_refinement(
        model, pt_dataset, out, alphas=(0.5,), taus=(0.02, math.inf), progress=False
    )
    selection = json.loads((out / "refinement.json").read_text())
    assert selection["elements"] == 4 and len(selection["grid"]) == 2
    best = min(selection["grid"], key=lambda r: r["relmse"])
    chosen = GatedRefinement.from_dict(selection["chosen"])
    assert chosen == GatedRefinement.from_dict({"alpha": best["alpha"], "tau": best["tau"]})
    rec = OIDNReconstructor.from_checkpoint(path)
    assert rec.refine == chosen
    assert path.read_bytes() == model.read_bytes()  # weights copied unchanged
    assert "| (network alone) |" in (out / "refinement.md").read_text()
    shipped = OIDNReconstructor.from_checkpoint(ship_model(out, "oidn-grad", dest=tmp_path / "m"))
    assert shipped.refine == chosen and shipped.card["refine_selection"]["elements"] == 4


def test_an_existing_output_and_a_network_without_gradients_are_refused(pt_dataset, tmp_path):
    grad = fake_run(tmp_path / "grad", "oidn-grad", pt_dataset)
    with pytest.raises(FileExistsError, match="new --out"):
        select_refinement(grad, pt_dataset, tmp_path / "grad", progress=False)
    nograd = fake_run(tmp_path / "nograd", "oidn-nograd", pt_dataset)
    with pytest.raises(ValueError, match="reads no gradients"):
        select_refinement(nograd, pt_dataset, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()
