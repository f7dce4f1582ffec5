"""Choosing the gated refinement (:mod:`gdpt.reconstruct.refine`) of a gradient network on
procedural validation data.

``gdpt select-refinement --model RUN/model.safetensors --data DATA --out RUN2``: every element
of ``DATA`` (every crop and input level; use a dataset the network was not trained on, e.g.
another ``gdpt dataset --seed``) is reconstructed by the network, then refined with every
``(alpha, tau)`` of the grid; the pair with the lowest mean relMSE against the targets wins.
``RUN2`` receives the network with ``"refine"`` in its card (the weights are copied unchanged),
the source run's ``config.json``, ``log.jsonl`` and ``val.jsonl`` (so ``gdpt model-report`` can
report and ship it like a training run), and ``refinement.json`` / ``refinement.md`` with the
whole grid (mean relMSE, LDR-FLIP, geometric-mean relMSE ratio to the unrefined network, share
of elements improved). The evaluation scenes are never looked at.
"""

from __future__ import annotations

import json
import math
import shutil
import statistics
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from gdpt.io.atomic import atomic_write

__all__ = ["ALPHAS", "TAUS", "select_refinement"]

#: Default grid of the L1 data weight.
ALPHAS = (0.2, 0.5, 1.0)
#: Default grid of the gate width (PU units); ``inf`` is the ungated L1 solution.
TAUS = (0.01, 0.02, 0.04, 0.08, 0.16, math.inf)


def _table(rows: list[dict[str, Any]], unrefined: dict[str, float]) -> str:
    lines = [
        "| alpha | tau | mean relMSE | relMSE ratio (geo-mean) | share improved |",
        "|---|---|---|---|---|",
        f"| (network alone) | | {unrefined['relmse']:.5f} | 1 | |",
    ]
    best = min(rows, key=lambda r: r["relmse"])
    for r in rows:
        mark = "**" if r is best else ""
        lines.append(
            f"| {r['alpha']} | {r['tau']} | {mark}{r['relmse']:.5f}{mark} | {r['ratio']:.4f} | "
            f"{r['improved']:.3f} |"
        )
    return "\n".join(lines) + "\n"


def select_refinement(
    model: str | Path,
    data: str | Path,
    out: str | Path,
    *,
    alphas: Sequence[float] = ALPHAS,
    taus: Sequence[float] = TAUS,
    window: int = 5,
    preset: str = "refine",
    progress: bool = True,
) -> Path:
    """Grid-search the refinement of ``model`` on ``data`` and write the refined model to ``out``.

    Args:
        model: a gradient design's delta checkpoint (``.safetensors``) inside a run directory.
        data: ``gdpt dataset`` directory (every element is used).
        out: new run directory (must not exist).
        alphas: L1 data weights to try.
        taus: gate widths to try.
        window: gate max-pool side.
        preset: IRLS schedule of the L1 solve.
        progress: show a progress bar.

    Returns:
        Path of the refined ``model.safetensors``.

    Raises:
        FileExistsError: ``out`` exists.
        ValueError: ``model`` reads no gradients, or an empty grid.
    """
    from tqdm.auto import tqdm

    from gdpt.metrics import flip_ldr, relmse
    from gdpt.reconstruct.oidn_finetune import OIDNReconstructor, load_model
    from gdpt.reconstruct.refine import GatedRefinement
    from gdpt.training.dataset import CropDataset

    out, model = Path(out), Path(model)
    if out.exists():
        raise FileExistsError(f"{out} exists; choose a new --out directory")
    if not alphas or not taus:
        raise ValueError("the grid needs at least one alpha and one tau")
    net, design, card = load_model(model)
    if not design.gradients:
        raise ValueError(f"{model}: {design.description} reads no gradients to refine with")
    rec = OIDNReconstructor(net, design, {k: v for k, v in card.items() if k != "refine"})
    dataset = CropDataset(data, kind=design.input_kind)
    grid = [(a, t) for a in alphas for t in taus]
    scores: dict[Any, dict[str, list[float]]] = {k: {"relmse": []} for k in grid}
    scores["network"] = {"relmse": [], "flip": []}
    for index in tqdm(range(len(dataset)), unit="element", desc="refinement", disable=not progress):
        item = dataset.load(index)
        inputs, target = item["inputs"], item["target"]
        with torch.inference_mode():
            image = rec(inputs)
            scores["network"]["relmse"].append(relmse(image, target))
            scores["network"]["flip"].append(flip_ldr(image, target))
            for alpha in alphas:
                solver = GatedRefinement(alpha=alpha, tau=1.0, window=window, preset=preset)
                refined = solver.solve(image, inputs["dx"], inputs["dy"])
                for tau in taus:
                    g = GatedRefinement(alpha, tau, window, preset).gate(refined, image)
                    result = g * refined + (1.0 - g) * image
                    scores[(alpha, tau)]["relmse"].append(relmse(result, target))
    base = scores.pop("network")
    rows = []
    for (alpha, tau), s in scores.items():
        logs = [
            math.log(max(r, 1e-12) / max(b, 1e-12))
            for r, b in zip(s["relmse"], base["relmse"], strict=True)
        ]
        rows.append(
            {
                "alpha": alpha,
                "tau": tau,
                "relmse": statistics.fmean(s["relmse"]),
                "ratio": math.exp(statistics.fmean(logs)),
                "improved": statistics.fmean(
                    float(r < b) for r, b in zip(s["relmse"], base["relmse"], strict=True)
                ),
            }
        )
    best = min(rows, key=lambda r: r["relmse"])
    chosen = GatedRefinement(best["alpha"], best["tau"], window, preset)
    unrefined = {"relmse": statistics.fmean(base["relmse"]), "flip": statistics.fmean(base["flip"])}
    selection = {
        "data": str(data),
        "elements": len(dataset),
        "rule": "lowest mean relMSE over every element of data",
        "chosen": chosen.to_dict(),
        "network": unrefined,
        "grid": [
            {**r, "tau": GatedRefinement(r["alpha"], r["tau"]).to_dict()["tau"]} for r in rows
        ],
    }
    out.mkdir(parents=True)
    source = model.parent
    for name in ("config.json", "log.jsonl", "val.jsonl"):
        if (source / name).is_file():
            shutil.copyfile(source / name, out / name)
    card = json.loads(model.with_suffix(".json").read_text())
    card["refine"] = chosen.to_dict()
    card["refine_selection"] = {k: selection[k] for k in ("data", "elements", "rule", "network")}
    atomic_write(out / "model.safetensors", model.with_suffix(".safetensors").read_bytes())
    atomic_write(out / "model.json", json.dumps(card, indent=2) + "\n")
    atomic_write(out / "refinement.json", json.dumps(selection, indent=2) + "\n")
    atomic_write(out / "refinement.md", _table(rows, unrefined))
    return out / "model.safetensors"
