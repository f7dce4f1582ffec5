"""Fixtures and hooks shared by the whole suite.

* ``variant`` (session): Mitsuba's ``llvm_ad_rgb`` with the gdpt plugins registered.
* ``random_buffers``: a factory of random :class:`~gdpt.buffers.GradientBuffers` on the CPU.
* ``single_thread``: one torch intra-op thread during the test (restored after), for tiny
  workloads on shared CPUs (``pytestmark = pytest.mark.usefixtures("single_thread")``).

Tests of the shared real scenes (marker ``shared_scenes``, :mod:`shared_scenes`): skipped with
the path in the reason when the folder is missing, except in CI (``CI=true``), where the run
fails at collection with the path it looked at; the terminal summary counts how many ran.

Property tests (hypothesis) run without its clocks (profile ``gdpt``: no deadline, no
``too_slow`` health check), so that they do not depend on the machine's speed either.

``--burn N`` (``make test-burn``, ``BURN=N``): N busy-loop processes at pytest's priority beside
the whole session (:mod:`cpu_burner`), so the suite can be checked on a loaded machine (no test
may depend on the machine's speed); the terminal summary says how much CPU time they took.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable, Iterator

import cpu_burner
import pytest
import torch
from hypothesis import HealthCheck, settings
from shared_scenes import MARKER, SHARED_SCENES, in_ci

from gdpt.buffers import CHANNELS, GradientBuffers

# Hypothesis's two clocks off for every property test: no per-example deadline and no
# "generation too slow" health check (both depend on the machine's speed and load; test_exr.py's
# round trip, which draws thousands of floats per example, failed beside a CPU burner).
settings.register_profile("gdpt", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("gdpt")

#: Outcomes (passed, failed, skipped) of the ``shared_scenes`` tests of this run.
_SHARED_OUTCOMES: Counter[str] = Counter()


#: The ``--burn`` processes of this run (none without the option).
_BURNERS = cpu_burner.Burners()


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--burn",
        type=int,
        default=0,
        metavar="N",
        help="run N busy-loop processes (at pytest's priority) beside the session: the suite "
        "under CPU load",
    )


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", f"{MARKER}: reads the shared real scenes (../shared/scenes, GDPT_SHARED_SCENES)"
    )
    burn = config.getoption("burn")
    if burn < 0:
        raise pytest.UsageError(f"--burn must be >= 0, got {burn}")
    _BURNERS.start(burn)


def pytest_unconfigure(config: pytest.Config) -> None:
    _BURNERS.stop()  # (a run that ended before its terminal summary)


@pytest.hookimpl(trylast=True)  # after -m and -k deselected tests
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Skip the selected ``shared_scenes`` tests when the folder is missing (fail in CI)."""
    shared = [item for item in items if item.get_closest_marker(MARKER)]
    if not shared or SHARED_SCENES.is_dir():
        return
    where = f"{SHARED_SCENES} (../shared/scenes beside the clone; GDPT_SHARED_SCENES overrides)"
    if in_ci():
        pytest.exit(
            f"CI is set but the shared real scenes are missing: looked for {where}; "
            f"{len(shared)} selected tests read them",
            returncode=pytest.ExitCode.USAGE_ERROR,
        )
    skip = pytest.mark.skip(reason=f"shared real scenes not found: looked for {where}")
    for item in shared:
        item.add_marker(skip)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if MARKER in report.keywords and (report.when == "call" or report.outcome != "passed"):
        _SHARED_OUTCOMES[report.outcome] += 1


def pytest_terminal_summary(terminalreporter) -> None:
    """One line: how many ``shared_scenes`` tests passed, failed and were skipped; with
    ``--burn``, one line: the burners' CPU time over the session's wall time."""
    if _BURNERS.processes:
        pids = _BURNERS.pids
        cpu, wall = _BURNERS.stop()
        terminalreporter.write_line(
            f"burner: {len(pids)} busy-loop process(es) (pid {', '.join(map(str, pids))}) beside "
            f"the tests: {cpu:.1f} CPU-s in {wall:.1f} s ({cpu / max(wall, 1e-9):.2f} cores)"
        )
    if _SHARED_OUTCOMES:
        counts = ", ".join(f"{_SHARED_OUTCOMES[k]} {k}" for k in ("passed", "failed", "skipped"))
        terminalreporter.write_line(f"shared real scenes ({SHARED_SCENES}): {counts}")


@pytest.fixture(scope="session")
def variant() -> str:
    """Mitsuba's ``llvm_ad_rgb`` variant with the gdpt plugins registered."""
    import gdpt

    return gdpt.set_variant("llvm_ad_rgb")


def make_random_buffers(
    h: int = 12,
    w: int = 10,
    *,
    names: Iterable[str] = tuple(CHANNELS),
    seed: int = 0,
    spp: int = 16,
    metadata: dict | None = None,
) -> GradientBuffers:
    """Buffers ``names`` of ``(h, w, C)`` float32 uniform [0, 1) values (CPU, seeded)."""
    g = torch.Generator().manual_seed(seed)
    tensors = {n: torch.rand(h, w, CHANNELS[n], generator=g) for n in names}
    return GradientBuffers(**tensors, spp=spp, metadata=dict(metadata or {}))


@pytest.fixture
def random_buffers() -> Callable[..., GradientBuffers]:
    """:func:`make_random_buffers`, as a fixture."""
    return make_random_buffers


@pytest.fixture
def single_thread() -> Iterator[None]:
    """One torch intra-op thread during the test (the previous count is restored)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
