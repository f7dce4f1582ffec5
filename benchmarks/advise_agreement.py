"""``gdpt advise`` against references: does its estimated ratio agree with the true one?

Per scene and budget, runs :func:`gdpt.advise` (default candidates ``pt+oidn-tuned``,
``gdpt+fuse``, ``pt+oidn``; calibrated to the budget on this machine, one render each per
replicate, one plain render ``P`` per replicate) and compares every ratio it prints (each
candidate / the baseline ``pt+oidn-tuned``: one case each) with the ratio of the *same
renders* against a reference (:func:`gdpt.metrics.relmse`, reference weights; replicates
pooled), and with the same ratio under the estimator's weights (the mean of the weights of
``P``'s six pairs of quarters, :func:`~gdpt.reconstruct.reference_free.plain_pairs`), which
separates the weights' assumption from the estimator's noise. Timed: run it on an idle machine.

Scenes: ``../shared/scenes/NAME`` (box filter, 128 px long side) or ``random:SEED`` (128 px);
``random:193`` is a room lit by a sun and sky through a window (a procedural sky with a sun
of strength 30, overcast 0.05: sunlit floor, dark corners). References from
``--references`` (one or more folders, searched in order), named like the study's cache
(``NAME-WxH-dDEPTH-<spp>spp-seed<seed>.exr``, e.g. ``cornell-box-128x128-d6-8192spp-
seed1000003.exr``; the film size and depth must match); with ``--render-missing SPP``, a
missing one is rendered into the first folder first (the study's chunked reference, seed
1000003; not timed). Usage::

    .venv/bin/python benchmarks/advise_agreement.py --references out/refs128
        [--scenes cornell-box sponza veach-mis living-room-2 random:202 random:311 random:193]
        [--budgets 4 8] [--replicates 1] [--study out/study/results.json]
        [--render-missing 8192] [--out out/advise_agreement.json]

**The reference's own noise.** A reference of ``n_r`` samples has the per-pixel variance
``v_r = sigma^2 / n_r``, which adds ``w v_r`` to every method's expected squared error
against it (``E[(X - R)^2] = (X - I)^2 + v_r`` for ``X`` independent of ``R``) and pulls the
"true" ratio toward 1 (advise's estimate subtracts ``P``'s variance, so it does not). The
corrected ratio subtracts it pixel by pixel: ``v_r`` from ``P``'s measured variance
(``sigma^2 / n_P`` per pixel, :func:`gdpt.reconstruct.reference_free.half_variance`; ``P`` is
the same plain path tracing as the reference), scaled by ``n_P / n_r`` (replicates' ``P``
averaged); ``n_r`` from the reference's name. This is the per-pixel form of the study's
``relmse-corrected`` (``benchmarks/study_summary.py``), which subtracts the same term summed
over the image, estimated from the ``pt`` cell's error. The intervals are counted against the
corrected ratio (``inside``) and, beside it, against the raw one (``inside_raw``).

**Time.** Each case records advise's seconds and their ratio to the budget per candidate
(``seconds / (budget * candidates)``; the bar: 6x at 4 s, 128 px).

With ``--study`` (a ``gdpt evaluate`` run with paired replicates of both methods on the same
scenes and budgets), each case also gets the study's verdict: ``lower``/``higher`` where the
paired 95% interval of the ratio (geometric mean over replicates,
:func:`gdpt.statistics.mean_interval` of the log ratios) excludes 1, else ``none``; advise's
verdict is the same from its own interval, and ``match`` says whether the two agree.

**Wrong recommendations.** A recommendation is counted wrong where it names a method other
than the baseline whose true corrected ratio of the same renders is above 1, or which the
study (``--study``) finds worse than the baseline (separated).

Prints one Markdown row per case, the count of cases whose interval covers the corrected and
the raw true ratio, of verdicts that match, of wrong recommendations, and the range of the
time per candidate over the budget; writes every number, the advice's report and the machine
to ``--out`` (JSON).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import time
from pathlib import Path

from gdpt.reconstruct.reference_free import relmse_weights

import gdpt
from gdpt.advice import _load
from gdpt.io.exr import load_image
from gdpt.metrics import relmse
from gdpt.statistics import mean_interval
from gdpt.study.references import reference_seed, render_reference
from gdpt.study.results import machine_info, versions

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "scenes"
SCENES = (
    "cornell-box",
    "sponza",
    "veach-mis",
    "living-room-2",
    "random:202",
    "random:311",
    "random:193",
)
BASELINE = "pt+oidn-tuned"


def source(name: str) -> tuple[str, str, bool]:
    """``(advise's scene argument, the references' name, box_filter)`` of a scene name."""
    if name.startswith(("random:", "builtin:")):
        return (
            name,
            name.split(":", 1)[1] if name.startswith("builtin:") else name.replace(":", "-"),
            False,
        )
    return str(SHARED / name / "scene.xml"), name, True


def reference(folders: list[Path] | Path, name: str, size: tuple[int, int], depth: int):
    """The reference of ``name`` at film ``size`` ``(W, H)`` and ``depth``, the first found in
    ``folders`` (finished ones: not the chunks of one being rendered)."""
    folders = [folders] if isinstance(folders, Path) else folders
    pattern = f"{name}-{size[0]}x{size[1]}-d{depth}-*spp-seed*.exr"
    for folder in folders:
        found = sorted(p for p in folder.glob(pattern) if ".chunk-" not in p.name)
        if found:
            return load_image(found[-1]), found[-1].name
    where = ", ".join(str(f) for f in folders)
    raise FileNotFoundError(
        f"no reference {name}-{size[0]}x{size[1]}-d{depth}-* in {where} (--render-missing SPP "
        "renders it)"
    )


def reference_spp(file_name: str) -> int:
    """The sample count in a reference's name (``...-8192spp-seed1000003.exr``)."""
    found = re.search(r"-(\d+)spp-", file_name)
    if found is None:
        raise ValueError(f"no sample count (-<N>spp-) in the reference's name {file_name}")
    return int(found.group(1))


