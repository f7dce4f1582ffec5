"""Per-pixel unbiasedness table of ``gdpt`` (and ``gdpt_rr``) on the shared real scenes.

The statistic and the decision rule are the test suite's (``tests/integrators/pixel_stats.py``,
``tests/integrators/test_gdpt_unbiased.py``): per pixel and channel, z of the means of ``--runs``
renders x ``--spp`` against ``--ref-runs`` x ``--ref-spp`` renders of Mitsuba's ``path`` (primal)
and its forward differences (``dx``, ``dy``), with run-to-run variances; each cell is the share
of pixel-channels with |z| > 3.29 and the largest |z| (pass: <= 1% and <= 6). ``path`` against
itself (other seeds) is the calibration row. Usage::

    .venv/bin/python benchmarks/unbiasedness.py [--scenes cornell-box ...] [--depths 2 6]
        [--integrators gdpt gdpt_rr] [--long-side 24] [--runs 48] [--spp 192]
        [--ref-runs 32] [--ref-spp 512] [--markdown PATH]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "scenes"
SCENES = [
    "cornell-box",
    "veach-mis",
    "matpreview-dof",
    "sponza",
    "staircase",
    "torus",
    "veach-bidir",
]
sys.path.insert(0, str(ROOT / "tests" / "integrators"))  # the suite's statistic, not a copy

from pixel_stats import Oracle, pixel_z, render_runs  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=SCENES)
    parser.add_argument("--depths", nargs="+", type=int, default=[2, 6])
    parser.add_argument("--integrators", nargs="+", default=["gdpt"])
    parser.add_argument("--long-side", type=int, default=24)
    parser.add_argument("--runs", type=int, default=48)
    parser.add_argument("--spp", type=int, default=192)
    parser.add_argument("--ref-runs", type=int, default=32)
    parser.add_argument("--ref-spp", type=int, default=512)
    parser.add_argument("--markdown", type=Path, help="also write the table to this file")
    args = parser.parse_args()

    import mitsuba as mi
    from tqdm import tqdm

    import gdpt

    gdpt.set_variant()
    header = ["scene, max depth", "estimator", "primal", "dx", "dy"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    jobs = [(s, d) for s in args.scenes for d in args.depths]
    for name, depth in tqdm(jobs, desc="scenes", unit="scene"):
        scene = gdpt.load_scene(
            SHARED / name / "scene.xml", box_filter=True, long_side=args.long_side
        )
        path = mi.load_dict({"type": "path", "max_depth": depth})
        oracle = Oracle(render_runs(scene, path, args.ref_runs, args.ref_spp, 100_000)["primal"])
        rows = {
            "path (self-test)": Oracle(render_runs(scene, path, args.runs, args.spp, 7)["primal"])
        }
        for integrator in args.integrators:
            plugin = mi.load_dict({"type": integrator, "max_depth": depth, "features": False})
            runs = render_runs(scene, plugin, args.runs, args.spp, seed=1)
            fired = {k: v for k, v in plugin.guard_counts.items() if v}
            rows[integrator + (f" (guards {fired})" if fired else "")] = runs
        for label, test in rows.items():
            get = (lambda b, t=test: getattr(t, b)) if isinstance(test, Oracle) else test.get
            cells = [str(pixel_z(get(b), getattr(oracle, b))) for b in ("primal", "dx", "dy")]
            cells = [c.replace(" |z|>3.29, max |z| ", ", ") for c in cells]
            lines.append(f"| {name}, {depth} | {label} | " + " | ".join(cells) + " |")
            tqdm.write(lines[-1])
    table = "\n".join(lines)
    print(
        f"\n{args.runs} x {args.spp} spp against {args.ref_runs} x {args.ref_spp} spp of "
        f"path, {args.long_side} px long side; cells: share of |z| > 3.29, max |z|\n"
    )
    print(table)
    if args.markdown:
        args.markdown.write_text(table + "\n")


if __name__ == "__main__":
    main()
