"""The properties of the ``gdpt`` / ``gdpt_rr`` plugins: one table, read by the plugins'
constructor (:func:`read_properties`) and by whoever names settings as text, such as a study
method ``gdpt+fuse@max_depth=4`` (:func:`parse_property`).

A property added to :data:`PROPERTIES` is accepted, checked and typed in both places; the plugin
reads it from ``GradientIntegratorBase.settings`` (plain Python, no Mitsuba import here).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Property:
    """One plugin property.

    Attributes:
        kind: ``bool``, ``int``, ``float`` or ``str``: the value's Python type.
        default: the value when the property is not given.
        values: for a ``str`` property, the values it takes (``None``: any).
        check: ``None`` or a predicate on the typed value (``False``: invalid).
        expected: what a valid value is, for messages (e.g. ``"-1 or >= 0"``).
    """

    kind: type
    default: Any
    values: tuple[str, ...] | None = None
    check: Callable[[Any], bool] | None = None
    expected: str = ""

    def valid(self, value: Any) -> bool:
        """Whether the typed ``value`` is one this property takes."""
        if self.values is not None and value not in self.values:
            return False
        return self.check is None or bool(self.check(value))

    def describe(self) -> str:
        """What a valid value is: :attr:`expected`, the :attr:`values`, else the type."""
        if self.values is not None:
            return "one of " + ", ".join(map(repr, self.values))
        return self.expected or {bool: "true or false", int: "an integer"}.get(
            self.kind, "a number"
        )


#: Name -> :class:`Property` of every property the plugins accept (their meaning: the plugins'
#: docstrings and ``docs/integrators.md``).
PROPERTIES: dict[str, Property] = {
    "max_depth": Property(int, 6, check=lambda v: v >= -1, expected="-1 (unbounded) or >= 0"),
    "rr_depth": Property(int, 5, check=lambda v: v > 0, expected="an integer > 0"),
    "gradients": Property(bool, True),
    "features": Property(bool, True),
    "variance": Property(bool, False),
    "halves": Property(bool, False),
    # samples traced per kernel launch (bounds memory and kernel size)
    "samples_per_pass": Property(int, 1 << 20, check=lambda v: v >= 1, expected="an integer >= 1"),
    # roughness at or below which a lobe is near-specular (Kettunen et al. 2015's default)
    "shift_threshold": Property(
        float, 0.001, check=lambda v: 0.0 <= v < math.inf, expected="a finite roughness >= 0"
    ),
    "freeze": Property(bool, True),
    # the primal estimator: the base path alone, or every base and offset path that lands in the
    # pixel with its pixel pair's MIS weight (integrators/common.py's module docstring)
    "primal": Property(str, "base", values=("base", "mis")),
}


def checked(plugin: str, name: str, value: Any) -> Any:
    """``value`` of property ``name`` as its type, checked.

    Raises:
        ValueError: ``plugin: 'name' must be EXPECTED, got VALUE`` (also for a value of another
            type, e.g. a string for an integer).
    """
    prop = PROPERTIES[name]
    typed: Any = None
    if isinstance(value, str):
        typed = value if prop.kind is str else None
    elif prop.kind is bool and value in (True, False):  # also 0 / 1 and numpy's booleans
        typed = bool(value)
    elif prop.kind is int and isinstance(value, numbers.Integral) and not isinstance(value, bool):
        typed = int(value)
    elif prop.kind is float and isinstance(value, numbers.Real) and not isinstance(value, bool):
        typed = float(value)
    if typed is None or not prop.valid(typed):
        raise ValueError(f"{plugin}: '{name}' must be {prop.describe()}, got {value!r}")
    return typed


def read_properties(props: Any, plugin: str) -> dict[str, Any]:
    """Every property of :data:`PROPERTIES` from ``props`` (an ``mi.Properties``), its default
    where absent, typed and checked (:func:`checked`)."""
    return {
        name: checked(plugin, name, props.get(name, prop.default))
        for name, prop in PROPERTIES.items()
    }


def parse_property(item: str, plugin: str = "gdpt") -> tuple[str, Any]:
    """``NAME=VALUE`` as ``(name, typed value)``: booleans ``true``/``false``, numbers as
    Python reads them, strings as they are.

    Raises:
        ValueError: no ``=``, an unknown name (the valid names listed) or an invalid value.
    """
    name, sep, text = item.partition("=")
    name, text = name.strip(), text.strip()
    if not sep or not name:
        raise ValueError(f"{item!r}: expected PROPERTY=VALUE")
    if name not in PROPERTIES:
        raise ValueError(
            f"unknown {plugin} integrator property {name!r}; valid: {', '.join(PROPERTIES)}"
        )
    kind = PROPERTIES[name].kind
    value: Any = text
    try:
        if kind is bool:
            value = {"true": True, "false": False}[text.lower()]
        elif kind is int:
            value = int(text)
        elif kind is float:
            value = float(text)
    except (KeyError, ValueError):
        pass  # the text itself: checked() names what was expected
    return name, checked(plugin, name, value)
