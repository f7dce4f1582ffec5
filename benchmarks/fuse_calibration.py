"""How well ``fuse``'s statistics predict, on scenes it may be tuned on (procedural and built-in).

Per scene and gradient sample count: renders ``fuse``'s input (pooled, variances, halves) and a
path-traced reference, denoises with the primal-only network, and prints

* the cross-half error estimate against the true error of ``D``: log-correlation of the
  edge-aware averages and the ratio of their means (``true / estimate``);
* the spread of the two half denoises (variance only) against the true error, the same way;
* relative MSE of ``fuse`` over ``D`` (the same input, so < 1 means the gradients helped),
  with the estimated error and with the true error (an oracle bound);
* the per-pixel predicted gain (:func:`gdpt.reconstruct.fuse.predicted_gain`), optimistic by
  10-26x here (:mod:`gdpt.auto_route` uses only its ratio between two sample counts).

No timing (run it on a busy machine). Usage::

    .venv/bin/python benchmarks/fuse_calibration.py [--scenes builtin:cbox-demo random:5]
        [--spp 8 32] [--reference-spp 2048]
"""

from __future__ import annotations

import argparse

import torch
from gdpt.reconstruct import fuse as F

import gdpt
from gdpt.adapters import plain_denoiser
from gdpt.metrics import relmse
from gdpt.study.scenes import load_eval_scene, resolve_scenes


def log_corr(a: torch.Tensor, b: torch.Tensor) -> float:
    ok = (a > 0) & (b > 0)
    return float(torch.corrcoef(torch.stack([a[ok].log(), b[ok].log()]))[0, 1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["builtin:cbox-demo", "random:5"])
    parser.add_argument("--spp", nargs="+", type=int, default=[8, 32])
    parser.add_argument("--reference-spp", type=int, default=2048)
    parser.add_argument("--resolution", type=int, default=128)
    args = parser.parse_args()
    gdpt.set_variant()
    den = plain_denoiser()
    print(f"denoiser {den}; reference {args.reference_spp} spp path tracing")
    for source in args.scenes:
        scene = load_eval_scene(resolve_scenes([source])[0], resolution=args.resolution)
        depth = scene.max_depth
        ref = gdpt.render(
            scene.scene, spp=args.reference_spp, seed=99, max_depth=depth, gradients=False
        ).primal.clone()
        for spp in args.spp:
            b = gdpt.render(
                scene.scene,
                spp=spp,
                seed=1,
                primal_spp=round(2.5 * spp),
                variance=True,
                halves=True,
                max_depth=depth,
            )
            d = gdpt.reconstruct_image(b.replace(dx=None, dy=None), den)
            d_a = gdpt.reconstruct_image(b.half("a"), den)
            d_b = gdpt.reconstruct_image(b.half("b"), den)
            guide = F.log_luminance(d)

            def smooth(x, guide=guide):
                return F.edge_aware_mean(x, guide, F.ERROR_RADIUS, F.GUIDE_SIGMA)

            true = (d - ref).square().mean(-1, keepdim=True)
            cross = smooth(F.cross_half_error(d_a, d_b, b.primal_a, b.primal_b, radius=0))
            spread = smooth(((d_a - d_b).square() / 4).mean(-1, keepdim=True))
            fused, _ = F.fuse_halves(
                d, d_a, d_b, b.primal_a, b.primal_b, b.dx, b.dy, b.var_dx, b.var_dy
            )
            v_x = F.edge_aware_mean(b.var_dx, guide, F.VARIANCE_RADIUS, F.GUIDE_SIGMA)
            v_y = F.edge_aware_mean(b.var_dy, guide, F.VARIANCE_RADIUS, F.GUIDE_SIGMA)
            oracle, _ = F.fuse(d, b.dx, b.dy, v_x, v_y, smooth(true), error_floor=1e-12)
            floor = max(1e-4 * float(d.mean(-1).square().mean()), 1e-12)
            predicted = F.predicted_gain(d, (F.ERROR_SCALE * cross).clamp_min(floor), v_x, v_y)
            base = relmse(d, ref)
            print(
                f"{source} {spp} spp: cross-half logcorr {log_corr(cross, smooth(true)):.2f} "
                f"true/est {float(true.mean() / cross.clamp_min(0).mean()):.2f}; spread logcorr "
                f"{log_corr(spread, smooth(true)):.2f} true/est "
                f"{float(true.mean() / spread.mean()):.2f}; fuse/D {relmse(fused, ref) / base:.3f} "
                f"(oracle error {relmse(oracle, ref) / base:.3f}); predicted gain "
                f"{predicted:.3f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
