"""What ``fuse`` costs per stage, at 128x128 and 1280x720, against OIDN alone.

Renders the built-in ``cbox-demo`` once per size as ``fuse`` reads it (``--spp`` gradient
samples, 2.5 pooled plain samples each, variances and halves), then times on those buffers, in
the order ``fuse`` runs them: OIDN alone (the ``oidn`` method, the anchor), the primal-only
network ``D``, the two half-buffer denoises, the statistics (cross-half error, edge-aware
averages: :func:`gdpt.reconstruct.fuse.fusion_statistics` on denoises already made), the solve
of the whole render (weighted CG + trust region), the two half renders' solves and the held-out
choice (the rest of :func:`~gdpt.reconstruct.fuse.fuse_checked`), and the whole ``fuse``
method. Per size and thread count (``torch.set_num_threads`` and ``drjit.set_thread_count``:
OIDN runs on Dr.Jit's pool) each stage runs once untimed (weight loading, torch's first-call
set-up), then ``--repeats`` times; medians are printed, with the ratio to OIDN alone, in wall
time and in the process's CPU time (``time.process_time``, all threads: on a machine loaded by
other jobs the CPU-time ratio is the steadier one; at 1 thread it approximates the idle
wall-time ratio). Rendering is not timed here (see ``benchmarks/method_cost.py``). The script
prints the load average::

    .venv/bin/python benchmarks/fuse_stages.py [--sizes 128x128 1280x720] [--threads 1 2]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time

import drjit as dr
import torch
from gdpt.reconstruct import fuse as F

import gdpt
from gdpt.adapters import plain_denoiser
from gdpt.buffers import gradient_half_count
from gdpt.scenes import builtin_scene


def median_seconds(fn, repeats: int) -> tuple[float, float]:
    """Median wall and CPU seconds of ``fn()`` over ``repeats`` runs after an untimed one."""
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return statistics.median(wall), statistics.median(cpu)


def stages(b: gdpt.GradientBuffers, repeats: int) -> dict[str, tuple[float, float]]:
    """Median wall and CPU seconds of each stage of ``fuse`` on the render ``b``."""
    plain, half_a, half_b = b.replace(dx=None, dy=None), b.half("a"), b.half("b")
    den = plain_denoiser()
    d = gdpt.reconstruct_image(plain, den)
    parts = {
        "full": d,
        "a": gdpt.reconstruct_image(half_a, den),
        "b": gdpt.reconstruct_image(half_b, den),
    }

    def statistics_stage():
        return F.fusion_statistics(parts.__getitem__, b.primal_a, b.primal_b, b.var_dx, b.var_dy)

    stats = statistics_stage()
    counts = gradient_half_count(b)
    scales = tuple(b.spp / n if n > 0 else math.inf for n in counts)
    halves = ((b.dx_a, b.dy_a), (b.dx_b, b.dy_b))
    solve = median_seconds(lambda: F.fuse_statistics(stats, b.dx, b.dy), repeats)
    checked = median_seconds(
        lambda: F.fuse_checked(stats, b.dx, b.dy, halves, (b.primal_a, b.primal_b), scales),
        repeats,
    )
    return {
        "oidn alone": median_seconds(lambda: gdpt.reconstruct_image(plain, "oidn"), repeats),
        f"D ({den})": median_seconds(lambda: gdpt.reconstruct_image(plain, den), repeats),
        "two half denoises": median_seconds(
            lambda: (gdpt.reconstruct_image(half_a, den), gdpt.reconstruct_image(half_b, den)),
            repeats,
        ),
        "statistics": median_seconds(statistics_stage, repeats),
        "solve": solve,
        "half solves + choice": (checked[0] - solve[0], checked[1] - solve[1]),
        "fuse (all)": median_seconds(lambda: gdpt.reconstruct_image(b, "fuse"), repeats),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["128x128", "1280x720"])
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--spp", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    variant = gdpt.set_variant()
    print(f"variant {variant}, load average {os.getloadavg()[0]:.1f}")
    for size in args.sizes:
        width, height = (int(v) for v in size.split("x"))
        scene = gdpt.load_scene(builtin_scene("cbox-demo", resolution=(width, height)))
        b = gdpt.render(
            scene, spp=args.spp, primal_spp=round(2.5 * args.spp), variance=True, halves=True
        )
        for threads in args.threads:
            torch.set_num_threads(threads)
            dr.set_thread_count(threads)
            times = stages(b, args.repeats)
            base, base_cpu = times["oidn alone"]
            load = os.getloadavg()[0]
            print(f"\n{width}x{height}, {threads} threads, load average {load:.1f}")
            print("(wall seconds, ratio to OIDN alone; CPU seconds, ratio to OIDN alone)")
            for name, (wall, cpu) in times.items():
                print(
                    f"  {name:<22} {wall:8.3f}  {wall / base:6.2f}x  {cpu:8.3f}  "
                    f"{cpu / base_cpu:6.2f}x"
                )


if __name__ == "__main__":
    main()
