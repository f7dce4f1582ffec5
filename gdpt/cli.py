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

from gdpt.denoise import METHODS
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
    parser.add_argument("--model", type=Path, help="NGPT checkpoint for --method ngpt*")
    parser.add_argument("--force", action="store_true", help="overwrite existing outputs")


def _run_reconstruct(args: argparse.Namespace) -> int:
    from gdpt.denoise import reconstruct
    from gdpt.io.exr import check_writable, load_buffers, save_image
    from gdpt.io.images import preview_path, save_png

    if args.output.suffix.lower() != ".exr":
        raise UsageError(f"output must be an .exr file, got '{args.output}'")
    if not (math.isfinite(args.alpha) and args.alpha > 0):
        raise UsageError(f"--alpha must be a finite number > 0, got {args.alpha}")
    outputs = [args.output, *([preview_path(args.output)] if args.png else [])]
    for path in outputs:  # fail before the (possibly slow) reconstruction
        check_writable(path, force=args.force)

    buffers = load_buffers(args.file)
    options = {"model": args.model} if args.model is not None else {}
    image = reconstruct(buffers, method=args.method, alpha=args.alpha, **options)
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
    parser.add_argument(
        "scene", help="Mitsuba XML file, builtin:NAME or random:SEED[:VIEW] (see gdpt.scene_io)"
    )
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
    from gdpt.io.exr import check_writable, save_buffers
    from gdpt.io.images import preview_path, save_png
    from gdpt.rendering import render
    from gdpt.scene_io import load_scene

    check_writable(args.output, force=args.force)
    scene = load_scene(args.scene)
    buffers = render(
        scene,
        spp=args.spp,
        seed=args.seed,
        integrator=args.integrator,
        progress=True,
        max_depth=args.max_depth,
        gradients=not args.no_gradients,
        variance=args.variance,
    )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    save_buffers(args.output, buffers, half=args.half, force=args.force)
    save_png(preview_path(args.output), buffers.primal, force=True)
    print(f"wrote {args.output} ({buffers.metadata['render_seconds']:.2f} s)")
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
    parser.add_argument("--methods", nargs="+", help="methods to compare (default: all)")
    parser.add_argument("--metrics", nargs="+", help="metrics; the first one ranks methods")
    parser.add_argument("--reference-spp", type=int, help="samples per pixel of the reference")
    parser.add_argument(
        "--max-depth", type=int, help="longest path (default: the scene's own setting, else 6)"
    )
    parser.add_argument("--seed", type=int, help="base seed")
    parser.add_argument(
        "--references", type=Path, help="reference cache folder (default: OUT/references)"
    )
    parser.add_argument(
        "--references-only",
        action="store_true",
        help="only render the cached references (no timing: safe on a busy "
        "machine); run again without it on an idle machine for the cells",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_evaluate(args: argparse.Namespace) -> int:
    import dataclasses
    import shlex

    from gdpt.metrics import METRICS
    from gdpt.study.config import PRESETS
    from gdpt.study.evaluate import evaluate, render_references
    from gdpt.study.methods import EVAL_METHODS
    from gdpt.study.report import best_methods

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
        "reference_dir": args.references,
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
    results = evaluate(args.scenes, args.out, cfg, progress=not args.no_progress, command=command)
    for scene, row in best_methods(results).items():
        best = ", ".join(f"{k} s: {v[0] if v else 'n/a'}" for k, v in row.items())
        print(f"{scene}: {best}")
    for scene, entry in results["scenes"].items():
        if entry.get("status") != "ok":
            print(f"{scene}: FAILED ({entry.get('error')})")
    print(f"wrote {args.out}/ (results.json, results.md, plots/, crops/, index.html)")
    return 0


# ------------------------------------------------------------------------------------ dataset
def _add_dataset_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="dataset directory")
    parser.add_argument("--scenes", type=int, required=True, help="procedural scenes")
    parser.add_argument("--views", type=int, required=True, help="camera views per scene")
    parser.add_argument("--resolution", type=int, default=128, help="crop side (default: 128)")
    parser.add_argument("--spp-min", type=int, default=2, help="lowest input spp (default: 2)")
    parser.add_argument("--spp-max", type=int, default=256, help="highest input spp (default: 256)")
    parser.add_argument("--target-spp", type=int, default=4096, help="target spp (default: 4096)")
    parser.add_argument(
        "--target",
        choices=["l1", "pt"],
        default="l1",
        help="target: G-PT + L1 Poisson (l1, the paper's) or path tracing (pt; default: l1)",
    )
    parser.add_argument("--levels", type=int, default=5, help="noisy inputs per crop (default: 5)")
    parser.add_argument(
        "--pt-factor",
        type=float,
        default=2.5,
        help="path-traced input spp / G-PT input spp, the equal-time ratio (default: 2.5)",
    )
    parser.add_argument("--max-depth", type=int, default=6, help="longest path (default: 6)")
    parser.add_argument("--seed", type=int, default=0, help="dataset seed (default: 0)")
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

    config = DatasetConfig(
        scenes=args.scenes,
        views=args.views,
        resolution=args.resolution,
        spp_min=args.spp_min,
        spp_max=args.spp_max,
        target_spp=args.target_spp,
        target=args.target,
        levels=args.levels,
        pt_factor=args.pt_factor,
        max_depth=args.max_depth,
        seed=args.seed,
    )
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
    parser.add_argument(
        "--config",
        required=True,
        metavar="NAME",
        help="model config, a key of "
        "gdpt.reconstruct.dense_unet.CONFIGS (paper, nograd, fast, fast_xs, ...), or a design "
        "of gdpt.reconstruct.oidn_ngpt.DESIGNS (oidn-grad, oidn-grad-l1, oidn-nograd: OIDN's "
        "U-Net fine-tuned)",
    )
    parser.add_argument("--data", required=True, help="dataset directory (gdpt dataset)")
    parser.add_argument("--out", required=True, help="run directory")
    parser.add_argument(
        "--val-data",
        default=None,
        help="validation dataset directory (default: every --holdout-every-th scene of --data)",
    )
    parser.add_argument("--holdout-every", type=int, default=10, help="default: 10")
    parser.add_argument(
        "--loss",
        choices=["flip", "flip_rel", "flip_log", "flip_hdr", "l1", "elpips", "l1_rel"],
        default="flip",
        help="training loss (default: flip; flip_rel / flip_log "
        "add a relative / log-space L1, see gdpt.reconstruct.losses; fine-tuning OIDN "
        "(--config oidn-*): l1 (PU space) or l1_rel (+ relative MSE)",
    )
    parser.add_argument("--steps", type=int, default=1000, help="updates (default: 1000)")
    parser.add_argument("--batch", type=int, default=8, help="crops per update and process")
    parser.add_argument(
        "--crop", type=int, default=None, help="random sub-crop side (default: the dataset crop)"
    )
    parser.add_argument("--lr", type=float, default=5e-4, help="base learning rate")
    parser.add_argument("--seed", type=int, default=0, help="training seed (default: 0)")
    parser.add_argument("--val-every", type=int, default=100, help="default: 100 (0: never)")
    parser.add_argument("--val-crops", type=int, default=32, help="validation elements")
    parser.add_argument("--ckpt-every", type=int, default=100, help="default: 100")
    parser.add_argument("--device", default=None, help="torch device (default: automatic)")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out")


