"""How close does each method of a study come to its budget? The charged seconds of every
replicate of ``gdpt evaluate``'s ``results.json`` against the cell's budget.

Only reads what the study recorded (``scenes.*.cell_runs.*.replicates.*``): per replicate its
sample count, charged seconds (under the study's protocol), their relative error, its render
and reconstruction seconds, the 1-minute load average before it, whether it was redone (its
first run's error) and, for ``auto``, its route and the pilot's seconds; then per method and
scene the range of the errors and how many replicates lie within ``--tolerance`` (default 5%).
Timings are only meaningful from a study run on an otherwise idle machine.

    .venv/bin/python benchmarks/budget_charges.py out/study/results.json \\
        [--methods auto pt+oidn-tuned] [--tolerance 0.05] [--out out/study/charges.md]
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path


def replicates(results: dict, methods: list[str] | None) -> list[dict]:
    """One row per replicate: ``scene``, ``budget``, ``replicate``, ``method`` and what the
    study recorded of its timed run (``methods``: only these, where given)."""
    rows = []
    for scene, entry in results["scenes"].items():
        for cell in entry.get("cell_runs", {}).values():
            for method, run in cell.get("replicates", {}).items():
                if methods and method not in methods or "charged_seconds" not in run:
                    continue
                route = run.get("route") or {}
                rows.append(
                    {
                        "scene": scene,
                        "budget": run["budget"],
                        "replicate": cell["replicate"],
                        "method": method,
                        "spp": run.get("spp"),
                        "charged": run["charged_seconds"],
                        "error": run["relative_error"],
                        "render": run["render_seconds"],
                        "reconstruct": run["reconstruct_seconds"],
                        "load": run.get("loadavg_1min"),
                        "redone": (run.get("redone") or {}).get("relative_error"),
                        "route": route.get("route"),
                        "pilot": route.get("pilot_seconds"),
                    }
                )
    return sorted(rows, key=lambda r: (r["method"], r["scene"], r["budget"], r["replicate"]))


def _number(value: float | None, spec: str) -> str:
    return "" if value is None else format(value, spec)


def report(rows: list[dict], tolerance: float) -> str:
    """The per-replicate table and the per-method and scene summary, as Markdown."""
    out = [
        "| method | scene | budget s | rep | spp | charged s | error | render s | reconstruct s "
        "| load | redone (first error) | route | pilot s |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|",
    ]
    for r in rows:
        out.append(
            f"| {r['method']} | {r['scene']} | {r['budget']:g} | {r['replicate']} "
            f"| {_number(r['spp'], 'd')} | {r['charged']:.3f} | {r['error']:+.1%} "
            f"| {r['render']:.3f} | {r['reconstruct']:.3f} | {_number(r['load'], '.2f')} "
            f"| {_number(r['redone'], '+.1%')} | {r['route'] or ''} "
            f"| {_number(r['pilot'], '.3f')} |"
        )
    groups: dict[tuple[str, str], list[float]] = defaultdict(list)
    for r in rows:
        groups[r["method"], r["scene"]].append(r["error"])
    out += [
        "",
        f"| method | scene | replicates | error min | error max | within {tolerance:.0%} |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for (method, scene), errors in groups.items():
        within = sum(abs(e) <= tolerance for e in errors)
        out.append(
            f"| {method} | {scene} | {len(errors)} | {min(errors):+.1%} | {max(errors):+.1%} "
            f"| {within}/{len(errors)} |"
        )
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results", type=Path, help="a study's results.json")
    parser.add_argument("--methods", nargs="+", help="only these methods (default: all)")
    parser.add_argument("--tolerance", type=float, default=0.05, help="relative (default 0.05)")
    parser.add_argument("--out", type=Path, help="also write the tables here (Markdown)")
    args = parser.parse_args(argv)
    if not args.results.is_file():
        parser.error(f"no results file at {args.results}")
    text = report(replicates(json.loads(args.results.read_text()), args.methods), args.tolerance)
    print(text, end="")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
