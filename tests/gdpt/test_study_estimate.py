"""The study's reference-free estimate (:mod:`gdpt.study.estimate`): beside the true ratio
with a reference, instead of it with ``--no-reference`` (tiny studies: 32 px, 0.1 s)."""

from __future__ import annotations

import json

import pytest

from gdpt.cli import main

pytestmark = pytest.mark.usefixtures("variant", "single_thread")


def study(out, *extra: str) -> dict:
    argv = ["evaluate", "--scenes", "builtin:cbox-demo", "--out", str(out), "--quick"]
    argv += ["--resolution", "32", "--budgets", "0.1", "--reference-spp", "256"]
    argv += ["--methods", "pt+oidn-tuned", "pt", "--metrics", "relmse", "--no-progress"]
    assert main([*argv, *extra]) == 0
    return json.loads((out / "results.json").read_text())["scenes"]["cbox-demo"]


def test_feature_with_a_reference_both_ratios(tmp_path):
    """Every non-baseline cell records the estimate, its interval and the true ratio of the
    same renders; results.md shows them."""
    entry = study(tmp_path / "r")
    cell = entry["methods"]["pt"]["cells"]["0.1"]
    estimate = cell["estimate"]
    assert estimate["baseline"] == "pt+oidn-tuned" and estimate["plain_spp"] == cell["spp"]
    true = cell["replicates"][0]["metrics"]["relmse"]
    base = entry["methods"]["pt+oidn-tuned"]["cells"]["0.1"]["replicates"][0]["metrics"]
    assert estimate["true_ratio"] == pytest.approx(true / base["relmse"])
    assert isinstance(estimate["ratio"], float) and len(estimate["interval"]) == 2
    assert "estimate" not in entry["methods"]["pt+oidn-tuned"]["cells"]["0.1"]
    text = (tmp_path / "r" / "results.md").read_text()
    assert "Reference-free estimate of the relMSE ratio to `pt+oidn-tuned`" in text
    assert "| pt | 0.1 |" in text


def test_feature_no_reference_estimate_only(tmp_path):
    """``--no-reference``: no reference rendered, no metrics, the estimate as the result (its
    value is not asserted: at 0.1 s on 32 px the baseline's error is within ``P``'s noise, so
    the estimated ratio can take either sign, with an unbounded interval)."""
    entry = study(tmp_path / "n", "--no-reference")
    assert entry["reference"] is None and not (tmp_path / "n" / "references").exists()
    cell = entry["methods"]["pt"]["cells"]["0.1"]
    assert cell["metrics"] == {} and "true_ratio" not in cell["estimate"]
    estimate = cell["estimate"]
    assert isinstance(estimate["ratio"], float) and len(estimate["interval"]) == 2
    text = (tmp_path / "n" / "results.md").read_text()
    assert "no reference (--no-reference)" in text and "| pt | 0.1 |" in text


def test_exception_no_reference_without_the_baseline(tmp_path, capsys):
    argv = ["evaluate", "--scenes", "builtin:cbox-demo", "--out", str(tmp_path), "--quick"]
    assert main([*argv, "--methods", "pt", "--no-reference", "--no-progress"]) == 2
    assert "--no-reference estimates ratios to pt+oidn-tuned" in capsys.readouterr().err
