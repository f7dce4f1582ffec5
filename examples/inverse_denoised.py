"""Inverse rendering through a denoiser: recover the ceiling light's radiance of the built-in
Cornell box from a reference image, with and without differentiable denoising, at equal time per
iteration.

    .venv/bin/python examples/inverse_denoised.py [--tiny] [--size 128] [--seconds 90]
        [--spp 4] [--out out/inverse_denoised]

The light is hidden from the camera (``hide_emitters``), so its radiance shows only through the
light it sheds, which the renders estimate with noise. Four runs start from the same radiance
and minimise the mean squared error to a high-sample reference with Adam (``mi.ad.Adam``),
each for ``--seconds`` of wall time:

* ``low``: ``--spp`` samples per pixel, the image as rendered (``prb``; the adjoint pass with
  other random numbers, Mitsuba's default);
* ``low+oidn-tuned``: the same samples reconstructed by the fine-tuned OIDN network,
  differentiated with it (:func:`gdpt.render_differentiable`; the adjoint pass replays the
  primal's paths, its default with a network);
* ``low+oidn-tuned decorr.``: the same with Mitsuba's decorrelated adjoint pass;
* ``high``: no denoiser, and as many samples as make an iteration cost what one of
  ``low+oidn-tuned`` costs (measured here first).

The radiance does not change the features the network reads (albedo, normal, depth), so the
gradient through the denoiser is exact here (for an albedo it would omit the features' share).
It prints a table (seconds per iteration, iterations, final relative error of the radiance and
its median over the second half of the run, time to reach a tenth of the starting error,
largest over median gradient) and writes
``results.json`` and, if matplotlib is installed, ``curves.png`` (loss and radiance error
against wall time) to ``--out``. ``--tiny`` (or ``GDPT_EXAMPLE_TINY=1``) runs a 32 px image
for a few iterations, for tests.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

import gdpt
from gdpt.scenes.loading import load_scene

#: The optimised parameter and its start value (the scene's truth is 20, 15.5, 10).
KEY = "light.emitter.radiance.value"
START = (8.0, 8.0, 8.0)
METHOD = "oidn-tuned"
MAX_DEPTH = 6


def integrator():
    """``prb`` with the light hidden from the camera."""
    return mi.load_dict({"type": "prb", "max_depth": MAX_DEPTH, "hide_emitters": True})


def render(scene, params, spp: int, seed: int, method: str | None, replay: bool):
    """The run's image of one iteration (attached to ``params``); ``replay``: the adjoint pass
    replays the primal's paths, else it uses other random numbers (Mitsuba's default)."""
    return gdpt.render_differentiable(
        scene, params, spp=spp, seed=seed, seed_grad=seed if replay else 0, method=method,
        integrator=integrator(), max_depth=MAX_DEPTH,
    )  # fmt: skip


def relative_error(value, truth) -> float:
    """RMS over the channels of ``(value - truth) / truth``."""
    return float((((value - truth) / truth) ** 2).mean() ** 0.5)


def optimise(
    scene, reference, truth, *, spp: int, method: str | None, replay: bool, seconds: float,
    iterations: int, lr: float,
) -> list[dict]:  # fmt: skip
    """Adam on :data:`KEY` from :data:`START` until ``seconds`` or ``iterations`` are spent.

    Returns one record per iteration: wall time since the start (after one untimed warm-up
    iteration that compiles the kernels), its duration (``step``), loss, relative error of the
    radiance and the loss gradient w.r.t. it.
    """
    params = mi.traverse(scene)
    records = []
    for warm_up in (True, False):
        params[KEY] = mi.Color3f(START)
        params.update()
        opt = mi.ad.Adam(lr=lr)
        opt[KEY] = params[KEY]
        params.update(opt)
        start = time.perf_counter()
        for it in range(1 if warm_up else iterations):
            begin = time.perf_counter()
            seed = it + (10_000 if warm_up else 1)
            image = render(scene, params, spp, seed, method, replay)
            loss = dr.mean(dr.square(image - reference), axis=None)
            dr.backward(loss)
            grad = dr.grad(opt[KEY]).numpy().ravel()
            opt.step()
            opt[KEY] = dr.maximum(opt[KEY], 0.0)
            params.update(opt)
            value = params[KEY].numpy().ravel()
            dr.sync_thread()
            if warm_up:
                break
            error = relative_error(value, truth)
            now = time.perf_counter()
            records.append(
                {"seconds": now - start, "step": now - begin, "loss": float(loss.array[0]),
                 "error": error, "gradient": grad.tolist()}
            )  # fmt: skip
            if records[-1]["seconds"] > seconds:
                break
    return records


def seconds_per_iteration(scene, reference, spp: int, method: str | None, lr: float) -> float:
    """Median duration of three timed iterations (after a warm-up)."""
    records = optimise(
        scene, reference, START, spp=spp, method=method, replay=method is not None,
        seconds=1e9, iterations=3, lr=lr,
    )  # fmt: skip
    return sorted(r["step"] for r in records)[1]


def equal_time_spp(scene, reference, spp: int, lr: float) -> int:
    """Samples per pixel of an undenoised iteration that takes as long as a denoised one at
    ``spp``: a proportional guess, then one secant step on the measured times."""
    target = seconds_per_iteration(scene, reference, spp, METHOD, lr)
    low = seconds_per_iteration(scene, reference, spp, None, lr)
    guess = max(spp + 1, round(spp * target / low))
    slope = (seconds_per_iteration(scene, reference, guess, None, lr) - low) / (guess - spp)
    return max(spp, round(spp + (target - low) / slope)) if slope > 0 else guess


def gradient_tail(records: list[dict]) -> float:
    """Largest over median gradient magnitude (over iterations, channels pooled): how heavy
    the tail of the gradient estimates is."""
    g = np.abs(np.array([r["gradient"] for r in records]))
    return float(g.max() / max(np.median(g), 1e-30))


def floor(records: list[dict]) -> float:
    """Median radiance error over the second half of the run (where it fluctuates)."""
    return float(np.median([r["error"] for r in records[len(records) // 2 :]]))


def first_time_below(records: list[dict], threshold: float) -> float | None:
    """Wall time of the first iteration whose radiance error is at most ``threshold``."""
    return next((r["seconds"] for r in records if r["error"] <= threshold), None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tiny", action="store_true", help="32 px, a few iterations (tests)")
    parser.add_argument("--size", type=int, default=128, help="film side in pixels")
    parser.add_argument("--spp", type=int, default=4, help="samples per pixel of the low runs")
    parser.add_argument("--seconds", type=float, default=90.0, help="wall time per run")
    parser.add_argument("--iterations", type=int, default=10_000, help="iteration cap per run")
    parser.add_argument("--lr", type=float, default=0.5, help="Adam learning rate")
    parser.add_argument("--reference-spp", type=int, default=1024)
    parser.add_argument(
        "--threads", type=int, default=0, help="CPU threads of Dr.Jit and torch (0: all)"
    )
    parser.add_argument("--out", type=Path, default=Path("out/inverse_denoised"))
    args = parser.parse_args()
    if args.tiny or os.environ.get("GDPT_EXAMPLE_TINY") == "1":
        args.size, args.iterations, args.reference_spp = 32, 6, 64

    variant = gdpt.set_variant()
    if args.threads:
        import torch

        dr.set_thread_count(args.threads)
        torch.set_num_threads(args.threads)
    scene = load_scene("builtin:cbox-demo", long_side=args.size)
    truth = mi.traverse(scene)[KEY].numpy().ravel().copy()
    reference = mi.render(scene, integrator=integrator(), spp=args.reference_spp, seed=2**20)

    high_spp = equal_time_spp(scene, reference, args.spp, args.lr)

    runs = {
        "low": (args.spp, None, False),
        f"low+{METHOD}": (args.spp, METHOD, True),
        f"low+{METHOD} decorr.": (args.spp, METHOD, False),
        "high": (high_spp, None, False),
    }
    results = {}
    for name, (spp, method, replay) in runs.items():
        records = optimise(
            scene, reference, truth, spp=spp, method=method, replay=replay,
            seconds=args.seconds, iterations=args.iterations, lr=args.lr,
        )  # fmt: skip
        results[name] = {"spp": spp, "method": method, "replay": replay, "records": records}

    start_error = relative_error(np.asarray(START), truth)
    threshold = 0.1 * start_error
    print(f"{variant}, {args.size} px, relative radiance error at the start {start_error:.3f}")
    reach_head = f"t(err<={threshold:.3f})"
    print(
        f"{'run':<25} {'spp':>5} {'s/it':>6} {'its':>5} {'error':>7} {'floor':>7} "
        f"{reach_head:>14} {'grad max/median':>15}"
    )
    for name, run in results.items():
        recs = run["records"]
        per_it = recs[-1]["seconds"] / len(recs)
        reach = first_time_below(recs, threshold)
        tail = gradient_tail(recs)
        run.update(
            seconds_per_iteration=per_it, time_to_threshold=reach, gradient_tail=tail,
            floor=floor(recs),
        )  # fmt: skip
        reach_text = f"{reach:.1f} s" if reach is not None else "not reached"
        print(
            f"{name:<25} {run['spp']:>5} {per_it:>6.2f} {len(recs):>5} "
            f"{recs[-1]['error']:>7.4f} {run['floor']:>7.4f} {reach_text:>14} {tail:>15.1f}"
        )

    args.out.mkdir(parents=True, exist_ok=True)
    summary = {
        "variant": variant,
        "size": args.size,
        "parameter": KEY,
        "truth": truth.tolist(),
        "start": list(START),
        "threshold": threshold,
        "runs": results,
    }
    (args.out / "results.json").write_text(json.dumps(summary, indent=1))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print(f"wrote {args.out}/results.json (matplotlib is not installed: no plot)")
        return
    fig, (ax_loss, ax_err) = plt.subplots(1, 2, figsize=(10, 3.8))
    for name, run in results.items():
        t = [r["seconds"] for r in run["records"]]
        label = f"{name} ({run['spp']} spp)"
        ax_loss.semilogy(t, [r["loss"] for r in run["records"]], label=label)
        ax_err.semilogy(t, [r["error"] for r in run["records"]], label=label)
    ax_err.axhline(threshold, color="grey", lw=0.8, ls="--")
    ax_loss.set(xlabel="wall time [s]", ylabel="loss (MSE of the run's image)")
    ax_err.set(xlabel="wall time [s]", ylabel="relative radiance error")
    ax_err.legend()
    fig.tight_layout()
    fig.savefig(args.out / "curves.png", dpi=120)
    print(f"wrote {args.out}/results.json and {args.out}/curves.png")


if __name__ == "__main__":
    main()
