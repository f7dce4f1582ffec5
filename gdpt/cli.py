"""Command-line interface: ``gdpt <command> ...`` (also ``python -m gdpt``).

Every subcommand is a :class:`Command`: a name, a one-line help text, a function that adds its
arguments to an argparse sub-parser and a function that runs it. To add a subcommand, write
``_add_<name>_arguments(parser)`` and ``_run_<name>(args) -> int`` and append a
:class:`Command` to :data:`COMMANDS`. Heavy modules (torch, Mitsuba) are imported inside these
functions only: a sub-parser adds its arguments when it is used (:class:`_CommandParser`), so
``gdpt --help`` and the light commands stay fast. Options of typed configurations
(``TrainConfig``, ``DatasetConfig``) are generated from their fields (:mod:`gdpt.cli_config`).

User errors (missing or malformed input, refusing to overwrite, invalid options) print one line
``gdpt <command>: error: <message>`` to stderr and exit with status 2, without a traceback.
Set ``GDPT_DEBUG=1`` to get the traceback instead. gdpt's own ``DeprecationWarning`` (a
method's former name, ``GDPT_NGPT_MODEL``) is printed to stderr, once per place.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from gdpt.cli_config import add_config_arguments, config_from_args
from gdpt.methods import METHODS
from gdpt.scene_io import DEFAULT_MAX_DEPTH
from gdpt.study.config import PROTOCOLS
from gdpt.version import __version__


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

    from gdpt.io.exr import channel_names, load_buffers

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


def _method_name(name: str) -> str:
    """``--method``'s value: a reconstruction method's current name (a deprecated one warns)."""
    return METHODS.resolve(name)


def _study_method_name(name: str) -> str:
    """A ``--methods`` value: a study method's current name (a deprecated one warns)."""
    from gdpt.study.methods import EVAL_METHODS

    return EVAL_METHODS.resolve(name)


