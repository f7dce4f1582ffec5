"""``gdpt/training`` does not depend on the study: no module of it imports ``gdpt.study``, at
the top or inside a function (statistics they share live in ``gdpt/statistics.py``)."""

from __future__ import annotations

import ast
from pathlib import Path

import gdpt.training

TRAINING = Path(gdpt.training.__file__).parent


def imported_modules(path: Path) -> set[str]:
    """Every module ``path`` imports (``import x.y``, ``from x.y import z``), lazy ones too."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def test_training_imports_nothing_from_the_study():
    found = {
        f"{path.relative_to(TRAINING.parent)}: {name}"
        for path in sorted(TRAINING.rglob("*.py"))
        for name in imported_modules(path)
        if name == "gdpt.study" or name.startswith("gdpt.study.")
    }
    assert len(list(TRAINING.rglob("*.py"))) > 10 and not found, sorted(found)


def test_the_shared_statistics_import_no_other_gdpt_module():
    path = Path(gdpt.training.__file__).parents[1] / "statistics.py"
    assert not {n for n in imported_modules(path) if n.split(".")[0] == "gdpt"}
