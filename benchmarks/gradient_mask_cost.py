"""Render time of ``gdpt`` with a gradient mask against the linear model of its share.

For each scene and resolution, in one run: ``path`` (``gdpt`` with ``gradients=False``: plain
samples with features), the full ``gdpt`` render (offsets everywhere, features), and ``gdpt``
with a gradient mask of share 0, 25, 50, 75% in two patterns, ``tiles`` (random 16 px tiles,
seeded) and ``region`` (one contiguous band of rows from the top). The model of a masked render
is ``path + share * (gdpt - path)`` with ``share`` the masked pixels' share; the table gives the
median over rounds of each round's ``time / model`` (1 = the offset work shrinks in proportion
to the mask). Every configuration has its own integrator and renders twice untimed first (JIT
compilation and the frozen-pass recordings of both wavefronts excluded); then ``--repeats``
interleaved rounds with new seeds (:func:`render_timing.interleaved_rounds`), so that a drifting
machine speed affects all of a round alike. Usage::

    .venv/bin/python benchmarks/gradient_mask_cost.py [--scenes cornell-box sponza staircase]
        [--resolutions 128 512] [--spp 32 8] [--max-depth 6] [--repeats 3] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
from pathlib import Path

from render_timing import interleaved_rounds, load_shared

SCENES = ["cornell-box", "sponza", "staircase"]
SHARES = (0.25, 0.5, 0.75)
TILE = 16


def _masks(width: int, height: int, seed: int = 0) -> dict[str, tuple[object, float]]:
    """``label -> (mask (H, W) bool, masked share)`` of the measured configurations."""
    import numpy as np

    rng = np.random.default_rng(seed)
    tiles_y, tiles_x = -(-height // TILE), -(-width // TILE)
    order = rng.permutation(tiles_y * tiles_x)
    out = {"mask 0%": np.zeros((height, width), bool)}
    for share in SHARES:
        picked = np.zeros(tiles_y * tiles_x, bool)
        picked[order[: round(share * tiles_y * tiles_x)]] = True
        tiles = picked.reshape(tiles_y, tiles_x).repeat(TILE, 0).repeat(TILE, 1)
        out[f"tiles {share:.0%}"] = tiles[:height, :width].copy()
        region = np.zeros((height, width), bool)
        region[: round(share * height)] = True
        out[f"region {share:.0%}"] = region
    return {label: (m, float(m.mean())) for label, m in out.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=SCENES)
    parser.add_argument("--resolutions", type=int, nargs="+", default=[128, 512])
    parser.add_argument("--spp", type=int, nargs="+", default=[32, 8], help="one per resolution")
    parser.add_argument("--max-depth", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if len(args.spp) != len(args.resolutions):
        parser.error("give one --spp per --resolutions")

    import mitsuba as mi

    import gdpt

    variant = gdpt.set_variant()
    rows = []
    for name in args.scenes:
        for resolution, spp in zip(args.resolutions, args.spp, strict=True):
            scene, (width, height) = load_shared(name, resolution)
            props = {"type": "gdpt", "max_depth": args.max_depth}
            configs = {
                "path": (mi.load_dict({**props, "gradients": False}), None),
                "gdpt": (mi.load_dict(props), 1.0),
            }
            for label, (mask, share) in _masks(width, height).items():
                integrator = mi.load_dict(props)
                integrator.gradient_mask = mask
                configs[label] = (integrator, share)
            integrators = {label: integrator for label, (integrator, _) in configs.items()}
            _, runs = interleaved_rounds(scene, integrators, spp, args.repeats)
            result = {}
            for label, (_, share) in configs.items():
                share = 0.0 if share is None else share
                models = [
                    p + share * (g - p) for p, g in zip(runs["path"], runs["gdpt"], strict=True)
                ]
                ratios = [t / m for t, m in zip(runs[label], models, strict=True)]
                result[label] = {
                    "share": share,
                    "seconds": statistics.median(runs[label]),
                    "time_over_model": statistics.median(ratios),
                    "range": [min(ratios), max(ratios)],
                }
            row = {"scene": name, "size": [width, height], "spp": spp, "configs": result}
            rows.append(row)
            worst = max(abs(c["time_over_model"] - 1) for c in result.values())
            print(f"{name} {width}x{height}: worst |time / model - 1| {worst:.3f}", flush=True)

    print(
        f"\n{variant}, max_depth {args.max_depth}, {args.repeats} interleaved rounds, JIT "
        "compilation and frozen-pass recording excluded (two untimed renders per configuration)\n"
    )
    labels = list(rows[0]["configs"])
    print("| scene | size | spp | path [s] | gdpt [s] | " + " | ".join(labels[2:]) + " |")
    print("|---|---|---:|---:|---:|" + "---:|" * (len(labels) - 2))
    for row in rows:
        c = row["configs"]
        cells = " | ".join(f"{c[label]['time_over_model']:.2f}" for label in labels[2:])
        print(
            f"| {row['scene']} | {'x'.join(str(v) for v in row['size'])} | {row['spp']} | "
            f"{c['path']['seconds']:.2f} | {c['gdpt']['seconds']:.2f} | {cells} |"
        )
    if args.json:
        meta = {
            "variant": variant,
            "machine": platform.processor() or platform.machine(),
            "args": {k: str(v) for k, v in vars(args).items()},
        }
        args.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
