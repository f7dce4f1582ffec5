"""The study's reference-free estimate: each method's relMSE ratio to ``pt+oidn-tuned`` from an
independent plain render instead of a reference (:mod:`gdpt.reconstruct.reference_free`).

Shared by :func:`gdpt.advise` and the study: :func:`plain_render` renders the plain image ``P``
(two independent folds of two halves each: four quarters, each of whose six pairs is weighted
by the other two, weights that favour no method), :func:`estimate_ratios` scores images of the
same scene against it. In the study (:func:`estimate_scene`), per scene and budget, one ``P`` with
the ``pt`` cell's sample count (else the baseline's) scores the first replicate of every
method; with a reference the cell records the estimate beside the true ratio of the same renders
(the study's ``relmse``), so that every study run checks the estimator; without one
(``gdpt evaluate --no-reference``) the estimate is the result. ``P``'s seed is
``cell_seed(seed, scene, budget, "plain")``, independent of every replicate's.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch

    from gdpt.reconstruct.reference_free import RatioEstimate
    from gdpt.study.config import EvaluateConfig
    from gdpt.study.scenes import EvalScene

__all__ = [
    "BASELINE",
    "MIN_PLAIN_SPP",
    "estimate_ratios",
    "estimate_scene",
    "markdown",
    "plain_record",
    "plain_render",
]

#: The method every estimated ratio is relative to.
BASELINE = "pt+oidn-tuned"

#: Fewest samples per pixel of ``P``: each of its four quarters needs one.
MIN_PLAIN_SPP = 4

#: Mixed into ``P``'s seed for its second fold (independent of the first's samples).
FOLD_SEED_SALT = 0x5BD1E995


def few_pass_sizes(spp: int, bits: int = 3) -> int:
    """``spp`` rounded down to its ``bits`` highest set bits (at most a quarter fewer samples):
    a render splits its count into passes whose sizes are powers of two below a full pass
    (:func:`gdpt.integrators.common.plan_passes`), each size traced once per integrator, so
    ``P`` (an integrator of its own) traces at most ``bits`` of them (about 1 s each on a
    room at 128 px)."""
    kept = 0
    for _ in range(bits):
        if spp <= kept:
            break
        kept |= 1 << ((spp - kept).bit_length() - 1)
    return max(1, kept)


def plain_render(scene: EvalScene, spp: int, seed: int) -> dict[str, Any]:
    """``P``: plain path tracing (``gdpt``, no gradients, no features) at ``spp`` in two
    independent folds (seeds ``seed`` and ``seed ^ FOLD_SEED_SALT``) of two halves each
    (:mod:`gdpt.reconstruct.reference_free`).

    Returns:
        ``{"image": (H, W, 3) the folds pooled, "variance": (H, W, 1) its variance,
        "counts": the folds' sample counts, "folds": two {"image": (H, W, 3), "variance":
        (H, W, 1) (:func:`~gdpt.reconstruct.reference_free.half_variance`), "halves": two
        (H, W, 3), "counts": two ints}, "pairs": the six
        :func:`~gdpt.reconstruct.reference_free.plain_pairs` of the four halves}``, float32
        on the CPU.

    Raises:
        ValueError: ``spp <`` :data:`MIN_PLAIN_SPP` (a quarter without samples).
    """
    import torch

    from gdpt.rendering import render

    if spp < MIN_PLAIN_SPP:
        raise ValueError(
            f"P would have {spp} sample{'s' if spp != 1 else ''} per pixel: its variance and "
            f"weights need at least {MIN_PLAIN_SPP} (two folds of two halves)"
        )
    folds = []
    for count, fold_seed in ((spp // 2, seed), (spp - spp // 2, seed ^ FOLD_SEED_SALT)):
        buffers = render(
            scene.scene,
            spp=count,
            seed=fold_seed,
            max_depth=scene.max_depth,
            gradients=False,
            features=False,
            halves=True,
        )
        halves = [t.detach().to("cpu", torch.float32) for t in (buffers.primal_a, buffers.primal_b)]
        folds.append((*halves, [int(c) for c in buffers.metadata["half_spp"]]))
    return plain_record(folds)


def plain_record(folds: list[tuple[torch.Tensor, torch.Tensor, list[int]]]) -> dict[str, Any]:
    """The record of :func:`plain_render` from two folds' ``(half_a, half_b, counts)``
    (``(H, W, 3)`` half means, their sample counts; float32 on the CPU)."""
    from gdpt.reconstruct.reference_free import half_variance, plain_pairs

    records = []
    for half_a, half_b, counts in folds:
        records.append(
            {
                "image": (counts[0] * half_a + counts[1] * half_b) / sum(counts),
                "variance": half_variance(half_a, half_b, *counts),
                "halves": (half_a, half_b),
                "counts": list(counts),
            }
        )
    counts = [sum(f["counts"]) for f in records]
    n = sum(counts)
    return {
        "image": sum(c * f["image"] for c, f in zip(counts, records, strict=True)) / n,
        "variance": sum(c * c * f["variance"] for c, f in zip(counts, records, strict=True)) / n**2,
        "counts": counts,
        "folds": records,
        "pairs": plain_pairs(
            [h for f in records for h in f["halves"]], [c for f in records for c in f["counts"]]
        ),
    }


def estimate_ratios(
    images: list[list[torch.Tensor]], plains: list[dict[str, Any]]
) -> list[tuple[RatioEstimate, float]]:
    """Each method's relMSE ratio to the first, and ``P``'s share of its variance.

    Args:
        images: ``images[m][r]``: method ``m``'s ``(H, W, 3)`` float image of replicate ``r``
            (CPU); ``images[0]`` is the baseline.
        plains: one :func:`plain_render` per replicate, independent of every image (its
            pairs' weights score every method alike).

    Returns:
        For ``images[1:]``, in order: the :class:`~gdpt.reconstruct.reference_free.
        RatioEstimate` (block sums of the replicates pooled) and
        :func:`~gdpt.reconstruct.reference_free.plain_share`.
    """
    import torch

    from gdpt.reconstruct.reference_free import (
        block_sums,
        cross_fitted_terms,
        lit_blocks,
        plain_share,
        ratio_interval,
    )

    baseline = [cross_fitted_terms(x, p["pairs"]) for x, p in zip(images[0], plains, strict=True)]
    lit = torch.cat([lit_blocks(plain["image"]) for plain in plains])
    out = []
    for method in images[1:]:
        scored = [cross_fitted_terms(x, p["pairs"]) for x, p in zip(method, plains, strict=True)]
        full = [
            torch.cat([block_sums(sum(t) / len(t)) for t in group]) for group in (baseline, scored)
        ]
        estimate = ratio_interval(full[1], full[0], lit=lit)
        rho = estimate.ratio
        folds = [
            torch.cat(
                [block_sums(b[k] - rho * a[k]) for a, b in zip(baseline, scored, strict=True)]
            )
            for k in range(2)  # the first two pairs: the folds (PAIRS)
        ]
        out.append((estimate, plain_share(*folds, full[1] - rho * full[0])))
    return out


def _record(estimate: RatioEstimate, share: float, plain_spp: int) -> dict[str, Any]:
    finite = lambda v: v if math.isfinite(v) else None  # noqa: E731 (JSON has no inf/nan)
    return {
        "baseline": BASELINE,
        "ratio": finite(estimate.ratio),
        "interval": [finite(estimate.low), finite(estimate.high)],
        "z": finite(estimate.z),
        "separated": estimate.separated,
        "lit_blocks": estimate.lit,
        "plain_share": finite(share),
        "plain_spp": plain_spp,
    }


def estimate_scene(
    scene: EvalScene, entry: dict[str, Any], cfg: EvaluateConfig, out: Path, bar: Any = None
) -> None:
    """Record ``cell["estimate"]`` in every cell of ``entry`` (a scene of ``results.json``)
    that lacks one, per budget where :data:`BASELINE` has a cell: the estimated ratio of the
    cell's first replicate (its saved image) to the baseline's, its interval, ``z``,
    ``separated``, ``lit_blocks``, ``plain_share``, ``plain_spp``, and with a reference
    ``true_ratio``: the ratio of the two first replicates' ``relmse``."""
    from gdpt.io.exr import load_image
    from gdpt.study.results import budget_key, cell_seed

    methods = entry.get("methods", {})
    for budget in cfg.budgets:
        key = budget_key(budget)
        base = methods.get(BASELINE, {}).get("cells", {}).get(key)
        if base is None:
            continue
        todo = {}
        for name, info in methods.items():
            cell = info.get("cells", {}).get(key)
            if name != BASELINE and cell is not None and "estimate" not in cell:
                todo[name] = cell
        if not todo:
            continue
        if bar is not None:
            bar.set_postfix_str(f"{scene.name}: estimate at {key} s")
        spp = methods.get("pt", {}).get("cells", {}).get(key, base)["spp"]
        if spp < MIN_PLAIN_SPP:
            for cell in todo.values():
                cell["estimate"] = {
                    "note": f"P would have {spp} spp: its variance and weights need {MIN_PLAIN_SPP}"
                }
            continue
        plain = plain_render(scene, spp, cell_seed(cfg.seed, scene.name, key, "plain"))
        images = [load_image(out / base["image"])]
        images += [load_image(out / cell["image"]) for cell in todo.values()]
        for cell, (estimate, share) in zip(
            todo.values(), estimate_ratios([[i] for i in images], [plain]), strict=True
        ):
            cell["estimate"] = _record(estimate, share, spp)
            true = [c["replicates"][0]["metrics"].get("relmse") for c in (cell, base)]
            if None not in true and true[1] > 0:
                cell["estimate"]["true_ratio"] = true[0] / true[1]


def markdown(entry: dict[str, Any]) -> list[str]:
    """Lines of a Markdown table of the scene's estimates (none: ``[]``)."""
    rows = []
    for name, info in entry.get("methods", {}).items():
        for key, cell in info.get("cells", {}).items():
            e = cell.get("estimate")
            if not e or "ratio" not in e:
                continue
            low, high = e["interval"]
            interval = "unbounded" if low is None or high is None else f"{low:.2f}-{high:.2f}"
            true = e.get("true_ratio")
            inside = "" if true is None or low is None else ("yes" if low <= true <= high else "no")
            rows.append(
                f"| {name} | {key} | {e['ratio']:.3f} | {interval} | "
                f"{'n/a' if true is None else f'{true:.3f}'} | {inside} | {e['plain_spp']} |"
            )
    if not rows:
        return []
    return [
        f"Reference-free estimate of the relMSE ratio to `{BASELINE}` (one plain render P per "
        "budget; 95% Fieller interval from 8 px block sums; `gdpt.advise`):",
        "",
        "| method | budget s | estimate | 95% interval | true ratio | inside | P spp |",
        "|---|---|---:|---|---:|---|---:|",
        *rows,
    ]
