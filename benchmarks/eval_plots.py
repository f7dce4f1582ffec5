"""The error-versus-time plots of ``docs/eval/`` redrawn from the full tables of
``docs/lab/2026-12-evaluation-history.md`` (the nine-scene study of 2026-12-03).

The study's ``results.json`` is not kept in the repository; its per-scene tables
("Full tables": method, budget, spp, achieved time, relMSE, SMAPE, 1-SSIM, LDR-FLIP, replicate
means) hold every point of the plots. This script reads them back
into the shape of a ``results.json`` and draws them with the study's own report
(:func:`gdpt.study.report.plot_scene`), so method names and style are the current ones.
Rounded as printed (times to 0.01 s, metrics to 4 digits). Usage::

    .venv/bin/python benchmarks/eval_plots.py cornell-box veach-mis --out docs/eval
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import Any

from gdpt.study.report import plot_scene
from gdpt.study.results import budget_key

ROOT = Path(__file__).resolve().parents[1]

#: Column label in the tables -> metric name in ``results.json``.
COLUMNS = {"relMSE": "relmse", "SMAPE": "smape", "1-SSIM": "one_minus_ssim", "LDR-FLIP": "flip_ldr"}


def scene_table(text: str, scene: str) -> dict[str, Any]:
    """The ``results.json`` entry of ``scene`` from its ``### scene`` section under
    ``## Full tables`` (the quick budgets; the longer ones have their own section)."""
    full = text.split("\n## Full tables", 1)[1].split("\n### At ", 1)[0]
    match = re.search(rf"^### {re.escape(scene)}\n(.*?)(?=^### |\Z)", full, re.M | re.S)
    if match is None:
        raise SystemExit(f"no section '### {scene}' under '## Full tables'")
    section = match.group(1)
    width, height = (int(v) for v in re.search(r"^(\d+)x(\d+) px", section, re.M).groups())
    rows = [line.strip("|").split("|") for line in section.splitlines() if line.startswith("| ")]
    head = [cell.strip() for cell in rows[0]]
    methods: dict[str, dict[str, Any]] = {}
    for row in rows[1:]:
        cells = dict(zip(head, (cell.strip() for cell in row), strict=True))
        budget = float(cells["budget s"])
        metrics = {COLUMNS[k]: float(v) for k, v in cells.items() if k in COLUMNS and v}
        seconds = float(cells["time s"].rstrip("*"))
        cell = {"seconds": seconds, "metrics": metrics}
        methods.setdefault(cells["method"], {"cells": {}})["cells"][budget_key(budget)] = cell
    return {"status": "ok", "resolution": [width, height], "methods": methods}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="+", help="scene sections of the full tables")
    history = ROOT / "docs" / "lab" / "2026-12-evaluation-history.md"
    parser.add_argument("--doc", type=Path, default=history)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "eval")
    args = parser.parse_args()
    text = args.doc.read_text()
    scenes = {scene: scene_table(text, scene) for scene in args.scenes}
    cells = [c for e in scenes.values() for m in e["methods"].values() for c in m["cells"]]
    budgets = sorted({float(key) for key in cells})
    results = {
        "config": {"metrics": list(COLUMNS.values()), "budgets": budgets, "protocol": "total"},
        "scenes": scenes,
    }
    for scene, entry in scenes.items():
        plot_scene(results, scene, entry, args.out / f"{scene}.png")
        print(f"wrote {args.out / f'{scene}.png'}")


if __name__ == "__main__":
    main()
