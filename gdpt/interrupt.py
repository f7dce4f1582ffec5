"""Ctrl-C (``SIGINT``) where native code is involved: recognising it when it reaches Python
wrapped in another exception, and holding it while native modules initialise.

A ``KeyboardInterrupt`` raised inside a function that Dr.Jit records (``dr.freeze``) comes out
as a ``RuntimeError`` ("error encountered while recording a frozen function") whose
``__cause__`` is the interrupt; one raised in a Python plugin's constructor while Mitsuba's
scene parser instantiates it (``mi.load_dict``, ``mi.load_file``) comes out as a
``RuntimeError`` with no chain, whose message carries the formatted traceback ending in
``KeyboardInterrupt``. Code that catches ``Exception`` to record a failure must let such errors
through (:func:`caused_by_interrupt`). A ``KeyboardInterrupt`` raised while
Mitsuba's nanobind modules initialise (``import mitsuba``, ``mi.set_variant``) aborts the
process (``std::terminate``, or a fatal error at interpreter exit); :func:`interrupts_deferred`
holds it until the block ends.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager


def caused_by_interrupt(error: BaseException) -> bool:
    """Whether ``error`` is a ``KeyboardInterrupt``, has one in its chain, or is Mitsuba's
    parser error reporting one.

    Args:
        error: any exception; its ``__cause__`` and ``__context__`` links are followed.

    Returns:
        ``True`` if ``error`` or an exception it was raised from (or during) is a
        ``KeyboardInterrupt``, or is a ``RuntimeError`` whose message holds a Python
        traceback that ends with one (Mitsuba's scene parser, see the module docstring).
    """
    seen: set[int] = set()
    pending: list[BaseException] = [error]
    while pending:
        current = pending.pop()
        if id(current) in seen:
            continue
        seen.add(id(current))
        if isinstance(current, KeyboardInterrupt):
            return True
        if isinstance(current, RuntimeError) and _reports_interrupt(str(current)):
            return True
        pending += [e for e in (current.__cause__, current.__context__) if e is not None]
    return False


def _reports_interrupt(message: str) -> bool:
    """Whether ``message`` holds a Python traceback whose exception line is a
    ``KeyboardInterrupt`` (as Mitsuba's parser formats a plugin's exception)."""
    exception_lines = message.split("Traceback (most recent call last):", 1)[1:]
    return any(
        line.strip().startswith("KeyboardInterrupt")
        for text in exception_lines
        for line in text.splitlines()
    )


@contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold a Ctrl-C received inside the block; raise it as ``KeyboardInterrupt`` at the end.

    Only the main thread receives signals: in another thread the block runs unchanged. A
    ``SIGINT`` handler other than Python's default one is left alone.
    """
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGINT) is not signal.default_int_handler
    ):
        yield
        return
    received: list[int] = []
    signal.signal(signal.SIGINT, lambda number, frame: received.append(number))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if received:
        raise KeyboardInterrupt
