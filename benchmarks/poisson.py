"""Benchmark of the screened-Poisson solvers (gdpt.reconstruct.poisson) on a G-PT-like input.

Times the exact L2 solve (DCT), the reference L1 schedule (preset ``"l1"`` = L1D: 20 IRLS
rounds x 50 CG iterations) and the accelerated L1 preset (``"fast"``), and reports the final L1
energy of both L1 solvers. Each timing is the median (and IQR) of ``--repeats`` runs after one
excluded warm-up run. The torch thread count is left at torch's default unless ``--threads`` is
given.

Usage::

    .venv/bin/python benchmarks/poisson.py                 # 1280x720 RGB, Markdown table
    .venv/bin/python benchmarks/poisson.py --json benchmarks/results/poisson.json
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gdpt.reconstruct import poisson

from gdpt.machine import cpu_name


def make_gpt_like(
    height: int, width: int, *, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Synthetic G-PT-like buffers: ``(reference, primal, dx, dy)``, HWC float32 on the CPU.

    The reference is piecewise smooth with hard-edged discs, a fine texture and a small very
    bright emitter. The primal has heteroscedastic noise (std ~ 0.5 sqrt(I)) plus 0.2% fireflies;
    the gradients have 5x less noise (the G-PT variance reduction) plus 0.3% large outliers
    (failed shifts), which is the regime where L1 beats L2.
    """
    rng = np.random.default_rng(seed)
    yy, xx = np.meshgrid(np.linspace(0, 1, height), np.linspace(0, 1, width), indexing="ij")
    img = np.stack(
        [0.4 + 0.3 * np.sin(3 * xx + 1) * np.cos(2 * yy), 0.3 + 0.2 * xx, 0.5 - 0.3 * yy], -1
    )
    aspect = width / height
    for _ in range(12):
        cx, cy, r = rng.random(3)
        disc = (xx - cx) ** 2 * aspect**2 + (yy - cy) ** 2 < (0.15 * r) ** 2
        img[disc] = 2.0 * rng.random(3)
    img[(xx - 0.8) ** 2 + (yy - 0.15) ** 2 < 0.003] = (20.0, 18.0, 15.0)
    img *= (1.0 + 0.1 * np.sin(40 * xx) * np.sin(30 * yy))[..., None]

    dx = np.zeros_like(img)
    dy = np.zeros_like(img)
    dx[:, :-1] = img[:, 1:] - img[:, :-1]
    dy[:-1] = img[1:] - img[:-1]
    std = np.sqrt(np.maximum(img, 0.05))
    primal = img + 0.5 * std * rng.standard_normal(img.shape)
    primal += (rng.random((height, width, 1)) < 0.002) * 30.0 * rng.random((height, width, 1))
    for d in (dx, dy):
        d += 0.1 * std * rng.standard_normal(img.shape)
        outlier = rng.random((height, width, 1)) < 0.003
        d += outlier * 20.0 * rng.standard_normal((height, width, 1))
    ref_t, primal_t, dx_t, dy_t = (
        torch.from_numpy(a.astype(np.float32)) for a in (img, primal, dx, dy)
    )
    return ref_t, primal_t, dx_t, dy_t


def time_runs(fn: Callable[[], Any], repeats: int) -> tuple[list[float], Any]:
    """One warm-up call (excluded), then ``repeats`` timed calls; returns (seconds, last result)."""
    out = fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return times, out


def summary(times: list[float]) -> dict[str, float]:
    q = np.percentile(times, [25, 50, 75])
    return {"median_s": float(q[1]), "iqr_s": float(q[2] - q[0]), "min_s": float(min(times))}


def git_commit() -> str | None:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
            cwd=Path(__file__).resolve().parent,
        )
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def load_average() -> list[float] | None:
    try:
        return [float(v) for v in Path("/proc/loadavg").read_text().split()[:3]]
    except (OSError, ValueError):
        return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per solver (median)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--alpha", type=float, default=poisson.DEFAULT_ALPHA)
    ap.add_argument(
        "--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)"
    )
    ap.add_argument("--json", type=Path, default=None, help="also write results + metadata here")
    args = ap.parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)

    ref, primal, dx, dy = make_gpt_like(args.height, args.width, seed=args.seed)
    alpha = args.alpha
    load_before = load_average()

    rows: dict[str, dict[str, Any]] = {}
    t, x = time_runs(lambda: poisson.solve_l2(primal, dx, dy, alpha=alpha), args.repeats)
    rows["l2"] = {
        **summary(t),
        "times_s": t,
        "l2_energy": poisson.l2_energy(x, primal, dx, dy, alpha=alpha),
        "l1_energy": poisson.l1_energy(x, primal, dx, dy, alpha=alpha),
        "cg_iterations": 0,
        "rmse_vs_reference": float((x - ref).square().mean().sqrt()),
    }
    for name in ("l1", "fast"):
        t, (x, info) = time_runs(
            lambda name=name: poisson.solve_l1(
                primal, dx, dy, alpha=alpha, preset=name, return_info=True
            ),
            args.repeats,
        )
        rows[name] = {
            **summary(t),
            "times_s": t,
            "l1_energy": poisson.l1_energy(x, primal, dx, dy, alpha=alpha),
            "cg_iterations": info.cg_iterations,
            "rmse_vs_reference": float((x - ref).square().mean().sqrt()),
        }
    load_after = load_average()

    e_ref, e_fast = rows["l1"]["l1_energy"], rows["fast"]["l1_energy"]
    speedup = rows["l1"]["median_s"] / rows["fast"]["median_s"]
    print(
        f"Screened Poisson, {args.width}x{args.height} RGB, alpha={alpha}, "
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, {cpu_name()}, "
        f"median of {args.repeats} runs after 1 warm-up (load avg before/after: "
        f"{load_before} / {load_after})\n"
    )
    print(
        "| solver | median time [s] | IQR [s] | min [s] | CG iterations | final L1 energy "
        "| L1 energy / `l1` | RMSE vs. clean image |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    r = rows["l2"]
    labels = {"l2": "L2 exact (DCT)", "l1": "L1 preset `l1` (ref. L1D)", "fast": "L1 preset `fast`"}
    for name, label in labels.items():
        r = rows[name]
        print(
            f"| {label} | {r['median_s']:.3f} | {r['iqr_s']:.3f} | {r['min_s']:.3f} | "
            f"{r['cg_iterations']} | "
            f"{r['l1_energy']:.1f} | {r['l1_energy'] / e_ref:.6f} | {r['rmse_vs_reference']:.4f} |"
        )
    print(
        f"\nspeed-up `fast` vs `l1`: {speedup:.1f}x; L1 energy change "
        f"{(e_fast - e_ref) / e_ref:+.2e} (relative; negative = `fast` lower)"
    )

    if args.json is not None:
        meta = {
            "benchmark": "poisson",
            "width": args.width,
            "height": args.height,
            "channels": 3,
            "alpha": alpha,
            "seed": args.seed,
            "repeats": args.repeats,
            "warmup": 1,
            "torch": torch.__version__,
            "numpy": np.__version__,
            "python": sys.version.split()[0],
            "platform": platform.platform(),
            "cpu": cpu_name(),
            "threads": torch.get_num_threads(),
            "device": "cpu",
            "commit": git_commit(),
            "loadavg_before": load_before,
            "loadavg_after": load_after,
            "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        payload = {"metadata": meta, "results": rows, "speedup_fast_vs_l1": speedup}
        args.json.write_text(json.dumps(payload, indent=2) + "\n")
        print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
