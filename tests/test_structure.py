"""The import graph of the package: no cycle inside it, and the two lower rooms stay apart.

Every module of ``gdpt`` (folder ``gdpt/``), ``gdpt.reconstruct`` (``reconstruct/``) and
``gdpt.integrators`` (``integrators/``) is parsed with :mod:`ast`; every import statement is an
edge, those inside functions and under ``if TYPE_CHECKING:`` included (a type-only import never
runs, but a cycle through one still says a type lives above the code that reads it).
``gdpt/__init__.py`` imports its public functions by name on first use (``_LAZY``); those count
as edges of ``gdpt`` too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Package -> its folder in the repository (pyproject's ``package-dir``).
ROOMS = {"gdpt": ROOT / "gdpt", "gdpt.reconstruct": ROOT / "reconstruct"}
ROOMS["gdpt.integrators"] = ROOT / "integrators"


def module_files() -> dict[str, Path]:
    """Module name -> source file, for every ``.py`` file of the three rooms."""
    modules = {}
    for package, folder in ROOMS.items():
        for path in folder.rglob("*.py"):
            parts = path.relative_to(folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join((package, *parts))] = path
    return modules


def _imports(tree: ast.AST):
    """Import nodes of ``tree``, at any depth (``if TYPE_CHECKING:`` blocks included)."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Module -> the modules of ``modules`` it imports (itself excluded)."""
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets = set()
        for node in _imports(tree):
            if isinstance(node, ast.Import):
                candidates = [alias.name for alias in node.names]
            else:
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*anchor, base] if base else anchor)
                candidates = [f"{base}.{alias.name}" for alias in node.names] + [base]
                # "from a import b": the submodule a.b if it is one, else the module a
                candidates = [c for c in candidates[:-1] if c in modules] or [base]
            for target in candidates:
                while target and target not in modules:  # "import a.b.c" of a non-module name
                    target = target.rpartition(".")[0]
                if target and target != name:
                    targets.add(target)
        if name == "gdpt":
            lazy = next(
                n.value
                for n in ast.walk(tree)
                if isinstance(n, ast.AnnAssign) and getattr(n.target, "id", "") == "_LAZY"
            )
            targets |= {ast.literal_eval(v) for v in lazy.values}
        graph[name] = targets
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as ``[a, b, ..., a]``, or ``None``."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt) :], nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph(module_files())


def test_the_graph_sees_function_local_relative_and_type_checking_imports(graph):
    """Sanity of the parser on known edges: a relative import, a function-local one, a lazy
    public name of ``gdpt``, an import under ``if TYPE_CHECKING:``."""
    assert "gdpt.reconstruct.poisson" in graph["gdpt.reconstruct.fuse.solve"]  # from ..poisson
    assert "gdpt.reconstruct.autograd" in graph["gdpt.methods"]  # inside reconstruct_image
    assert "gdpt.pipeline" in graph["gdpt"]
    assert "gdpt.training.config" in graph["gdpt.training.schedule"]  # under TYPE_CHECKING only


def test_find_cycle_names_the_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_cycle(graph):
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


@pytest.mark.parametrize("room", ["gdpt.reconstruct", "gdpt.integrators"])
def test_lower_rooms_import_only_themselves(graph, room):
    """``gdpt.reconstruct`` and ``gdpt.integrators`` import no other module of the package."""
    outside = {
        f"{module} -> {target}"
        for module, targets in graph.items()
        if module == room or module.startswith(room + ".")
        for target in targets
        if not (target == room or target.startswith(room + "."))
    }
    assert not outside, f"{room} imports outside itself: {sorted(outside)}"


#: Most lines of a module of ``gdpt/`` or ``reconstruct/`` (a file past it holds more than one
#: concept; ``integrators/`` keeps a whole path tracer per file).
MAX_LINES = 600


@pytest.mark.parametrize("folder", ["gdpt", "reconstruct"])
def test_modules_stay_under_the_line_limit(folder):
    too_long = {
        str(path.relative_to(ROOT)): n
        for path in (ROOT / folder).rglob("*.py")
        if (n := len(path.read_text().splitlines())) > MAX_LINES
    }
    assert not too_long, f"modules over {MAX_LINES} lines: {too_long}"
