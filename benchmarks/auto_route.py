"""``auto`` against ``pt+oidn-tuned`` at equal time: the route it takes and its relMSE ratio.

Runs the equal-time study (:func:`gdpt.study.evaluate.evaluate`; the two methods share the cost
calibration of the plain route, so they render the same sample counts) and prints, per scene and
budget, the routes ``auto`` took over the replicates and the geometric mean of the paired
relMSE ratios ``auto / pt+oidn-tuned`` with its 95% interval (Student t on the log ratios).
Usage::

    .venv/bin/python benchmarks/auto_route.py --out out/auto-route
        [--scenes ../shared/scenes/cornell-box ... random:202] [--budgets 2 8] [--seeds 2]
        [--resolution 128] [--reference-spp 4096]

Torch runs on ``--threads`` threads (default 1: on a machine whose 2 cores are shared, a
thread pool stalls on every small tensor operation, which made the 128 px ``fuse`` solve take
seconds). ``--spp N ...`` instead compares at fixed plain sample counts, no timing (a loaded machine
calibrates budgets to few samples): per scene, count and seed, ``auto``, the primal-only
denoiser on the same count and ``fuse`` on gradient samples of the same cost (the pilot's
measured cost ratio), each against the study's cached reference.

An interrupted run resumes (``results.json`` in ``--out``); ``--summary-only``
prints the table of an earlier run.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch

from gdpt.statistics import mean_interval
from gdpt.study.config import EvaluateConfig
from gdpt.study.evaluate import evaluate
from gdpt.study.results import read_results

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"
DEFAULT_SCENES = [
    *(str(SHARED / n) for n in ("cornell-box", "sponza", "veach-mis", "living-room-2")),
    "random:202",
]
METHODS = ("pt+oidn-tuned", "auto")


def summary(results: dict) -> list[str]:
    """Markdown table rows: scene, budget, spp of both, routes, ratio and interval."""
    rows = [
        "| scene | budget s | spp (pt+oidn-tuned / auto) | auto routes | auto s / pt s "
        "| relMSE auto / pt+oidn-tuned [95%] |",
        "|---|---:|---|---|---:|---|",
    ]
    for scene, entry in results["scenes"].items():
        methods = entry.get("methods", {})
        if not all(m in methods for m in METHODS):
            continue
        base, auto = (methods[m]["cells"] for m in METHODS)
        for key in sorted(set(base) & set(auto), key=float):
            pairs = [
                (a["metrics"]["relmse"], b["metrics"]["relmse"], a.get("route", {}))
                for a, b in zip(auto[key]["replicates"], base[key]["replicates"], strict=False)
            ]
            logs = [math.log(a / b) for a, b, _ in pairs if a and b]
            mean, low, high = mean_interval(logs) if logs else (math.nan,) * 3
            routes = ", ".join(r.get("route", "?") for _, _, r in pairs)
            seconds = auto[key]["seconds"] / max(base[key]["seconds"], 1e-9)
            rows.append(
                f"| {scene} | {key} | {base[key]['spp']} / {auto[key]['spp']} | {routes} | "
                f"{seconds:.2f} | {math.exp(mean):.3f} [{math.exp(low):.3f}, "
                f"{math.exp(high):.3f}] |"
            )
    return rows


def at_sample_counts(args: argparse.Namespace) -> list[str]:
    """Table rows of the ``--spp`` mode (see the module docstring)."""
    import gdpt
    from gdpt.adapters import FUSE_PRIMAL_SPP_FACTOR, plain_denoiser
    from gdpt.metrics import relmse
    from gdpt.study.references import reference_seed, render_reference
    from gdpt.study.scenes import load_eval_scene, resolve_scenes

    rows = [
        "| scene | plain spp | seed | auto route (reason) | auto / D | fuse / D (gradient spp) |",
        "|---|---:|---:|---|---:|---:|",
    ]
    cache = args.references or args.out / "references"
    for spec in resolve_scenes(args.scenes):
        scene = load_eval_scene(spec, resolution=args.resolution, max_depth=None)
        reference, _ = render_reference(
            scene, cache, spp=args.reference_spp, chunk_spp=256, seed=reference_seed(0)
        )
        for spp in args.spp:
            for seed in range(args.seeds):
                kwargs = {"seed": seed, "max_depth": scene.max_depth}
                auto = gdpt.render_and_denoise(scene.scene, spp=spp, **kwargs)
                plain = gdpt.render_and_denoise(
                    scene.scene, spp=spp, method=plain_denoiser(), **kwargs
                )
                cost = auto.route.cost_ratio + FUSE_PRIMAL_SPP_FACTOR
                gradient_spp = max(1, round(spp / cost))
                fuse = gdpt.render_and_denoise(
                    scene.scene, spp=gradient_spp, method="fuse", **kwargs
                )
                base = relmse(plain.image, reference)
                rows.append(
                    f"| {spec.name} | {spp} | {seed} | {auto.route.route} ({auto.route.reason}) "
                    f"| {relmse(auto.image, reference) / base:.3f} "
                    f"| {relmse(fuse.image, reference) / base:.3f} ({gradient_spp}) |"
                )
                print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/auto-route"))
    parser.add_argument("--scenes", nargs="+", default=DEFAULT_SCENES)
    parser.add_argument("--budgets", type=float, nargs="+", default=[2.0, 8.0])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--reference-spp", type=int, default=4096)
    parser.add_argument("--references", type=Path, help="reference cache (OUT/references)")
    parser.add_argument(
        "--threads", type=int, default=1, help="torch threads (1: a loaded machine's pool stalls)"
    )
    parser.add_argument("--summary-only", action="store_true")
    parser.add_argument("--spp", type=int, nargs="+", help="fixed plain sample counts, no timing")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.spp:
        print("\n".join(at_sample_counts(args)))
        return
    if not args.summary_only:
        cfg = EvaluateConfig(
            budgets=tuple(args.budgets),
            resolution=args.resolution,
            reference_spp=args.reference_spp,
            metrics=("relmse", "smape"),
            metric_options={},
            methods=METHODS,
            seeds=args.seeds,
            keep_going=True,
            reference_dir=args.references,
            profile="auto-route",
        )
        evaluate(args.scenes, args.out, cfg, progress=False, report=False)
    print("\n".join(summary(read_results(args.out / "results.json"))))


if __name__ == "__main__":
    main()
