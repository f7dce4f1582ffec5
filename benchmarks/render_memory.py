"""Peak memory (RSS) of rendering 720p-sized images with many samples: ``path`` against ``gdpt``.

The default scene, staircase, has a 9:16 film: at a long side of 1280 px it has 720x1280 =
921,600 pixels, as many as 1280x720. Each integrator renders in its own Python process, so that
the peak resident set size (``ru_maxrss``) is that render's: the process loads the scene,
renders once at 1 spp (compiles the kernels), reports its RSS as the baseline, then renders
``--spp`` samples per pixel and reports the peak. ``gdpt`` traces ``samples_per_pass`` samples
per kernel launch (default 2^20), so its memory is bounded by the pass, not by the spp: the
table also lists the passes. Usage::

    .venv/bin/python benchmarks/render_memory.py [--scene staircase] [--long-side 1280]
        [--spp 64] [--samples-per-pass 1048576]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"
INTEGRATORS = {
    "path": {"type": "path"},
    "gdpt": {"type": "gdpt"},
    "gdpt, primal only": {"type": "gdpt", "gradients": False},
}

_CHILD = """
import json, resource, sys, time
import drjit as dr, mitsuba as mi
import gdpt
from gdpt.scenes.loading import load_scene
args = json.loads(sys.argv[1])
gdpt.set_variant()
from gdpt.integrators.common import plan_passes
scene = load_scene(args["xml"], box_filter=True, long_side=args["long_side"])
props = dict(args["props"], max_depth=6)
if props["type"] != "path":
    props["samples_per_pass"] = args["samples_per_pass"]
integrator = mi.load_dict(props)
dr.eval(mi.render(scene, integrator=integrator, spp=1))
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
start = time.perf_counter()
image = mi.render(scene, integrator=integrator, spp=args["spp"], seed=1)
dr.eval(image)
dr.sync_thread()
seconds = time.perf_counter() - start
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
w, h = (int(v) for v in scene.sensors()[0].film().crop_size())
passes = len(plan_passes(w * h, args["spp"], args["samples_per_pass"]))
print(json.dumps({"size": f"{w}x{h}", "baseline_mb": base / 1024, "peak_mb": peak / 1024,
                  "seconds": seconds, "passes": passes if props["type"] != "path" else 1}))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default="staircase")
    parser.add_argument("--long-side", type=int, default=1280)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--samples-per-pass", type=int, default=1 << 20)
    args = parser.parse_args()
    print(f"\n{args.scene}, {args.spp} spp, samples_per_pass {args.samples_per_pass}\n")
    print("| integrator | size | passes | RSS after compiling [MB] | peak RSS [MB] | render [s] |")
    print("|---|---|---:|---:|---:|---:|")
    for label, props in INTEGRATORS.items():
        child = {
            "xml": str(SHARED / args.scene / "scene.xml"),
            "long_side": args.long_side,
            "spp": args.spp,
            "samples_per_pass": args.samples_per_pass,
            "props": props,
        }
        proc = subprocess.run(
            [sys.executable, "-c", _CHILD, json.dumps(child)],
            check=False,
            capture_output=True,
            text=True,
        )
        if proc.returncode:
            raise RuntimeError(f"{label}: the render process failed:\n{proc.stderr[-2000:]}")
        last = proc.stdout.strip().splitlines()[-1]  # Mitsuba's log may precede it on the line
        r = json.loads(last[last.rindex("{") :])
        print(
            f"| {label} | {r['size']} | {r['passes']} | {r['baseline_mb']:.0f} | "
            f"{r['peak_mb']:.0f} | {r['seconds']:.1f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
