"""The machine a timing ran on: the CPU's model name, for the records of the study and the
benchmarks."""

from __future__ import annotations

import platform
from pathlib import Path


def cpu_name() -> str:
    """The CPU's model name (``model name`` of ``/proc/cpuinfo`` on Linux), else the processor
    or machine string Python reports (e.g. ``'x86_64'``)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