# ---------------------------------------------------------------------------------- reconstruct
def _add_reconstruct_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "file", type=Path, help="an EXR file of buffers (gdpt render): what --method reads"
    )
    parser.add_argument(
        "--method",
        type=_method_name,
        choices=list(METHODS),
        default="l1",
        help="reconstruction, as gdpt.reconstruct_image (default: l1)",
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
    parser.add_argument(
        "--model", type=Path, help="trained checkpoint for a network method (oidn-grad, ...)"
    )
    parser.add_argument("--force", action="store_true", help="overwrite existing outputs")


def _run_reconstruct(args: argparse.Namespace) -> int:
    from gdpt.io.exr import check_writable, load_buffers, save_image
    from gdpt.io.images import preview_path, save_png
    from gdpt.methods import reconstruct_image

    if args.output.suffix.lower() != ".exr":
        raise UsageError(f"output must be an .exr file, got '{args.output}'")
    if not (math.isfinite(args.alpha) and args.alpha > 0):
        raise UsageError(f"--alpha must be a finite number > 0, got {args.alpha}")
    outputs = [args.output, *([preview_path(args.output)] if args.png else [])]
    for path in outputs:  # fail before the (possibly slow) reconstruction
        check_writable(path, force=args.force)

    buffers = load_buffers(args.file)
    options = {"model": args.model} if args.model is not None else {}
    image = reconstruct_image(buffers, method=args.method, alpha=args.alpha, **options)
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
def _add_scene_arguments(parser: argparse.ArgumentParser) -> None:
    """The scene and sampling options shared by ``render`` and ``render-and-denoise``."""
    parser.add_argument(
        "scene", help="Mitsuba XML file, builtin:NAME or random:SEED[:VIEW] (see gdpt.scene_io)"
    )
    parser.add_argument("--spp", type=int, default=64, help="samples per pixel (default: 64)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    parser.add_argument("--integrator", choices=["gdpt", "gdpt_rr"], default="gdpt")
    parser.add_argument(
        "--max-depth",
        type=int,
        help="longest path, -1: unbounded (default: the scene's integrator max_depth, else "
        f"{DEFAULT_MAX_DEPTH})",
    )
    parser.add_argument(
        "--box-filter",
        action="store_true",
        help="XML scenes: replace the film's pixel filter (Mitsuba's default is Gaussian) by "
        "the box filter gradient-domain rendering needs",
    )
    parser.add_argument(
        "--long-side",
        type=int,
        help="rescale the film to this many pixels on its long side (XML: aspect ratio kept; "
        "builtin:/random: square)",
    )


def _load_scene(args: argparse.Namespace) -> tuple[object, int]:
    """The scene of ``args`` (:func:`gdpt.scene_io.read_scene` with ``--box-filter`` and
    ``--long-side``) and the max depth to render with; prints what loading changed and where
    the depth comes from.

    Raises:
        UsageError: a bad option value, or a film without a box filter and no ``--box-filter``.
    """
    from gdpt.scene_io import BOX_FILTER, choose_max_depth, read_scene

    if args.spp < 1:
        raise UsageError(f"--spp must be >= 1, got {args.spp}")
    if args.long_side is not None and args.long_side < 1:
        raise UsageError(f"--long-side must be >= 1, got {args.long_side}")
    if args.max_depth is not None and args.max_depth < -1:
        raise UsageError(f"--max-depth must be -1 (unbounded) or >= 0, got {args.max_depth}")
    loaded = read_scene(args.scene, box_filter=args.box_filter, long_side=args.long_side)
    if loaded.original_filter != BOX_FILTER and not args.box_filter:
        raise UsageError(
            f"{args.scene}: the film's pixel filter is '{loaded.original_filter}', "
            "gradient-domain rendering needs a box filter: add --box-filter to replace it"
        )
    depth, note = choose_max_depth(args.max_depth, loaded.max_depth, option="--max-depth")
    for line in [*loaded.notes, note]:
        print(f"{args.scene}: {line}")
    return loaded.scene, depth


def _add_render_arguments(parser: argparse.ArgumentParser) -> None:
    _add_scene_arguments(parser)
    parser.add_argument("-o", "--output", type=Path, required=True, help="output buffers EXR")
    parser.add_argument("--no-gradients", action="store_true", help="plain path tracing")
    parser.add_argument(
        "--primal-spp",
        type=int,
        default=0,
        help="also render this many plain path samples per pixel and pool them into the primal "
        "(the input of a pooled network such as oidn-grad: its card's primal_spp_factor x "
        "--spp)",
    )
    parser.add_argument("--variance", action="store_true", help="also store variance buffers")
    parser.add_argument(
        "--halves",
        action="store_true",
        help="also store the primal and features of two independent halves of the samples "
        "(read by nfor and fuse)",
    )
    parser.add_argument("--half", action="store_true", help="store half floats")
    parser.add_argument("--force", action="store_true", help="overwrite an existing output")


def _run_render(args: argparse.Namespace) -> int:
    from gdpt.io.exr import check_writable, save_buffers
    from gdpt.io.images import preview_path, save_png
    from gdpt.rendering import render

    if args.output.suffix.lower() != ".exr":
        raise UsageError(f"output must be an .exr file, got '{args.output}'")
    check_writable(args.output, force=args.force)
    scene, max_depth = _load_scene(args)
    buffers = render(
        scene,
        spp=args.spp,
        seed=args.seed,
        integrator=args.integrator,
        progress=True,
        max_depth=max_depth,
        gradients=not args.no_gradients,
        variance=args.variance,
        halves=args.halves,
        primal_spp=args.primal_spp,
    )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    save_buffers(args.output, buffers, half=args.half, force=args.force)
    save_png(preview_path(args.output), buffers.primal, force=True)
    print(f"wrote {args.output} ({buffers.metadata['render_seconds']:.2f} s)")
    return 0


# -------------------------------------------------------------------------- render-and-denoise
def _add_render_and_denoise_arguments(parser: argparse.ArgumentParser) -> None:
    _add_scene_arguments(parser)
    parser.add_argument(
        "--method",
        type=_method_name,
        choices=["auto", *METHODS],
        default="auto",
        help="reconstruction (default: auto: --spp plain samples + the primal-only denoiser, "
        "or from 360 spp on a pilot render chooses between that and fuse on gradient-domain "
        "samples of the same cost); the render has the buffers it reads",
    )
    parser.add_argument(
        "--alpha", type=float, default=0.2, help="weight of the primal term (default: 0.2)"
    )
    parser.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        help="output RGB EXR (R, G, B channels); a PNG preview is written next to it",
    )
    parser.add_argument(
        "--save-buffers", type=Path, metavar="PATH", help="also write the render's buffers (EXR)"
    )
    parser.add_argument("--force", action="store_true", help="overwrite existing outputs")


def _run_render_and_denoise(args: argparse.Namespace) -> int:
    from gdpt.io.exr import check_writable, save_buffers, save_image
    from gdpt.io.images import preview_path, save_png
    from gdpt.pipeline import render_and_denoise

    if not (math.isfinite(args.alpha) and args.alpha > 0):
        raise UsageError(f"--alpha must be a finite number > 0, got {args.alpha}")
    if args.method != "auto" and (reason := METHODS[args.method].check()):
        raise UsageError(f"--method {args.method} cannot run here: {reason}")
    outputs = {"--output": args.output, "--save-buffers": args.save_buffers}
    for option, path in outputs.items():
        if path is not None and path.suffix.lower() != ".exr":
            raise UsageError(f"{option} must be an .exr file, got '{path}'")
        if path is not None and not path.parent.is_dir():
            raise UsageError(f"{option} {path}: the folder {path.parent} does not exist")
    if args.save_buffers is not None and args.save_buffers.resolve() == args.output.resolve():
        raise UsageError(f"--save-buffers and --output are the same file: {args.output}")
    for path in (args.output, preview_path(args.output), args.save_buffers):
        if path is not None:  # fail before the render
            check_writable(path, force=args.force)
    scene, max_depth = _load_scene(args)

    result = render_and_denoise(
        scene,
        spp=args.spp,
        method=args.method,
        seed=args.seed,
        alpha=args.alpha,
        progress=True,
        integrator=args.integrator,
        max_depth=max_depth,
    )
    metadata = {
        "scene": args.scene,
        "method": args.method,
        "alpha": args.alpha,
        "spp": args.spp,
        "timings": result.timings,
        "render": result.buffers.metadata,
    }
    if result.route is not None:
        metadata["route"] = result.route.to_json()
        print(f"auto: {result.route.route} route ({result.route.method}): {result.route.reason}")
    save_image(args.output, result.image, metadata=metadata, force=args.force)
    print(f"wrote {args.output}")
    print(f"wrote {save_png(preview_path(args.output), result.image, force=args.force)}")
    if args.save_buffers is not None:
        save_buffers(args.save_buffers, result.buffers, force=args.force)
        print(f"wrote {args.save_buffers}")
    times = ", ".join(f"{k} {v:.2f} s" for k, v in result.timings.items())
    print(f"timings: {times} (render includes kernel compilation)")
    return 0


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
            reference_spp=args.reference_spp,
            force=args.force,
        )
    )
    return 0


