"""The README's cost figures from one run on one machine: ``docs/cost-table.md`` and its JSON.

For every method of :data:`gdpt.methods.METHODS` that can run here, at 128x128 and 1280x720 on
the built-in ``cbox-demo``: the render cost of one sample of what the method reads relative to
one plain path sample, and the reconstruction's seconds (measured by
``benchmarks/method_cost.py``'s :func:`measure`: one untimed run first, then the median of
``--repeats``). The page states the command, date, machine, thread counts and load average, and
a one-line condition (``--condition``, e.g. "idle machine"); the README's methods table copies
its cells (``tests/test_docs.py`` checks that it does).

``--skip-slow`` leaves out the reconstructions that take minutes at 1280x720 (:data:`SLOW`;
``nfor``: ~5 min idle); their cells read "—" and the page says why. Usage::

    .venv/bin/python benchmarks/cost_table.py --threads 1 --condition "idle machine"
    .venv/bin/python benchmarks/cost_table.py --sizes 128x128 --condition "machine shared"
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import sys
from pathlib import Path

import torch
from method_cost import PLAIN, measure, parse_size

import gdpt
from gdpt.machine import cpu_name
from gdpt.methods import METHODS

ROOT = Path(__file__).resolve().parents[1]

#: Reconstructions that take minutes at 1280x720 (``nfor``: ~320 s idle, 2 threads).
SLOW = ("nfor",)

#: The size of the slow reconstructions (``--skip-slow`` skips them there only).
LARGE = (1280, 720)

#: A cell that was not measured.
NOT_RUN = "—"


def seconds_cell(value: float) -> str:
    """Seconds with two significant digits (at least whole seconds): ``0.063 s``, ``6.1 s``,
    ``67 s``."""
    if value >= 10:
        return f"{value:.0f} s"
    if value >= 1:
        return f"{value:.1f} s"
    return f"{value:.2g} s"


def ratio_cell(value: float) -> str:
    """A render cost relative to a plain path sample: ``2.7x``."""
    return f"{value:.1f}x"


def table_rows(results: dict[str, dict[str, dict[str, float]]]) -> list[list[str]]:
    """``[method, (render / sample, reconstruct) per size ...]`` cells, plain path tracing first."""
    names = list(dict.fromkeys(name for rows in results.values() for name in rows))
    cells = []
    for name in names:
        row = [name if name == PLAIN else f"`{name}`"]
        for rows in results.values():
            if name not in rows:
                row += [NOT_RUN, NOT_RUN]
                continue
            ratio = rows[name]["render_per_spp"] / rows[PLAIN]["render_per_spp"]
            reconstruct = NOT_RUN if name == PLAIN else seconds_cell(rows[name]["reconstruct"])
            row += [ratio_cell(ratio), reconstruct]
        cells.append(row)
    return cells


def markdown(record: dict) -> str:
    """The page ``docs/cost-table.md`` for one run's ``record`` (see :func:`main`)."""
    labels = list(record["results"])
    header = ["method"] + [f"{h}, {s}" for s in labels for h in ("render / sample", "reconstruct")]
    lines = [
        "# Cost of each method",
        "",
        "Written by `benchmarks/cost_table.py` (do not edit by hand; the README's methods table "
        "copies its cells, `tests/test_docs.py` checks that).",
        "",
        f"**Condition: {record['condition']}.**",
        "",
        f"- command: `{record['command']}`",
        f"- date: {record['date']}",
        f"- machine: {record['machine']}",
        f"- threads: {record['threads']}",
        f"- load average (1 min): {record['load_start']:.2f} at start, "
        f"{record['load_end']:.2f} at end",
        f"- what: the built-in `cbox-demo` scene, {record['spp']} gradient samples per pixel, "
        f"median of {record['repeats']} runs after an untimed one (kernel compilation, "
        "frozen-pass recording and weight loading excluded)",
        "- render / sample: one sample of what the method reads, relative to one plain path "
        "sample (`gdpt` with `gradients=false`, features on) at the same size; `N` spp cost "
        "about `N` samples + the reconstruction",
    ]
    if record["skipped"]:
        lines.append(
            f"- {NOT_RUN}: not measured in this run (`--skip-slow`: {', '.join(record['skipped'])})"
        )
    lines += [
        "",
        "| " + " | ".join(header) + " |",
        "|---|" + "---:|" * (len(header) - 1),
    ]
    lines += ["| " + " | ".join(row) + " |" for row in table_rows(record["results"])]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", type=parse_size, default=[(128, 128), LARGE])
    parser.add_argument("--spp", type=int, default=4, help="gradient samples per pixel")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per measurement")
    parser.add_argument(
        "--threads",
        type=int,
        help="torch and Dr.Jit threads (default: their own defaults); on a machine shared "
        "with other jobs use 1 (torch's spinning threads slow each other down)",
    )
    parser.add_argument(
        "--skip-slow",
        action="store_true",
        help=f"skip {', '.join(SLOW)} at {LARGE[0]}x{LARGE[1]} (minutes)",
    )
    parser.add_argument(
        "--condition",
        required=True,
        help="one line on the machine's state, printed in bold on the page (e.g. 'idle "
        "machine', 'machine shared with other jobs; to be re-run idle')",
    )
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "cost-table.md")
    args = parser.parse_args()
    if args.spp < 1 or args.repeats < 1 or (args.threads is not None and args.threads < 1):
        parser.error("--spp, --repeats and --threads must be >= 1")

    variant = gdpt.set_variant()
    import drjit as dr

    if args.threads is not None:
        torch.set_num_threads(args.threads)
        dr.set_thread_count(args.threads)
    load_start = os.getloadavg()[0]
    results, skipped = {}, []
    for size in args.sizes:
        label = f"{size[0]}x{size[1]}"
        methods = list(METHODS)
        if args.skip_slow and size == LARGE:
            skipped += [f"`{name}` at {label}" for name in SLOW]
            methods = [name for name in methods if name not in SLOW]
        print(f"{label}: load average {os.getloadavg()[0]:.2f}", flush=True)
        results[label] = measure(size, args.spp, args.repeats, methods)
    record = {
        "condition": args.condition,
        "command": shlex.join(["python", *sys.argv]),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": f"{cpu_name()}, {os.cpu_count()} logical CPUs, {platform.system()}, "
        f"Mitsuba variant {variant}, torch {torch.__version__}",
        "threads": f"torch {torch.get_num_threads()}, Dr.Jit {dr.thread_count()}",
        "load_start": load_start,
        "load_end": os.getloadavg()[0],
        "spp": args.spp,
        "repeats": args.repeats,
        "skipped": skipped,
        "results": results,
    }
    args.out.write_text(markdown(record))
    args.out.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
    print(markdown(record))
    print(f"wrote {args.out} and {args.out.with_suffix('.json')}")


if __name__ == "__main__":
    main()
