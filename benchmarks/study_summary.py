"""Summarise a replicated equal-time study (``gdpt evaluate --seeds N``): wins that hold up.

Per metric, over every scene x budget cell of ``results.json``:

* each method's mean over the replicates and its 95% interval (as recorded by the study);
* which method has the lowest mean, and in how many cells that lead is *separated*: the paired
  95% interval of ``log(best / second)`` over the replicates (the study renders the same seeds
  for every method) lies below 0;
* an overview: per method, its cells, per metric the geometric mean over its cells and the
  geometric-mean ratio to ``--against`` over the cells both have, and its mean render and
  reconstruction seconds per run;
* for each candidate (``--candidates``, default ``gdpt+fuse auto``) against a baseline
  (``--against``, default ``pt+oidn-tuned``): the cells where its mean is lower, separated
  wins and losses, the geometric mean of
  the ratio of means per scene and overall, and the largest per-cell ratio.

Results of an earlier study name some methods by their deprecated names (``gdpt+ngpt``,
``pt+ngpt-nograd``); they are read under the current ones (:func:`gdpt.study.results.read_results`),
and so are such names given as options (with a ``DeprecationWarning``).

``relmse`` is also given corrected for the reference's own noise: with ``n_r`` reference and
``n`` ``pt`` samples, ``E[relMSE(pt)] = v (1/n + 1/n_r)``, so the reference adds
``relMSE(pt) n / (n + n_r)`` to every method's relMSE (per cell), which is subtracted
(``relmse-corrected``; the noise of a 4096-spp reference pulls every ratio toward 1).

    .venv/bin/python benchmarks/study_summary.py out/eval/results.json \\
        [--candidates gdpt+fuse auto] [--against pt+oidn-tuned] [--metrics relmse flip_ldr] \\
        [--budgets 4 8] [--out out/eval/summary.md]
"""

from __future__ import annotations

import argparse
import math
from collections import Counter
from pathlib import Path

from gdpt.statistics import mean_interval
from gdpt.study.methods import EVAL_METHODS
from gdpt.study.results import read_results


def replicate_values(cell: dict, metric: str) -> list[float] | None:
    """The per-replicate values of ``metric`` (a single-run study: its one value)."""
    reps = cell.get("replicates") or [cell]
    values = [r.get("metrics", {}).get(metric) for r in reps]
    if any(v is None or not math.isfinite(v) for v in values):
        return None
    return values


def table(
    results: dict, metric: str, budgets: list[str] | None = None
) -> dict[tuple[str, str], dict[str, list[float]]]:
    """``(scene, budget) -> {method: per-replicate values}`` (only ``budgets``, keys as in
    ``results.json``, where given); ``relmse-corrected`` subtracts the reference noise estimated
    from the cell's ``pt`` (see the module docstring) and holds only the cells that have
    ``pt``."""
    base = "relmse" if metric == "relmse-corrected" else metric
    ref_spp = results["config"]["reference_spp"]
    out: dict[tuple[str, str], dict[str, list[float]]] = {}
    for scene, entry in results["scenes"].items():
        for method, data in entry.get("methods", {}).items():
            for budget, cell in data.get("cells", {}).items():
                if budgets is not None and budget not in budgets:
                    continue
                values = replicate_values(cell, base)
                if values is not None:
                    out.setdefault((scene, budget), {})[method] = values
        if metric == "relmse-corrected":
            for (s, budget), errors in list(out.items()):
                if s != scene:
                    continue
                pt = entry.get("methods", {}).get("pt", {}).get("cells", {}).get(budget)
                if "pt" not in errors or pt is None:
                    del out[(s, budget)]  # no estimate of the reference's noise
                    continue
                noise = sum(errors["pt"]) / len(errors["pt"]) * pt["spp"] / (pt["spp"] + ref_spp)
                out[(s, budget)] = {m: [v - noise for v in vs] for m, vs in errors.items()}
    return out


def mean(values: list[float]) -> float:
    return sum(values) / len(values)


def paired_log_interval(a: list[float], b: list[float]) -> tuple[float, float] | None:
    """95% t-interval of the mean of ``log(a_r / b_r)`` over paired replicates (``None``:
    fewer than 2 replicates or a non-positive value)."""
    if len(a) != len(b) or len(a) < 2 or min(a + b) <= 0:
        return None
    _, low, high = mean_interval([math.log(x / y) for x, y in zip(a, b, strict=True)])
    return low, high


def separated(a: list[float], b: list[float]) -> int:
    """+1 where ``a`` is lower than ``b`` with a separated interval, -1 higher, 0 otherwise."""
    interval = paired_log_interval(a, b)
    if interval is None:
        return 0
    return 1 if interval[1] < 0 else -1 if interval[0] > 0 else 0


def geo(ratios: list[float]) -> float:
    return math.exp(mean([math.log(r) for r in ratios])) if ratios else float("nan")


def seconds(results: dict, key: str) -> dict[str, float]:
    """Per method, the mean of the replicates' ``key`` (``render_seconds``,
    ``reconstruct_seconds``) over all its cells."""
    values: dict[str, list[float]] = {}
    for entry in results["scenes"].values():
        for method, data in entry.get("methods", {}).items():
            for cell in data.get("cells", {}).values():
                for r in cell.get("replicates") or [cell]:
                    if r.get(key) is not None:
                        values.setdefault(method, []).append(r[key])
    return {m: mean(v) for m, v in values.items()}