def _add_model_option(parser: argparse.ArgumentParser, text: str) -> None:
    """``--model NAME=CHECKPOINT``, repeatable, into ``args.models``."""
    parser.add_argument(
        "--model", action="append", default=[], metavar="NAME=CHECKPOINT", dest="models", help=text
    )


def _split_named(item: str, option: str, value: str) -> tuple[str, str]:
    """``NAME=VALUE`` of a command-line ``option`` as ``(NAME, VALUE)``.

    Raises:
        ValueError: either side is empty or there is no ``=``.
    """
    name, sep, rest = item.partition("=")
    if not sep or not name or not rest:
        raise ValueError(f"{option} {item!r}: expected NAME={value}")
    return name, rest


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
        "--methods", nargs="+", type=_study_method_name, help="methods to compare (default: all)"
    )
    _add_model_option(
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
        "--references", type=Path, help="reference cache folder (default: OUT/references)"
    )
    parser.add_argument(
        "--references-only",
        action="store_true",
        help="only render the cached references (no timing: safe on a busy "
        "machine); run again without it on an idle machine for the cells",
    )
    parser.add_argument(
        "--keep-going",
        action="store_true",
        help="record a scene, method or budget cell that fails and continue (exit status 0); "
        "without it the study stops at the first failure with exit status 1",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_evaluate(args: argparse.Namespace) -> int:
    import dataclasses
    import shlex

    from gdpt.methods import register_checkpoint
    from gdpt.metrics import METRICS
    from gdpt.study.config import PRESETS
    from gdpt.study.evaluate import StudyFailure, evaluate, failures, render_references
    from gdpt.study.methods import EVAL_METHODS, register_denoiser
    from gdpt.study.report import best_methods

    for item in args.models:
        name, path = _split_named(item, "--model", "CHECKPOINT")
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
        "protocol": args.protocol,
        "reference_dir": args.references,
        "keep_going": args.keep_going,
    }
    cfg = PRESETS["quick" if args.quick else "full"]
    cfg = dataclasses.replace(cfg, **{k: v for k, v in changes.items() if v is not None})
    if args.references_only:
        cache = args.references or args.out / "references"
        status = render_references(args.scenes, cache, cfg, progress=not args.no_progress)
        for scene, path in status.items():
            print(f"{scene}: {path}")
        return 1 if any(p.startswith("failed:") for p in status.values()) else 0
    command = shlex.join(["gdpt", *sys.argv[1:]]) if sys.argv[1:2] == ["evaluate"] else None
    try:
        results = evaluate(
            args.scenes, args.out, cfg, progress=not args.no_progress, command=command
        )
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


