"""The L1 solvers at 128 px and 1280x720, 1 and 2 threads: time against final L1 energy.

Times the exact L2 solve, the accelerated L1 preset ``"fast"`` (Jacobi-preconditioned CG) and
its multigrid variant ``"fast-multigrid"`` (defined here: multigrid-preconditioned CG, 2
iterations per late round) and, with ``--schedules``, cuts of ``"fast"``'s schedule
(:data:`SCHEDULES`), interleaved (one run of each per round, the rounds repeated), and
reports the median time over the rounds after one excluded warm-up round (torch runs eagerly
here: the warm-up only fills caches and allocator pools). The final L1 energy of each solver is
given relative to the reference preset ``"l1"`` (20 IRLS rounds x 50 plain CG iterations),
solved once per input.

Inputs: the synthetic G-PT-like buffers of ``benchmarks/poisson.py`` at each ``--sizes`` entry,
and any rendered buffers given by ``--buffers`` (files written by ``gdpt.save_buffers``).

Usage::

    .venv/bin/python benchmarks/poisson_720p.py --threads 1 2 --repeats 5 \\
        --buffers /tmp/cbox720 /tmp/sponza720
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from pathlib import Path

import torch
from gdpt.reconstruct import poisson
from poisson import load_average, make_gpt_like

#: ``"fast"`` with the multigrid preconditioner: fewer, dearer iterations (2 per late round).
FAST_MULTIGRID = dataclasses.replace(
    poisson.L1_PRESETS["fast"],
    name="fast-multigrid",
    cg_iters=30,
    late_cg_iters=2,
    precondition="multigrid",
)


#: ``"fast"``'s schedule cut (``--schedules``): fewer late iterations, a looser early stop, fewer
#: rounds with the same last regulariser, and multigrid variants.
_FAST = poisson.L1_PRESETS["fast"]
SCHEDULES = {
    "fast-late8": dataclasses.replace(_FAST, name="fast-late8", late_cg_iters=8),
    "fast-rtol0.2": dataclasses.replace(_FAST, name="fast-rtol0.2", cg_rtol=0.2),
    "fast-16-rounds": dataclasses.replace(
        _FAST, name="fast-16-rounds", rounds=16, reg_decay=0.5 ** (18 / 14), late_round=8
    ),
    "fast-16-rounds-late8": dataclasses.replace(
        _FAST,
        name="fast-16-rounds-late8",
        rounds=16,
        reg_decay=0.5 ** (18 / 14),
        late_round=8,
        late_cg_iters=8,
    ),
    "fast-multigrid-late3": dataclasses.replace(
        FAST_MULTIGRID, name="fast-multigrid-late3", late_cg_iters=3
    ),
}


def inputs(sizes: list[str], buffers: list[Path]) -> list[tuple[str, tuple[torch.Tensor, ...]]]:
    out = []
    for size in sizes:
        w, h = (int(v) for v in size.split("x"))
        _, primal, dx, dy = make_gpt_like(h, w)
        out.append((f"synthetic {w}x{h}", (primal, dx, dy)))
    for path in buffers:
        import gdpt

        b = gdpt.load_buffers(path)
        h, w = b.primal.shape[:2]
        out.append((f"{path.name} {w}x{h}", (b.primal, b.dx, b.dy)))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", nargs="*", default=["128x128", "1280x720"], help="WxH")
    ap.add_argument("--buffers", nargs="*", type=Path, default=[], help="gdpt.save_buffers files")
    ap.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--repeats", type=int, default=5, help="timed rounds (median)")
    ap.add_argument("--schedules", action="store_true", help="also the SCHEDULES variants")
    args = ap.parse_args(argv)

    solvers = {
        "l2": lambda p, dx, dy: poisson.solve_l2(p, dx, dy, return_info=True),
        "fast": lambda p, dx, dy: poisson.solve_l1(p, dx, dy, preset="fast", return_info=True),
        "fast-multigrid": lambda p, dx, dy: poisson.solve_l1(
            p, dx, dy, preset=FAST_MULTIGRID, return_info=True
        ),
    }
    if args.schedules:
        for key, preset in SCHEDULES.items():
            solvers[key] = lambda p, dx, dy, preset=preset: poisson.solve_l1(
                p, dx, dy, preset=preset, return_info=True
            )
    print(
        f"torch {torch.__version__}, median of {args.repeats} interleaved rounds after 1 "
        f"excluded warm-up round; load average before: {load_average()}\n"
    )
    print(
        "| input | threads | solver | median [s] | time / `fast` | L1 energy / `l1` "
        "| CG iterations |"
    )
    print("|---|---:|---|---:|---:|---:|---:|")
    for name, (p, dx, dy) in inputs(args.sizes, args.buffers):
        x = poisson.solve_l1(p, dx, dy, preset="l1")
        e_ref = poisson.l1_energy(x, p, dx, dy)
        for threads in args.threads:
            torch.set_num_threads(threads)
            times: dict[str, list[float]] = {k: [] for k in solvers}
            energy: dict[str, float] = {}
            iterations: dict[str, int] = {}
            for rnd in range(args.repeats + 1):
                for key, fn in solvers.items():
                    t0 = time.perf_counter()
                    x, info = fn(p, dx, dy)
                    if rnd > 0:
                        times[key].append(time.perf_counter() - t0)
                    energy[key] = poisson.l1_energy(x, p, dx, dy)
                    iterations[key] = info.cg_iterations
            base = statistics.median(times["fast"])
            for key in solvers:
                med = statistics.median(times[key])
                print(
                    f"| {name} | {threads} | {key} | {med:.3f} | {med / base:.2f} | "
                    f"{energy[key] / e_ref:.6f} | {iterations[key]} |",
                    flush=True,
                )
    print(f"\nload average after: {load_average()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
