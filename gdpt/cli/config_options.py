"""Command-line options generated from a typed configuration dataclass, and the config back.

:func:`add_config_arguments` adds one ``--kebab-case`` option per dataclass field: the field's
type (``int``, ``float``, ``str``, ``bool`` or one of them ``| None``), its default, and the help
text of its entry in the ``Attributes:`` section of the class docstring. ``bool`` fields become
``--name`` / ``--no-name`` pairs. :func:`config_from_args` builds the dataclass back from the
parsed namespace (the option of field ``name`` stores into ``args.name``). No default is typed
twice: changing a dataclass default changes the command line.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
from collections.abc import Collection, Mapping, Sequence
from typing import Any

__all__ = ["add_config_arguments", "attribute_docs", "config_fields", "config_from_args"]

#: Field annotation (as written, ``from __future__ import annotations``) -> argparse type.
_TYPES: dict[str, type] = {"int": int, "float": float, "str": str, "bool": bool}


def attribute_docs(cls: type) -> dict[str, str]:
    """Field name -> its one-paragraph description in the ``Attributes:`` section of ``cls``.

    Sphinx roles (``:func:`x```) and inline literals (````x````) are reduced to plain text and
    whitespace is collapsed to single spaces.
    """
    lines = (cls.__doc__ or "").splitlines()
    start = next((i + 1 for i, line in enumerate(lines) if line.strip() == "Attributes:"), None)
    if start is None:
        return {}
    docs: dict[str, list[str]] = {}
    indent = None
    current: list[str] | None = None
    for line in lines[start:]:
        if not line.strip():
            continue
        width = len(line) - len(line.lstrip())
        entry = re.match(r"\s*(\w+): (.*)", line)
        if indent is None and entry:
            indent = width
        if indent is None or width < indent:
            break
        if width == indent and entry:
            current = docs.setdefault(entry.group(1), [entry.group(2)])
        elif current is not None:
            current.append(line.strip())
    plain = {}
    for name, parts in docs.items():
        text = re.sub(r":\w+:`~?([^`]+)`", r"\1", " ".join(parts)).replace("``", "")
        plain[name] = " ".join(text.split())
    return plain


def config_fields(cls: type, exclude: Collection[str] = ()) -> list[dataclasses.Field]:
    """The fields of dataclass ``cls`` that become options (all but ``exclude``)."""
    return [f for f in dataclasses.fields(cls) if f.name not in exclude]


def _field_type(cls: type, field: dataclasses.Field) -> type:
    """The argparse type of ``field`` (``X`` or ``X | None`` with ``X`` in :data:`_TYPES`)."""
    annotation = field.type if isinstance(field.type, str) else field.type.__name__
    base = annotation.removesuffix(" | None")
    if base not in _TYPES:
        raise TypeError(
            f"{cls.__name__}.{field.name}: annotation {annotation!r} has no command-line form; "
            "exclude the field"
        )
    return _TYPES[base]


def add_config_arguments(
    parser: argparse.ArgumentParser,
    cls: type,
    *,
    exclude: Collection[str] = (),
    names: Mapping[str, str] | None = None,
    required: Collection[str] = (),
    choices: Mapping[str, Sequence[Any]] | None = None,
) -> None:
    """Add one option per field of dataclass ``cls`` to ``parser``.

    Args:
        parser: the (sub-)parser to extend.
        cls: a dataclass; fields without a default get a required option.
        exclude: fields without an option (their dataclass default is used).
        names: field -> option string replacing ``--field-name`` (e.g. ``{"model": "--config"}``).
        required: fields whose option must be given (the dataclass default is not a usable
            value, or the command wants it explicit).
        choices: field -> allowed values.

    Raises:
        TypeError: a field's type has no command-line form (exclude it).
    """
    docs = attribute_docs(cls)
    names, choices = dict(names or {}), dict(choices or {})
    for field in config_fields(cls, exclude):
        option = names.get(field.name, "--" + field.name.replace("_", "-"))
        kind = _field_type(cls, field)
        text = docs.get(field.name, "").replace("%", "%%")
        kwargs: dict[str, Any] = {"dest": field.name}
        if field.name in required or field.default is dataclasses.MISSING:
            kwargs["required"] = True
        else:
            kwargs["default"] = field.default
        if kind is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        else:
            kwargs["type"] = kind
        if kwargs.get("default") is not None:
            text = f"{text} (default: %(default)s)".strip()
        if field.name in choices:
            kwargs["choices"] = list(choices[field.name])
        parser.add_argument(option, help=text, **kwargs)


def config_from_args(cls: type, args: argparse.Namespace, *, exclude: Collection[str] = ()):
    """``cls`` built from the options :func:`add_config_arguments` added (same ``exclude``)."""
    return cls(**{f.name: getattr(args, f.name) for f in config_fields(cls, exclude)})
