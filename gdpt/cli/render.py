"""The render commands: ``info``, ``reconstruct``, ``render`` and ``render-and-denoise``."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from gdpt.cli.command import Command, UsageError
from gdpt.methods import METHODS
from gdpt.scenes.loading import DEFAULT_MAX_DEPTH

#: ``--spp`` when neither it nor ``--time`` is given.
DEFAULT_SPP = 64


# ----------------------------------------------------------------------------------------- info
def _add_info_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", type=Path, help="an EXR file written by gdpt")


def _run_info(args: argparse.Namespace) -> int:
    from gdpt.io.exr import describe_exr

    print(describe_exr(args.file))
    return 0


def _method_name(name: str) -> str:
    """``--method``'s value: a reconstruction method's current name (a deprecated one warns)."""
    return METHODS.resolve(name)


# ---------------------------------------------------------------------------------- reconstruct
def _add_reconstruct_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "file",
        type=Path,
        help="an EXR of buffers (gdpt render) or of Mitsuba's aov integrator: what --method reads",
    )
    parser.add_argument(
        "--method",
        type=_method_name,
        choices=list(METHODS),
        default="l1-fast",
        help="reconstruction, as gdpt.reconstruct_image (default: l1-fast)",
    )
    parser.add_argument(
        "--aov",
        action="append",
        metavar="KIND=LAYER",
        help="for a Mitsuba AOV EXR: the layer of a kind (primal, albedo, normal, depth) where "
        "it is ambiguous, e.g. --aov normal=nn (repeatable)",
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

    from gdpt.io.mitsuba_aov import parse_aov_kinds

    buffers = load_buffers(args.file, aov_kinds=parse_aov_kinds(args.aov))
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
        "scene",
        help="Mitsuba XML file, builtin:NAME or random:SEED[:VIEW] (see gdpt.scenes.loading)",
    )
    parser.add_argument(
        "--spp",
        type=int,
        help="samples per pixel (default: 64). render-and-denoise: one sample of a method that "
        "reads gradients costs several plain ones (cbox-demo, 128 px, docs/cost-table.md: "
        "about 2.6x for l2/l1/l1-fast, 5.1x oidn-grad, 5.4x fuse; 1.0-1.1x for oidn, "
        "oidn-tuned, kpcn, nfor); with auto, plain samples' worth; --time gives seconds instead",
    )
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
    parser.add_argument(
        "--gradient-mask",
        type=Path,
        metavar="IMAGE",
        help="PNG or EXR of the film's size: offset paths only for the pixels set in it (any "
        "channel above half its range), plain paths elsewhere (gdpt.render's gradient_mask); "
        "needs gradients",
    )


def _load_scene(args: argparse.Namespace) -> tuple[object, int]:
    """The scene of ``args`` (:func:`gdpt.scenes.loading.read_scene` with ``--box-filter`` and
    ``--long-side``) and the max depth to render with; prints what loading changed and where
    the depth comes from.

    Raises:
        UsageError: a bad option value, or a film without a box filter and no ``--box-filter``.
    """
    from gdpt.scenes.loading import BOX_FILTER, choose_max_depth, read_scene

    if args.spp is not None and args.spp < 1:
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


def _gradient_mask(args: argparse.Namespace, reason: str | None):
    """``--gradient-mask`` read (:func:`gdpt.io.images.load_mask`), or ``None``; ``reason``:
    why this command's render has no gradients (``None``: it has)."""
    if args.gradient_mask is None:
        return None
    if reason is not None:
        raise UsageError(f"--gradient-mask selects where offsets are traced, but {reason}")
    from gdpt.io.images import load_mask

    return load_mask(args.gradient_mask)


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
        help="also store the primal, features and gradients of two independent halves of the "
        "samples (read by nfor and fuse)",
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
    mask = _gradient_mask(args, "--no-gradients is set" if args.no_gradients else None)
    scene, max_depth = _load_scene(args)
    buffers = render(
        scene,
        spp=DEFAULT_SPP if args.spp is None else args.spp,
        seed=args.seed,
        integrator=args.integrator,
        progress=True,
        max_depth=max_depth,
        gradients=not args.no_gradients,
        variance=args.variance,
        halves=args.halves,
        primal_spp=args.primal_spp,
        gradient_mask=mask,
    )
    args.output.parent.mkdir(parents=True, exist_ok=True)
    save_buffers(args.output, buffers, half=args.half, force=args.force)
    save_png(preview_path(args.output), buffers.primal, force=True)
    print(f"wrote {args.output} ({buffers.metadata['render_seconds']:.2f} s)")
    return 0


def _written_at_the_end(args: argparse.Namespace) -> str:
    return f"interrupted; nothing written ({args.output} is written at the end)"


