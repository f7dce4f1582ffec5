"""The study commands: ``demo`` and ``evaluate``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gdpt.cli.command import Command, UsageError, add_model_option, split_named
from gdpt.study.config import PROTOCOLS


def _study_method_name(name: str) -> str:
    """A ``--methods`` value: a study method's current name (a deprecated one warns), its
    ``@`` integrator properties checked (a bad one: a usage error naming it)."""
    from gdpt.study.methods import EVAL_METHODS

    try:
        return EVAL_METHODS.resolve(name)
    except KeyError:  # an unknown method (or a --model's, registered later): checked later
        return name
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


# ----------------------------------------------------------------------------------------- demo
def _add_demo_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")
    parser.add_argument(
        "--budget",
        type=float,
        default=2.0,
        help="seconds of sampling + reconstruction per image (default: 2)",
    )
    parser.add_argument("--resolution", type=int, default=192, help="image width and height")
    parser.add_argument(
        "--gradient-budget",
        type=float,
        default=8.0,
        help="seconds per image of the second run (auto, pt+oidn-tuned, gdpt+fuse on the diffuse "
        "box at 128 px, where auto takes the gradient route; default: 8; 0 leaves it out)",
    )
    parser.add_argument(
        "--reference-spp", type=int, default=4096, help="path-traced reference spp (default: 4096)"
    )
    parser.add_argument("--force", action="store_true", help="overwrite an earlier demo's outputs")


def _run_demo(args: argparse.Namespace) -> int:
    from gdpt.study.demo import DemoConfig, run_demo

    run_demo(
        DemoConfig(
            out=args.out,
            budget=args.budget,
            resolution=args.resolution,
            gradient_budget=args.gradient_budget,
            reference_spp=args.reference_spp,
            force=args.force,
        )
    )
    return 0


# ------------------------------------------------------------------------------------ evaluate
def _add_evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scenes",
        nargs="+",
        required=True,
        metavar="SCENE",
        help="scene folders/XML files, a folder of <name>/scene.xml, builtin:NAME or "
        "random:SEED[:VIEW]; comma-separated lists work too",
    )
    parser.add_argument("--out", type=Path, required=True, help="report folder (resumed)")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="quick profile: small budgets and resolution, minutes on 2 cores",
    )
    parser.add_argument("--budgets", type=float, nargs="+", help="time budgets in seconds")
    parser.add_argument("--resolution", type=int, help="pixels on the long side")
    parser.add_argument(
        "--methods",
        nargs="+",
        type=_study_method_name,
        help="methods to compare (default: all); METHOD@NAME=VALUE,NAME=VALUE renders METHOD "
        "with those gdpt integrator properties (e.g. gdpt+fuse@max_depth=4), calibrated on "
        "its own",
    )
    add_model_option(
        parser,
        "also compare a checkpoint written by gdpt train, as method gdpt+NAME (pt+NAME "
        "without gradients); repeat for several",
    )
    parser.add_argument("--metrics", nargs="+", help="metrics; the first one ranks methods")
    parser.add_argument("--reference-spp", type=int, help="samples per pixel of the reference")
    parser.add_argument(
        "--max-depth", type=int, help="longest path (default: the scene's own setting, else 6)"
    )
    parser.add_argument("--seed", type=int, help="base seed")
    parser.add_argument(
        "--protocol",
        choices=PROTOCOLS,
        help="what a budget pays for: 'total' (sampling + reconstruction, default) or "
        "'render-time' (sampling only, reconstruction reported beside it: the paper's "
        "equal-time protocol)",
    )
    parser.add_argument(
        "--seeds",
        type=int,
        help="replicates per cell (paired: every method renders the same seeds); the report "
        "gives their mean and a 95%% interval (default: 1)",
    )
    parser.add_argument(
        "--until-interval",
        type=float,
        metavar="SHARE",
        help="add paired replicates to a cell (up to --max-seeds) while the 95%% interval of "
        "its first metric reaches further than SHARE of its mean (e.g. 0.1)",
    )
    parser.add_argument(
        "--max-seeds", type=int, help="most replicates per cell with --until-interval (default 8)"
    )
    parser.add_argument(
        "--references", type=Path, help="reference cache folder (default: OUT/references)"
    )
    parser.add_argument(
        "--references-only",
        action="store_true",
        help="only render the cached references (no timing: safe on a busy "
        "machine); run again without it on an idle machine for the cells",
    )
    parser.add_argument(
        "--no-reference",
        action="store_true",
        help="render no reference: each cell gets the reference-free estimate of its relMSE "
        "ratio to pt+oidn-tuned (as gdpt advise; reported as an estimate) instead of metrics",
    )
    parser.add_argument(
        "--keep-going",
        action="store_true",
        help="record a scene, method or budget cell that fails and continue (exit status 0); "
        "without it the study stops at the first failure with exit status 1",
    )
    parser.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="run reference chunks and cells as tasks of a local Ray instance with N workers "
        "(at most one timed cell at a time; references beside it); default: one after the "
        "other in this process",
    )
    parser.add_argument(
        "--ray-address",
        metavar="ADDR",
        help="run them on the Ray cluster at ADDR (HOST:PORT, ray://HOST:PORT or auto; each "
        "node started with --resources='{\"gdpt_timed_cell\": 1}')",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_evaluate(args: argparse.Namespace) -> int:
    import dataclasses
    import shlex

    from gdpt.methods import register_checkpoint
    from gdpt.metrics import METRICS
    from gdpt.study.config import PRESETS
    from gdpt.study.estimate import BASELINE
    from gdpt.study.evaluate import StudyFailure, evaluate, failures, render_references
    from gdpt.study.methods import EVAL_METHODS, register_denoiser
    from gdpt.study.report import best_methods

    for item in args.models:
        name, path = split_named(item, "--model", "CHECKPOINT")
        study_name = register_denoiser(name, register_checkpoint(name, path))
        if args.methods is not None and study_name not in args.methods:
            args.methods.append(study_name)
    for option, names, valid in (
        ("--methods", args.methods, EVAL_METHODS),
        ("--metrics", args.metrics, METRICS),
    ):
        if unknown := [n for n in names or () if n not in valid]:
            raise UsageError(f"{option}: unknown {', '.join(unknown)}; valid: {', '.join(valid)}")
    changes = {
        "budgets": args.budgets,
        "resolution": args.resolution,
        "methods": args.methods,
        "metrics": args.metrics,
        "reference_spp": args.reference_spp,
        "max_depth": args.max_depth,
        "seed": args.seed,
        "seeds": args.seeds,
        "until_interval": args.until_interval,
        "max_seeds": args.max_seeds,
        "protocol": args.protocol,
        "reference_dir": args.references,
        "keep_going": args.keep_going,
        "reference": False if args.no_reference else None,
    }
    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers must be >= 1, got {args.workers}")
    if args.no_reference and args.methods is not None and BASELINE not in args.methods:
        raise UsageError(f"--no-reference estimates ratios to {BASELINE}: add it to --methods")
    cfg = PRESETS["quick" if args.quick else "full"]
    cfg = dataclasses.replace(cfg, **{k: v for k, v in changes.items() if v is not None})
    if args.references_only:
        cache = args.references or args.out / "references"
        try:
            status = render_references(
                args.scenes,
                cache,
                cfg,
                progress=not args.no_progress,
                workers=args.workers,
                ray_address=args.ray_address,
            )
        except ConnectionError as error:  # before any work
            raise UsageError(str(error)) from None
        for scene, path in status.items():
            print(f"{scene}: {path}")
        return 1 if any(p.startswith("failed:") for p in status.values()) else 0
    command = shlex.join(["gdpt", *sys.argv[1:]]) if sys.argv[1:2] == ["evaluate"] else None
    try:
        results = evaluate(
            args.scenes,
            args.out,
            cfg,
            progress=not args.no_progress,
            command=command,
            workers=args.workers,
            ray_address=args.ray_address,
        )
    except ConnectionError as error:  # a Ray address that does not answer: before any work
        raise UsageError(str(error)) from None
    except StudyFailure as failure:
        message = " ".join(str(failure).split())
        print(
            f"gdpt evaluate: failed: {message} (recorded in {args.out}/results.json; a run "
            "with the same --out retries it; --keep-going records failures and continues)",
            file=sys.stderr,
        )
        return 1
    for scene, row in best_methods(results).items():
        best = ", ".join(f"{k} s: {v[0] if v else 'n/a'}" for k, v in row.items())
        print(f"{scene}: {best}")
    for line in failures(results):
        print(f"FAILED {line}")
    print(f"wrote {args.out}/ (results.json, results.md, plots/, crops/, index.html)")
    return 0


def _evaluate_interrupted(args: argparse.Namespace) -> str:
    if args.references_only:
        cache = args.references or args.out / "references"
        return f"interrupted; finished reference chunks are kept in {cache}; " + _AGAIN
    from gdpt.study.results import cells_done, read_results

    path = args.out / "results.json"
    done = cells_done(read_results(path)) if path.is_file() else 0
    return f"interrupted with {done} cells done in {path}; " + _AGAIN


#: How an interrupted study continues.
_AGAIN = "run the same command to resume"


#: The study commands, in the order ``gdpt --help`` lists them.
COMMANDS: tuple[Command, ...] = (
    Command(
        "demo", "every method on a built-in scene at equal time", _add_demo_arguments, _run_demo
    ),
    Command(
        "evaluate",
        "equal-time study: error vs measured time of every method on a scene set",
        _add_evaluate_arguments,
        _run_evaluate,
        _evaluate_interrupted,
    ),
)
