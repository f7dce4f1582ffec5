"""A progress bar in seconds over the stages of one piece of work (:class:`SecondsBar`), or one
per stage (:class:`StageBars`)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


class SecondsBar:
    """A tqdm bar (stderr) of the wall seconds elapsed against ``total`` (a budget in seconds;
    ``None``: open-ended), the current stage in its description; a background thread advances
    it every ``interval`` seconds, so that a long stage (a pilot, a reconstruction) shows
    progress too. A context manager; ``disable=True`` draws nothing.
    """

    def __init__(
        self, total: float | None, stage: str = "", *, disable: bool = False, interval: float = 0.2
    ):
        from tqdm.auto import tqdm

        self.total = total
        self._bar: Any = tqdm(
            total=None if total is None else round(total, 2),
            unit="s",
            desc=stage,
            disable=disable,
            leave=False,
            bar_format=None
            if total is None
            else "{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} s budget",
        )
        self._start = time.perf_counter()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = None
        if not disable:
            self._thread = threading.Thread(target=self._tick, args=(interval,), daemon=True)
            self._thread.start()

    def _tick(self, interval: float) -> None:
        while not self._stop.wait(interval):
            self._advance()

    def _advance(self) -> None:
        with self._lock:  # one thread draws at a time; tqdm's own (multiprocessing) lock is
            # not taken from two threads (it deadlocked the main thread and this one)
            elapsed = round(time.perf_counter() - self._start, 1)  # a full bar past the budget
            self._bar.n = elapsed if self.total is None else min(elapsed, self._bar.total)
            self._bar.refresh(nolock=True)

    def stage(self, name: str) -> None:
        """Show ``name`` as the current stage."""
        with self._lock:
            self._bar.set_description_str(name, refresh=False)
            self._bar.refresh(nolock=True)

    def close(self) -> None:
        """Stop the thread and close the bar."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._advance()
        self._bar.close()

    def __enter__(self) -> SecondsBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class StageBars:
    """Progress over work of several stages (:func:`gdpt.advise`): one :class:`SecondsBar` per
    stage (``with bars(kind, label, budget):``, against the stage's budget where it has one),
    and :attr:`seconds`, the wall seconds per kind of stage; ``progress`` off draws nothing."""

    def __init__(self, progress: bool):
        self.progress = progress
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, kind: str, label: str, budget: float | None = None) -> Iterator[None]:
        start = time.perf_counter()
        try:
            with SecondsBar(budget, label, disable=not self.progress):
                yield
        finally:
            self.seconds[kind] = self.seconds.get(kind, 0.0) + time.perf_counter() - start
