"""Cost of gradient-domain sampling relative to Mitsuba's ``path`` integrator.

For each scene and resolution: time per sample per pixel of ``gdpt`` with and without the
feature buffers, ``gdpt`` with features traced anew in every pass (``freeze=False``, as before
frozen passes), ``gdpt_rr`` and the primal-only mode (``gdpt`` with ``gradients=False``), each
divided by ``path`` at the same max depth, resolution and spp, measured in one run. Every
integrator renders twice first: the first render compiles the kernels (reported separately as
``compile [s]``: first render minus the median timed render) and records the frozen pass
(dr.freeze may record once more on the second call); then ``--repeats`` interleaved rounds with
new seeds (:func:`render_timing.interleaved_rounds`) reuse the cached kernels and recordings
(``recordings``: how many the frozen pass holds after all rounds; it does not grow when the
timed renders replay). The ratio to ``path`` is the median over rounds of the per-round ratio
(IQR reported). Usage::

    .venv/bin/python benchmarks/render_cost.py [--scenes cornell-box veach-mis ...]
        [--resolutions 128 256] [--spp 32] [--max-depth 6] [--repeats 3] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from render_timing import interleaved_rounds, load_shared

from gdpt.machine import cpu_name

SCENES = [
    "cornell-box",
    "veach-mis",
    "staircase",
    "sponza",
    "matpreview-dof",
    "torus",
    "veach-bidir",
]
INTEGRATORS = {
    "path": {"type": "path"},
    "gdpt+features": {"type": "gdpt", "features": True},
    "gdpt+features, traced": {"type": "gdpt", "features": True, "freeze": False},
    "gdpt": {"type": "gdpt", "features": False},
    "gdpt_rr": {"type": "gdpt_rr", "features": False},
    "primal-only": {"type": "gdpt", "gradients": False, "features": False},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=SCENES)
    parser.add_argument("--resolutions", type=int, nargs="+", default=[128, 256], help="long sides")
    parser.add_argument("--spp", type=int, default=32)
    parser.add_argument("--max-depth", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    import mitsuba as mi

    import gdpt

    variant = gdpt.set_variant()
    rows = []
    for name, resolution in ((n, r) for n in args.scenes for r in args.resolutions):
        scene, (width, height) = load_shared(name, resolution)
        integrators = {
            label: mi.load_dict({**props, "max_depth": args.max_depth})
            for label, props in INTEGRATORS.items()
        }
        first, runs = interleaved_rounds(scene, integrators, args.spp, args.repeats)
        times = {}
        for label, t in runs.items():
            median = statistics.median(t)
            ratios = [a / b for a, b in zip(t, runs["path"], strict=True)]
            q1, _, q3 = statistics.quantiles(ratios, n=4) if len(ratios) > 1 else ratios * 3
            frozen = getattr(integrators[label], "_frozen_pass", None)
            times[label] = {
                "seconds": median,
                "ns_per_sample": 1e9 * median / (width * height * args.spp),
                "compile_seconds": max(first[label] - median, 0.0),
                "ratio_to_path": statistics.median(ratios),
                "ratio_iqr": [q1, q3],
                "recordings": frozen.n_recordings if frozen is not None else None,
            }
        rows.append({"scene": name, "size": [width, height], "times": times})
        ratio = times["gdpt+features"]["ratio_to_path"]
        print(f"{name} {width}x{height}: gdpt+features / path {ratio:.2f}", flush=True)

    print(
        f"\n{variant}, {args.spp} spp, max_depth {args.max_depth}, {args.repeats} interleaved "
        "rounds (compile time excluded)\n"
    )
    header = "| scene | size | integrator | ns / sample | ratio to path (IQR) | compile [s] |"
    print(header + " recordings |")
    print("|---|---|---|---:|---:|---:|---:|")
    for row in rows:
        size = "x".join(str(v) for v in row["size"])
        for label, t in row["times"].items():
            q1, q3 = t["ratio_iqr"]
            rec = "" if t["recordings"] is None else t["recordings"]
            print(
                f"| {row['scene']} | {size} | {label} | {t['ns_per_sample']:.0f} | "
                f"{t['ratio_to_path']:.2f} ({q1:.2f}-{q3:.2f}) | {t['compile_seconds']:.1f} | "
                f"{rec} |"
            )
    if args.json:
        meta = {
            "variant": variant,
            "machine": cpu_name(),
            "args": {k: str(v) for k, v in vars(args).items()},
        }
        args.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