def _run_train(args: argparse.Namespace) -> int:
    from gdpt.training.train import TrainConfig, train

    config = TrainConfig(
        model=args.config,
        data=args.data,
        out=args.out,
        val_data=args.val_data,
        holdout_every=args.holdout_every,
        loss=args.loss,
        steps=args.steps,
        batch=args.batch,
        crop=args.crop,
        lr=args.lr,
        seed=args.seed,
        val_every=args.val_every,
        val_crops=args.val_crops,
        ckpt_every=args.ckpt_every,
        device=args.device,
    )
    path = train(config, resume=args.resume)
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
        help="a gdpt train run directory and its model name (ngpt, "
        "ngpt-nograd); repeat for several",
    )
    parser.add_argument("--out", type=Path, required=True, help="report folder")
    parser.add_argument(
        "--holdout-every",
        type=int,
        default=10,
        help="held-out scenes, as in gdpt train (default: 10)",
    )
    parser.add_argument(
        "--ship",
        action="store_true",
        help="copy each run's network into gdpt/models/NAME with a model card",
    )


def _run_model_report(args: argparse.Namespace) -> int:
    from gdpt.training.model_report import (
        compare_models,
        comparison_markdown,
        plot_training,
        ship_model,
    )

    runs = {}
    for item in args.runs:
        name, sep, run = item.partition("=")
        if not sep or not name or not run:
            raise ValueError(f"--run {item!r}: expected NAME=RUN_DIR")
        if not (Path(run) / "model.safetensors").is_file():
            raise FileNotFoundError(f"--run {item!r}: {run}/model.safetensors not found")
        runs[name] = Path(run)
    args.out.mkdir(parents=True, exist_ok=True)
    plot_training(runs, args.out / "training.png")
    result = compare_models(
        args.data,
        {k: v / "model.safetensors" for k, v in runs.items()},
        holdout_every=args.holdout_every,
    )
    (args.out / "comparison.json").write_text(json.dumps(result, indent=2) + "\n")
    table = comparison_markdown(result)
    (args.out / "comparison.md").write_text(table)
    print(table)
    if args.ship:
        for name, run in runs.items():
            print(f"shipped {ship_model(run, name, comparison=result)}")
    print(f"wrote {args.out}/ (training.png, comparison.json, comparison.md)")
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
        "render NGPT training crops (resumable, parallel, Ray)",
        _add_dataset_arguments,
        _run_dataset,
    ),
    Command(
        "train",
        "train an NGPT network on a dataset (torchrun-ready)",
        _add_train_arguments,
        _run_train,
    ),
    Command(
        "model-report",
        "training curves and held-out comparison of trained networks",
        _add_model_report_arguments,
        _run_model_report,
    ),
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
