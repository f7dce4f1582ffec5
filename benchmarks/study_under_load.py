"""Does the equal-time study hold on a busy machine? The same quick study idle and loaded.

Runs ``gdpt evaluate`` twice with the same settings (default: cornell-box and living-room-2
from ``../shared/scenes``; budgets 2 and 4 s; 3 paired seeds; ``pt+oidn-tuned``, ``gdpt+fuse``,
``auto``; 128 px; 8192-spp references from ``--references``): once on the idle machine, once
with one busy-loop process at normal priority beside it (a Python ``while True`` loop, started
before the study and ended after it, by its process id). Each run is its own process and
output folder (``OUT/idle``, ``OUT/loaded``); a run whose ``results.json`` is complete is
reused (``--force``: run again).

It then prints, and writes to ``OUT/summary.md`` and ``OUT/summary.json`` (with the commit,
versions and machine):

* per cell (scene, budget, replicate seed; every method of a cell ran back to back on one
  worker, ``gdpt.study.cells``) the relMSE ratio of each method to ``pt+oidn-tuned`` in the
  same cell, idle and loaded, and loaded / idle;
* per method, the geometric mean over cells of the ratio, idle and loaded, and their agreement
  ``loaded / idle`` (bar: within 10%, i.e. 0.909-1.1);
* every replicate flagged for missing its budget (``missed_budget``, after one redo), per run,
  with its charged seconds, the 1-minute load average and CPU / wall time of its timed run;
* per cell the sample-count proportion of each method to ``pt+oidn-tuned`` (``spp`` over the
  baseline's ``spp``), idle and loaded, and loaded / idle (the idle/busy bar: within 10%);
* the machine's own answer, measured in the same run after the studies (``--anchor-reps``, 0:
  skipped): each method run at the idle study's median count of the first budget, per scene
  (``auto``: the plain samples' worth its idle replicates rendered, given as a count, its pilot
  and route included, the seeds the same idle and loaded), timed as the study times it
  (``EvalMethod.run``: sampling + reconstruction, kernel compilation excluded, two untimed
  warm-ups first), idle and beside the same busy loop, alternating; ``(t_base loaded / t_base
  idle) / (t_m loaded / t_m idle)`` is the proportion change that equal time itself asks for
  when a method's cost grows more under load than the baseline's.

How close each timed run comes to its budget is the study's (its calibration re-renders beyond
``EvaluateConfig.tolerance``, a replicate beyond ``gdpt.study.cells.MISS_TOLERANCE`` is redone
then flagged; ``auto`` fills its seconds itself and its ``spp`` is the plain samples' worth it
rendered); this script only reads what the study recorded. Run it on an otherwise idle
machine (the second run adds its own load)::

    .venv/bin/python benchmarks/study_under_load.py --references /work/main/out/refs128 \\
        --out out/study-under-load

``--control`` adds a third run, idle again (``OUT/idle-2``), after the loaded one, and puts its
count proportions beside the loaded run's (``idle 2/idle``): how far two idle runs of the same
study disagree per cell, the noise floor the idle/busy bar is read against.

``--workers N`` passes ``--workers N`` to the studies (Ray; default: sequential).
``--compare-workers N`` adds a run, idle, with ``--workers N`` (``OUT/workers-N``), and
compares it with the idle sequential run: the key structure of ``results.json`` (every key
path, the values aside) and the report files, and per method the cells' ratios, workers over
sequential: their geometric mean and its 95% t interval over the cells (the two runs' seeds are
the same, their noise is not: "within the noise" means the interval holds 1).
``--summary-only`` recomputes the tables from existing runs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
SCENES = REPO.parent / "shared" / "scenes"
BASELINE = "pt+oidn-tuned"
AGREEMENT = 0.10  # the bar: loaded / idle geometric means within 10%
BURNER = "while True:\n    pass\n"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--scenes",
        nargs="+",
        default=[os.path.relpath(SCENES / n) for n in ("cornell-box", "living-room-2")],
        help="scene folders (default: cornell-box and living-room-2 of ../shared/scenes)",
    )
    parser.add_argument("--references", type=Path, required=True, help="reference cache folder")
    parser.add_argument("--out", type=Path, default=Path("out/study-under-load"))
    parser.add_argument("--budgets", type=float, nargs="+", default=[2.0, 4.0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--methods", nargs="+", default=[BASELINE, "gdpt+fuse", "auto"])
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--reference-spp", type=int, default=8192)
    parser.add_argument("--workers", type=int, help="pass --workers N to gdpt evaluate (Ray)")
    parser.add_argument(
        "--compare-workers",
        type=int,
        metavar="N",
        help="also run the study idle with --workers N and compare it with the sequential run",
    )
    parser.add_argument(
        "--control",
        action="store_true",
        help="also run the study idle a second time (OUT/idle-2): the count bar's noise floor",
    )
    parser.add_argument("--force", action="store_true", help="run again even if complete")
    parser.add_argument(
        "--anchor-reps",
        type=int,
        default=3,
        help="fixed-count cost anchors: idle/loaded pairs per scene (0: none; default 3)",
    )
    parser.add_argument("--summary-only", action="store_true", help="only read existing runs")
    return parser.parse_args(argv)


def study_command(args: argparse.Namespace, out: Path, workers: int | None = None) -> list[str]:
    """The ``gdpt evaluate`` command line of one run (``workers``: instead of ``--workers``)."""
    command = [sys.executable, "-m", "gdpt", "evaluate", "--quick", "--scenes", *args.scenes]
    command += ["--out", str(out), "--references", str(args.references)]
    command += ["--budgets", *(f"{b:g}" for b in args.budgets), "--seeds", str(args.seeds)]
    command += ["--methods", *args.methods, "--resolution", str(args.resolution)]
    command += ["--reference-spp", str(args.reference_spp), "--no-progress"]
    if workers or args.workers:
        command += ["--workers", str(workers or args.workers)]
    return command


def complete(out: Path, args: argparse.Namespace) -> bool:
    path = out / "results.json"
    if not path.is_file():
        return False
    results = json.loads(path.read_text())
    finished = results.get("runs", [{}])[-1].get("finished")
    cells = [
        entry.get("cell_runs", {})
        for entry in results.get("scenes", {}).values()
        if entry.get("status") == "ok"
    ]
    wanted = len(args.budgets) * args.seeds
    return (
        bool(finished) and len(cells) == len(args.scenes) and all(len(c) >= wanted for c in cells)
    )


def run_study(
    args: argparse.Namespace, out: Path, loaded: bool, workers: int | None = None
) -> dict:
    """One study run (with a busy loop beside it when ``loaded``); returns its timing."""
    if complete(out, args) and not args.force:
        print(f"{out}: complete, reused", flush=True)
        return {}
    burner = None
    if loaded:  # normal priority, as any other program a user runs
        burner = subprocess.Popen([sys.executable, "-c", BURNER])
    start = time.perf_counter()
    load_start = os.getloadavg()
    try:
        status = subprocess.run(study_command(args, out, workers), check=False).returncode
    finally:
        if burner is not None:
            burner.terminate()
            burner.wait()
    if status != 0:
        raise SystemExit(f"{out}: gdpt evaluate exited with status {status}")
    return {"seconds": time.perf_counter() - start, "loadavg_start": list(load_start)}


def relmse(replicate: dict) -> float | None:
    """A replicate's relMSE, ``None`` where it has none."""
    return replicate.get("metrics", {}).get("relmse")


