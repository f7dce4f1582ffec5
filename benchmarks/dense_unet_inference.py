"""CPU inference time of every registered NGPT network next to OIDN and the machine's conv peak.

Measures, in one process and one run:

* the fp32 3x3-convolution throughput of this machine (128 -> 128 channels, 256x512,
  channels-last, ``torch.inference_mode``) as the practical peak in GFLOP/s;
* ``mitsuba_oidn.denoise(color, albedo, normal, hdr=True, quality=High)`` at the image size
  (OIDN's CPU device, on Dr.Jit's thread pool: ``drjit.set_thread_count`` sets its threads);
* :class:`gdpt.reconstruct.dense_unet_reconstructor.DenseUNetReconstructor` end to end
  (transforms, padding, network, ``exp(y) - 1``, crop) for each config with freshly initialised
  weights.

Every task is warmed up once, then all tasks are timed in ``--repeats`` interleaved rounds;
times, GFLOP/s, fractions of the peak and ratios to OIDN are medians over the rounds. FLOPs count
2 per multiply-add of every convolution; "executed" FLOPs include the tile overlap. The load
average is recorded because the machine may be shared. Usage::

    .venv/bin/python benchmarks/dense_unet_inference.py                # all configs, 1280x720
    .venv/bin/python benchmarks/dense_unet_inference.py --configs fast fast_xs --tile-size 512 \\
        --json benchmarks/results/dense_unet_inference.json
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F
from gdpt.reconstruct.dense_unet import CONFIGS, build_model, parameter_count
from gdpt.reconstruct.dense_unet_reconstructor import DenseUNetReconstructor
from poisson import git_commit

from gdpt.machine import cpu_name


def _time(fn: Callable[[], object]) -> float:
    """Wall time of one call of ``fn`` in seconds."""
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


_CONV_SHAPE = (128, 128, 3, 256, 512)  # C_in, C_out, kernel, H, W of the peak measurement


def conv_peak_task() -> tuple[Callable[[], object], float]:
    """``(fn, flops)``: a 128->128 3x3 conv on (1, 128, 256, 512) channels-last fp32."""
    cin, cout, k, h, w = _CONV_SHAPE
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(1, cin, h, w, generator=gen).contiguous(memory_format=torch.channels_last)
    weight = torch.randn(cout, cin, k, k, generator=gen)

    def run() -> torch.Tensor:
        with torch.inference_mode():
            return F.conv2d(x, weight, padding=k // 2)

    return run, 2.0 * cin * cout * k * k * h * w


def synthetic_buffers(height: int, width: int) -> dict[str, torch.Tensor]:
    """A smooth HDR image with noise, its forward differences and plausible features."""
    gen = torch.Generator().manual_seed(0)
    yy, xx = torch.meshgrid(
        torch.linspace(0, 6, height), torch.linspace(0, 10, width), indexing="ij"
    )
    base = (2 + torch.sin(xx) * torch.cos(yy)).unsqueeze(-1) * torch.tensor([1.0, 0.8, 0.6])
    primal = (base * torch.rand(height, width, 3, generator=gen) * 2).contiguous()
    dx, dy = torch.zeros_like(base), torch.zeros_like(base)
    dx[:, :-1] = base[:, 1:] - base[:, :-1]
    dy[:-1] = base[1:] - base[:-1]
    normal = F.normalize(torch.rand(height, width, 3, generator=gen) * 2 - 1, dim=-1)
    return {
        "primal": primal,
        "dx": dx,
        "dy": dy,
        "albedo": torch.rand(height, width, 3, generator=gen),
        "normal": normal,
        "depth": 1 + yy.unsqueeze(-1).contiguous(),
    }


def oidn_task(buffers: dict[str, torch.Tensor]) -> Callable[[], object]:
    """``mitsuba_oidn.denoise`` (HDR, albedo + normal, quality high) on the synthetic buffers
    (read in place)."""
    import mitsuba_oidn

    color, albedo, normal = (
        buffers[k].float().contiguous() for k in ("primal", "albedo", "normal")
    )
    high = mitsuba_oidn.Quality.High
    return lambda: mitsuba_oidn.denoise(color, albedo, normal, hdr=True, quality=high)


def main() -> None:
    """Parse arguments, run the measurements, print a Markdown table, optionally write JSON."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--tile-size", type=int, default=0, help="0 = untiled")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0 = default)")
    parser.add_argument("--skip-oidn", action="store_true")
    parser.add_argument("--json", type=Path, help="write results with metadata here")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    load_before = os.getloadavg()
    h, w = args.height, args.width
    buffers = synthetic_buffers(h, w)
    peak_fn, peak_flops = conv_peak_task()
    tasks: dict[str, Callable[[], object]] = {"peak": peak_fn}
    if not args.skip_oidn:
        tasks["oidn"] = oidn_task(buffers)
    info = {}
    for name in args.configs:
        model = build_model(name)
        rec = DenseUNetReconstructor(model, tile_size=args.tile_size or None)
        ph = h + 2 * rec.margin + (-(h + 2 * rec.margin) % rec.alignment)
        pw = w + 2 * rec.margin + (-(w + 2 * rec.margin) % rec.alignment)
        executed = sum(model.flops(y1 - y0, x1 - x0) for _, (y0, y1, x0, x1) in rec.tiles(ph, pw))
        info[name] = (parameter_count(model), model.flops(h, w), executed)
        tasks[name] = lambda rec=rec: rec(buffers)
    # Warm up everything, then time in interleaved rounds so that a change in the load of the
    # (possibly shared) machine affects all candidates alike; ratios are medians per round.
    for fn in tasks.values():
        fn()
    rounds: list[dict[str, float]] = []
    for r in range(args.repeats):
        rounds.append({name: _time(fn) for name, fn in tasks.items()})
        print(
            f"  round {r + 1}: " + ", ".join(f"{k} {v:.2f} s" for k, v in rounds[-1].items()),
            flush=True,
        )

    def med(fn: Callable[[dict[str, float]], float]) -> float:
        return statistics.median(fn(rd) for rd in rounds)

    peak = med(lambda rd: peak_flops / rd["peak"] / 1e9)
    oidn = None if args.skip_oidn else med(lambda rd: rd["oidn"])
    rows = []
    for name in args.configs:
        params, image_flops, executed = info[name]
        rows.append(
            {
                "config": name,
                "parameters": params,
                "gflop_image": image_flops / 1e9,
                "gflop_executed": executed / 1e9,
                "seconds": med(lambda rd, n=name: rd[n]),
                "times": [rd[name] for rd in rounds],
                "gflops_achieved": med(lambda rd, n=name, e=executed: e / rd[n] / 1e9),
                "fraction_of_peak": med(
                    lambda rd, n=name, e=executed: e / rd[n] / (peak_flops / rd["peak"])
                ),
                "ratio_to_oidn": None
                if oidn is None
                else med(lambda rd, n=name: rd[n] / rd["oidn"]),
            }
        )

    print(
        f"\nNGPT inference at {w}x{h}, {torch.get_num_threads()} threads, "
        f"tiles: {args.tile_size or 'none'}; conv peak {peak:.0f} GFLOP/s; "
        f"OIDN high: {'-' if oidn is None else f'{oidn:.2f} s'}\n"
    )
    print(
        "| config | params (M) | GFLOP (image) | GFLOP (executed) | time (s) | GFLOP/s "
        "| % of conv peak | time / OIDN |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        ratio = "-" if r["ratio_to_oidn"] is None else f"{r['ratio_to_oidn']:.2f}"
        print(
            f"| {r['config']} | {r['parameters'] / 1e6:.2f} | {r['gflop_image']:.0f} "
            f"| {r['gflop_executed']:.0f} | {r['seconds']:.2f} | {r['gflops_achieved']:.0f} "
            f"| {100 * r['fraction_of_peak']:.0f} | {ratio} |"
        )
    if oidn is not None:
        print(f"| OIDN 'high' (mitsuba-oidn) | - | - | - | {oidn:.2f} | - | - | 1.00 |")

    if args.json:
        result = {
            "benchmark": "dense_unet_inference",
            "metadata": {
                "date": datetime.datetime.now(datetime.timezone.utc).isoformat(),
                "commit": git_commit(),
                "torch": torch.__version__,
                "python": platform.python_version(),
                "cpu": cpu_name(),
                "threads": torch.get_num_threads(),
                "load_average_before": load_before,
                "load_average_after": os.getloadavg(),
                "height": h,
                "width": w,
                "repeats": args.repeats,
                "tile_size": args.tile_size or None,
            },
            "conv_peak_gflops": peak,
            "conv_peak_shape": list(_CONV_SHAPE),
            "oidn_seconds": oidn,
            "rounds": rounds,
            "results": rows,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
