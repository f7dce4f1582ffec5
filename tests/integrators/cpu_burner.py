"""CPU load beside the test suite: busy-loop processes at the priority of the process that
starts them (``pytest --burn N``, ``make test-burn``), so that the suite can be checked on a
loaded machine.

Each burner is ``python -c BURNER``: a loop of pure Python that checks every few milliseconds
whether its parent (the process that started it) is still there and ends when it is not, so a
killed pytest leaves no burner behind. :meth:`Burners.stop` ends them and returns the CPU time they
took (``os.wait4``'s resource usage), which the run prints as evidence of the load.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass, field

#: The busy loop, given its parent's pid as argument: runs until that parent is gone
#: (``getppid`` changes when it is reparented; the pid is passed, not read at start-up, so
#: that a parent killed before the loop starts is seen too).
BURNER = (
    "import os, sys\n"
    "parent = int(sys.argv[1])\n"
    "while os.getppid() == parent:\n"
    "    for _ in range(200_000):\n"
    "        pass\n"
)


@dataclass
class Burners:
    """Burner processes: :meth:`start` some, :meth:`stop` them all."""

    processes: list[subprocess.Popen] = field(default_factory=list)
    started: float = 0.0

    @property
    def pids(self) -> list[int]:
        """Process ids of the running burners."""
        return [p.pid for p in self.processes]

    def start(self, count: int) -> None:
        """Start ``count`` burner processes (``count >= 0``).

        Raises:
            ValueError: ``count`` is negative.
        """
        if count < 0:
            raise ValueError(f"the number of burner processes must be >= 0, got {count}")
        self.started = time.monotonic()
        command = [sys.executable, "-c", BURNER, str(os.getpid())]
        for _ in range(count):
            self.processes.append(subprocess.Popen(command))

    def stop(self) -> tuple[float, float]:
        """End the burners (idempotent); ``(their CPU seconds, wall seconds since the start)``."""
        cpu = 0.0
        for process in self.processes:
            if process.returncode is None:
                process.kill()
                _, _, usage = os.wait4(process.pid, 0)
                process.returncode = -9  # reaped here: Popen must not wait for it again
                cpu += usage.ru_utime + usage.ru_stime
        self.processes.clear()
        return cpu, time.monotonic() - self.started