# -------------------------------------------------------------------------- render-and-denoise
def _add_render_and_denoise_arguments(parser: argparse.ArgumentParser) -> None:
    _add_scene_arguments(parser)
    parser.add_argument(
        "--method",
        type=_method_name,
        choices=["auto", *METHODS],
        default="auto",
        help="reconstruction (default: auto: a pilot render, whose samples go into the image, "
        "chooses between --spp plain samples + the primal-only denoiser and fuse on "
        "gradient-domain samples of the same cost); the render has the buffers it reads",
    )
    parser.add_argument(
        "--time",
        type=float,
        metavar="SECONDS",
        help="instead of --spp: seconds of sampling and reconstruction (auto's pilot included) "
        "to fill; the sample count comes from a cost model of the scene, fitted by probe "
        "renders first (with the kernel compilation and pass recording: reported apart)",
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
    if args.time is not None and args.spp is not None:
        raise UsageError("give --spp or --time, not both")
    if args.time is not None and not (math.isfinite(args.time) and args.time > 0):
        raise UsageError(f"--time must be a finite number of seconds > 0, got {args.time}")
    if args.method != "auto" and (reason := METHODS[args.method].check()):
        raise UsageError(f"--method {args.method} cannot run here: {reason}")
    outputs = {"--output": args.output, "--save-buffers": args.save_buffers}
    for option, path in outputs.items():
        if path is not None and path.suffix.lower() != ".exr":
            raise UsageError(f"{option} must be an .exr file, got '{path}'")
        if path is not None and any(p.exists() and not p.is_dir() for p in path.parents):
            raise UsageError(f"{option} {path}: a parent of it is a file, not a folder")
    if args.save_buffers is not None and args.save_buffers.resolve() == args.output.resolve():
        raise UsageError(f"--save-buffers and --output are the same file: {args.output}")
    for path in (args.output, preview_path(args.output), args.save_buffers):
        if path is not None:  # fail before the render
            check_writable(path, force=args.force)
    if args.method == "auto":
        mask = _gradient_mask(args, "--method auto chooses its own route (give e.g. fuse)")
    else:
        no_gradients = f"--method {args.method} reads no gradients"
        mask = _gradient_mask(args, None if METHODS[args.method].gradients else no_gradients)
    scene, max_depth = _load_scene(args)

    spp = DEFAULT_SPP if args.spp is None and args.time is None else args.spp
    result = render_and_denoise(
        scene,
        spp=spp,
        seconds=args.time,
        method=args.method,
        seed=args.seed,
        alpha=args.alpha,
        progress=True,
        integrator=args.integrator,
        max_depth=max_depth,
        **({} if mask is None else {"gradient_mask": mask}),
    )
    metadata = {
        "scene": args.scene,
        "method": args.method,
        "alpha": args.alpha,
        "spp": result.spp,
        "seconds": result.budget,
        "timings": result.timings,
        "render": result.buffers.metadata,
    }
    if result.route is not None:
        metadata["route"] = result.route.to_json()
        print(f"auto: {result.route.route} route ({result.route.method}): {result.route.reason}")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    save_image(args.output, result.image, metadata=metadata, force=args.force)
    print(f"wrote {args.output}")
    print(f"wrote {save_png(preview_path(args.output), result.image, force=args.force)}")
    if args.save_buffers is not None:
        args.save_buffers.parent.mkdir(parents=True, exist_ok=True)
        save_buffers(args.save_buffers, result.buffers, force=args.force)
        print(f"wrote {args.save_buffers}")
    print(timings_line(result, args.method))
    return 0


def timings_line(result, method: str) -> str:
    """The ``timings:`` line of ``render-and-denoise`` for a :class:`gdpt.pipeline.RenderResult`:
    the stages and their ``total`` (with ``--time``, against the budget) and the sample count
    of ``method``, then what was not timed: kernel compilation and ``--time``'s setup."""
    timings = dict(result.timings)
    apart = {k: timings.pop(k) for k in ("compile", "setup") if k in timings}
    line = "timings: " + ", ".join(f"{k} {v:.2f} s" for k, v in timings.items())
    if method == "auto":
        count = f"{result.spp} spp, plain samples' worth"
    else:
        count = f"{result.spp} {'gradient ' if METHODS[method].gradients else ''}spp"
    if result.budget is not None:
        line += f" of a {result.budget:.2f} s budget ({count})"
    else:
        line += f" ({count})"
    words = [f"kernel compilation {apart.get('compile', 0.0):.2f} s"]
    if "setup" in apart:
        words.append(
            f"setup {apart['setup']:.2f} s (compilation, pass recording, cost-model probes; "
            "once per scene and configuration in a process)"
        )
    return f"{line}; not timed: {', '.join(words)}"


#: The render commands, in the order ``gdpt --help`` lists them.
COMMANDS: tuple[Command, ...] = (
    Command("info", "describe a gdpt EXR file", _add_info_arguments, _run_info),
    Command(
        "reconstruct",
        "reconstruct an image from primal + gradient buffers",
        _add_reconstruct_arguments,
        _run_reconstruct,
        _written_at_the_end,
    ),
    Command(
        "render",
        "render gradient-domain buffers to EXR",
        _add_render_arguments,
        _run_render,
        _written_at_the_end,
    ),
    Command(
        "render-and-denoise",
        "render and reconstruct in one go: image EXR + PNG preview (gdpt.render_and_denoise)",
        _add_render_and_denoise_arguments,
        _run_render_and_denoise,
        _written_at_the_end,
    ),
)
