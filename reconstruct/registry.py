"""The one name -> entry registry used for losses, metrics and reconstruction/study methods.

It lives in the lowest room (``reconstruct/``, standard library only) so that the losses here
and the metrics and methods in :mod:`gdpt` share it::

    LOSSES = Registry("loss")

    @LOSSES.register("l1")
    def l1_loss(...): ...

    LOSSES["l1"]          # KeyError naming the valid entries if unknown
    list(LOSSES)          # names, in registration order (CLI choices are taken from here)

A :class:`Registry` is a ``dict`` (``in``, iteration, ``monkeypatch.setitem`` work as usual);
only :meth:`Registry.register` refuses to overwrite an entry.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar, overload

T = TypeVar("T")


class Registry(dict[str, T]):
    """Registered entries by name, in registration order.

    Args:
        kind: what the entries are (``"loss"``, ``"metric"``, ``"method"``), for messages.
    """

    def __init__(self, kind: str) -> None:
        super().__init__()
        self.kind = kind

    @overload
    def register(self, name: str) -> Callable[[T], T]: ...
    @overload
    def register(self, name: str, entry: T) -> T: ...

    def register(self, name: str, entry: T | None = None) -> T | Callable[[T], T]:
        """Add ``entry`` under ``name``; without ``entry``, a decorator that adds the function.

        Raises:
            ValueError: ``name`` is already registered.
        """

        def add(value: T) -> T:
            if name in self:
                raise ValueError(f"{self.kind} {name!r} is already registered")
            self[name] = value
            return value

        return add if entry is None else add(entry)

    def __missing__(self, name: str) -> T:
        raise KeyError(f"unknown {self.kind} {name!r}; valid names: {', '.join(self)}")

    def check(self, names: object) -> None:
        """Raise ``ValueError`` naming every unknown entry of ``names`` (an iterable of str)."""
        if unknown := [n for n in names if n not in self]:  # type: ignore[attr-defined]
            listed = ", ".join(map(repr, unknown))
            raise ValueError(f"unknown {self.kind} {listed}; valid names: {', '.join(self)}")
