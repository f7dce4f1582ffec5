"""Which relMSE weights make the reference-free estimate measure the study's metric?

Untimed: at fixed sample counts, per scene, renders each candidate once per replicate
(``--spp``) and an independent plain render ``P`` per replicate (``--plain-spp``, two folds of
two halves, :func:`gdpt.study.estimate.plain_render`, rendered with features for the ``oidn``
design), and scores every pair of candidates (the first the baseline) with the estimator of
:mod:`gdpt.reconstruct.reference_free` under several weight designs:

- ``own``: ``1 / (eps + L^2)`` of the baseline's output, errors against the whole ``P`` (the
  former design);
- ``plain-r0``: :func:`~gdpt.reconstruct.reference_free.plain_weights` as advise uses them,
  cross-fitted (each fold weighted by the other fold's product of its halves' luminances, each
  pixel alone: unbiased denominators, heavy-tailed weights at few samples);
- ``plain-r1``, ``plain-r2``: the same with the halves' luminances averaged over 3x3 and 5x5 px
  first (less noise, a blur at edges);
- ``median3``: ``1 / (eps + the 3x3 px median of the products)``; ``clipped``: each product
  raised to at least a quarter of that median (a floor against the heavy tail);
- ``oidn``: ``1 / (eps + L^2)`` of OIDN's denoise of the other fold (with its albedo and
  normal), cross-fitted;
- ``pooled``: ``1 / (eps + L^2)`` of the mean of the two candidates' outputs and ``P`` (symmetric
  in the candidates, not independent of their errors), errors against the whole ``P``.

The truth is the ratio of the same renders' relMSE against the reference (reference weights),
its own noise subtracted per pixel (``benchmarks/advise_agreement.py``'s ``corrected``). Per
design it prints the mean estimated ratio over replicates, its bias against the truth, in how
many replicates the estimated difference ``T_B - T_A`` has the truth's sign, how often the 95%
interval covers the truth, and the median effective blocks. Renders are cached in ``--cache``
(candidates per ``--spp``, ``P`` per ``--plain-spp``). Usage (from ``benchmarks/``)::

    ../.venv/bin/python advise_weights.py --references ../out/refs128 \\
        --scenes cornell-box random:193 --spp 32 --plain-spp 512 --replicates 4
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
from pathlib import Path

import advise_agreement as agreement
import torch
from gdpt.reconstruct.held_out import EPS
from gdpt.reconstruct.reference_free import (
    block_sums,
    cross_fitted_terms,
    error_terms,
    plain_weights,
    ratio_interval,
    relmse_weights,
)
from torch.nn import functional as F

import gdpt

DESIGNS = ("own", "plain-r0", "plain-r1", "plain-r2", "median3", "clipped", "oidn", "pooled")
CANDIDATES = ("pt+oidn-tuned", "gdpt+fuse", "pt+oidn")


def median3(image: torch.Tensor) -> torch.Tensor:
    """``image`` ``(H, W, 1)``: the median over 3x3 px (edges replicated)."""
    x = F.pad(image[..., 0][None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    return (
        x.unfold(0, 3, 1).unfold(1, 3, 1).reshape(*image.shape[:2], 9).median(-1).values[..., None]
    )


def robust_weights(half_a: torch.Tensor, half_b: torch.Tensor, design: str) -> torch.Tensor:
    """``median3``: ``1 / (eps + median3x3(L_a L_b))``; ``clipped``: the product raised to at
    least a quarter of that median."""
    product = (half_a.mean(-1, keepdim=True) * half_b.mean(-1, keepdim=True)).clamp_min(0)
    local = median3(product)
    return 1.0 / (EPS + (local if design == "median3" else torch.maximum(product, local / 4)))


def plain_folds(scene, spp: int, seed: int) -> dict:
    """``P`` as :func:`gdpt.study.estimate.plain_render` plus each fold's OIDN denoise."""
    from gdpt.oidn import oidn_denoise
    from gdpt.rendering import render
    from gdpt.study.estimate import FOLD_SEED_SALT, plain_record

    folds, denoised = [], []
    for count, fold_seed in ((spp // 2, seed), (spp - spp // 2, seed ^ FOLD_SEED_SALT)):
        b = render(
            scene.scene,
            spp=count,
            seed=fold_seed,
            max_depth=scene.max_depth,
            gradients=False,
            features=True,
            halves=True,
        )
        halves = [t.detach().to("cpu", torch.float32) for t in (b.primal_a, b.primal_b)]
        folds.append((*halves, [int(c) for c in b.metadata["half_spp"]]))
        denoised.append(oidn_denoise(b.primal, b.albedo, b.normal).cpu())
    plain = plain_record(folds)
    plain["denoised"] = denoised
    return plain


def totals(design: str, base: torch.Tensor, other: torch.Tensor, plain: dict):
    """Block sums ``(T_A, T_B)`` of the pair under ``design``."""
    folds = plain["folds"]
    images = tuple(f["image"] for f in folds)
    variances = tuple(f["variance"] for f in folds)
    if design in ("own", "pooled"):
        source = base if design == "own" else (base + other + plain["image"]) / 3
        w = relmse_weights(source)
        return [
            block_sums(error_terms(x, plain["image"], plain["variance"], w)) for x in (base, other)
        ]
    if design == "plain":
        weights = tuple(f["weights"] for f in folds)
    elif design.startswith("plain-r"):
        radius = int(design[-1])
        weights = tuple(plain_weights(*f["halves"], radius=radius) for f in folds)
    elif design in ("median3", "clipped"):
        weights = tuple(robust_weights(*f["halves"], design) for f in folds)
    else:
        weights = tuple(relmse_weights(d) for d in plain["denoised"])
    out = []
    for x in (base, other):
        t = cross_fitted_terms(x, images, variances, weights)
        out.append(block_sums(0.5 * (t[0] + t[1])))
    return out


def effective_blocks(difference: torch.Tensor) -> float:
    """How many blocks carry a difference's block sums ``d``: ``(sum |d|)^2 / sum d^2`` (``n``
    when they are alike, 1 when one carries it all): low means a heavy tail."""
    spread = float(difference.square().sum())
    return float(difference.abs().sum()) ** 2 / spread if spread > 0 else 0.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--references", type=Path, required=True)
    parser.add_argument("--scenes", nargs="+", default=["cornell-box", "random:193"])
    parser.add_argument("--spp", type=int, default=32)
    parser.add_argument("--plain-spp", type=int, default=128)
    parser.add_argument("--replicates", type=int, default=4)
    parser.add_argument("--long-side", type=int, default=128)
    parser.add_argument("--out", type=Path, default=Path("out/advise_weights.json"))
    parser.add_argument(
        "--cache", type=Path, default=Path("out/advise_weights_cache"), help="renders, reused"
    )
    args = parser.parse_args()
    gdpt.set_variant()
    from gdpt.advice import _load
    from gdpt.study.methods import EVAL_METHODS

    rows = []
    for name in args.scenes:
        source, ref_name, box = agreement.source(name)
        scene = _load(source, args.long_side, box, None)
        ref, ref_file = agreement.reference(
            args.references, ref_name, scene.resolution, scene.max_depth
        )
        ref_spp = agreement.reference_spp(ref_file)
        images = {m: [] for m in CANDIDATES}
        plains = []
        for r in range(args.replicates):
            cached = [
                args.cache / f"{ref_name}-c{args.spp}-{r}.pt",
                args.cache / f"{ref_name}-p{args.plain_spp}-{r}.pt",
            ]
            args.cache.mkdir(parents=True, exist_ok=True)
            if cached[0].exists():
                renders = torch.load(cached[0], weights_only=False)
            else:
                renders = {
                    m: EVAL_METHODS[m].run(scene, spp=args.spp, seed=1000 + r).image
                    for m in CANDIDATES
                }
                torch.save(renders, cached[0])
            if cached[1].exists():
                renders["P"] = torch.load(cached[1], weights_only=False)
            else:
                renders["P"] = plain_folds(scene, args.plain_spp, 5000 + r)
                torch.save(renders["P"], cached[1])
            for m in CANDIDATES:
                images[m].append(renders[m])
            plains.append(renders["P"])
        for base_name, other_name in itertools.combinations(CANDIDATES, 2):
            per_design = {d: [] for d in DESIGNS}
            truths = []
            for r in range(args.replicates):
                base, other = images[base_name][r], images[other_name][r]
                noise = agreement.reference_variance([plains[r]], ref_spp)
                errors = [
                    agreement.squared_error(x, ref, ref_variance=noise) for x in (base, other)
                ]
                truth = agreement.ratio(errors)
                truths.append(truth)
                for d in DESIGNS:
                    a, b = totals(d, base, other, plains[r])
                    e = ratio_interval(b, a)
                    per_design[d].append(
                        {
                            "ratio": e.ratio,
                            "sign": (float(b.sum() - a.sum()) > 0) == (errors[1] > errors[0]),
                            "covers": e.low <= truth <= e.high,
                            "effective_blocks": effective_blocks(b - a),
                            "separated_wrong": e.separated and (e.high < 1) != (truth < 1),
                        }
                    )
            truth = statistics.mean(truths)
            print(
                f"\n{name}: {other_name} / {base_name}, true corrected ratio {truth:.3f} "
                f"(per replicate {', '.join(f'{t:.3f}' for t in truths)})"
            )
            print(
                "| design | mean estimate | bias | sign agrees | covers | separated wrong "
                "| median effective blocks |"
            )
            print("|---|---:|---:|---:|---:|---:|---:|")
            for d in DESIGNS:
                rs = per_design[d]
                mean = statistics.mean(x["ratio"] for x in rs)
                print(
                    f"| {d} | {mean:.3f} | {mean - truth:+.3f} | {sum(x['sign'] for x in rs)}"
                    f"/{len(rs)} | {sum(x['covers'] for x in rs)}/{len(rs)} "
                    f"| {sum(x['separated_wrong'] for x in rs)} "
                    f"| {statistics.median(x['effective_blocks'] for x in rs):.1f} |",
                    flush=True,
                )
            rows.append(
                {
                    "scene": name,
                    "pair": [base_name, other_name],
                    "truths": truths,
                    "designs": per_design,
                }
            )
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(
            json.dumps(
                {"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows},
                indent=1,
                default=float,
            )
        )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
