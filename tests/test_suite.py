"""The test suite's own rules: the shared-scene gate of ``tests/conftest.py``, the files the
tests' docstrings cite, and the CPU burner of ``pytest --burn N``
(``tests/integrators/cpu_burner.py``)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import cpu_burner
import pytest

ROOT = Path(__file__).resolve().parents[1]
#: A fast test marked ``shared_scenes``.
SHARED_CASE = "tests/gdpt/test_evaluate.py::test_real_scene_loads_with_box_filter"


def _pytest(
    tmp_path: Path, ci: str | None, *args: str, case: str = SHARED_CASE
) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "CI"}
    env["GDPT_SHARED_SCENES"] = str(tmp_path / "no-scenes")
    if ci is not None:
        env["CI"] = ci
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *args, case],
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


def _alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (Linux ``/proc``)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_burner_burns_until_stopped():
    """A burner takes CPU time (busy, not sleeping) and is gone once stopped."""
    burners = cpu_burner.Burners()
    burners.start(1)
    (pid,) = burners.pids
    time.sleep(1.0)
    cpu, wall = burners.stop()
    # a tenth of a core: any fair share on a loaded machine; a sleeping loop takes ~0.015 s
    # (the interpreter's start-up)
    assert cpu > 0.1 and wall >= 1.0
    assert not _alive(pid) and not burners.processes
    assert burners.stop()[0] == 0.0  # idempotent
    with pytest.raises(ValueError, match="must be >= 0"):
        burners.start(-1)


@pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="reads /proc (Linux)")
def test_burner_ends_with_a_killed_parent():
    """A burner whose parent (the pytest process) is killed ends by itself."""
    code = "import cpu_burner, time\nb = cpu_burner.Burners()\nb.start(1)\n"
    code += "print(b.pids[0], flush=True)\ntime.sleep(600)"
    env = {**os.environ, "PYTHONPATH": str(Path(cpu_burner.__file__).parent)}
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, env=env)
    pid = int(parent.stdout.readline())
    assert _alive(pid)
    parent.send_signal(signal.SIGKILL)
    parent.wait(timeout=60)
    deadline = time.monotonic() + 30  # (it checks every few ms; 30 s: any load)
    while _alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    alive = _alive(pid)
    if alive:  # this test's own process: it must not outlive the test either
        os.kill(pid, signal.SIGKILL)
    assert not alive, "the burner outlived its killed parent"


def test_burn_option_runs_burners_beside_the_session(tmp_path):
    """``pytest --burn 2``: two burners ran beside the tests (the summary line says how much CPU
    they took) and none is left when pytest ends; a negative count is a usage error."""
    case = "tests/test_suite.py::test_files_cited_by_the_tests_exist"
    result = _pytest(tmp_path, None, "--burn", "2", case=case)
    assert result.returncode == 0, result.stdout
    line = re.search(
        r"burner: 2 busy-loop process\(es\) \(pid (\d+), (\d+)\) beside the tests: "
        r"([0-9.]+) CPU-s in ([0-9.]+) s",
        result.stdout,
    )
    assert line, result.stdout  # (that they burn: test_burner_burns_until_stopped)
    assert not any(_alive(int(pid)) for pid in line.groups()[:2])
    result = _pytest(tmp_path, None, "--burn", "-1", case=case)
    assert result.returncode == pytest.ExitCode.USAGE_ERROR
    assert "--burn must be >= 0, got -1" in result.stderr
