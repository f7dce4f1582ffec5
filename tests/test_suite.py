"""The test suite's own rules: the shared-scene gate of ``tests/conftest.py`` and the files the
tests' docstrings cite."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: A fast test marked ``shared_scenes``.
SHARED_CASE = "tests/gdpt/test_evaluate.py::test_real_scene_loads_with_box_filter"


def _pytest(tmp_path: Path, ci: str | None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "CI"}
    env["GDPT_SHARED_SCENES"] = str(tmp_path / "no-scenes")
    if ci is not None:
        env["CI"] = ci
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", SHARED_CASE],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def test_missing_shared_scenes_fail_the_run_in_ci(tmp_path):
    result = _pytest(tmp_path, "true")
    assert result.returncode != 0, result.stdout
    expected = f"the shared real scenes are missing: looked for {tmp_path / 'no-scenes'}"
    assert expected in result.stdout + result.stderr, result.stdout


def test_missing_shared_scenes_skip_locally_with_the_path_and_a_count(tmp_path):
    result = _pytest(tmp_path, None)
    assert result.returncode == 0, result.stdout
    assert f"shared real scenes not found: looked for {tmp_path / 'no-scenes'}" in result.stdout
    assert f"shared real scenes ({tmp_path / 'no-scenes'}): 0 passed, 0 failed, 1 skipped" in (
        result.stdout
    )


def test_files_cited_by_the_tests_exist():
    """Every ``tests/...`` or package path named in a test file's text exists."""
    cited = {}
    for path in (ROOT / "tests").rglob("*.py"):
        for name in re.findall(
            r"``((?:tests|gdpt|integrators|reconstruct)/[\w/.-]+\.py)``", path.read_text()
        ):
            cited.setdefault(name, path.relative_to(ROOT))
    missing = {name: str(where) for name, where in cited.items() if not (ROOT / name).is_file()}
    assert cited and not missing, missing
