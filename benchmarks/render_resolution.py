"""Render seconds at the resolution you render at: what a newcomer's ``gdpt render`` costs.

Per scene and long side, in one process: ``gdpt.render`` as ``gdpt render`` runs it (the
``gdpt`` integrator with features; ``gradients``) and as ``gdpt render --no-gradients`` (plain
path tracing with features; ``plain``), each rendered twice untimed first (kernel compilation
and the frozen passes' recording: a fresh process pays them once,
``docs/mitsuba.md#first-render-kernel-compilation``), then ``--repeats`` interleaved timed
renders (:func:`render_timing.interleaved_rounds`); the median in seconds and in seconds per
sample per pixel per megapixel (``s / (spp * MP)``; a render's time is about linear in both).
Usage::

    nice -n 19 .venv/bin/python benchmarks/render_resolution.py \\
        [--scenes cornell-box sponza] [--resolutions 256 512 1024] [--spp 4] [--repeats 2] \\
        [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from render_timing import interleaved_rounds, load_shared

from gdpt.machine import cpu_name


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--scenes", nargs="+", default=["cornell-box", "sponza"])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--spp", type=int, default=4)
    parser.add_argument("--max-depth", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    import drjit as dr
    import mitsuba as mi

    import gdpt

    variant = gdpt.set_variant()
    print(f"{cpu_name()}, {variant}, Dr.Jit threads {dr.thread_count()}; spp {args.spp}")
    print("| scene | film | MP | gradients s | plain s | gradients s/(spp MP) | plain s/(spp MP) |")
    print("|---|---|---:|---:|---:|---:|---:|")
    rows = []
    for name in args.scenes:
        for long_side in args.resolutions:
            scene, (width, height) = load_shared(name, long_side)
            integrators = {
                kind: mi.load_dict(
                    {"type": "gdpt", "max_depth": args.max_depth, "gradients": kind == "gradients"}
                )
                for kind in ("gradients", "plain")
            }
            _, runs = interleaved_rounds(scene, integrators, args.spp, args.repeats)
            mp = width * height / 1e6
            median = {k: statistics.median(v) for k, v in runs.items()}
            per = {k: s / (args.spp * mp) for k, s in median.items()}
            rows.append({"scene": name, "film": [width, height], "seconds": median, "per": per})
            print(
                f"| {name} | {width}x{height} | {mp:.3f} | {median['gradients']:.2f} "
                f"| {median['plain']:.2f} | {per['gradients']:.2f} | {per['plain']:.2f} |",
                flush=True,
            )
    if args.json:
        record = {"cpu": cpu_name(), "variant": variant, "args": vars(args) | {"json": None}}
        args.json.write_text(json.dumps({**record, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