# ------------------------------------------------------------------------------------ dataset
#: DatasetConfig fields without an option: the generator knobs are a nested config.
_DATASET_EXCLUDED = ("scene_config",)


def _add_dataset_arguments(parser: argparse.ArgumentParser) -> None:
    from gdpt.training.dataset import TARGET_KINDS, DatasetConfig

    parser.add_argument("--out", type=Path, required=True, help="dataset directory")
    add_config_arguments(
        parser,
        DatasetConfig,
        exclude=_DATASET_EXCLUDED,
        required=("scenes", "views"),
        choices={"target": TARGET_KINDS},
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=1,
        help="local worker processes, or the CPUs of a '--ray local' instance (default: 1)",
    )
    parser.add_argument(
        "--ray",
        metavar="ADDRESS",
        default=None,
        help="render with Ray tasks: "
        "'local' starts a private instance, else a cluster address ('auto', ...)",
    )
    parser.add_argument("--variant", default=None, help="Mitsuba variant (default: automatic)")


def _run_dataset(args: argparse.Namespace) -> int:
    from gdpt.training.dataset import DatasetConfig, build_dataset

    config = config_from_args(DatasetConfig, args, exclude=_DATASET_EXCLUDED)
    summary = build_dataset(
        config, args.out, workers=args.workers, ray_address=args.ray, variant=args.variant
    )
    print(
        f"{args.out}: rendered {summary.rendered} crops, {summary.skipped} already done, "
        f"{summary.seconds:.0f} s ({summary.crops_per_minute:.2f} crops/min)"
    )
    return 0


# -------------------------------------------------------------------------------------- train
def _add_train_arguments(parser: argparse.ArgumentParser) -> None:
    from gdpt.reconstruct.families import FAMILIES
    from gdpt.training.config import TrainConfig

    losses = list(dict.fromkeys(name for f in FAMILIES.values() for name in f.losses))
    add_config_arguments(
        parser,
        TrainConfig,
        names={"model": "--config"},
        required=("model", "data", "out"),
        choices={"loss": losses},
    )
    parser.add_argument("--resume", action="store_true", help="continue the run in --out")


def _run_train(args: argparse.Namespace) -> int:
    from gdpt.training.config import TrainConfig
    from gdpt.training.train import train

    path = train(config_from_args(TrainConfig, args), resume=args.resume)
    if int(os.environ.get("RANK", "0")) == 0:
        print(f"wrote {path}")
    return 0


# ------------------------------------------------------------------------------- model-report
def _add_model_report_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, help="dataset directory (gdpt dataset)")
    parser.add_argument(
        "--run",
        action="append",
        required=True,
        metavar="NAME=RUN_DIR",
        dest="runs",
        help="a gdpt train run directory and its model name (oidn-grad, "
        "oidn-tuned); repeat for several",
    )
    _add_model_option(
        parser,
        "a checkpoint (.safetensors, e.g. a shipped gdpt/models/oidn-tuned.safetensors) "
        "to compare as well; neither plotted nor shipped; repeat for several",
    )
    parser.add_argument("--out", type=Path, required=True, help="report folder")
    parser.add_argument(
        "--holdout-every",
        type=int,
        default=10,
        help="held-out scenes, as in gdpt train (default: 10)",
    )
    parser.add_argument(
        "--pair",
        nargs=2,
        action="append",
        default=[],
        metavar=("A", "B"),
        help="also compare A with B element by element, in relMSE and in LDR-FLIP (per-element "
        "ratio, its 95%% interval, share of elements where A is lower); repeat for several",
    )
    parser.add_argument(
        "--ship",
        nargs="*",
        metavar="NAME",
        default=None,
        help="copy the runs NAME (default: every run) into gdpt/models/NAME with a model card",
    )


