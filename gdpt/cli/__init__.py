"""Command-line interface: ``gdpt <command> ...`` (also ``python -m gdpt``).

The commands come in groups, one module each: :mod:`.render` (``info``, ``reconstruct``,
``render``, ``render-and-denoise``), :mod:`.advice` (``advise``), :mod:`.study` (``demo``,
``evaluate``) and :mod:`.training` (``dataset``, ``train``, ``select-refinement``,
``model-report``). Every command is a :class:`~gdpt.cli.command.Command`: a name, a one-line
help text, a function that adds its arguments to an argparse sub-parser and a function that runs
it. To add a command, write ``_add_<name>_arguments(parser)`` and ``_run_<name>(args) -> int``
in its group and append a ``Command`` to the group's ``COMMANDS``. Heavy modules (torch,
Mitsuba) are imported inside these functions only: a sub-parser adds its arguments when it is
used (:class:`_CommandParser`), so ``gdpt --help`` and the light commands stay fast. Options of
typed configurations (``TrainConfig``, ``DatasetConfig``) are generated from their fields
(:mod:`gdpt.cli.config_options`).

User errors (missing or malformed input, refusing to overwrite, invalid options) print one line
``gdpt <command>: error: <message>`` to stderr and exit with status 2, without a traceback.
Set ``GDPT_DEBUG=1`` to get the traceback instead. A Ctrl-C (``SIGINT``), wherever it lands
(also inside a Dr.Jit frozen function, which wraps it in a ``RuntimeError``), prints one line
``gdpt <command>: <what was kept, how to resume>`` (:attr:`Command.interrupted`) and exits
with status 130. gdpt's own ``DeprecationWarning`` (a
method's former name, ``GDPT_NGPT_MODEL``) is printed to stderr, once per place.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from collections.abc import Callable, Sequence

from gdpt.cli import advice, render, study, training
from gdpt.cli.command import Command, UsageError
from gdpt.interrupt import caused_by_interrupt
from gdpt.version import __version__

#: Exceptions reported as one-line user errors with exit status 2.
_USER_ERRORS = (
    UsageError,
    FileNotFoundError,
    FileExistsError,
    IsADirectoryError,
    PermissionError,
    ValueError,
)


#: The subcommands, in the order ``gdpt --help`` lists them.
COMMANDS: tuple[Command, ...] = (
    *render.COMMANDS,
    *advice.COMMANDS,
    *study.COMMANDS,
    *training.COMMANDS,
)


class _CommandParser(argparse.ArgumentParser):
    """A sub-parser that adds its command's arguments on first use (parsing, help or usage).

    Attributes:
        add_arguments: the command's ``_add_<name>_arguments``; ``None`` once called.
    """

    add_arguments: Callable[[argparse.ArgumentParser], None] | None = None

    def _add_arguments_once(self) -> None:
        add, self.add_arguments = self.add_arguments, None
        if add is not None:
            add(self)

    def parse_known_args(self, args=None, namespace=None):  # noqa: D102 (argparse's)
        self._add_arguments_once()
        return super().parse_known_args(args, namespace)

    def format_usage(self) -> str:  # noqa: D102 (argparse's)
        self._add_arguments_once()
        return super().format_usage()

    def format_help(self) -> str:  # noqa: D102 (argparse's)
        self._add_arguments_once()
        return super().format_help()


def build_parser() -> argparse.ArgumentParser:
    """The ``gdpt`` argument parser with one (lazily filled) sub-parser per :data:`COMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="gdpt",
        description="Gradient-domain path tracing for Mitsuba 3 with Poisson and neural "
        "reconstruction.",
    )
    parser.add_argument("--version", action="version", version=f"gdpt {__version__}")
    subparsers = parser.add_subparsers(
        dest="command", metavar="COMMAND", required=True, parser_class=_CommandParser
    )
    for command in COMMANDS:
        sub = subparsers.add_parser(command.name, help=command.help, description=command.help)
        sub.add_arguments = command.add_arguments
        sub.set_defaults(run=command.run, interrupted=command.interrupted)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``gdpt`` command line.

    Args:
        argv (Sequence[str] | None): arguments without the program name; ``None`` uses
            ``sys.argv[1:]``.

    Returns:
        The exit status: 0 on success, 2 for user errors, 130 when interrupted.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("default", category=DeprecationWarning, module=r"gdpt(\.|$)")
        parser = build_parser()
        args = None
        try:
            args = parser.parse_args(argv)  # (imports the command's modules)
            return args.run(args)
        except BaseException as error:
            debug = os.environ.get("GDPT_DEBUG")
            if caused_by_interrupt(error) and not debug:
                if args is None:
                    print("gdpt: interrupted", file=sys.stderr)
                else:
                    print(f"gdpt {args.command}: {_interrupted(args)}", file=sys.stderr)
                return 130
            if not isinstance(error, _USER_ERRORS) or debug:
                raise
            message = " ".join(str(error).split())  # one line, whatever the exception text
            print(f"gdpt {args.command}: error: {message}", file=sys.stderr)
            return 2


def _interrupted(args: argparse.Namespace) -> str:
    """The command's line after a Ctrl-C; plain "interrupted" if it has none or it fails."""
    if args.interrupted is None:
        return "interrupted"
    try:
        return args.interrupted(args)
    except Exception:  # the state on disk could not be read: say only what happened
        return "interrupted"


if __name__ == "__main__":
    raise SystemExit(main())
