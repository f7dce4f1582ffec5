"""Summarise an equal-time study (``gdpt evaluate``) against the bar of the reconstruction issue.

For one method (default ``gdpt+ngpt``) and each metric, over every scene x budget cell of
``results.json``: in how many cells it has the lowest error of all methods, in how many it is
within 1.25x of ``pt+oidn``, below ``gdpt+l1`` and below its ablation (default
``pt+ngpt-nograd``); the geometric mean and range of its ratio to ``pt+oidn``; and which method is
lowest how often. Cells where a method is missing or was skipped are left out of that comparison
(and counted). ``--only`` restricts "lowest" to the methods named, e.g. to count a pair of
networks registered with ``gdpt evaluate --model`` against the baselines without the shipped
pair.

    .venv/bin/python benchmarks/study_summary.py out/eval-v11/results.json [--method gdpt+ngpt]
        [--ablation pt+ngpt-nograd] [--only METHOD ...] [--metrics relmse flip_ldr]
        [--out out/eval-v11-summary.md]
"""

from __future__ import annotations

import argparse
import json
import math
from collections import Counter
from pathlib import Path


def cells(
    results: dict, metric: str, only: set[str] | None = None
) -> dict[tuple[str, str], dict[str, float]]:
    """``(scene, budget) -> {method: error}`` of every scored cell (methods in ``only``, if
    given)."""
    out: dict[tuple[str, str], dict[str, float]] = {}
    for scene, entry in results["scenes"].items():
        for method, data in entry.get("methods", {}).items():
            if only is not None and method not in only:
                continue
            for budget, cell in data.get("cells", {}).items():
                value = cell.get("metrics", {}).get(metric)
                if value is not None and math.isfinite(value):
                    out.setdefault((scene, budget), {})[method] = value
    return out


def summarise(
    results: dict,
    method: str,
    metric: str,
    ablation: str = "pt+ngpt-nograd",
    only: set[str] | None = None,
) -> list[str]:
    """Markdown lines for ``method`` under ``metric``, against ``ablation`` and the baselines,
    among the methods in ``only`` (all if ``None``)."""
    table = cells(results, metric, only)
    lowest = Counter(min(errors, key=errors.get) for errors in table.values())
    lines = [f"### {method}, {metric} ({len(table)} cells)", ""]

    def count(other: str, test) -> str:
        pairs = [(e[method], e[other]) for e in table.values() if method in e and other in e]
        return f"{sum(test(a, b) for a, b in pairs)} / {len(pairs)}"

    ratios = [e[method] / e["pt+oidn"] for e in table.values() if {method, "pt+oidn"} <= set(e)]
    geo = math.exp(sum(math.log(r) for r in ratios) / len(ratios)) if ratios else float("nan")
    lines += [
        "| criterion | cells |",
        "|---|---|",
        f"| lowest of all methods | {lowest.get(method, 0)} / {len(table)} |",
        f"| within 1.25x of pt+oidn | {count('pt+oidn', lambda a, b: a <= 1.25 * b)} |",
        f"| below gdpt+l1 | {count('gdpt+l1', lambda a, b: a < b)} |",
        f"| below {ablation} | {count(ablation, lambda a, b: a < b)} |",
        f"| below pt+oidn | {count('pt+oidn', lambda a, b: a < b)} |",
        "",
        f"Ratio to pt+oidn: geometric mean {geo:.3f}, range "
        f"{min(ratios, default=float('nan')):.2f}-{max(ratios, default=float('nan')):.2f}. "
        "Lowest per cell: " + ", ".join(f"{m} {n}" for m, n in lowest.most_common()) + ".",
        "",
        "| scene | budget | lowest | " + method + " / pt+oidn |",
        "|---|---|---|---|",
    ]
    for (scene, budget), errors in sorted(table.items()):
        best = min(errors, key=errors.get)
        ratio = errors[method] / errors["pt+oidn"] if {method, "pt+oidn"} <= set(errors) else None
        shown = f"{ratio:.2f}" if ratio is not None else "-"
        lines.append(f"| {scene} | {budget} s | {best} ({errors[best]:.3g}) | {shown} |")
    return lines + [""]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, help="results.json of gdpt evaluate")
    parser.add_argument("--method", default="gdpt+ngpt", help="the method to summarise")
    parser.add_argument("--ablation", default="pt+ngpt-nograd", help="its no-gradient ablation")
    parser.add_argument("--only", nargs="+", help="count only these methods (default: all)")
    parser.add_argument("--metrics", nargs="+", default=["relmse", "flip_ldr"])
    parser.add_argument("--out", type=Path, help="also write the Markdown here")
    args = parser.parse_args()
    results = json.loads(args.results.read_text())
    lines = [f"# {args.results}", ""]
    for metric in args.metrics:
        only = set(args.only) | {args.method, args.ablation} if args.only else None
        lines += summarise(results, args.method, metric, args.ablation, only)
    text = "\n".join(lines)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
