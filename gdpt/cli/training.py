"""The training commands: ``dataset``, ``train``, ``select-refinement`` and ``model-report``."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from gdpt.cli.command import Command, add_model_option, split_named
from gdpt.cli.config_options import add_config_arguments, config_from_args

# ------------------------------------------------------------------------------------ dataset
#: DatasetConfig fields without an option: the generator knobs are a nested config.
_DATASET_EXCLUDED = ("scene_config",)


def _add_dataset_arguments(parser: argparse.ArgumentParser) -> None:
    from gdpt.training.preprocess import PRIMAL_KINDS, TARGET_KINDS, DatasetConfig

    parser.add_argument("--out", type=Path, required=True, help="dataset directory")
    add_config_arguments(
        parser,
        DatasetConfig,
        exclude=_DATASET_EXCLUDED,
        required=("scenes", "views"),
        choices={"target": TARGET_KINDS, "primal": PRIMAL_KINDS},
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
    from gdpt.training.preprocess import DatasetConfig, build_dataset

    config = config_from_args(DatasetConfig, args, exclude=_DATASET_EXCLUDED)
    summary = build_dataset(
        config, args.out, workers=args.workers, ray_address=args.ray, variant=args.variant
    )
    print(
        f"{args.out}: rendered {summary.rendered} crops, {summary.skipped} already done, "
        f"{summary.seconds:.0f} s ({summary.crops_per_minute:.2f} crops/min)"
    )
    return 0


def _dataset_interrupted(args: argparse.Namespace) -> str:
    from gdpt.training.manifest import read_manifest

    records, _ = read_manifest(args.out)
    done = sum(r["scene"] < args.scenes and r["view"] < args.views for r in records)
    return (
        f"interrupted after {done} of {args.scenes * args.views} crops; "
        "run the same command to resume"
    )


# -------------------------------------------------------------------------------------- train
def _add_train_arguments(parser: argparse.ArgumentParser) -> None:
    from gdpt.reconstruct.families import FAMILIES
    from gdpt.training.config import FINETUNE_INPUTS, TrainConfig

    losses = list(dict.fromkeys(name for f in FAMILIES.values() for name in f.losses))
    add_config_arguments(
        parser,
        TrainConfig,
        names={"model": "--config"},
        required=("model", "data", "out"),
        choices={"loss": losses, "input": FINETUNE_INPUTS},
    )
    parser.add_argument("--resume", action="store_true", help="continue the run in --out")


def _run_train(args: argparse.Namespace) -> int:
    from gdpt.training.config import TrainConfig
    from gdpt.training.train import train

    path = train(config_from_args(TrainConfig, args), resume=args.resume)
    if int(os.environ.get("RANK", "0")) == 0:
        print(f"wrote {path}")
    return 0


def _train_interrupted(args: argparse.Namespace) -> str:
    from gdpt.training.run_dir import complete_checkpoints

    found = complete_checkpoints(Path(args.out))
    kept = f"step {found[0][0]} is kept in {found[0][1]}.*" if found else "no checkpoint yet"
    again = "the same command" if args.resume else "the same command with --resume"
    return f"interrupted; {kept}; run {again} to continue"


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
    add_model_option(
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
    from gdpt.training.model_report import BASELINES, write_report

    runs = {}
    for item in args.runs:
        name, run = split_named(item, "--run", "RUN_DIR")
        if not (Path(run) / "model.safetensors").is_file():
            raise FileNotFoundError(f"--run {item!r}: {run}/model.safetensors not found")
        runs[name] = Path(run)
    models = {}
    for item in args.models:
        name, path = split_named(item, "--model", "CHECKPOINT")
        if name in runs:
            raise ValueError(f"--model {item!r}: the name {name!r} is taken by a --run")
        if not Path(path).is_file():
            raise FileNotFoundError(f"--model {item!r}: {path} not found")
        models[name] = Path(path)
    names = [*runs, *models]
    for a, b in args.pair:
        if unknown := [x for x in (a, b) if x not in names and x not in BASELINES]:
            raise ValueError(
                f"--pair {a} {b}: {', '.join(unknown)} is neither a --run/--model name "
                f"({', '.join(names)}) nor a baseline ({', '.join(BASELINES)})"
            )
    ship = list(runs) if args.ship == [] else args.ship or []
    if unknown := sorted(set(ship) - set(runs)):
        raise ValueError(f"--ship {' '.join(unknown)}: not among the --run names {sorted(runs)}")
    report = write_report(
        args.data,
        runs,
        args.out,
        models=models,
        holdout_every=args.holdout_every,
        pairs=args.pair,
        ship=ship,
    )
    print(report.markdown)
    for path in report.shipped:
        print(f"shipped {path}")
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


#: The training commands, in the order ``gdpt --help`` lists them.
COMMANDS: tuple[Command, ...] = (
    Command(
        "dataset",
        "render training crops for the networks (resumable, parallel, Ray)",
        _add_dataset_arguments,
        _run_dataset,
        _dataset_interrupted,
    ),
    Command(
        "train",
        "train a reconstruction network on a dataset (torchrun-ready)",
        _add_train_arguments,
        _run_train,
        _train_interrupted,
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
