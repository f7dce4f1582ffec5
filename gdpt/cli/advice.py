"""The ``advise`` command: which method pays on a scene at a budget, without a reference
(:func:`gdpt.advice.advise`)."""

from __future__ import annotations

import argparse

from gdpt.advice import DEFAULT_BUDGET, DEFAULT_METHODS
from gdpt.cli.command import Command, UsageError


def _add_advise_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "scene",
        help="Mitsuba XML file, builtin:NAME or random:SEED[:VIEW] (see gdpt.scenes.loading)",
    )
    parser.add_argument(
        "--budget",
        type=float,
        help=f"seconds of sampling + reconstruction per method, calibrated on this machine "
        f"(default: {DEFAULT_BUDGET:g})",
    )
    parser.add_argument(
        "--spp", type=int, help="instead of --budget: every method renders this many spp"
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        default=list(DEFAULT_METHODS),
        metavar="METHOD",
        help="study methods to compare, the first the baseline of every ratio (default: "
        f"{' '.join(DEFAULT_METHODS)}; gdpt evaluate --help lists them; METHOD@NAME=VALUE,... "
        "with gdpt integrator properties)",
    )
    parser.add_argument(
        "--replicates",
        type=int,
        default=1,
        help="renders of every method and of the plain render P (default: 1); more tighten "
        "the intervals",
    )
    plain = parser.add_mutually_exclusive_group()
    plain.add_argument(
        "--plain-budget",
        type=float,
        help="seconds of plain path tracing in P, which scores the methods (default: --budget)",
    )
    plain.add_argument(
        "--plain-spp",
        type=int,
        help="P's samples per pixel instead (at least 4: two folds of two "
        "halves, which give its variance and the relMSE weights)",
    )
    parser.add_argument(
        "--max-depth",
        type=int,
        help="longest path, -1: unbounded (default: the scene's integrator max_depth, else 6)",
    )
    parser.add_argument(
        "--box-filter",
        action="store_true",
        help="XML scenes: replace the film's pixel filter by the box filter gradient-domain "
        "rendering needs",
    )
    parser.add_argument(
        "--long-side", type=int, help="rescale the film to this many pixels on its long side"
    )
    parser.add_argument("--seed", type=int, default=0, help="base seed (default: 0)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_advise(args: argparse.Namespace) -> int:
    from gdpt.advice import advise

    if args.spp is not None and args.budget is not None:
        raise UsageError("give --budget or --spp, not both")
    advice = advise(
        args.scene,
        budget=args.budget,
        spp=args.spp,
        methods=args.methods,
        replicates=args.replicates,
        plain_budget=args.plain_budget,
        plain_spp=args.plain_spp,
        long_side=args.long_side,
        box_filter=args.box_filter,
        max_depth=args.max_depth,
        seed=args.seed,
        progress=not args.no_progress,
    )
    print(advice)
    return 0 if advice.recommended is not None else 1


#: The advice command.
COMMANDS: tuple[Command, ...] = (
    Command(
        "advise",
        "which method pays on a scene at equal time, estimated without a reference",
        _add_advise_arguments,
        _run_advise,
    ),
)
