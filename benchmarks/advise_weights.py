"""Which weights and pairings make the reference-free estimate measure the study's metric?

Untimed: at fixed sample counts, per scene, renders each candidate once per replicate
(``--spp``) and an independent plain render ``P`` per replicate (``--plain-spp``, two folds of
two halves: four quarters, :func:`gdpt.study.estimate.plain_render`, rendered with features for
the ``oidn`` design), and scores every pair of candidates (the first the baseline) with the
estimator of :mod:`gdpt.reconstruct.reference_free` under several designs. ``folds-*``: each
fold's terms weighted by the other fold (two pairs of quarters, the estimator before the six
pairs), with the weights

- ``folds``: :func:`~gdpt.reconstruct.reference_free.plain_weights`, each pixel alone;
  ``folds-cap64``: each product raised to at least 1/64 of the product of the halves' 3x3 px
  mean luminances (a floor tied to the neighbourhood: the weight at most 64 times that of the
  3x3 means);
- ``folds-r1``, ``folds-r2``: the halves' luminances averaged over 3x3 and 5x5 px first;
- ``folds-median3``: ``1 / (eps + the 3x3 px median of the products)``; ``folds-clipped``: each
  product raised to at least a quarter of that median (a local floor against the heavy tail);
- ``folds-floor-q05``: each product raised to at least the square of the 5% quantile of the
  fold's luminance (a global floor: the darkest 5% of pixels weighed as that quantile);
  ``folds-floor-m10``: to at least ``(0.1 mean luminance)^2``;
- ``folds-oidn``: ``1 / (eps + L^2)`` of OIDN's denoise of the other fold (with its albedo and
  normal);
- ``folds-reference``: the reference's own weights (an oracle: what no weight design can beat);

``pairs``: all six pairs of quarters, each weighted by the other two
(:func:`~gdpt.reconstruct.reference_free.plain_pairs`, what advise uses), ``pairs-cap64``
and ``pairs-r1`` with the weights of ``folds-cap64`` and ``folds-r1``, and ``pairs-reference``
with the reference's weights; ``own``: ``1 / (eps + L^2)`` of the
baseline's output, errors against the whole ``P`` (the first design); ``pooled``: of the mean
of the two candidates' outputs and ``P`` (symmetric in the candidates, not independent of
their errors).

The truth is the ratio of the same renders' relMSE against the reference (reference weights),
its own noise subtracted per pixel (``benchmarks/advise_agreement.py``'s ``corrected``); beside
it, the same with the reference's weights capped (``cap64`` of the reference as both halves:
the cap's bias alone). Per
design it prints the mean estimated ratio over replicates, its bias against the truth, in how
many replicates the estimated difference ``T_B - T_A`` has the truth's sign, how many 95%
intervals are bounded, how many cover the truth (an unbounded one does not count), the wrong
separated verdicts, and the median effective blocks. Renders are cached in ``--cache``
(candidates per ``--spp``, ``P``'s halves per ``--plain-spp``). Usage (from the repository
root)::

    .venv/bin/python benchmarks/advise_weights.py --references /work/refs128 \
        --scenes random:193 --spp 512 --plain-spp 512 --replicates 4
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
    PAIRS,
    PlainPair,
    block_sums,
    cross_fitted_terms,
    error_terms,
    plain_weights,
    ratio_interval,
    relmse_weights,
)
from torch.nn import functional as F

import gdpt

DESIGNS = (
    "own",
    "pooled",
    "folds",
    "folds-cap64",
    "folds-r1",
    "folds-r2",
    "folds-median3",
    "folds-clipped",
    "folds-floor-q05",
    "folds-floor-m10",
    "folds-oidn",
    "folds-reference",
    "pairs",
    "pairs-cap64",
    "pairs-r1",
    "pairs-reference",
)
CANDIDATES = ("pt+oidn-tuned", "gdpt+fuse", "pt+oidn")


def median3(image: torch.Tensor) -> torch.Tensor:
    """``image`` ``(H, W, 1)``: the median over 3x3 px (edges replicated)."""
    x = F.pad(image[..., 0][None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    return (
        x.unfold(0, 3, 1).unfold(1, 3, 1).reshape(*image.shape[:2], 9).median(-1).values[..., None]
    )


def robust_weights(half_a: torch.Tensor, half_b: torch.Tensor, design: str) -> torch.Tensor:
    """``median3``: ``1 / (eps + median3x3(L_a L_b))``; ``clipped``: the product raised to at
    least a quarter of that median; ``floor-q05``: to at least the square of the 5% quantile
    of ``(L_a + L_b) / 2``; ``floor-m10``: to at least ``(0.1 mean((L_a + L_b) / 2))^2``;
    ``cap64``: to at least ``box3x3(L_a) box3x3(L_b) / 64``."""
    luminance = [h.mean(-1, keepdim=True) for h in (half_a, half_b)]
    product = (luminance[0] * luminance[1]).clamp_min(0)
    pooled = 0.5 * (luminance[0] + luminance[1])
    if design == "floor-q05":
        return 1.0 / (EPS + product.clamp_min(float(pooled.flatten().quantile(0.05)) ** 2))
    if design == "floor-m10":
        return 1.0 / (EPS + product.clamp_min((0.1 * float(pooled.mean())) ** 2))
    if design == "cap64":
        box = [
            F.avg_pool2d(F.pad(x[..., 0][None, None], (1,) * 4, mode="replicate"), 3, stride=1)
            for x in luminance
        ]
        return 1.0 / (EPS + torch.maximum(product, (box[0] * box[1])[0, 0, ..., None] / 64))
    local = median3(product)
    return 1.0 / (EPS + (local if design == "median3" else torch.maximum(product, local / 4)))


def plain_folds(scene, spp: int, seed: int) -> dict:
    """``P``'s folds' halves and counts (as :func:`gdpt.study.estimate.plain_render` renders
    them) and each fold's OIDN denoise: ``{"folds": [{"halves", "counts"}] * 2, "denoised"}``."""
    from gdpt.oidn import oidn_denoise
    from gdpt.rendering import render
    from gdpt.study.estimate import FOLD_SEED_SALT

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
    return {"folds": [{"halves": f[:2], "counts": f[2]} for f in folds], "denoised": denoised}


