"""The README's cost figures from one run on one machine: ``docs/cost-table.md`` and its JSON.

For every method of :data:`gdpt.methods.METHODS` that can run here, at 128x128 and 1280x720 on
the built-in ``cbox-demo``: the render cost of one sample of what the method reads relative to
one plain path sample, and the reconstruction's seconds (measured by
``benchmarks/method_cost.py``'s :func:`measure`: one untimed run first, then the median of
``--repeats``). The page states the command, date, machine, thread counts and load average, and
a one-line condition (``--condition``, e.g. "idle machine"). The README's methods table copies
its cells and its condition, and figures of the README and ``docs/`` cite its cells as links
whose title names the cell (:data:`CITED`); ``--docs`` writes both from the run
(``tests/test_docs.py`` checks that they agree with the JSON).

The reconstructions that take minutes at 1280x720 (:data:`SLOW`; ``nfor``: ~7 min per run on one
thread) are timed ``--slow-repeats`` times there (default 1, after the untimed run);
``--skip-slow`` leaves them out (their cells read "—" and the page says why). ``--rewrite``
measures nothing: it writes the page (and with ``--docs`` the others) again from the JSON.
Usage::

    .venv/bin/python benchmarks/cost_table.py --threads 1 --docs --condition "idle machine"
    .venv/bin/python benchmarks/cost_table.py --sizes 128x128 --condition "machine shared" \
        --out /tmp/cost-table.md
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
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

#: The size of the slow reconstructions (``--skip-slow`` and ``--slow-repeats`` act there only).
LARGE = (1280, 720)

#: A cell that was not measured.
NOT_RUN = "—"

#: The page the README's methods table cites, the README, and the pages that cite it.
PAGE = ROOT / "docs" / "cost-table.md"
README = ROOT / "README.md"
CITING = (README, *sorted(p for p in PAGE.parent.glob("*.md") if p != PAGE))

#: A figure that cites a cell of the page: a link to it whose title names the cell,
#: ``[1.5 s](cost-table.md "oidn: reconstruct, 1280x720")``; a ratio of two methods' cells,
#: ``[256x](cost-table.md "nfor / oidn: reconstruct, 128x128")``; a render cost relative to a
#: plain path sample, as the page gives it, ``[5.4x](cost-table.md "fuse: render / sample,
#: 128x128")``. The title may wrap to the next line.
CITED = re.compile(r'\[(\d+(?:\.\d+)?) ?(s|ms|x)\]\([^)\s]*cost-table\.md\s+"([^"]*)"\)')
#: A cell's name in such a title: method, a second method to divide by, quantity, size.
CELL = re.compile(r"([\w-]+)(?: / ([\w-]+))?: (reconstruct|render / sample), (\d+x\d+)")

#: The README's methods table lies between these two lines' prefixes; the first line after the
#: start marker is the condition line (:func:`condition_line`).
TABLE_START, TABLE_END = "<!-- methods-table:", "<!-- methods-table: end -->"


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


def skipped_note(record: dict) -> str | None:
    """What the "—" cells of a run with ``--skip-slow`` stand for (``None``: nothing skipped)."""
    if not record["skipped"]:
        return None
    return f"{NOT_RUN}: not measured in this run (`--skip-slow`: {', '.join(record['skipped'])})"


def repeats_note(record: dict) -> str:
    """How many timed runs a cell is the median of."""
    text = f"median of {record['repeats']} runs after an untimed one"
    slow = [f"`{name}`" for name in SLOW if name in record["results"].get(label(LARGE), {})]
    if slow and record.get("slow_repeats", record["repeats"]) != record["repeats"]:
        text += f" ({', '.join(slow)} at {label(LARGE)}: {record['slow_repeats']})"
    return text


def label(size: tuple[int, int]) -> str:
    """``(1280, 720)`` -> ``'1280x720'``: a size's column label."""
    return f"{size[0]}x{size[1]}"


def page_header(record: dict) -> list[str]:
    """The page's column headers: ``method``, then render / sample and reconstruct per size."""
    labels = list(record["results"])
    return ["method"] + [f"{h}, {s}" for s in labels for h in ("render / sample", "reconstruct")]


