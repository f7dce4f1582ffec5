"""Error relative to one method against the time budget, pooled over scenes, from study results.

Reads one or more ``results.json`` of ``gdpt evaluate`` (for instance a quick run at 0.5-2 s and
a run of the same scenes at 4-8 s) and, per budget and method, takes the geometric mean over
scenes of the per-cell ratio ``metric(method) / metric(--against)`` (cell means over the
replicates). Prints the table and, with ``--plot``, writes a PNG (log-log: budget against
ratio; 1 is the reference method). Scenes whose ``pt`` relMSE exceeds 1 (unconverged
references) are left out with ``--skip-unconverged``. Usage::

    .venv/bin/python benchmarks/budget_curve.py out/eval/results.json out/eval-long/results.json \\
        --against pt+ngpt-nograd --plot docs/gradients-budget.png --skip-unconverged
"""

from __future__ import annotations

import argparse
import json
import math
from collections import defaultdict


def ratios(paths: list[str], against: str, metric: str, skip_unconverged: bool) -> dict:
    """``{method: {budget: [per-scene ratio, ...]}}`` over every results file."""
    out: dict[str, dict[float, list[float]]] = defaultdict(lambda: defaultdict(list))
    for path in paths:
        with open(path) as f:
            results = json.load(f)
        for scene in results["scenes"].values():
            methods = scene.get("methods", {})
            pt = methods.get("pt", {}).get("cells", {})
            if skip_unconverged and any(
                c.get("metrics", {}).get("relmse", 0) > 1 for c in pt.values()
            ):
                continue
            base = methods.get(against, {}).get("cells", {})
            for name, method in methods.items():
                for budget, cell in method.get("cells", {}).items():
                    ref = base.get(budget, {}).get("metrics", {}).get(metric)
                    value = cell.get("metrics", {}).get(metric)
                    if ref and value:
                        out[name][float(budget)].append(value / ref)
    return out


def geometric_mean(values: list[float]) -> float:
    return math.exp(sum(math.log(v) for v in values) / len(values))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", nargs="+")
    parser.add_argument("--against", default="pt+ngpt-nograd")
    parser.add_argument("--metric", default="relmse")
    parser.add_argument("--plot", default=None, help="write the curves to this PNG")
    parser.add_argument("--skip-unconverged", action="store_true")
    args = parser.parse_args()

    table = ratios(args.results, args.against, args.metric, args.skip_unconverged)
    budgets = sorted({b for per in table.values() for b in per})
    print(f"geometric mean over scenes of {args.metric} / {args.against} (scenes per cell)")
    print("| method | " + " | ".join(f"{b:g} s" for b in budgets) + " |")
    print("|---|" + "---:|" * len(budgets))
    for name in sorted(table):
        cells = [
            f"{geometric_mean(table[name][b]):.2f} ({len(table[name][b])})"
            if table[name].get(b)
            else "-"
            for b in budgets
        ]
        print(f"| {name} | " + " | ".join(cells) + " |")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
        for name in sorted(table):
            if name == args.against:
                continue
            xs = [b for b in budgets if table[name].get(b)]
            ax.plot(xs, [geometric_mean(table[name][b]) for b in xs], marker="o", label=name)
        ax.axhline(1.0, color="black", lw=1, label=args.against)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(budgets, [f"{b:g}" for b in budgets])
        ax.set_xticks([], minor=True)
        ticks = [0.5, 0.7, 1, 1.5, 2, 3, 5, 8]
        ax.set_yticks(ticks, [f"{t:g}" for t in ticks])
        ax.set_yticks([], minor=True)
        counts = sorted({len(v) for per in table.values() for v in per.values()})
        ax.set_title(f"scenes per budget: {', '.join(map(str, counts))}", fontsize=8)
        ax.set_xlabel("time budget per 128 px image (s), render + reconstruction")
        ax.set_ylabel(f"{args.metric} / {args.against} (geo. mean)")
        ax.legend(fontsize=7)
        ax.grid(True, which="both", alpha=0.3)
        fig.tight_layout()
        fig.savefig(args.plot)
        print(f"wrote {args.plot}")


if __name__ == "__main__":
    main()
