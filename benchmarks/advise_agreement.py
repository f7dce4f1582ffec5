"""``gdpt advise`` against references: does its estimated ratio agree with the true one?

Per scene and budget, runs :func:`gdpt.advise` (default candidates ``pt+oidn-tuned``,
``gdpt+fuse``, ``pt+oidn``; calibrated to the budget on this machine, one render each per
replicate, one plain render ``P`` per replicate) and compares its estimated relMSE ratio
``gdpt+fuse`` / ``pt+oidn-tuned`` with the ratio of the *same renders* against a reference
(:func:`gdpt.metrics.relmse`, reference weights; replicates pooled), and with the same ratio
under the estimator's weights (the baseline's luminance), which separates the weights'
assumption from the estimator's noise. Timed: run it on an idle machine.

Scenes: ``../shared/scenes/NAME`` (box filter, 128 px long side) or ``random:SEED`` (128 px);
references from ``--references``, named like the study's cache
(``NAME-WxH-dDEPTH-<spp>spp-seed<seed>.exr``, e.g. ``cornell-box-128x128-d6-8192spp-
seed1000003.exr``; the film size and depth must match). Usage::

    .venv/bin/python benchmarks/advise_agreement.py --references out/refs128
        [--scenes cornell-box sponza veach-mis living-room-2 random:202 random:311]
        [--budgets 4 8] [--replicates 1] [--study out/study/results.json]
        [--out out/advise_agreement.json]

With ``--study`` (a ``gdpt evaluate`` run with paired replicates of both methods on the same
scenes and budgets), each case also gets the study's verdict: ``lower``/``higher`` where the
paired 95% interval of the ratio (geometric mean over replicates,
:func:`gdpt.statistics.mean_interval` of the log ratios) excludes 1, else ``none``; advise's
verdict is the same from its own interval, and ``match`` says whether the two agree.

Prints one Markdown row per case, the count of cases whose interval covers the true ratio and
of verdicts that match; writes every number, the advice's report and the machine to ``--out``
(JSON).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from gdpt.reconstruct.reference_free import relmse_weights

import gdpt
from gdpt.io.exr import load_image
from gdpt.metrics import relmse
from gdpt.statistics import mean_interval
from gdpt.study.results import machine_info, versions

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "scenes"
SCENES = ("cornell-box", "sponza", "veach-mis", "living-room-2", "random:202", "random:311")
BASELINE, CANDIDATE = "pt+oidn-tuned", "gdpt+fuse"


def source(name: str) -> tuple[str, str, bool]:
    """``(advise's scene argument, the references' name, box_filter)`` of a scene name."""
    if name.startswith(("random:", "builtin:")):
        return (
            name,
            name.split(":", 1)[1] if name.startswith("builtin:") else name.replace(":", "-"),
            False,
        )
    return str(SHARED / name / "scene.xml"), name, True


def reference(folder: Path, name: str, size: tuple[int, int], depth: int):
    """The reference of ``name`` at film ``size`` ``(W, H)`` and ``depth`` in ``folder``."""
    found = sorted(folder.glob(f"{name}-{size[0]}x{size[1]}-d{depth}-*spp-seed*.exr"))
    if not found:
        raise FileNotFoundError(f"no reference {name}-{size[0]}x{size[1]}-d{depth}-* in {folder}")
    return load_image(found[-1]), found[-1].name


def squared_error(image, ref, weights=None) -> float:
    """Sum of the per-pixel relMSE terms: reference weights, else ``weights``."""
    if weights is None:
        return relmse(image, ref) * ref.shape[0] * ref.shape[1]
    return float((weights * (image - ref).square().mean(-1, keepdim=True)).sum())


def verdict(low: float, high: float) -> str:
    """``lower``/``higher`` where the interval ``[low, high]`` of a ratio excludes 1, else
    ``none``."""
    return "lower" if high < 1 else "higher" if low > 1 else "none"


def study_verdict(study: dict | None, scene: str, budget: float) -> str | None:
    """The study's verdict on ``CANDIDATE`` / ``BASELINE`` at ``budget`` on ``scene`` from its
    paired replicates (``None``: not in the study)."""
    if study is None:
        return None
    methods = study["scenes"].get(scene, {}).get("methods", {})
    cells = [methods.get(m, {}).get("cells", {}).get(f"{budget:g}") for m in (CANDIDATE, BASELINE)]
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
        "args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
        "cases": cases,
    }
    args.out.write_text(json.dumps(record, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--references", type=Path, required=True)
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--budgets", type=float, nargs="+", default=[4.0, 8.0])
    parser.add_argument("--replicates", type=int, default=1)
    parser.add_argument("--long-side", type=int, default=128)
    parser.add_argument("--study", type=Path, help="results.json of a study of the same scenes")
    parser.add_argument("--out", type=Path, default=Path("out/advise_agreement.json"))
    args = parser.parse_args()
    study = json.loads(args.study.read_text()) if args.study else None
    gdpt.set_variant()
    cases = []
    print(
        "| scene | budget s | estimate | 95% interval | true | true (estimator's weights) "
        "| inside | advise | study | recommended | spp tuned/fuse/P | advise s |"
    )
    print("|---|---:|---:|---|---:|---:|---|---|---|---|---|---:|")
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
            fuse = next(m for m in advice.methods if m.name == CANDIDATE)
            images = advice.images
            ref, ref_file = reference(
                args.references, ref_name, advice.resolution, advice.max_depth
            )
            true = [sum(squared_error(x, ref) for x in images[n]) for n in (BASELINE, CANDIDATE)]
            own = [
                sum(
                    squared_error(x, ref, relmse_weights(b))
                    for x, b in zip(images[n], images[BASELINE], strict=True)
                )
                for n in (BASELINE, CANDIDATE)
            ]
            e = fuse.estimate
            case = {
                "scene": name,
                "budget": budget,
                "reference": ref_file,
                "spp": {m.name: m.spp for m in advice.methods},
                "plain_spp": advice.plain_spp,
                "estimate": None if e is None else [e.ratio, e.low, e.high, e.z],
                "true_ratio": true[1] / true[0],
                "true_ratio_estimator_weights": own[1] / own[0],
                "inside": e is not None and e.low <= true[1] / true[0] <= e.high,
                "recommended": advice.recommended,
                "advise_verdict": "none" if e is None else verdict(e.low, e.high),
                "study_verdict": study_verdict(study, ref_name, budget),
                "seconds": seconds,
                "report": advice.lines,
            }
            cases.append(case)
            write(args, cases)  # after every case: an interrupted run keeps what it measured
            interval = "n/a" if e is None else f"{e.low:.2f}-{e.high:.2f}"
            print(
                f"| {name} | {budget:g} | {'n/a' if e is None else f'{e.ratio:.2f}'} | {interval} "
                f"| {case['true_ratio']:.2f} | {case['true_ratio_estimator_weights']:.2f} "
                f"| {'yes' if case['inside'] else 'no'} | {case['advise_verdict']} "
                f"| {case['study_verdict'] or 'n/a'} | {advice.recommended} "
                f"| {case['spp'][BASELINE]}/{fuse.spp}/{advice.plain_spp} | {seconds:.0f} |",
                flush=True,
            )
    inside = sum(c["inside"] for c in cases)
    print(f"\ninterval covers the true ratio in {inside} of {len(cases)} cases")
    compared = [c for c in cases if c["study_verdict"] is not None]
    matches = sum(c["advise_verdict"] == c["study_verdict"] for c in compared)
    print(f"advise's verdict matches the study's in {matches} of {len(compared)} cases")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