def spp(replicate: dict) -> float | None:
    """A replicate's sample count, ``None`` where it has none."""
    return replicate.get("spp")


def cell_ratios(
    results: dict, value: Callable[[dict], float | None] = relmse
) -> dict[tuple[str, str, int], dict[str, float]]:
    """``(scene, budget, replicate) -> {method: value / value of pt+oidn-tuned}`` from the
    cells (``cell_runs``) of a study; ``value``: a replicate's relMSE (default) or ``spp``."""
    out = {}
    for scene, entry in results["scenes"].items():
        for unit, run in entry.get("cell_runs", {}).items():
            budget, replicate = unit.split("/")
            reps = run["replicates"]
            base = value(reps.get(BASELINE, {}))
            if not base:
                continue
            out[(scene, budget, int(replicate))] = {
                m: value(r) / base
                for m, r in reps.items()
                if m != BASELINE and value(r) is not None
            }
    return out


def count_table(idle: dict, loaded: dict, control: dict | None = None) -> tuple[str, dict]:
    """Per cell and method the sample-count proportion to the baseline, idle and loaded (and,
    with ``control``, a second idle run: the bar's noise floor, the same comparison without
    the load)."""
    runs = {"idle": idle, "loaded": loaded, **({"control": control} if control else {})}
    counts = {name: cell_ratios(results, spp) for name, results in runs.items()}
    cells = sorted(set.intersection(*(set(c) for c in counts.values())))
    methods = sorted({m for r in counts["idle"].values() for m in r})
    lines = [f"Per cell: spp / spp of `{BASELINE}` in the same cell (the idle/busy bar)", ""]
    head = "| scene | budget s | seed | method | idle | loaded | loaded/idle | within 10% |"
    rule = "|---|---:|---:|---|---:|---:|---:|---|"
    if control:
        lines[0] += "; the control: a second idle run against the first"
        head += " idle 2 | idle 2/idle | within 10% |"
        rule += "---:|---:|---|"
    lines[0] += "."
    lines += [head, rule]
    numbers: dict = {}
    within = lambda change: 1 / (1 + AGREEMENT) <= change <= 1 + AGREEMENT  # noqa: E731
    for cell in cells:
        for m in methods:
            a, b = counts["idle"][cell].get(m), counts["loaded"][cell].get(m)
            if not (a and b):
                continue
            entry = {"cell": list(cell), "change": b / a, "ok": within(b / a)}
            row = f"| {cell[0]} | {cell[1]} | {cell[2]} | {m} | {a:.3f} | {b:.3f} | {b / a:.3f} "
            row += f"| {'yes' if entry['ok'] else 'NO'} |"
            if control and (c := counts["control"][cell].get(m)):
                entry.update(control=c / a, control_ok=within(c / a))
                row += f" {c:.3f} | {c / a:.3f} | {'yes' if entry['control_ok'] else 'NO'} |"
            numbers.setdefault(m, []).append(entry)
            lines.append(row)
    entries = [e for v in numbers.values() for e in v]
    lines += ["", f"Within 10%: loaded/idle {sum(e['ok'] for e in entries)} of {len(entries)}"]
    if control:
        lines[-1] += f"; idle 2/idle {sum(e.get('control_ok', 0) for e in entries)}"
    return "\n".join(lines) + "\n", numbers


