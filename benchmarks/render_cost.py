"""Cost of gradient-domain sampling relative to Mitsuba's ``path`` integrator.

For each scene: time per sample per pixel of ``gdpt``, ``gdpt_rr`` and the primal-only mode
(``gdpt`` with ``gradients=False``), each divided by ``path`` at the same max depth, resolution
and spp, measured in one run. Every integrator renders once to compile its kernels (reported
separately as ``compile [s]``: first run minus the median timed run), then ``--repeats`` rounds
with new seeds reuse the cached kernels. A round times every integrator once, back to back, and
the ratio to ``path`` is the median over rounds of the per-round ratio (IQR reported): on a
shared virtual machine the speed drifts by 10-20% over tens of seconds, which would bias ratios
of integrators timed one after the other. Usage::

    .venv/bin/python benchmarks/render_cost.py [--scenes cornell-box veach-mis staircase]
        [--resolution 256] [--spp 16] [--max-depth 6] [--repeats 3] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"
INTEGRATORS = {
    "path": {"type": "path"},
    "gdpt": {"type": "gdpt", "features": False},
    "gdpt_rr": {"type": "gdpt_rr", "features": False},
    "primal-only": {"type": "gdpt", "gradients": False, "features": False},
}


def _time_render(scene, integrator, spp: int, seed: int) -> float:
    import drjit as dr
    import mitsuba as mi

    start = time.perf_counter()
    image = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
    dr.eval(image)
    dr.sync_thread()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["cornell-box", "veach-mis", "staircase"])
    parser.add_argument("--resolution", type=int, default=256, help="long side in pixels")
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--max-depth", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    import mitsuba as mi

    import gdpt
    from gdpt.scene_io import load_scene

    variant = gdpt.set_variant()
    rows = []
    for name in args.scenes:
        xml = SHARED / name / "scene.xml"
        scene = load_scene(xml, box_filter=True, long_side=args.resolution)
        pixels = int(mi.ScalarVector2u(scene.sensors()[0].film().crop_size()).x) * int(
            mi.ScalarVector2u(scene.sensors()[0].film().crop_size()).y
        )
        integrators = {
            label: mi.load_dict({**props, "max_depth": args.max_depth})
            for label, props in INTEGRATORS.items()
        }
        first = {
            label: _time_render(scene, i, args.spp, seed=0) for label, i in integrators.items()
        }
        runs = {label: [] for label in integrators}
        for r in range(args.repeats):
            for label, integrator in integrators.items():
                runs[label].append(_time_render(scene, integrator, args.spp, seed=1 + r))
        times = {}
        for label, t in runs.items():
            median = statistics.median(t)
            ratios = [a / b for a, b in zip(t, runs["path"], strict=True)]
            q1, _, q3 = statistics.quantiles(ratios, n=4) if len(ratios) > 1 else ratios * 3
            times[label] = {
                "seconds": median,
                "ns_per_sample": 1e9 * median / (pixels * args.spp),
                "compile_seconds": max(first[label] - median, 0.0),
                "ratio_to_path": statistics.median(ratios),
                "ratio_iqr": [q1, q3],
            }
        rows.append({"scene": name, "pixels": pixels, "times": times})

    print(
        f"\n{variant}, {args.resolution} px long side, {args.spp} spp, max_depth "
        f"{args.max_depth}, {args.repeats} interleaved rounds (compile time excluded)\n"
    )
    print("| scene | integrator | ns / sample | ratio to path (IQR) | compile [s] |")
    print("|---|---|---:|---:|---:|")
    for row in rows:
        for label, t in row["times"].items():
            q1, q3 = t["ratio_iqr"]
            print(
                f"| {row['scene']} | {label} | {t['ns_per_sample']:.0f} | "
                f"{t['ratio_to_path']:.2f} ({q1:.2f}-{q3:.2f}) | {t['compile_seconds']:.1f} |"
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
