"""Error relative to one method against the time budget, pooled over scenes, from study results.

Reads one or more ``results.json`` of ``gdpt evaluate`` (for instance a quick run at 0.5-2 s and
a run of the same scenes at 4-8 s) and, per budget and method, takes the geometric mean over
scenes of the per-cell ratio ``metric(method) / metric(--against)`` (cell means over the
replicates). Prints the table and, with ``--plot``, writes a PNG (log-log: budget against
ratio; 1 is the reference method). Scenes whose ``pt`` relMSE exceeds 1 (unconverged
references) are left out with ``--skip-unconverged``. Usage::

    .venv/bin/python benchmarks/budget_curve.py out/eval/results.json out/eval-long/results.json \\
        --against pt+oidn-tuned --plot docs/gradients-budget.png --skip-unconverged

Methods recorded or given under a deprecated name (``pt+ngpt-nograd``) are read as the current
one (``pt+oidn-tuned``), as in ``study_summary.py``.
"""

from __future__ import annotations

import argparse
from collections import defaultdict

from study_summary import geo, mean, table

from gdpt.study.methods import EVAL_METHODS
from gdpt.study.results import read_results


def ratios(paths: list[str], against: str, metric: str, skip_unconverged: bool) -> dict:
    """``{method: {budget: [per-scene ratio of replicate means, ...]}}`` over every results
    file (cells from :func:`study_summary.table`)."""
    out: dict[str, dict[float, list[float]]] = defaultdict(lambda: defaultdict(list))
    for path in paths:
        results = read_results(path)
        unconverged = {
            scene
            for (scene, _), errors in table(results, "relmse").items()
            if "pt" in errors and mean(errors["pt"]) > 1
        }
        for (scene, budget), errors in table(results, metric).items():
            if against not in errors or (skip_unconverged and scene in unconverged):
                continue
            for name, values in errors.items():
                out[name][float(budget)].append(mean(values) / mean(errors[against]))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", nargs="+")
    parser.add_argument("--against", default="pt+oidn-tuned")
    parser.add_argument("--metric", default="relmse")
    parser.add_argument("--plot", default=None, help="write the curves to this PNG")
    parser.add_argument("--skip-unconverged", action="store_true")
    args = parser.parse_args()
    args.against = EVAL_METHODS.resolve(args.against)

    curves = ratios(args.results, args.against, args.metric, args.skip_unconverged)
    budgets = sorted({b for per in curves.values() for b in per})
    print(f"geometric mean over scenes of {args.metric} / {args.against} (scenes per cell)")
    print("| method | " + " | ".join(f"{b:g} s" for b in budgets) + " |")
    print("|---|" + "---:|" * len(budgets))
    for name in sorted(curves):
        cells = [
            f"{geo(curves[name][b]):.2f} ({len(curves[name][b])})" if curves[name].get(b) else "-"
            for b in budgets
        ]
        print(f"| {name} | " + " | ".join(cells) + " |")
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
        for name in sorted(curves):
            if name == args.against:
                continue
            xs = [b for b in budgets if curves[name].get(b)]
            ax.plot(xs, [geo(curves[name][b]) for b in xs], marker="o", label=name)
        ax.axhline(1.0, color="black", lw=1, label=args.against)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(budgets, [f"{b:g}" for b in budgets])
        ax.set_xticks([], minor=True)
        ticks = [0.5, 0.7, 1, 1.5, 2, 3, 5, 8]
        ax.set_yticks(ticks, [f"{t:g}" for t in ticks])
        ax.set_yticks([], minor=True)
        counts = sorted({len(v) for per in curves.values() for v in per.values()})
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