def pair_weights(design: str, quarters: list, pair: tuple[int, int], ref: torch.Tensor):
    """The weights of ``pair`` of quarters under a ``pairs-*`` design (from its complement)."""
    if design == "pairs-reference":
        return relmse_weights(ref)
    k, m = (q for q in range(4) if q not in pair)
    if design == "pairs-cap64":
        return robust_weights(quarters[k], quarters[m], "cap64")
    return plain_weights(quarters[k], quarters[m], radius=1)


def totals(design: str, base: torch.Tensor, other: torch.Tensor, plain: dict, ref: torch.Tensor):
    """Block sums ``(T_A, T_B)`` of the pair under ``design``."""
    if design in ("own", "pooled"):
        source = base if design == "own" else (base + other + plain["image"]) / 3
        w = relmse_weights(source)
        return [
            block_sums(error_terms(x, plain["image"], plain["variance"], w)) for x in (base, other)
        ]
    if design.startswith("pairs"):
        pairs = plain["pairs"]
        if design != "pairs":
            quarters = [h for f in plain["folds"] for h in f["halves"]]
            pairs = [
                PlainPair(p.image, p.variance, pair_weights(design, quarters, pair, ref))
                for p, pair in zip(pairs, PAIRS, strict=True)
            ]
    else:
        folds = plain["folds"]
        kind = design.removeprefix("folds").removeprefix("-")
        if kind in ("", "r1", "r2"):
            radius = int(kind[-1]) if kind else 0
            weights = [plain_weights(*f["halves"], radius=radius) for f in folds]
        elif kind == "oidn":
            weights = [relmse_weights(d) for d in plain["denoised"]]
        elif kind == "reference":
            weights = [relmse_weights(ref)] * 2
        else:
            weights = [robust_weights(*f["halves"], kind) for f in folds]
        pairs = [  # each fold weighted by the other
            PlainPair(f["image"], f["variance"], w)
            for f, w in zip(folds, weights[::-1], strict=True)
        ]
    out = []
    for x in (base, other):
        t = cross_fitted_terms(x, pairs)
        out.append(block_sums(sum(t) / len(t)))
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
    from gdpt.study.estimate import plain_record
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
            if not cached[1].exists():
                torch.save(plain_folds(scene, args.plain_spp, 5000 + r), cached[1])
            loaded = torch.load(cached[1], weights_only=False)
            renders["P"] = plain_record([(*f["halves"], f["counts"]) for f in loaded["folds"]])
            renders["P"]["denoised"] = loaded["denoised"]
            for m in CANDIDATES:
                images[m].append(renders[m])
            plains.append(renders["P"])
        for base_name, other_name in itertools.combinations(CANDIDATES, 2):
            per_design = {d: [] for d in DESIGNS}
            truths, capped_truths = [], []
            capped = robust_weights(ref, ref, "cap64")  # the cap alone: the reference as both
            for r in range(args.replicates):
                base, other = images[base_name][r], images[other_name][r]
                noise = agreement.reference_variance([plains[r]], ref_spp)
                errors = [
                    agreement.squared_error(x, ref, ref_variance=noise) for x in (base, other)
                ]
                truth = agreement.ratio(errors)
                truths.append(truth)
                capped_truths.append(
                    agreement.ratio(
                        [agreement.squared_error(x, ref, capped, noise) for x in (base, other)]
                    )
                )
                for d in DESIGNS:
                    a, b = totals(d, base, other, plains[r], ref)
                    e = ratio_interval(b, a)
                    per_design[d].append(
                        {
                            "ratio": e.ratio,
                            "sign": (float(b.sum() - a.sum()) > 0) == (errors[1] > errors[0]),
                            "bounded": e.bounded,
                            "covers": e.bounded and e.low <= truth <= e.high,
                            "effective_blocks": effective_blocks(b - a),
                            "separated_wrong": e.separated and (e.high < 1) != (truth < 1),
                        }
                    )
            truth = statistics.mean(truths)
            print(
                f"\n{name}: {other_name} / {base_name}, true corrected ratio {truth:.3f} "
                f"(per replicate {', '.join(f'{t:.3f}' for t in truths)}; with the capped "
                f"reference weights {', '.join(f'{t:.3f}' for t in capped_truths)})"
            )
            print(
                "| design | mean estimate | bias | sign agrees | bounded | covers "
                "| separated wrong | median effective blocks |"
            )
            print("|---|---:|---:|---:|---:|---:|---:|---:|")
            for d in DESIGNS:
                rs = per_design[d]
                mean = statistics.mean(x["ratio"] for x in rs)
                print(
                    f"| {d} | {mean:.3f} | {mean - truth:+.3f} | {sum(x['sign'] for x in rs)}"
                    f"/{len(rs)} | {sum(x['bounded'] for x in rs)}/{len(rs)} "
                    f"| {sum(x['covers'] for x in rs)}/{len(rs)} "
                    f"| {sum(x['separated_wrong'] for x in rs)} "
                    f"| {statistics.median(x['effective_blocks'] for x in rs):.1f} |",
                    flush=True,
                )
            rows.append(
                {
                    "scene": name,
                    "pair": [base_name, other_name],
                    "truths": truths,
                    "capped_truths": capped_truths,
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