def reference_variance(plains: list[dict], spp: int):
    """The reference's per-pixel variance (channel mean, ``(H, W, 1)``) from the plain renders
    ``P`` (:func:`gdpt.study.estimate.plain_render`; ``variance`` is ``sigma^2 / n_P``) for a
    reference of ``spp`` samples: ``sigma^2 / spp``, averaged over the ``P``'s."""
    scaled = [p["variance"].double() * sum(p["counts"]) / spp for p in plains]
    return sum(scaled) / len(scaled)


def squared_error(image, ref, weights=None, ref_variance=None) -> float:
    """Sum of the per-pixel relMSE terms: reference weights, else ``weights``; with
    ``ref_variance`` (``(H, W, 1)``), the reference's own noise subtracted in every pixel."""
    if weights is None and ref_variance is None:
        return relmse(image, ref) * ref.shape[0] * ref.shape[1]
    if weights is None:
        weights = relmse_weights(ref)
    squared = (image.double() - ref.double()).square().mean(-1, keepdim=True)
    if ref_variance is not None:
        squared = squared - ref_variance
    return float((weights.double() * squared).sum())


def ratio(errors: list[float]) -> float:
    """``errors[1] / errors[0]`` (``nan`` where the baseline's error is not positive, as a
    corrected one can be when the reference's noise is most of it)."""
    return errors[1] / errors[0] if errors[0] > 0 else math.nan


def covers(estimate, value: float) -> bool:
    """Whether the estimate's interval covers ``value`` (a finite one)."""
    return estimate is not None and math.isfinite(value) and estimate.low <= value <= estimate.high