def median(values: list[float]) -> float:
    ordered = sorted(values)
    n = len(ordered)
    return (ordered[n // 2] + ordered[(n - 1) // 2]) / 2


def measure_anchors(args: argparse.Namespace, idle: dict) -> dict:
    """Fixed-count seconds of each method idle and loaded, alternating; see the module
    docstring. ``{scene: {method: {"spp", "idle", "loaded"}}}`` (median seconds)."""
    from gdpt.study.methods import EVAL_METHODS
    from gdpt.study.scenes import load_eval_scene, resolve_scenes

    budget = f"{args.budgets[0]:g}"
    found: dict = {}
    for spec in resolve_scenes(args.scenes):
        entry = idle["scenes"].get(spec.name, {})
        seen: dict[str, list[int]] = {}
        for unit, run in entry.get("cell_runs", {}).items():
            if unit.split("/")[0] in (budget, f"{float(budget):g}"):
                for m, r in run["replicates"].items():
                    if r.get("spp"):
                        seen.setdefault(m, []).append(int(r["spp"]))
        if BASELINE not in seen:
            continue
        counts = {m: int(median(v)) for m, v in seen.items()}
        scene = load_eval_scene(spec, resolution=args.resolution)
        seconds: dict = {m: {"idle": [], "loaded": []} for m in counts}
        for m, n in counts.items():  # warm-ups: compilation and pass recording, untimed
            for k in range(2):
                EVAL_METHODS[m].run(scene, spp=n, seed=9000 + k)
        for rep in range(args.anchor_reps):
            for condition in ("idle", "loaded"):
                burner = None
                if condition == "loaded":
                    burner = subprocess.Popen([sys.executable, "-c", BURNER])
                    time.sleep(0.5)
                try:
                    for m, n in counts.items():
                        result = EVAL_METHODS[m].run(scene, spp=n, seed=rep)
                        seconds[m][condition].append(result.seconds)
                finally:
                    if burner is not None:
                        burner.terminate()
                        burner.wait()
        found[spec.name] = {
            m: {"spp": counts[m], **{c: median(seconds[m][c]) for c in ("idle", "loaded")}}
            for m in counts
        }
        print(f"anchors {spec.name}: {found[spec.name]}", flush=True)
    return found


def anchor_table(anchors: dict, counts: dict) -> str:
    """The anchors against the study's count proportions (geometric mean over the cells)."""
    lines = [
        "Fixed-count anchors (same run, after the studies): seconds at the idle study's median "
        "count, idle and beside the busy loop; the proportion change equal time asks for, "
        f"(t_{BASELINE} loaded / idle) / (t_method loaded / idle), against the study's.",
        "",
        "| scene | method | spp | seconds idle | seconds loaded | loaded/idle | "
        "proportion change asked | study's (geomean) |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for scene, methods in anchors.items():
        base = methods[BASELINE]
        slow_base = base["loaded"] / base["idle"]
        for m, a in methods.items():
            slow = a["loaded"] / a["idle"]
            asked = slow_base / slow
            study = [c["change"] for c in counts.get(m, []) if c["cell"][0] == scene]
            shown = f"{geomean(study):.3f}" if study else "n/a"
            lines.append(
                f"| {scene} | {m} | {a['spp']} | {a['idle']:.3f} | {a['loaded']:.3f} | "
                f"{slow:.3f} | {asked:.3f} | {shown} |"
            )
    return "\n".join(lines) + "\n"


def geomean(values: list[float]) -> float:
    return math.exp(sum(math.log(v) for v in values) / len(values)) if values else math.nan


def flagged(results: dict) -> list[str]:
    lines = []
    for scene, entry in results["scenes"].items():
        for unit, run in sorted(entry.get("cell_runs", {}).items()):
            for method, rep in run["replicates"].items():
                if rep.get("missed_budget"):
                    lines.append(
                        f"{scene} {unit} {method}: {rep['charged_seconds']:.2f} s charged "
                        f"({rep['relative_error']:+.0%}), load {rep.get('loadavg_1min')}, "
                        f"CPU/wall {rep.get('cpu_per_wall') or float('nan'):.2f}"
                    )
    return lines


def summarise(idle: dict, loaded: dict) -> tuple[str, dict]:
    """The Markdown tables and their numbers."""
    ratios = {"idle": cell_ratios(idle), "loaded": cell_ratios(loaded)}
    cells = sorted(set(ratios["idle"]) & set(ratios["loaded"]))
    methods = sorted({m for r in ratios["idle"].values() for m in r})
    lines = [f"Per cell: relMSE / relMSE of `{BASELINE}` in the same cell.", ""]
    head = "| scene | budget s | seed | " + " | ".join(
        f"{m} idle | {m} loaded | loaded/idle" for m in methods
    )
    lines += [head + " |", "|---|---:|---:|" + "---:|" * (3 * len(methods))]
    for cell in cells:
        row = [cell[0], cell[1], str(cell[2])]
        for m in methods:
            a, b = ratios["idle"][cell].get(m), ratios["loaded"][cell].get(m)
            row += [f"{a:.3f}" if a else "n/a", f"{b:.3f}" if b else "n/a"]
            row.append(f"{b / a:.3f}" if a and b else "n/a")
        lines.append("| " + " | ".join(row) + " |")
    numbers: dict = {"cells": len(cells), "methods": {}}
    lines += ["", "| method | cells | geomean idle | geomean loaded | loaded / idle | within 10% |"]
    lines += ["|---|---:|---:|---:|---:|---|"]
    for m in methods:
        both = [c for c in cells if m in ratios["idle"][c] and m in ratios["loaded"][c]]
        gi = geomean([ratios["idle"][c][m] for c in both])
        gl = geomean([ratios["loaded"][c][m] for c in both])
        agree = gl / gi
        ok = 1 / (1 + AGREEMENT) <= agree <= 1 + AGREEMENT
        numbers["methods"][m] = {"cells": len(both), "idle": gi, "loaded": gl, "agreement": agree}
        numbers["methods"][m]["within_bar"] = ok
        lines.append(
            f"| {m} | {len(both)} | {gi:.3f} | {gl:.3f} | {agree:.3f} | {'yes' if ok else 'NO'} |"
        )
    for name, results in (("idle", idle), ("loaded", loaded)):
        missed = flagged(results)
        numbers[f"flagged_{name}"] = missed
        lines += ["", f"Replicates flagged for missing the budget, {name}: {len(missed)}"]
        lines += [f"- {line}" for line in missed]
    return "\n".join(lines) + "\n", numbers


def key_paths(value: Any, prefix: str = "") -> set[str]:
    """Every key path of a JSON value; the keys of ``scenes``, ``cell_runs``, ``calibrations``
    and ``cells`` (names, units) and list positions are written ``*``."""
    paths: set[str] = set()
    if isinstance(value, dict):
        wild = prefix.rsplit(".", 1)[-1] in {"scenes", "cell_runs", "calibrations", "cells"}
        for key, item in value.items():
            path = f"{prefix}.{'*' if wild else key}"
            paths |= {path} | key_paths(item, path)
    elif isinstance(value, list):
        for item in value:
            paths |= key_paths(item, f"{prefix}[]")
    return paths


#: Key paths whose presence depends on the run, not on the engine: timing records only a redo
#: or a flag writes, the engine's own description.
RUN_DEPENDENT = (
    "redone",
    "missed_budget",
    "engine",
    "added",
    "worker.",
    "threads.address",  # Ray's: the cluster's address, CPUs and timed cell slots
    "threads.cluster_cpus",
    "threads.timed_cell_slots",
)


def compare_workers(sequential: dict, parallel: dict, out: Path, workers: Path) -> tuple[str, dict]:
    """The ``--compare-workers`` table: structure, report files, ratios workers / sequential."""
    from gdpt.statistics import mean_interval

    a, b = key_paths(sequential), key_paths(parallel)
    only = sorted(p for p in a ^ b if not any(w in p for w in RUN_DEPENDENT))
    files = sorted(p.name for p in out.iterdir() if p.is_file())
    missing = [f for f in files if not (workers / f).is_file()]
    ratios = {"sequential": cell_ratios(sequential), "workers": cell_ratios(parallel)}
    cells = sorted(set(ratios["sequential"]) & set(ratios["workers"]))
    methods = sorted({m for r in ratios["sequential"].values() for m in r})
    lines = [
        f"Workers ({workers.name}) against the sequential idle run: results.json key paths "
        f"only in one: {len(only)}; report files missing: {missing or 'none'}.",
        *(f"- {p} ({'sequential' if p in a else 'workers'} only)" for p in only),
        "",
        "| method | cells | geomean sequential | geomean workers | workers / sequential | "
        "95% interval | within the noise |",
        "|---|---:|---:|---:|---:|---|---|",
    ]
    numbers: dict = {"key_paths_only_in_one": only, "missing_files": missing, "methods": {}}
    for m in methods:
        both = [c for c in cells if m in ratios["sequential"][c] and m in ratios["workers"][c]]
        logs = [math.log(ratios["workers"][c][m] / ratios["sequential"][c][m]) for c in both]
        mean, low, high = (math.exp(v) for v in mean_interval(logs))
        gs = geomean([ratios["sequential"][c][m] for c in both])
        gw = geomean([ratios["workers"][c][m] for c in both])
        ok = low <= 1.0 <= high
        numbers["methods"][m] = {
            "cells": len(both),
            "sequential": gs,
            "workers": gw,
            "ratio": mean,
            "interval": [low, high],
            "within_noise": ok,
        }
        lines.append(
            f"| {m} | {len(both)} | {gs:.3f} | {gw:.3f} | {mean:.3f} | "
            f"{low:.3f}-{high:.3f} | {'yes' if ok else 'NO'} |"
        )
    return "\n".join(lines) + "\n", numbers


def metadata() -> dict:
    from gdpt.study.results import machine_info, versions

    commit = subprocess.run(
        ["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True, check=False
    ).stdout.strip()
    return {"commit": commit, "versions": versions(), "machine": machine_info()}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    timing = {}
    if not args.summary_only:
        runs = [("idle", False), ("loaded", True), *([("idle-2", False)] if args.control else [])]
        for name, loaded in runs:
            print(f"== {name}: {' '.join(study_command(args, args.out / name))}", flush=True)
            timing[name] = run_study(args, args.out / name, loaded)
        if args.compare_workers:
            name, out = (
                f"workers-{args.compare_workers}",
                args.out / f"workers-{args.compare_workers}",
            )
            print(f"== {name}: {' '.join(study_command(args, out, args.compare_workers))}")
            timing[name] = run_study(args, out, False, args.compare_workers)
    runs = {n: json.loads((args.out / n / "results.json").read_text()) for n in ("idle", "loaded")}
    text, numbers = summarise(runs["idle"], runs["loaded"])
    control = args.out / "idle-2" / "results.json"
    control_run = json.loads(control.read_text()) if args.control and control.is_file() else None
    table, numbers["counts"] = count_table(runs["idle"], runs["loaded"], control_run)
    text += "\n" + table
    anchors_path = args.out / "anchors.json"
    if args.anchor_reps and not args.summary_only:
        anchors_path.write_text(json.dumps(measure_anchors(args, runs["idle"]), indent=1))
    if anchors_path.is_file():
        numbers["anchors"] = json.loads(anchors_path.read_text())
        text += "\n" + anchor_table(numbers["anchors"], numbers["counts"])
    if args.compare_workers:
        workers = args.out / f"workers-{args.compare_workers}"
        parallel = json.loads((workers / "results.json").read_text())
        table, numbers["workers"] = compare_workers(
            runs["idle"], parallel, args.out / "idle", workers
        )
        text += "\n" + table
    print(text)
    (args.out / "summary.md").write_text(text)
    record = {**metadata(), "args": {k: str(v) for k, v in vars(args).items()}, "runs": timing}
    (args.out / "summary.json").write_text(json.dumps({**record, **numbers}, indent=1))
    print(f"wrote {args.out}/summary.md and summary.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
