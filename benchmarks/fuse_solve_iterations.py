"""How many CG iterations ``fuse``'s solves should run: relMSE of ``fuse`` over its ``D`` per
iteration cap, paired on the same renders.

Per scene, gradient sample count and seed: one render as ``fuse`` reads it (as
``benchmarks/fuse_safety.py``), its statistics once (:func:`gdpt.reconstruct.fuse.fusion_statistics`
through the shipped denoiser), then :func:`~gdpt.reconstruct.fuse.fuse_checked` with each
``--iterations`` cap (all three solves), relMSE against the cached path-traced reference over
``D``'s; geometric mean over the seeds, and the iterations the whole render's solve took at the
largest cap. The renders' untraced gradients are filled as the ``fuse`` method fills them
(:func:`gdpt.buffers.fill_untraced`). The last line gives, per cap, the worst single render
(the safety bar of ``benchmarks/fuse_safety.py``: ``fuse`` <= 1.03x its ``D``). Usage::

    .venv/bin/python benchmarks/fuse_solve_iterations.py --scenes cornell-box sponza \\
        veach-mis living-room-2 --spp 16 64 --seeds 2 --iterations 100 50 30 20

    # the 48 renders of the safety table
    .venv/bin/python benchmarks/fuse_solve_iterations.py --scenes cornell-box sponza \\
        veach-mis living-room-2 staircase matpreview-dof room:202 room:311 \\
        --spp 16 64 256 --seeds 2 --iterations 30 20
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from fuse_safety import fuse_input, geomean, load, reference
from gdpt.reconstruct import fuse as F

import gdpt
from gdpt.adapters import fusion_statistics_of
from gdpt.buffers import fill_untraced, gradient_half_count
from gdpt.methods import primal_only
from gdpt.metrics import relmse


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["cornell-box", "sponza", "veach-mis"])
    parser.add_argument("--spp", nargs="+", type=int, default=[16, 64])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--iterations", nargs="+", type=int, default=[100, 50, 30, 20])
    parser.add_argument("--reference-spp", type=int, default=4096)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/fuse_safety/refs"))
    args = parser.parse_args()
    gdpt.set_variant()
    name_d, denoise = primal_only()
    print(f"D = {name_d}; references {args.reference_spp} spp; relMSE(fuse) / relMSE(D)")
    print("| scene | grad spp | " + " | ".join(f"{n} its" for n in args.iterations) + " | its |")
    print("|---|---:|" + "---:|" * (len(args.iterations) + 1))
    worst = {n: (0.0, "") for n in args.iterations}
    for name in args.scenes:
        scene, depth = load(name)
        ref = reference(name, scene, depth, args.reference_spp, args.cache)
        for spp in args.spp:
            ratios = {n: [] for n in args.iterations}
            used = []
            for seed in range(args.seeds):
                b = fill_untraced(fuse_input(scene, spp, seed + 1, depth), 0.0, 0.0)
                stats = fusion_statistics_of(b, denoise)
                counts = gradient_half_count(b)
                scales = tuple(b.spp / n if n > 0 else math.inf for n in counts)
                halves = ((b.dx_a, b.dy_a), (b.dx_b, b.dy_b))
                base = relmse(stats.denoised, ref)
                for n in args.iterations:
                    image, info = F.fuse_checked(
                        stats, b.dx, b.dy, halves, (b.primal_a, b.primal_b), scales, iterations=n
                    )
                    ratios[n].append(relmse(image, ref) / base)
                    if ratios[n][-1] > worst[n][0]:
                        worst[n] = (ratios[n][-1], f"{name} {spp} spp seed {seed + 1}")
                    if n == max(args.iterations):
                        used.append(info.cg_iterations)
            cells = " | ".join(f"{geomean(ratios[n]):.3f}" for n in args.iterations)
            print(f"| {name} | {spp} | {cells} | {used} |", flush=True)
    print("worst render: " + "; ".join(f"{n} its {r:.3f} ({at})" for n, (r, at) in worst.items()))


if __name__ == "__main__":
    main()