def overview(results: dict, metrics: list[str], against: str) -> list[str]:
    """One row per method: its cells, per metric the geometric mean over its cells and the
    geometric-mean ratio to ``against`` over the cells both have, and its mean render and
    reconstruction seconds per run."""
    tables = {m: table(results, m) for m in metrics}
    methods = sorted({m for cells in tables.values() for e in cells.values() for m in e})
    render, rec = seconds(results, "render_seconds"), seconds(results, "reconstruct_seconds")
    head = ["method", "cells"]
    for metric in metrics:
        head += [f"{metric} geo. mean", f"ratio to {against}"]
    lines = ["## Overview", "", "| " + " | ".join(head) + " | render s | reconstruct s |"]
    lines.append("|---" * (len(head) + 2) + "|")
    for method in methods:
        row = [method, str(sum(method in e for e in tables[metrics[0]].values()))]
        for metric in metrics:
            cells = tables[metric].values()
            own = [mean(e[method]) for e in cells if method in e and mean(e[method]) > 0]
            ratios = [
                mean(e[method]) / mean(e[against])
                for e in cells
                if method in e and against in e and mean(e[method]) > 0 and mean(e[against]) > 0
            ]
            row += [f"{geo(own):.4g}" if own else "-", f"{geo(ratios):.3f}" if ratios else "-"]
        row += [f"{render.get(method, math.nan):.2f}", f"{rec.get(method, math.nan):.2f}"]
        lines.append("| " + " | ".join(row) + " |")
    return [*lines, ""]


def summarise(
    results: dict,
    metric: str,
    candidates: list[str],
    against: str,
    budgets: list[str] | None = None,
) -> list[str]:
    cells = table(results, metric, budgets)
    lowest, firm = Counter(), Counter()
    for errors in cells.values():
        ranked = sorted(errors, key=lambda m: mean(errors[m]))
        lowest[ranked[0]] += 1
        if len(ranked) > 1 and separated(errors[ranked[0]], errors[ranked[1]]) == 1:
            firm[ranked[0]] += 1
    lines = [f"## {metric} ({len(cells)} cells)", ""]
    if not cells:
        why = (
            "no cell has `pt` (it estimates the reference's noise)" if "corrected" in metric else ""
        )
        return [*lines, f"Nothing to summarise: {why or 'no cell has this metric'}.", ""]
    lines.append(
        "Lowest mean per cell (separated from the second by the paired 95% interval): "
        + ", ".join(f"{m} {n} ({firm[m]})" for m, n in lowest.most_common())
        + "."
    )
    lines.append("")
    lines += [
        f"| candidate | vs {against}: lower mean | wins / losses (separated) | geo. mean ratio "
        "| max ratio |",
        "|---|---|---|---|---|",
    ]
    for c in candidates:
        pairs = [(e[c], e[against]) for e in cells.values() if c in e and against in e]
        wins = sum(separated(a, b) == 1 for a, b in pairs)
        losses = sum(separated(a, b) == -1 for a, b in pairs)
        lower = sum(mean(a) < mean(b) for a, b in pairs)
        ratios = [mean(a) / mean(b) for a, b in pairs if mean(b) > 0 and mean(a) > 0]
        lines.append(
            f"| {c} | {lower} of {len(pairs)} | {wins} / {losses} of {len(pairs)} | "
            f"{geo(ratios):.3f} | "
            f"{max(ratios, default=float('nan')):.2f} |"
        )
    lines += ["", f"Geometric-mean ratio to {against} per scene:", ""]
    scenes = sorted({s for s, _ in cells})
    lines += ["| scene | " + " | ".join(candidates) + " |", "|---" * (len(candidates) + 1) + "|"]
    for scene in scenes:
        row = []
        for c in candidates:
            ratios = [
                mean(e[c]) / mean(e[against])
                for (s, _), e in cells.items()
                if s == scene and c in e and against in e and mean(e[against]) > 0
            ]
            row.append(f"{geo(ratios):.2f}" if ratios else "-")
        lines.append(f"| {scene} | " + " | ".join(row) + " |")
    methods = sorted({m for e in cells.values() for m in e})
    lines += ["", "| scene | budget | " + " | ".join(methods) + " |"]
    lines.append("|---|---" + "|---" * len(methods) + "|")
    for (scene, budget), errors in sorted(cells.items()):
        shown = []
        for m in methods:
            if m not in errors:
                shown.append("-")
                continue
            v = errors[m]
            m_, lo, hi = mean(v), min(v), max(v)
            shown.append(f"{m_:.4g}" + (f" [{lo:.3g}, {hi:.3g}]" if len(v) > 1 else ""))
        lines.append(f"| {scene} | {budget} s | " + " | ".join(shown) + " |")
    return lines + [""]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, help="results.json of gdpt evaluate")
    parser.add_argument("--candidates", nargs="+", default=["gdpt+fuse", "auto"])
    parser.add_argument("--against", default="pt+oidn-tuned")
    parser.add_argument("--metrics", nargs="+", default=["relmse", "relmse-corrected", "flip_ldr"])
    parser.add_argument("--out", type=Path, help="also write the Markdown here")
    parser.add_argument(
        "--budgets", nargs="+", help="summarise these budget cells only (e.g. 4 8; default all)"
    )
    args = parser.parse_args()
    args.against = EVAL_METHODS.resolve(args.against)
    args.candidates = [EVAL_METHODS.resolve(c) for c in args.candidates]
    results = read_results(args.results)
    lines = [f"# {args.results}", "", "Per-cell values: mean [min, max] of the replicates.", ""]
    lines += overview(results, args.metrics, args.against)
    for metric in args.metrics:
        lines += summarise(results, metric, args.candidates, args.against, args.budgets)
    text = "\n".join(lines)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