def verdict(low: float, high: float) -> str:
    """``lower``/``higher`` where the interval ``[low, high]`` of a ratio excludes 1, else
    ``none``."""
    return "lower" if high < 1 else "higher" if low > 1 else "none"


def study_verdict(study: dict | None, scene: str, budget: float, method: str) -> str | None:
    """The study's verdict on ``method`` / ``BASELINE`` at ``budget`` on ``scene`` from its
    paired replicates (``None``: not in the study)."""
    if study is None:
        return None
    methods = study["scenes"].get(scene, {}).get("methods", {})
    cells = [methods.get(m, {}).get("cells", {}).get(f"{budget:g}") for m in (method, BASELINE)]
    if None in cells:
        return None
    by_seed = [{r["seed"]: r["metrics"]["relmse"] for r in c["replicates"]} for c in cells]
    logs = [math.log(by_seed[0][k] / by_seed[1][k]) for k in by_seed[0] if k in by_seed[1]]
    if len(logs) < 2:
        return None
    _, low, high = mean_interval(logs)
    return verdict(math.exp(low), math.exp(high))


def write(args: argparse.Namespace, cases: list[dict]) -> None:
    """``--out``: the machine, versions, arguments and the cases so far (JSON)."""
    args.out.parent.mkdir(parents=True, exist_ok=True)
    record = {
        "machine": machine_info(),
        "versions": versions(),
        "args": json.loads(json.dumps(vars(args), default=str)),  # paths as text
        "cases": cases,
    }
    args.out.write_text(json.dumps(record, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--references", type=Path, nargs="+", required=True)
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--budgets", type=float, nargs="+", default=[4.0, 8.0])
    parser.add_argument("--replicates", type=int, default=1)
    parser.add_argument("--long-side", type=int, default=128)
    parser.add_argument("--study", type=Path, help="results.json of a study of the same scenes")
    parser.add_argument(
        "--render-missing", type=int, metavar="SPP", help="render missing references first"
    )
    parser.add_argument("--out", type=Path, default=Path("out/advise_agreement.json"))
    args = parser.parse_args()
    study = json.loads(args.study.read_text()) if args.study else None
    gdpt.set_variant()
    if args.render_missing:  # before any timed run
        for name in args.scenes:
            scene, ref_name, box = source(name)
            loaded = _load(scene, args.long_side, box, None)
            try:
                reference(args.references, ref_name, loaded.resolution, loaded.max_depth)
            except FileNotFoundError:
                print(f"rendering the reference of {name} ({args.render_missing} spp)", flush=True)
                render_reference(
                    loaded,
                    args.references[0],
                    spp=args.render_missing,
                    chunk_spp=256,
                    seed=reference_seed(0),
                    source=scene,
                )
    cases = []
    print(
        "| scene | method | budget s | estimate | 95% interval | true, corrected | true (raw) "
        "| corrected, estimator's weights | inside corrected / raw | advise | study "
        "| recommended | spp method/tuned/P | advise s | per candidate / budget |"
    )
    print("|---|---|---:|---:|---|---:|---:|---:|---|---|---|---|---|---:|---:|")
    for budget in args.budgets:  # every scene at the first budget first
        for name in args.scenes:
            scene, ref_name, box = source(name)
            start = time.perf_counter()
            advice = gdpt.advise(
                scene,
                budget=budget,
                replicates=args.replicates,
                long_side=args.long_side,
                box_filter=box,
                progress=False,
            )
            seconds = time.perf_counter() - start
            images = advice.images
            ref, ref_file = reference(
                args.references, ref_name, advice.resolution, advice.max_depth
            )
            ref_spp = reference_spp(ref_file)
            noise = reference_variance(advice.plains, ref_spp) if advice.plains else None
            weights = [sum(q.weights for q in p["pairs"]) / len(p["pairs"]) for p in advice.plains]
            per_candidate = seconds / (budget * len(advice.methods))
            baseline = advice.methods[0]
            for method in advice.methods[1:]:
                if method.name not in images or not advice.plains:
                    continue
                pairs = [
                    list(zip(images[n], images[BASELINE], weights, strict=True))
                    for n in (BASELINE, method.name)
                ]
                true = [sum(squared_error(x, ref) for x, _, _ in p) for p in pairs]
                corrected = [
                    sum(squared_error(x, ref, ref_variance=noise) for x, _, _ in p) for p in pairs
                ]
                own = [sum(squared_error(x, ref, w, noise) for x, _, w in p) for p in pairs]
                e = method.estimate
                told = e is not None and e.bounded
                case = {
                    "scene": name,
                    "method": method.name,
                    "budget": budget,
                    "reference": ref_file,
                    "reference_spp": ref_spp,
                    "spp": {m.name: m.spp for m in advice.methods},
                    "plain_spp": advice.plain_spp,
                    "calibrations": advice.calibrations,
                    "estimate": None if e is None else [e.ratio, e.low, e.high, e.z, e.lit],
                    "true_ratio": ratio(true),
                    "true_ratio_corrected": ratio(corrected),
                    "true_ratio_corrected_estimator_weights": ratio(own),
                    "reference_noise_share": [
                        1 - c / t for c, t in zip(corrected, true, strict=True)
                    ],
                    "inside": told and covers(e, ratio(corrected)),
                    "inside_raw": told and covers(e, ratio(true)),
                    "recommended": advice.recommended,
                    "advise_verdict": verdict(e.low, e.high) if e and e.separated else "none",
                    "study_verdict": study_verdict(study, ref_name, budget, method.name),
                    "seconds": seconds,
                    "seconds_per_candidate_over_budget": per_candidate,
                    "report": advice.lines,
                }
                case["wrong_recommendation"] = advice.recommended == method.name and (
                    case["true_ratio_corrected"] > 1 or case["study_verdict"] == "higher"
                )
                cases.append(case)
                write(args, cases)  # after every case: an interrupted run keeps what it measured
                interval = "n/a" if not told else f"{e.low:.2f}-{e.high:.2f}"
                yes = lambda flag: "yes" if flag else "no"  # noqa: E731
                print(
                    f"| {name} | {method.name} | {budget:g} "
                    f"| {'n/a' if e is None else f'{e.ratio:.2f}'} | {interval} "
                    f"| {case['true_ratio_corrected']:.2f} | {case['true_ratio']:.2f} "
                    f"| {case['true_ratio_corrected_estimator_weights']:.2f} "
                    f"| {yes(case['inside'])} / {yes(case['inside_raw'])} "
                    f"| {case['advise_verdict']} | {case['study_verdict'] or 'n/a'} "
                    f"| {advice.recommended} | {method.spp}/{baseline.spp}/{advice.plain_spp} "
                    f"| {seconds:.0f} | {per_candidate:.1f}x |",
                    flush=True,
                )
    print()
    for label, key in (("corrected", "inside"), ("raw", "inside_raw")):
        inside = sum(c[key] for c in cases)
        print(f"interval covers the {label} true ratio in {inside} of {len(cases)} cases")
    compared = [c for c in cases if c["study_verdict"] is not None]
    matches = sum(c["advise_verdict"] == c["study_verdict"] for c in compared)
    print(f"advise's verdict matches the study's in {matches} of {len(compared)} cases")
    wrong = [c for c in cases if c["wrong_recommendation"]]
    print(
        f"recommendations of a method worse than {BASELINE}: {len(wrong)}"
        + "".join(f"; {c['scene']} at {c['budget']:g} s: {c['method']}" for c in wrong)
    )
    for budget in args.budgets:
        ratios = [c["seconds_per_candidate_over_budget"] for c in cases if c["budget"] == budget]
        if ratios:
            print(
                f"advise at {budget:g} s: {min(ratios):.1f}-{max(ratios):.1f}x the budget per "
                "candidate"
            )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
