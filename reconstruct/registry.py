"""The one name -> entry registry used for losses, metrics and reconstruction/study methods.

It lives in the lowest room (``reconstruct/``, standard library only) so that the losses here
and the metrics and methods in :mod:`gdpt` share it::

    LOSSES = Registry("loss")

    @LOSSES.register("l1")
    def l1_loss(...): ...

    LOSSES["l1"]          # KeyError naming the valid entries if unknown
    list(LOSSES)          # names, in registration order (CLI choices are taken from here)

    LOSSES.alias("l1-old", "l1")  # a renamed entry's former name, for one release
    LOSSES["l1-old"]              # the "l1" entry, with a DeprecationWarning naming "l1"

A :class:`Registry` is a ``dict`` (``in``, iteration, ``monkeypatch.setitem`` work as usual);
only :meth:`Registry.register` refuses to overwrite an entry. A deprecated alias answers to
``[]``, ``in`` and :meth:`Registry.resolve` only: iteration, ``len`` and messages name the
current entries.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import TypeVar, overload

T = TypeVar("T")


class Registry(dict[str, T]):
    """Registered entries by name, in registration order.

    Args:
        kind: what the entries are (``"loss"``, ``"metric"``, ``"method"``), for messages.

    Attributes:
        aliases: deprecated name -> current name (:meth:`alias`).
    """

    def __init__(self, kind: str) -> None:
        super().__init__()
        self.kind = kind
        self.aliases: dict[str, str] = {}

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

    def alias(self, old: str, new: str) -> None:
        """Accept ``old``, the former name of the entry ``new``, with a ``DeprecationWarning``:
        ``self[old]`` is ``self[new]`` and :meth:`resolve` maps ``old`` to ``new`` (both warn);
        ``old in self`` is true (without warning).

        Raises:
            ValueError: ``old`` is already a name or an alias, or ``new`` is not registered.
        """
        if old in self:
            raise ValueError(f"{self.kind} {old!r} is already registered")
        if not super().__contains__(new):
            raise ValueError(f"unknown {self.kind} {new!r}; valid names: {', '.join(self)}")
        self.aliases[old] = new

    def resolve(self, name: str, *, stacklevel: int = 1) -> str:
        """The current name of ``name``: for a deprecated alias its new name, with a
        ``DeprecationWarning`` naming both; else ``name`` itself (registered or not).

        Args:
            name: a name or a deprecated alias.
            stacklevel: the frame the warning names: 1 the caller of ``resolve``, 2 its
                caller, ... (as :func:`warnings.warn`'s, counted from the caller).
        """
        if super().__contains__(name) or name not in self.aliases:
            return name
        new = self.aliases[name]
        warnings.warn(
            f"{self.kind} {name!r} is deprecated; use {new!r}",
            DeprecationWarning,
            stacklevel=stacklevel + 1,
        )
        return new

    def __contains__(self, name: object) -> bool:
        return super().__contains__(name) or name in self.aliases

    def __missing__(self, name: str) -> T:
        if name in self.aliases:
            return self[self.resolve(name, stacklevel=2)]
        raise KeyError(f"unknown {self.kind} {name!r}; valid names: {', '.join(self)}")

    def check(self, names: object) -> None:
        """Raise ``ValueError`` naming every unknown entry of ``names`` (an iterable of str)."""
        if unknown := [n for n in names if n not in self]:  # type: ignore[attr-defined]
            listed = ", ".join(map(repr, unknown))
            raise ValueError(f"unknown {self.kind} {listed}; valid names: {', '.join(self)}")
