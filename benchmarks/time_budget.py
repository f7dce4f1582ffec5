"""Does ``gdpt render-and-denoise --time SECONDS`` take its budget? Each method in fresh
processes, the CLI as a user runs it.

For every method, ``--processes`` fresh ``gdpt render-and-denoise SCENE --time SECONDS``
processes one after the other (the first compiles the kernels into Dr.Jit's on-disk cache; the
later ones start from it, as a user's second command does), each with ``--renders`` renders of
the scene in the same process where ``--renders`` > 1 (through the API, :func:`render` below: the
later renders reuse the cost model). Read from the ``timings:`` line (or the result): the
timed total (sampling and reconstruction, ``auto``'s pilot included; kernel compilation and the
setup excluded and printed apart) against the budget. A run passes within ``--tolerance``.

Run on an idle machine::

    python benchmarks/time_budget.py --scene builtin:cbox-demo --time 3 \\
        --methods auto fuse oidn-tuned --processes 2

Smoke test (small, not a measurement)::

    python benchmarks/time_budget.py --time 0.5 --long-side 32 --methods l2 --processes 1
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

LINE = re.compile(r"total ([0-9.]+) s of a ([0-9.]+) s budget \((\d+) ")


def render(args: argparse.Namespace, method: str, out: Path) -> list[dict]:
    """One fresh process: the CLI once (``--renders 1``) or the API ``--renders`` times."""
    start = time.perf_counter()
    if args.renders == 1:
        argv = [sys.executable, "-m", "gdpt", "render-and-denoise", args.scene, "--time"]
        argv += [str(args.time), "--method", method, "-o", str(out), "--force"]
        if args.long_side:
            argv += ["--long-side", str(args.long_side)]
        done = subprocess.run(argv, capture_output=True, text=True, check=False)
        if done.returncode:
            raise RuntimeError(f"{' '.join(argv)}: exit {done.returncode}: {done.stderr[-2000:]}")
        line = next(x for x in done.stdout.splitlines() if x.startswith("timings:"))
        total, budget, spp = LINE.search(line).groups()
        compile_s = float(re.search(r"kernel compilation ([0-9.]+) s", line).group(1))
        setup = float(re.search(r"setup ([0-9.]+) s", line).group(1))
        runs = [{"total": float(total), "spp": int(spp), "compile": compile_s, "setup": setup}]
    else:
        code = (
            "import json, sys, gdpt\n"
            "from gdpt.scenes.loading import read_scene\n"
            f"s = read_scene({args.scene!r}, long_side={args.long_side!r}).scene\n"
            "runs = []\n"
            f"for i in range({args.renders}):\n"
            f"    r = gdpt.render_and_denoise(s, seconds={args.time}, method={method!r}, seed=i)\n"
            "    runs.append({'total': r.timings['total'], 'spp': r.spp,\n"
            "                 'compile': r.timings['compile'], 'setup': r.timings['setup']})\n"
            "print('RUNS', json.dumps(runs))\n"
        )
        done = subprocess.run(
            [sys.executable, "-c", code], check=False, capture_output=True, text=True
        )
        if done.returncode:
            raise RuntimeError(done.stderr[-2000:])
        line = next(x for x in done.stdout.splitlines() if x.startswith("RUNS "))
        runs = json.loads(line[5:])
    for run in runs:
        run["process_wall"] = time.perf_counter() - start
    return runs


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="builtin:cbox-demo")
    parser.add_argument("--time", type=float, default=3.0, help="the budget (seconds)")
    parser.add_argument("--long-side", type=int, help="rescale the film (default: the scene's)")
    parser.add_argument("--methods", nargs="+", default=["auto", "fuse", "oidn-tuned"])
    parser.add_argument("--processes", type=int, default=2, help="fresh processes per method")
    parser.add_argument("--renders", type=int, default=1, help="renders per process (API)")
    parser.add_argument("--tolerance", type=float, default=0.15)
    args = parser.parse_args()
    failed = 0
    with tempfile.TemporaryDirectory() as tmp:
        for method in args.methods:
            for process in range(args.processes):
                for k, run in enumerate(render(args, method, Path(tmp) / f"{method}.exr")):
                    error = run["total"] / args.time - 1.0
                    ok = abs(error) <= args.tolerance
                    failed += not ok
                    print(
                        f"{method:12s} process {process + 1} render {k + 1}: total "
                        f"{run['total']:.2f} s of {args.time:g} s ({error:+.1%}, "
                        f"{'ok' if ok else 'MISS'}), {run['spp']} spp; apart: compilation "
                        f"{run['compile']:.2f} s, setup {run['setup']:.2f} s; process wall "
                        f"{run['process_wall']:.1f} s",
                        flush=True,
                    )
    print(f"{failed} run(s) outside {args.tolerance:.0%} of the budget")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
