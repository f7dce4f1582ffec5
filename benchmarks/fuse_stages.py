"""What ``fuse`` costs per stage, at 128x128 and 1280x720, against OIDN alone.

Renders the built-in ``cbox-demo`` once per size as ``fuse`` reads it (``--spp`` gradient
samples, 2.5 pooled plain samples each, variances and halves), then times on those buffers:
OIDN alone (the ``oidn`` method), the primal-only network ``D``, the two half-buffer denoises,
the statistics (cross-half error, edge-aware averages), the solve (weighted CG + trust region),
and the whole ``fuse`` method. Each stage runs once untimed (weight loading, torch's first-call
set-up), then ``--repeats`` times; medians are printed, with the ratio to OIDN alone. Rendering
is not timed here (see ``benchmarks/method_cost.py``). On a shared machine use one thread
(``--threads 1``: torch's and Dr.Jit's, whose pool runs OIDN, as ``benchmarks/cost_table.py``
does); the script prints the thread counts and the load average::

    .venv/bin/python benchmarks/fuse_stages.py --threads 1 [--sizes 128x128 1280x720]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import torch
from gdpt.reconstruct import fuse as F

import gdpt
from gdpt.adapters import plain_denoiser
from gdpt.scenes import builtin_scene


def median_seconds(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def stages(width: int, height: int, spp: int, repeats: int) -> dict[str, float]:
    scene = gdpt.load_scene(builtin_scene("cbox-demo", resolution=(width, height)))
    b = gdpt.render(scene, spp=spp, primal_spp=round(2.5 * spp), variance=True, halves=True)
    plain, half_a, half_b = b.replace(dx=None, dy=None), b.half("a"), b.half("b")
    den = plain_denoiser()
    d = gdpt.reconstruct_image(plain, den)
    d_a, d_b = gdpt.reconstruct_image(half_a, den), gdpt.reconstruct_image(half_b, den)
    guide = F.log_luminance(d)

    def statistics_stage():
        raw = F.cross_half_error(d_a, d_b, b.primal_a, b.primal_b, radius=0)
        F.edge_aware_mean(raw, guide, F.ERROR_RADIUS, F.GUIDE_SIGMA)
        F.edge_aware_mean(b.var_dx, guide, F.VARIANCE_RADIUS, F.GUIDE_SIGMA)
        F.edge_aware_mean(b.var_dy, guide, F.VARIANCE_RADIUS, F.GUIDE_SIGMA)

    error = F.ERROR_SCALE * F.edge_aware_mean(
        F.cross_half_error(d_a, d_b, b.primal_a, b.primal_b, radius=0),
        guide,
        F.ERROR_RADIUS,
        F.GUIDE_SIGMA,
    )
    v_x = F.edge_aware_mean(b.var_dx, guide, F.VARIANCE_RADIUS, F.GUIDE_SIGMA)
    v_y = F.edge_aware_mean(b.var_dy, guide, F.VARIANCE_RADIUS, F.GUIDE_SIGMA)
    floor = max(1e-4 * float(d.mean(-1).square().mean()), 1e-12)
    return {
        "oidn alone": median_seconds(lambda: gdpt.reconstruct_image(plain, "oidn"), repeats),
        f"D ({den})": median_seconds(lambda: gdpt.reconstruct_image(plain, den), repeats),
        "two half denoises": median_seconds(
            lambda: (gdpt.reconstruct_image(half_a, den), gdpt.reconstruct_image(half_b, den)),
            repeats,
        ),
        "statistics": median_seconds(statistics_stage, repeats),
        "solve": median_seconds(
            lambda: F.fuse(d, b.dx, b.dy, v_x, v_y, error, error_floor=floor), repeats
        ),
        "fuse (all)": median_seconds(lambda: gdpt.reconstruct_image(b, "fuse"), repeats),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["128x128", "1280x720"])
    parser.add_argument("--spp", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--threads", type=int, help="torch and Dr.Jit threads (default: their own defaults)"
    )
    args = parser.parse_args()
    if args.threads is not None and args.threads < 1:
        parser.error("--threads must be >= 1")
    variant = gdpt.set_variant()
    import drjit as dr

    if args.threads is not None:
        torch.set_num_threads(args.threads)
        dr.set_thread_count(args.threads)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"variant {variant}, threads: torch {torch.get_num_threads()}, "
        f"Dr.Jit {dr.thread_count()}; load {load:.1f}"
    )
    for size in args.sizes:
        width, height = (int(v) for v in size.split("x"))
        times = stages(width, height, args.spp, args.repeats)
        base = times["oidn alone"]
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
        print(f"\n{width}x{height} (seconds, ratio to OIDN alone; load {load:.1f} at end)")
        for name, seconds in times.items():
            print(f"  {name:<22} {seconds:8.3f}  {seconds / base:6.2f}x")


if __name__ == "__main__":
    main()
