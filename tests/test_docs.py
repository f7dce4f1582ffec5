"""The README and the pages of ``docs/``: size, links, and the README's Python blocks running."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").glob("*.md"))]
#: The lab record (former runs, designs not kept): committed, linked, but its figures are history
#: and carry no names.
LAB_PAGES = sorted((ROOT / "docs" / "lab").glob("*.md"))


def _anchors(page: Path) -> set[str]:
    """GitHub's anchors of the headings of ``page`` (lower case, punctuation dropped)."""
    headings = re.findall(r"^#+ (.+)$", page.read_text(), re.M)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in headings}


def _python_blocks(page: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", page.read_text(), re.S)


def test_readme_is_a_short_guide():
    assert len(README.read_text().splitlines()) <= 250


@pytest.mark.parametrize("page", PAGES + LAB_PAGES, ids=lambda p: p.name)
def test_relative_links_resolve(page):
    broken = []
    for link in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
        if re.match(r"[a-z]+:", link):
            continue
        path, _, anchor = link.partition("#")
        target = (page.parent / path).resolve() if path else page
        if not target.exists():
            broken.append(f"{link}: no such file")
        elif anchor and target.suffix == ".md" and anchor not in _anchors(target):
            broken.append(f"{link}: no heading with that anchor")
    assert not broken, f"{page.name}: {broken}"


@pytest.mark.slow
@pytest.mark.parametrize("index", range(len(_python_blocks(README))))
def test_readme_python_block_runs_as_written(index, tmp_path):
    """Each block in a fresh interpreter, in an empty folder (it may write files there)."""
    block = _python_blocks(README)[index]
    result = subprocess.run(
        [sys.executable, "-c", block],
        check=False,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=900,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert result.returncode == 0, result.stderr[-2000:]


def _quick_start_commands() -> list[str]:
    """The ``gdpt ...`` lines of the README's quick start (comments dropped)."""
    text = README.read_text()
    section = text.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```sh\n(.*?)```", section, re.S)
    lines = (line.split("#")[0].strip() for block in blocks for line in block.splitlines())
    return [line for line in lines if line.startswith("gdpt ")]


@pytest.fixture(scope="module")
def quick_start_runs(tmp_path_factory) -> list[tuple[str, subprocess.CompletedProcess]]:
    """Every quick-start command run once, in order, in an empty folder holding the guide's
    scene.xml: ``(command, its finished process)``, up to the first that fails."""
    folder = tmp_path_factory.mktemp("quick-start")
    xml = re.findall(r"```xml\n(.*?)```", (ROOT / "docs" / "guide.md").read_text(), re.S)
    (folder / "scene.xml").write_text(xml[0])
    runs = []
    for command in _quick_start_commands():
        result = subprocess.run(
            [sys.executable, "-m", "gdpt", *shlex.split(command)[1:]],
            check=False,
            cwd=folder,
            capture_output=True,
            text=True,
            timeout=900,
            env={**os.environ, "OMP_NUM_THREADS": "1"},
        )
        runs.append((command, result))
        if result.returncode != 0:  # later commands may read what it writes
            break
    return runs


@pytest.mark.slow
def test_readme_quick_start_commands_run(quick_start_runs):
    """Every quick-start command runs (exit status 0)."""
    commands = _quick_start_commands()
    assert len(commands) >= 4, commands
    for command, result in quick_start_runs:
        assert result.returncode == 0, f"{command}: {result.stderr[-2000:]}"
    assert [command for command, _ in quick_start_runs] == commands


@pytest.mark.slow
def test_readme_auto_example_shows_a_route(quick_start_runs):
    """The quick start's ``auto`` commands (``render-and-denoise`` without ``--method``) print a
    route decided by a pilot (``on N pilot tiles at M gradient spp``), not one taken without a
    pilot (too few spp for one in the budget, or too few whole 16 px tiles), and, given
    ``--time``, their timings against that budget."""
    autos = [
        (command, result)
        for command, result in quick_start_runs
        if command.startswith("gdpt render-and-denoise ") and "--method" not in command
    ]
    assert autos, "the quick start has no auto example (or a command before it failed)"
    for command, result in autos:
        assert result.returncode == 0, f"{command}: {result.stderr[-2000:]}"
        route = [line for line in result.stdout.splitlines() if line.startswith("auto: ")]
        assert len(route) == 1, (command, result.stdout)
        assert re.search(r" on \d+ pilot tiles at \d+ gradient spp: ", route[0]), (command, route)
        words = shlex.split(command)
        if "--time" in words:
            budget = float(words[words.index("--time") + 1])
            assert f"s of a {budget:.2f} s budget (" in result.stdout, (command, result.stdout)


def _markdown_table(text: str) -> dict[str, dict[str, str]]:
    """The first markdown table in ``text``: first cell -> {column header: cell}."""
    lines = re.search(r"^\|.*?(?=^[^|]|\Z)", text, re.M | re.S).group(0).splitlines()
    split = [[cell.strip() for cell in line.strip().strip("|").split("|")] for line in lines]
    head, rows = split[0], split[2:]
    return {row[0]: dict(zip(head, row, strict=True)) for row in rows}


def test_readme_costs_are_the_cost_tables():
    """The README's methods table copies its cost columns from ``docs/cost-table.md``
    (``benchmarks/cost_table.py``): one run, one machine, one condition."""
    text = README.read_text()
    methods = _markdown_table(text.split("<!-- methods-table:", 1)[1].split("-->", 1)[1])
    costs = _markdown_table((ROOT / "docs" / "cost-table.md").read_text())
    columns = [h for h in next(iter(methods.values())) if h.startswith(("render", "reconstruct"))]
    shared = [h for h in columns if h in next(iter(costs.values()))]
    assert len(shared) >= 2 and shared == columns, (columns, shared)
    differ = [
        f"{method} {column}: README {row[column]!r}, cost table "
        f"{costs.get(method, {}).get(column)!r}"
        for method, row in methods.items()
        for column in shared
        if costs.get(method, {}).get(column) != row[column]
    ]
    assert not differ, differ


COST_TABLE = ROOT / "docs" / "cost-table.json"
#: A cost figure copied from the cost table is a link to it whose title names the cell:
#: ``[1.5 s](cost-table.md "oidn: reconstruct, 1280x720")``; a ratio of two methods' cells:
#: ``[256x](cost-table.md "nfor / oidn: reconstruct, 128x128")``; a render cost relative to a
#: plain path sample (the table's own ratio): ``[5.4x](cost-table.md "fuse: render / sample,
#: 128x128")``.
_CITED = re.compile(r'\[([^\]]*)\]\(([^)\s]*cost-table\.md)(?:\s+"([^"]*)")?\)')
_FIGURE = re.compile(r"(\d+(?:\.\d+)?) ?(s|ms|x)")
_CELL = re.compile(r"([\w-]+)(?: / ([\w-]+))?: (reconstruct|render / sample), (\d+x\d+)")


def _cell_value(record: dict, title: str) -> tuple[float, bool]:
    """The value of the cell ``title`` names in the cost table's ``record`` (seconds, or a
    ratio), and whether it is a ratio."""
    cell = _CELL.fullmatch(title)
    assert cell, f"{title!r} is not 'METHOD[ / METHOD]: reconstruct|render / sample, WxH'"
    first, second, quantity, size = cell.groups()
    rows = record["results"][size]
    if quantity == "render / sample":
        plain = next(iter(rows))  # the plain path-tracing row, the table's own denominator
        return rows[first]["render_per_spp"] / rows[second or plain]["render_per_spp"], True
    if second:
        return rows[first]["reconstruct"] / rows[second]["reconstruct"], True
    return rows[first]["reconstruct"], False


def _cited_figures() -> list[tuple[str, str, str]]:
    """``(where, figure, title)`` for every link to the cost table in the README and ``docs/``
    whose text is a number (a link may span lines)."""
    pages = [README, *sorted(p for p in (ROOT / "docs").glob("*.md") if p.stem != "cost-table")]
    cited = []
    for page in pages:
        text = page.read_text()
        for link in _CITED.finditer(text):
            figure, target, title = (" ".join(group.split()) for group in link.groups(""))
            if _FIGURE.fullmatch(figure):
                where = f"{page.relative_to(ROOT)}:{text.count(chr(10), 0, link.start()) + 1}"
                assert (page.parent / target).resolve() == COST_TABLE.with_suffix(".md"), where
                cited.append((where, figure, title))
    return cited


def test_cost_figures_citing_the_cost_table_are_its_values():
    """A figure that links to ``docs/cost-table.md`` names its cell in the link's title and
    equals the cell's value in ``docs/cost-table.json`` to the digits it is written with: one
    run, one condition (other cost figures state their own run and command)."""
    record = json.loads(COST_TABLE.read_text())
    cited = _cited_figures()
    assert len(cited) >= 10, cited  # the guard guards something
    wrong = []
    for where, figure, title in cited:
        if not title:
            wrong.append(f"{where}: {figure} links to the cost table, no title names its cell")
            continue
        number, unit = _FIGURE.fullmatch(figure).groups()
        value, ratio = _cell_value(record, title)
        if ratio != (unit == "x"):
            wrong.append(f"{where}: {figure} for {title!r}: a ratio is written Nx, seconds N s")
            continue
        value *= 1000 if unit == "ms" else 1
        decimals = len(number.partition(".")[2])
        if abs(value - float(number)) > 0.5 * 10**-decimals + 1e-12:
            wrong.append(f"{where}: {figure} for {title!r}: the table has {value:.{decimals}f}")
    assert not wrong, wrong


def test_readme_states_the_cost_tables_condition():
    """The condition line of the README's methods table (the line after its start marker) is
    that of the cost table's run."""
    record = json.loads(COST_TABLE.read_text())
    block = README.read_text().split("<!-- methods-table:", 1)[1]
    condition = block.splitlines()[1]
    assert f"**{record['condition']}**" in condition, condition
    for part in (record["machine"], record["threads"], record["date"], *record["skipped"]):
        assert part in condition, (part, condition)


#: A figure quoted in more than one place carries the same name everywhere, in an HTML comment
#: right before it (invisible on the rendered page): ``<!--fig:auto-per-cell-->0.93-1.03x``;
#: its number (a range included, the unit not) must be the same everywhere.
_NAMED = re.compile(r"<!--fig:([\w.-]+)-->(\d[\d.\-]*\d|\d)")


def _named_figures() -> dict[str, list[tuple[str, str]]]:
    """Name -> ``[(where, figure)]`` over the README, the CHANGELOG and ``docs/``."""
    named: dict[str, list[tuple[str, str]]] = {}
    for page in PAGES:
        text = page.read_text()
        for match in _NAMED.finditer(text):
            where = f"{page.relative_to(ROOT)}:{text.count(chr(10), 0, match.start()) + 1}"
            named.setdefault(match.group(1), []).append((where, match.group(2)))
    return named


#: Figures a reader meets on several pages (the README's claims and where they are measured):
#: each must stay named, so that a change on one page only fails the test below.
REQUIRED_NAMES = {
    "fuse-direct",  # fuse over pt+oidn-tuned on directly lit scenes, 2-8 s
    "fuse-direct-spp",  # the gradient spp of those cells
    "fuse-few-spp",  # fuse at fewer gradient spp (the former study)
    "fuse-rooms",  # fuse on rooms lit indirectly
    "fuse-living-room-2",  # fuse on living-room-2 at 128 px
    "pilot-sees-gain",  # the gradient spp from which auto's pilot sees fuse's gain
    "scenes-512px",  # how many scenes the 512 px study has
    "cell-interval",  # the noise of one cell's ratio
    "advise-per-candidate",  # what advise costs per candidate, in budgets
    "advise-cost",  # what advise costs in all, in budgets
    "gradient-sample-cost",  # a gradient sample in plain samples
    "auto-gradient-runs",
    "auto-over-fuse",
    "primal-mis-fuse",  # fuse with primal="mis" over "base" at the same count
}


def test_a_figure_quoted_twice_is_the_same_everywhere():
    """Every named figure (``_NAMED``) is quoted at least twice, each time with the same value:
    a figure changed in one place only fails here."""
    named = _named_figures()
    assert not REQUIRED_NAMES - set(named), sorted(REQUIRED_NAMES - set(named))
    wrong = [
        f"{name}: {quotes}"
        for name, quotes in named.items()
        if len(quotes) < 2 or len({figure for _, figure in quotes}) > 1
    ]
    assert not wrong, wrong
