"""What each reconstruction method costs: render seconds per sample and reconstruction seconds,
at 128x128 and at 1280x720, on the built-in ``cbox-demo`` scene.

For every method of :data:`gdpt.methods.METHODS` that can run here (its ``check()``), the script
renders what the method reads (:meth:`gdpt.methods.Method.sampling`: gradients and features as
needed, pooled plain path samples for a pooled network) with ``gdpt`` at ``--spp`` samples per
pixel, then times the reconstruction of those buffers. Every render and every reconstruction
runs once untimed first (kernel compilation, frozen-pass recording, weight loading and torch's
first-call set-up are excluded), then ``--repeats`` times; medians are reported. A row for plain
path tracing (``gdpt`` with ``gradients=false``: the primal and features, no reconstruction) is
included for comparison.

Render cost is per sample per pixel (a method's cost at ``N`` spp is about ``N x render s/spp +
reconstruct s``), also as a ratio to the plain path-tracing row; for a pooled network it counts
the pooled plain samples of one gradient sample too. Methods that read the same buffers share
one render timing.

Threads: torch's and Dr.Jit's defaults, unless ``OMP_NUM_THREADS`` sets torch's. On a machine
shared with other jobs use ``OMP_NUM_THREADS=1``: torch's spinning worker threads then
slow each other down by 20-50x on small images (an ``l1-fast`` solve at 128x128 took 5-15 s with
2 threads on 2 busy cores, 0.24-0.31 s with one). The script prints the thread count and the
load average. Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/method_cost.py  # 128x128 and 1280x720
    .venv/bin/python benchmarks/method_cost.py --sizes 128x128 --repeats 5 --json cost.json
    .venv/bin/python benchmarks/method_cost.py --methods kpcn m --model m=run/model.safetensors

``--methods`` restricts the rows (the plain path-tracing row is always measured);
``--model NAME=CHECKPOINT`` adds a ``gdpt train`` checkpoint as method ``NAME``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import torch

import gdpt
from gdpt.machine import cpu_name
from gdpt.methods import METHODS, register_checkpoint
from gdpt.scenes.loading import generated_scene

PLAIN = "(path tracing, no reconstruction)"


def parse_size(text: str) -> tuple[int, int]:
    """``'WxH'`` -> ``(W, H)``; a clear error otherwise."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--sizes: {text!r} is not WIDTHxHEIGHT") from None
    if width < 1 or height < 1:
        raise argparse.ArgumentTypeError(f"--sizes: {text!r} must be positive")
    return width, height


def median_seconds(fn, repeats: int) -> float:
    """Median wall time of ``repeats`` calls of ``fn`` after one untimed call (each call waits
    for the CUDA device, where torch has one: its kernels run asynchronously)."""

    def call() -> None:
        fn()
        if torch.cuda.is_available():
            torch.cuda.synchronize()

    call()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def measure(
    size: tuple[int, int], spp: int, repeats: int, methods: list[str] | None = None
) -> dict[str, dict[str, float]]:
    """``method -> {'render_per_spp', 'reconstruct'}`` (seconds) at film size ``size``, for
    ``methods`` (default: every registered method)."""
    import mitsuba as mi

    scene_dict = generated_scene("builtin:cbox-demo")
    scene_dict["sensor"]["film"]["width"], scene_dict["sensor"]["film"]["height"] = size
    scene = mi.load_dict(scene_dict)
    rows: dict[str, dict[str, float]] = {}
    plan = [(PLAIN, {"gradients": False, "features": True})]
    for name, method in METHODS.items():
        if methods is not None and name not in methods:
            continue
        reason = method.check()
        if reason is not None:
            print(f"  {name}: skipped ({reason})")
            continue
        plan.append((name, method.sampling(spp)))
    render_seconds: dict[tuple, float] = {}  # methods reading the same buffers share a timing
    for name, sampling in plan:
        render = lambda s=sampling: gdpt.render(scene, spp=spp, **s)  # noqa: E731
        key = tuple(sorted(sampling.items()))
        if key not in render_seconds:
            render_seconds[key] = median_seconds(render, repeats)
        row = {"render_per_spp": render_seconds[key] / spp, "reconstruct": 0.0}
        if name != PLAIN:
            buffers = render()
            run = lambda n=name, b=buffers: gdpt.reconstruct_image(b, n)  # noqa: E731
            row["reconstruct"] = median_seconds(run, repeats)
        rows[name] = row
        print(
            f"  {name}: render {row['render_per_spp']:.4f} s/spp, "
            f"reconstruct {row['reconstruct']:.3f} s"
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", type=parse_size, default=[(128, 128), (1280, 720)])
    parser.add_argument("--spp", type=int, default=4, help="gradient samples per pixel")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per measurement")
    parser.add_argument("--json", type=Path, help="also write the numbers here")
    parser.add_argument("--methods", nargs="+", help="only these methods (default: all)")
    parser.add_argument(
        "--model",
        action="append",
        default=[],
        metavar="NAME=CHECKPOINT",
        help="also measure a checkpoint of gdpt train as method NAME; repeat for several",
    )
    args = parser.parse_args()
    if args.spp < 1 or args.repeats < 1:
        parser.error("--spp and --repeats must be >= 1")
    for item in args.model:
        name, _, path = item.partition("=")
        if not name or not path:
            parser.error(f"--model {item!r}: expected NAME=CHECKPOINT")
        register_checkpoint(name, path)
        if args.methods:
            args.methods.append(name)  # measured as well as --methods
    if args.methods and (unknown := sorted(set(args.methods) - set(METHODS))):
        parser.error(f"--methods: unknown {unknown}; known: {', '.join(METHODS)}")

    variant = gdpt.set_variant()
    results = {}
    for size in args.sizes:
        print(
            f"{size[0]}x{size[1]} ({variant}, {torch.get_num_threads()} torch threads), "
            f"load average {os.getloadavg()[0]:.2f}"
        )
        results[f"{size[0]}x{size[1]}"] = measure(size, args.spp, args.repeats, args.methods)

    labels = list(results)
    print()
    header = " | ".join(f"render s/spp, {s} | / path tracing | reconstruct s, {s}" for s in labels)
    print(f"| method | {header} |")
    print("|---|" + "---:|---:|---:|" * len(labels))
    for name in results[labels[0]]:
        cells = []
        for label in labels:
            row, plain = results[label].get(name), results[label][PLAIN]
            if row is None:
                cells.append("| | ")
                continue
            ratio = row["render_per_spp"] / plain["render_per_spp"]
            cells.append(f"{row['render_per_spp']:.4f} | {ratio:.2f} | {row['reconstruct']:.3f}")
        print(f"| {name} | {' | '.join(cells)} |")
    print(
        f"\nmachine: {cpu_name()}, {os.cpu_count()} CPUs, "
        f"load average at end {os.getloadavg()[0]:.2f}; spp {args.spp}, "
        f"median of {args.repeats}"
    )
    if args.json:
        args.json.write_text(json.dumps({"spp": args.spp, "results": results}, indent=1))


if __name__ == "__main__":
    main()
