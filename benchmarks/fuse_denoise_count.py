"""Does ``fuse`` need three denoises? Two-denoise designs against the shipped three, paired.

Per scene, gradient sample count and seed: one render as ``fuse`` reads it (as
``benchmarks/fuse_safety.py``), its three primal-only denoises (the whole render ``D``, the
halves ``D_a``, ``D_b``), then, on that one render, relMSE against the cached path-traced
reference of:

* ``D``: the whole render's denoise (what ``fuse`` falls back to);
* ``three``: ``fuse`` as shipped (:func:`gdpt.reconstruct.fuse.fuse_checked` on
  :func:`~gdpt.reconstruct.fuse.fusion_statistics`: ``D``, ``D_a``, ``D_b``);
* ``halves``: ``D`` replaced by the mean of the half denoises ``(D_a + D_b) / 2`` (no third
  denoise), the error of that mean taken as ``--mean-error-scale`` times a half's (between
  0.5, variance only, and 1, bias only), the same held-out choice with that mean as the
  fallback;
* ``one half``: ``D`` and ``D_a`` only: the cross-half error and the held-out terms from one
  direction (``D_a`` against ``P_b``) instead of both.

Also printed: relMSE of the mean of the half denoises over ``D``'s, and its measured error over
a half denoise's (what ``--mean-error-scale`` should be). Geometric means over the seeds.
Usage::

    .venv/bin/python benchmarks/fuse_denoise_count.py --scenes cornell-box sponza veach-mis \\
        living-room-2 --spp 16 64 --seeds 2
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch
from fuse_safety import fuse_input, geomean, load, reference
from gdpt.reconstruct import fuse as F
from gdpt.reconstruct import held_out

import gdpt
from gdpt.adapters import fusion_statistics_of
from gdpt.methods import primal_only
from gdpt.metrics import relmse


def mse(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).square().mean())


def checked(stats, b, choice_terms=None):
    """``fuse_checked`` of ``stats`` on render ``b`` (``choice_terms``: replace the held-out
    terms by these, for the one-direction design)."""
    counts = b.metadata["gradient_half_spp"]
    scales = tuple(b.spp / n if n > 0 else math.inf for n in counts)
    halves = ((b.dx_a, b.dy_a), (b.dx_b, b.dy_b))
    if choice_terms is None:
        return F.fuse_checked(stats, b.dx, b.dy, halves, (b.primal_a, b.primal_b), scales)[0]
    image, _ = F.fuse_statistics(stats, b.dx, b.dy)
    terms, nonfinite = choice_terms
    choice = held_out.choose(
        terms,
        tile=F.CHECK_TILE,
        margin=F.CHECK_MARGIN,
        block=F.CHECK_BLOCK,
        image_margin=F.CHECK_IMAGE_MARGIN,
        nonfinite=nonfinite,
    )
    return held_out.apply(image, stats.denoised, choice)


def one_half(b, d: torch.Tensor, d_a: torch.Tensor):
    """The ``one half`` design: statistics from ``D`` and ``D_a``, held-out terms of half ``a``
    against ``P_b`` only."""
    guide = F.log_luminance(d)
    raw = ((d_a - b.primal_b).square() - 0.5 * (b.primal_a - b.primal_b).square()).mean(
        -1, keepdim=True
    )
    error = F.ERROR_SCALE * F.edge_aware_mean(raw, guide, F.ERROR_RADIUS, F.GUIDE_SIGMA)
    v_x, v_y = (
        F.average_finite(v, guide, F.VARIANCE_RADIUS, F.GUIDE_SIGMA) for v in (b.var_dx, b.var_dy)
    )
    floor = max(1e-4 * float(d.mean(-1).square().mean()), 1e-12)
    stats = F.FusionStatistics(d, error, floor, v_x, v_y, (d_a, d_a))
    counts = b.metadata["gradient_half_spp"]
    half = F.half_statistics(stats, 0, b.spp / counts[0] if counts[0] > 0 else math.inf)
    f_a, _ = F.fuse_statistics(half, b.dx_a, b.dy_a)
    lum = d.mean(-1, keepdim=True)
    raw_terms = ((f_a - d_a) * (f_a + d_a - 2.0 * b.primal_b)).mean(-1, keepdim=True)
    terms = raw_terms / (held_out.EPS + lum.square())
    finite = torch.isfinite(terms)
    return checked(stats, b, (torch.where(finite, terms, 0.0), int((~finite).sum())))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["cornell-box", "sponza", "veach-mis"])
    parser.add_argument("--spp", nargs="+", type=int, default=[16, 64])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--reference-spp", type=int, default=4096)
    parser.add_argument("--mean-error-scale", type=float, default=0.75)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/fuse_safety/refs"))
    args = parser.parse_args()
    gdpt.set_variant()
    name_d, denoise = primal_only()
    print(f"D = {name_d}; references {args.reference_spp} spp; relMSE ratios, geometric mean")
    columns = ["three / D", "halves / D", "one half / D", "halves / three", "one half / three"]
    extra = ["mean(D_a,D_b) / D", "err mean / err half"]
    print("| scene | grad spp | " + " | ".join(columns + extra) + " |")
    print("|---|---:|" + "---:|" * (len(columns) + len(extra)))
    for name in args.scenes:
        scene, depth = load(name)
        ref = reference(name, scene, depth, args.reference_spp, args.cache)
        for spp in args.spp:
            rows = {c: [] for c in columns + extra}
            for seed in range(args.seeds):
                b = fuse_input(scene, spp, seed + 1, depth)
                stats = fusion_statistics_of(b, denoise)
                d = stats.denoised
                d_a, d_b = stats.denoised_halves
                three = checked(stats, b)
                mean = 0.5 * (d_a + d_b)
                parts = {"full": mean, "a": d_a, "b": d_b}
                stats_mean = F.fusion_statistics(
                    parts.__getitem__,
                    b.primal_a,
                    b.primal_b,
                    b.var_dx,
                    b.var_dy,
                    error_scale=args.mean_error_scale,
                )
                halves = checked(stats_mean, b)
                single = one_half(b, d, d_a)
                base = relmse(d, ref)
                r3, rh, r1 = (relmse(x, ref) / base for x in (three, halves, single))
                rows["three / D"].append(r3)
                rows["halves / D"].append(rh)
                rows["one half / D"].append(r1)
                rows["halves / three"].append(rh / r3)
                rows["one half / three"].append(r1 / r3)
                rows["mean(D_a,D_b) / D"].append(relmse(mean, ref) / base)
                half_err = 0.5 * (mse(d_a, ref) + mse(d_b, ref))
                rows["err mean / err half"].append(mse(mean, ref) / half_err)
            cells = " | ".join(f"{geomean(rows[c]):.3f}" for c in columns + extra)
            print(f"| {name} | {spp} | {cells} |", flush=True)


if __name__ == "__main__":
    main()
