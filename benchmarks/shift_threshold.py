"""Gradient error and L1-reconstruction error of ``gdpt`` against its ``shift_threshold``.

On the built-in ``near-specular`` scene (rough glass alpha 0.03, rough mirror alpha 0.02) the
default threshold (0.001) reconnects at those vertices; thresholds above 0.02 / 0.03 copy the
base's half vector through them instead. For each threshold: the mean squared error of ``dx`` /
``dy`` against forward differences of a converged ``path`` reference, relMSE of the L1
reconstruction, and the render time (median of ``--repeats`` seeds, interleaved; kernel
compilation excluded by a warm-up render). Writes a table (stdout), optional JSON and a plot.
Usage::

    .venv/bin/python benchmarks/shift_threshold.py [--resolution 64] [--spp 16]
        [--thresholds 0.001 0.025 0.05 0.2] [--reference-spp 8192] [--png PATH] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default="near-specular")
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--max-depth", type=int, default=6)
    parser.add_argument("--thresholds", type=float, nargs="+", default=[0.001, 0.025, 0.05, 0.2])
    parser.add_argument("--reference-spp", type=int, default=8192)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--png", type=Path)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()

    import drjit as dr
    import mitsuba as mi

    import gdpt
    from gdpt.metrics import relmse
    from gdpt.scenes import builtin_scene
    from gdpt.scenes.loading import load_scene

    gdpt.set_variant()
    scene = load_scene(builtin_scene(args.scene, resolution=(args.resolution,) * 2))
    path = mi.load_dict({"type": "path", "max_depth": args.max_depth})
    ref = np.array(mi.render(scene, integrator=path, spp=args.reference_spp, seed=12345))
    ref_dx, ref_dy = ref[:, 1:] - ref[:, :-1], ref[1:] - ref[:-1]

    def run(threshold: float, seed: int):
        start = time.perf_counter()
        b = gdpt.render(
            scene,
            spp=args.spp,
            seed=seed,
            max_depth=args.max_depth,
            features=False,
            shift_threshold=threshold,
        )
        dr.sync_thread()
        return time.perf_counter() - start, b

    for t in args.thresholds:  # compile every variant once
        run(t, 0)
    stats = {t: {"seconds": [], "mse_grad": [], "relmse_l1": []} for t in args.thresholds}
    for r in range(args.repeats):
        for t in args.thresholds:
            seconds, b = run(t, 1 + r)
            dx, dy = b.dx.numpy()[:, :-1], b.dy.numpy()[:-1]
            mse = 0.5 * (np.mean((dx - ref_dx) ** 2) + np.mean((dy - ref_dy) ** 2))
            image = gdpt.reconstruct_image(b, method="l1").cpu()
            import torch

            stats[t]["seconds"].append(seconds)
            stats[t]["mse_grad"].append(float(mse))
            stats[t]["relmse_l1"].append(relmse(image, torch.from_numpy(ref)))
    rows = []
    for t, s in stats.items():
        rows.append({"threshold": t, **{k: statistics.median(v) for k, v in s.items()}})
    base = rows[0]
    print(
        f"\n{args.scene}, {args.resolution} px, {args.spp} spp, max_depth {args.max_depth}, "
        f"median of {args.repeats} seeds; reference: path {args.reference_spp} spp\n"
    )
    print("| shift_threshold | gradient MSE | ratio | L1 relMSE | ratio | render s | ratio |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['threshold']:g} | {r['mse_grad']:.3e} | {r['mse_grad'] / base['mse_grad']:.2f} "
            f"| {r['relmse_l1']:.3e} | {r['relmse_l1'] / base['relmse_l1']:.2f} "
            f"| {r['seconds']:.3f} | {r['seconds'] / base['seconds']:.2f} |"
        )
    if args.json:
        args.json.write_text(
            json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}, indent=2)
        )
    if args.png:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        ts = [r["threshold"] for r in rows]
        fig, ax = plt.subplots(figsize=(5, 3.2))
        ax.plot(ts, [r["mse_grad"] / base["mse_grad"] for r in rows], "o-", label="gradient MSE")
        ax.plot(
            ts,
            [r["relmse_l1"] / base["relmse_l1"] for r in rows],
            "s-",
            label="L1 reconstruction relMSE",
        )
        ax.set_xscale("log")
        ax.set_xlabel("shift_threshold")
        ax.set_ylabel(f"relative to {base['threshold']:g}")
        ax.set_title(f"{args.scene}, {args.spp} spp")
        ax.grid(True, alpha=0.3)
        ax.legend()
        fig.tight_layout()
        fig.savefig(args.png, dpi=120)


if __name__ == "__main__":
    main()
