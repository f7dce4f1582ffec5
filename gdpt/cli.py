"""Command-line interface: ``gdpt <command> ...`` (also ``python -m gdpt``).

Every subcommand is a :class:`Command`: a name, a one-line help text, a function that adds its
arguments to an argparse sub-parser and a function that runs it. To add a subcommand, write
``_add_<name>_arguments(parser)`` and ``_run_<name>(args) -> int`` and append a
:class:`Command` to :data:`COMMANDS`. Heavy modules (torch, Mitsuba) are imported inside the
``_run_*`` functions so that ``gdpt --help`` stays fast.

User errors (missing or malformed input, refusing to overwrite, invalid options) print one line
``gdpt <command>: error: <message>`` to stderr and exit with status 2, without a traceback.
Set ``GDPT_DEBUG=1`` to get the traceback instead.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from gdpt.version import __version__
from gdpt.reconstruction import METHODS


class UsageError(Exception):
    """An error caused by the command line or its input files (reported in one line)."""


#: Exceptions reported as one-line user errors with exit status 2.
_USER_ERRORS = (
    UsageError,
    FileNotFoundError,
    FileExistsError,
    IsADirectoryError,
    PermissionError,
    ValueError,
)


@dataclass(frozen=True)
class Command:
    """One ``gdpt`` subcommand.

    Attributes:
        name: the subcommand name on the command line.
        help: one-line description shown by ``gdpt --help``.
        add_arguments: adds the subcommand's arguments to its sub-parser.
        run: executes the subcommand with the parsed arguments; returns the exit status.
    """

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


# ----------------------------------------------------------------------------------------- info
def _add_info_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", type=Path, help="an EXR file written by gdpt")


def _run_info(args: argparse.Namespace) -> int:
    import torch

    from gdpt.exr import channel_names, load_buffers

    buffers = load_buffers(args.file)
    mode = "gradient-domain (dx, dy)" if buffers.has_gradients else "primal-only"
    print(f"file:     {args.file}")
    print(f"size:     {buffers.width} x {buffers.height} (W x H)")
    print(f"spp:      {buffers.spp}")
    print(f"mode:     {mode}")
    print("buffers:")
    print(f"  {'name':<11} {'channels':<32} {'NaN':>8} {'Inf':>8}")
    for name, tensor in buffers.items():
        channels = ",".join(channel_names(name))
        nan = int(torch.isnan(tensor).sum())
        inf = int(torch.isinf(tensor).sum())
        print(f"  {name:<11} {channels:<32} {nan:>8} {inf:>8}")
    print(f"metadata: {json.dumps(buffers.metadata, indent=2, sort_keys=True)}")
    return 0


# ---------------------------------------------------------------------------------- reconstruct
def _add_reconstruct_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", type=Path, help="an EXR file with primal, dx and dy buffers")
    parser.add_argument(
        "--method", choices=list(METHODS), default="l1", help="reconstruction (default: l1)"
    )
    parser.add_argument(
        "--alpha", type=float, default=0.2, help="weight of the primal term (default: 0.2)"
    )
    parser.add_argument(
        "-o", "--output", type=Path, required=True, help="output RGB EXR (R, G, B channels)"
    )
    parser.add_argument(
        "--png", action="store_true", help="also write a tone-mapped PNG next to the output"
    )
    parser.add_argument("--force", action="store_true", help="overwrite existing outputs")


def _run_reconstruct(args: argparse.Namespace) -> int:
    from gdpt.exr import check_writable, load_buffers, save_image
    from gdpt.images import preview_path, save_png
    from gdpt.reconstruction import reconstruct

    if args.output.suffix.lower() != ".exr":
        raise UsageError(f"output must be an .exr file, got '{args.output}'")
    if not (math.isfinite(args.alpha) and args.alpha > 0):
        raise UsageError(f"--alpha must be a finite number > 0, got {args.alpha}")
    outputs = [args.output, *([preview_path(args.output)] if args.png else [])]
    for path in outputs:  # fail before the (possibly slow) reconstruction
        check_writable(path, force=args.force)

    buffers = load_buffers(args.file)
    image = reconstruct(buffers, method=args.method, alpha=args.alpha)
    metadata = {
        "source": str(args.file),
        "method": args.method,
        "alpha": args.alpha,
        "spp": buffers.spp,
        "render": buffers.metadata,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    save_image(args.output, image, metadata=metadata, force=args.force)
    print(f"wrote {args.output}")
    if args.png:
        png = save_png(preview_path(args.output), image, force=args.force)
        print(f"wrote {png}")
    return 0


# ------------------------------------------------------------------------------------- render
def _add_render_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", help="Mitsuba XML file, or builtin:NAME (see gdpt.scenes)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="output buffers EXR")
    parser.add_argument("--spp", type=int, default=64, help="samples per pixel (default: 64)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    parser.add_argument("--integrator", choices=["gdpt", "gdpt_rr"], default="gdpt")
    parser.add_argument("--max-depth", type=int, default=6, help="longest path (default: 6)")
    parser.add_argument("--no-gradients", action="store_true", help="plain path tracing")
    parser.add_argument("--variance", action="store_true", help="also store variance buffers")
    parser.add_argument("--half", action="store_true", help="store half floats")
    parser.add_argument("--force", action="store_true", help="overwrite an existing output")


def _run_render(args: argparse.Namespace) -> int:
    from gdpt.exr import check_writable, save_buffers
    from gdpt.images import preview_path, save_png
    from gdpt.render import load_scene, render

    check_writable(args.output, force=args.force)
    if args.scene.startswith("builtin:"):
        from gdpt.backend import set_variant
        from gdpt.scenes import builtin_scene

        set_variant()
        scene = load_scene(builtin_scene(args.scene.split(":", 1)[1]))
    else:
        scene = load_scene(args.scene)
    buffers = render(
        scene, spp=args.spp, seed=args.seed, integrator=args.integrator, progress=True,
        max_depth=args.max_depth, gradients=not args.no_gradients, variance=args.variance,
    )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    save_buffers(args.output, buffers, half=args.half, force=args.force)
    save_png(preview_path(args.output), buffers.primal, force=True)
    print(f"wrote {args.output} ({buffers.metadata['render_seconds']:.2f} s)")
    return 0


# ----------------------------------------------------------------------------------------- demo
def _add_demo_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")
    parser.add_argument("--spp", type=int, default=32, help="G-PT samples per pixel")
    parser.add_argument("--resolution", type=int, default=192, help="image width and height")


def _run_demo(args: argparse.Namespace) -> int:
    from gdpt.demo import DemoConfig, run_demo

    run_demo(DemoConfig(out=args.out, spp=args.spp, resolution=args.resolution))
    return 0


# ------------------------------------------------------------------------------------- registry
#: The subcommands, in the order ``gdpt --help`` lists them.
COMMANDS: tuple[Command, ...] = (
    Command("info", "describe a gdpt EXR file", _add_info_arguments, _run_info),
    Command(
        "reconstruct",
        "reconstruct an image from primal + gradient buffers",
        _add_reconstruct_arguments,
        _run_reconstruct,
    ),
    Command("render", "render gradient-domain buffers to EXR", _add_render_arguments, _run_render),
    Command("demo", "G-PT + Poisson vs path tracing at equal time", _add_demo_arguments, _run_demo),
)


def build_parser() -> argparse.ArgumentParser:
    """The ``gdpt`` argument parser with one sub-parser per entry of :data:`COMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="gdpt",
        description="Gradient-domain path tracing for Mitsuba 3 with Poisson and neural "
        "reconstruction.",
    )
    parser.add_argument("--version", action="version", version=f"gdpt {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command in COMMANDS:
        sub = subparsers.add_parser(command.name, help=command.help, description=command.help)
        command.add_arguments(sub)
        sub.set_defaults(run=command.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``gdpt`` command line.

    Args:
        argv (Sequence[str] | None): arguments without the program name; ``None`` uses
            ``sys.argv[1:]``.

    Returns:
        The exit status: 0 on success, 2 for user errors, 130 when interrupted.
    """
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except _USER_ERRORS as error:
        if os.environ.get("GDPT_DEBUG"):
            raise
        message = " ".join(str(error).split())  # one line, whatever the exception text
        print(f"gdpt {args.command}: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"gdpt {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
