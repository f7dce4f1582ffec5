"""What every ``gdpt`` command group uses: :class:`Command`, :class:`UsageError` and the
``NAME=VALUE`` options."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass


class UsageError(Exception):
    """An error caused by the command line or its input files (reported in one line)."""


@dataclass(frozen=True)
class Command:
    """One ``gdpt`` subcommand.

    Attributes:
        name: the subcommand name on the command line.
        help: one-line description shown by ``gdpt --help``.
        add_arguments: adds the subcommand's arguments to its sub-parser.
        run: executes the subcommand with the parsed arguments; returns the exit status.
        interrupted: after a Ctrl-C, one line from the parsed arguments saying what was kept
            and how to resume (``None``: "interrupted").
    """

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    interrupted: Callable[[argparse.Namespace], str] | None = None


def add_model_option(parser: argparse.ArgumentParser, text: str) -> None:
    """``--model NAME=CHECKPOINT``, repeatable, into ``args.models``."""
    parser.add_argument(
        "--model", action="append", default=[], metavar="NAME=CHECKPOINT", dest="models", help=text
    )


def split_named(item: str, option: str, value: str) -> tuple[str, str]:
    """``NAME=VALUE`` of a command-line ``option`` as ``(NAME, VALUE)``.

    Raises:
        ValueError: either side is empty or there is no ``=``.
    """
    name, sep, rest = item.partition("=")
    if not sep or not name or not rest:
        raise ValueError(f"{option} {item!r}: expected NAME={value}")
    return name, rest