def markdown(record: dict) -> str:
    """The page ``docs/cost-table.md`` for one run's ``record`` (see :func:`main`)."""
    header = page_header(record)
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
        f"{repeats_note(record)} (kernel compilation, "
        "frozen-pass recording and weight loading excluded)",
        "- render / sample: one sample of what the method reads, relative to one plain path "
        "sample (`gdpt` with `gradients=false`, features on) at the same size; `N` spp cost "
        "about `N` samples + the reconstruction",
    ]
    if skipped_note(record):
        lines.append(f"- {skipped_note(record)}")
    lines += [
        "",
        "| " + " | ".join(header) + " |",
        "|---|" + "---:|" * (len(header) - 1),
    ]
    lines += ["| " + " | ".join(row) + " |" for row in table_rows(record["results"])]
    return "\n".join(lines) + "\n"


def condition_line(record: dict) -> str:
    """The README's line above its methods table: the run's condition, machine, threads, date."""
    line = (
        f"Condition: **{record['condition']}**; {record['machine']}; threads: "
        f"{record['threads']}; {record['date']}."
    )
    return f"{line} {skipped_note(record)}." if skipped_note(record) else line


def _cells(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def readme_with_costs(readme: str, record: dict) -> str:
    """``readme`` with its methods table's block (between :data:`TABLE_START` and
    :data:`TABLE_END`) rewritten: the condition line, then the table with its cost cells (the
    columns the page has too) from ``record``. ValueError naming what does not fit."""
    before, start, rest = readme.partition(TABLE_START)
    block, end, after = rest.partition(TABLE_END)
    if not start or not end:
        raise ValueError(f"README: no block from '{TABLE_START}' to '{TABLE_END}'")
    marker, _, body = block.partition("\n")
    table = [line for line in body.splitlines() if line.startswith("|")]
    if len(table) < 3:
        raise ValueError("README: no methods table after the start marker")
    page_columns = page_header(record)
    page = {
        row[0]: dict(zip(page_columns, row, strict=True)) for row in table_rows(record["results"])
    }
    header = _cells(table[0])
    costs = [h for h in header if h.startswith(("render / sample", "reconstruct"))]
    missing = [h for h in costs if h not in page_columns]
    if missing:
        raise ValueError(f"README's methods table: columns {missing} are not in the cost table")
    rows = []
    for line in table[2:]:
        cells = _cells(line)
        if cells[0] not in page:
            raise ValueError(f"README's methods table: {cells[0]} has no row in the cost table")
        for column in costs:
            cells[header.index(column)] = page[cells[0]][column]
        rows.append("| " + " | ".join(cells) + " |")
    lines = [condition_line(record), "", table[0], table[1], *rows, ""]
    return before + start + marker + "\n" + "\n".join(lines) + end + after


def cell_value(record: dict, title: str) -> tuple[float, bool]:
    """The value of the cell a :data:`CITED` title names (seconds, or a ratio) and whether it is
    a ratio; ValueError if ``record`` has no such cell."""
    cell = CELL.fullmatch(" ".join(title.split()))
    if cell is None:
        raise ValueError("the title is not 'METHOD[ / METHOD]: reconstruct|render / sample, WxH'")
    first, second, quantity, size = cell.groups()
    rows = record["results"].get(size, {})
    missing = [name for name in (first, second) if name and name not in rows]
    if missing:
        raise ValueError(f"the run has no {', '.join(missing)} at {size}")
    if quantity == "render / sample":
        return rows[first]["render_per_spp"] / rows[second or PLAIN]["render_per_spp"], True
    if second:
        return rows[first]["reconstruct"] / rows[second]["reconstruct"], True
    return rows[first]["reconstruct"], False


def with_cited_figures(text: str, record: dict, name: str) -> str:
    """``text`` (the page ``name``) with every :data:`CITED` figure written from ``record``, with
    as many decimals as it had; ValueError naming a figure whose cell does not exist."""

    def figure(match: re.Match) -> str:
        number, unit, title = match.groups()
        line = text.count("\n", 0, match.start()) + 1
        try:
            value, ratio = cell_value(record, title)
            if ratio != (unit == "x"):
                raise ValueError("a ratio is written Nx, seconds N s")
        except ValueError as error:
            raise ValueError(f"{name}:{line}: {match.group(0)!r}: {error}") from None
        value *= 1000 if unit == "ms" else 1
        new = f"{value:.{len(number.partition('.')[2])}f}"
        return match.group(0).replace(number, new, 1)

    return CITED.sub(figure, text)


def documents(record: dict) -> dict[Path, str]:
    """The README (its methods table and cited figures) and the ``docs/`` pages that cite the
    page, as ``record`` makes them; ValueError naming what does not fit."""
    texts = {}
    for page in CITING:
        text = page.read_text()
        if page == README:
            text = readme_with_costs(text, record)
        texts[page] = with_cited_figures(text, record, str(page.relative_to(ROOT)))
    return texts


def _placeholder_record(sizes: list[tuple[int, int]]) -> dict:
    """A record with every registered method at every size: to check the README's table and the
    cited figures before measuring."""
    row = {"render_per_spp": 1.0, "reconstruct": 1.0}
    results = {label(size): {PLAIN: row, **dict.fromkeys(METHODS, row)} for size in sizes}
    return {
        "condition": "",
        "machine": "",
        "threads": "",
        "date": "",
        "skipped": [],
        "results": results,
    }


def write(record: dict, out: Path, docs: bool) -> None:
    """The page ``out``, its JSON and (``docs``) the pages that copy or cite it, from
    ``record``."""
    out.write_text(markdown(record))
    out.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
    print(markdown(record))
    print(f"wrote {out} and {out.with_suffix('.json')}")
    if docs:
        try:
            texts = documents(record)
        except ValueError as error:
            message = f"{error} (the page and its JSON are written, the others are not)"
            raise SystemExit(message) from None
        for page, text in texts.items():
            if text != page.read_text():
                page.write_text(text)
                print(f"wrote {page.relative_to(ROOT)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", type=parse_size, default=[(128, 128), LARGE])
    parser.add_argument("--spp", type=int, default=4, help="gradient samples per pixel")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per measurement")
    parser.add_argument(
        "--slow-repeats",
        type=int,
        default=1,
        help=f"timed runs of {', '.join(SLOW)} at {label(LARGE)} (minutes each)",
    )
    parser.add_argument(
        "--threads",
        type=int,
        help="torch and Dr.Jit threads (default: their own defaults); on a machine shared "
        "with other jobs use 1 (torch's spinning threads slow each other down)",
    )
    parser.add_argument(
        "--skip-slow",
        action="store_true",
        help=f"skip {', '.join(SLOW)} at {label(LARGE)} (minutes)",
    )
    parser.add_argument(
        "--condition",
        help="one line on the machine's state, printed in bold on the page (e.g. 'idle "
        "machine, one thread', 'machine shared with other jobs; to be re-run idle'); the "
        "machine's CPU is recorded separately",
    )
    parser.add_argument("--out", type=Path, default=PAGE)
    parser.add_argument(
        "--docs",
        action="store_true",
        help="also write the condition line and the cost cells of README.md's methods table "
        "and every figure of README.md and docs/*.md that cites a cell (with the default --out, "
        "the page they cite)",
    )
    parser.add_argument(
        "--rewrite",
        action="store_true",
        help="measure nothing: write the page (and with --docs the others) again from the "
        "JSON beside --out",
    )
    args = parser.parse_args()
    if min(args.spp, args.repeats, args.slow_repeats, args.threads or 1) < 1:
        parser.error("--spp, --repeats, --slow-repeats and --threads must be >= 1")
    if args.docs and args.out.resolve() != PAGE:
        parser.error(
            f"--docs copies {PAGE.relative_to(ROOT)}, the page the others cite: "
            "leave --out at its default"
        )
    if args.rewrite:
        write(json.loads(args.out.with_suffix(".json").read_text()), args.out, args.docs)
        return
    if not args.condition:
        parser.error("--condition is required (the machine's state: idle, shared, ...)")
    if args.docs:
        try:
            documents(_placeholder_record(args.sizes))
        except ValueError as error:
            parser.error(str(error))

    variant = gdpt.set_variant()
    import drjit as dr

    if args.threads is not None:
        torch.set_num_threads(args.threads)
        dr.set_thread_count(args.threads)
    load_start = os.getloadavg()[0]
    results, skipped = {}, []
    for size in args.sizes:
        methods = list(METHODS)
        slow = [name for name in SLOW if name in methods] if size == LARGE else []
        methods = [name for name in methods if name not in slow]
        if args.skip_slow:
            skipped += [f"`{name}` at {label(size)}" for name in slow]
        print(f"{label(size)}: load average {os.getloadavg()[0]:.2f}", flush=True)
        results[label(size)] = measure(size, args.spp, args.repeats, methods)
        if slow and not args.skip_slow:
            print(f"{label(size)}, {', '.join(slow)}: load average {os.getloadavg()[0]:.2f}")
            rows = measure(size, args.spp, args.slow_repeats, slow)
            results[label(size)].update({name: rows[name] for name in slow if name in rows})
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
        "slow_repeats": args.slow_repeats,
        "skipped": skipped,
        "results": results,
    }
    write(record, args.out, args.docs)


if __name__ == "__main__":
    main()