def _run_model_report(args: argparse.Namespace) -> int:
    from gdpt.training.model_report import (
        compare_models,
        comparison_markdown,
        paired_comparison,
        paired_markdown,
        plot_training,
        ship_model,
    )

    runs = {}
    for item in args.runs:
        name, run = _split_named(item, "--run", "RUN_DIR")
        if not (Path(run) / "model.safetensors").is_file():
            raise FileNotFoundError(f"--run {item!r}: {run}/model.safetensors not found")
        runs[name] = Path(run)
    checkpoints = {k: v / "model.safetensors" for k, v in runs.items()}
    for item in args.models:
        name, path = _split_named(item, "--model", "CHECKPOINT")
        if name in checkpoints:
            raise ValueError(f"--model {item!r}: the name {name!r} is taken by a --run")
        if not Path(path).is_file():
            raise FileNotFoundError(f"--model {item!r}: {path} not found")
        checkpoints[name] = Path(path)
    baselines = ("gdpt+l1", "pt+oidn", "pt")
    for a, b in args.pair:
        if unknown := [x for x in (a, b) if x not in checkpoints and x not in baselines]:
            raise ValueError(
                f"--pair {a} {b}: {', '.join(unknown)} is neither a --run/--model name "
                f"({', '.join(checkpoints)}) nor a baseline ({', '.join(baselines)})"
            )
    args.out.mkdir(parents=True, exist_ok=True)
    plot_training(runs, args.out / "training.png")
    result = compare_models(args.data, checkpoints, holdout_every=args.holdout_every)
    result["pairs"] = [
        paired_comparison(result, a, b, metric)
        for a, b in args.pair
        for metric in ("relmse", "flip")
    ]
    (args.out / "comparison.json").write_text(json.dumps(result, indent=2) + "\n")
    table = comparison_markdown(result)
    for pair in result["pairs"]:
        table += "\n" + paired_markdown(pair)
    (args.out / "comparison.md").write_text(table)
    print(table)
    if args.ship is not None:
        unknown = sorted(set(args.ship) - set(runs))
        if unknown:
            raise ValueError(
                f"--ship {' '.join(unknown)}: not among the --run names {sorted(runs)}"
            )
        for name in args.ship or runs:
            print(f"shipped {ship_model(runs[name], name, comparison=result)}")
    print(f"wrote {args.out}/ (training.png, comparison.json, comparison.md)")
    return 0


# -------------------------------------------------------------------------- select-refinement
def _add_select_refinement_arguments(parser: argparse.ArgumentParser) -> None:
    from gdpt.training.refinement import ALPHAS, TAUS

    parser.add_argument(
        "--model", type=Path, required=True, help="a gradient network's model.safetensors"
    )
    parser.add_argument(
        "--data", type=Path, required=True, help="procedural dataset it was not trained on"
    )
    parser.add_argument("--out", type=Path, required=True, help="new run directory")
    parser.add_argument(
        "--alphas", type=float, nargs="+", default=list(ALPHAS), help="L1 data weights to try"
    )
    parser.add_argument(
        "--taus", type=float, nargs="+", default=list(TAUS), help="gate widths (PU) to try"
    )
    parser.add_argument("--window", type=int, default=5, help="gate max-pool side (default: 5)")
    parser.add_argument(
        "--preset", default="refine", help="IRLS schedule of the L1 solve (default: refine)"
    )


def _run_select_refinement(args: argparse.Namespace) -> int:
    from gdpt.training.refinement import select_refinement

    path = select_refinement(
        args.model,
        args.data,
        args.out,
        alphas=args.alphas,
        taus=args.taus,
        window=args.window,
        preset=args.preset,
    )
    print((args.out / "refinement.md").read_text())
    print(f"wrote {path}")
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
    Command(
        "render-and-denoise",
        "render and reconstruct in one go: image EXR + PNG preview (gdpt.render_and_denoise)",
        _add_render_and_denoise_arguments,
        _run_render_and_denoise,
    ),
    Command(
        "demo", "every method on a built-in scene at equal time", _add_demo_arguments, _run_demo
    ),
    Command(
        "evaluate",
        "equal-time study: error vs measured time of every method on a scene set",
        _add_evaluate_arguments,
        _run_evaluate,
    ),
    Command(
        "dataset",
        "render training crops for the networks (resumable, parallel, Ray)",
        _add_dataset_arguments,
        _run_dataset,
    ),
    Command(
        "train",
        "train a reconstruction network on a dataset (torchrun-ready)",
        _add_train_arguments,
        _run_train,
    ),
    Command(
        "select-refinement",
        "choose a gradient network's gated Poisson refinement on procedural data",
        _add_select_refinement_arguments,
        _run_select_refinement,
    ),
    Command(
        "model-report",
        "training curves and held-out comparison of trained networks",
        _add_model_report_arguments,
        _run_model_report,
    ),
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
    with warnings.catch_warnings():
        warnings.filterwarnings("default", category=DeprecationWarning, module=r"gdpt(\.|$)")
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
