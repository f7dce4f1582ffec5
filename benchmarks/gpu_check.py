"""GPU readiness numbers: render and reconstruction times at 1280x720 on ``builtin:cbox-demo``.

Runs on the active variant: ``cuda_ad_rgb`` where Dr.Jit sees a CUDA device, else
``llvm_ad_rgb`` (``GDPT_VARIANT`` overrides; :func:`gdpt.set_variant`). For every method of
:data:`gdpt.methods.METHODS` that can run here it renders what the method reads and reconstructs
it (:func:`method_cost.measure`). **Kernel compilation is excluded**: every render and every
reconstruction runs once untimed first (Dr.Jit kernel compilation, frozen-pass recording, weight
loading, torch's first-call set-up), then ``--repeats`` times; medians are printed, each call
waited for on the device.

On CUDA it also prints the three ways to run ``oidn`` on CUDA buffers: OIDN's U-Net in torch on
the GPU (``backend="torch"``), OIDN's own CUDA device through mitsuba-oidn on the CUDA tensors
in place (``backend="native"``, what ``oidn`` does there), and a round trip through the CPU
(buffers to the host, OIDN on the CPU, image back), and the peak memory torch allocated. Usage::

    .venv/bin/python benchmarks/gpu_check.py                      # 1280x720, 4 spp
    .venv/bin/python benchmarks/gpu_check.py --size 320x180 --spp 2 --json gpu.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from method_cost import PLAIN, measure, median_seconds, parse_size

import gdpt
from gdpt.machine import cpu_name
from gdpt.methods import METHODS


def oidn_on_cuda(size: tuple[int, int], spp: int, repeats: int) -> dict[str, float | str]:
    """Seconds of each way to run ``oidn`` on CUDA buffers (an error message where one fails)."""
    import mitsuba as mi

    from gdpt.scenes.loading import generated_scene

    scene_dict = generated_scene("builtin:cbox-demo")
    scene_dict["sensor"]["film"]["width"], scene_dict["sensor"]["film"]["height"] = size
    buffers = gdpt.render(mi.load_dict(scene_dict), spp=spp, **METHODS["oidn"].sampling(spp))
    ways = {
        "torch port on the GPU": lambda: gdpt.reconstruct_image(buffers, "oidn", backend="torch"),
        "OIDN's CUDA device, in place (oidn's choice)": lambda: gdpt.reconstruct_image(
            buffers, "oidn", backend="native"
        ),
        "OIDN on the CPU, round trip": lambda: gdpt.reconstruct_image(
            buffers.to("cpu"), "oidn", backend="native"
        ).to(buffers.device),
    }
    out: dict[str, float | str] = {}
    for label, run in ways.items():
        try:
            out[label] = median_seconds(run, repeats)
        except Exception as error:  # a way that cannot run here is reported, not fatal
            out[label] = f"failed: {' '.join(str(error).split())[:200]}"
        value = out[label]
        print(f"  oidn, {label}: {value if isinstance(value, str) else f'{value:.3f} s'}")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=parse_size, default=(1280, 720), help="WIDTHxHEIGHT")
    parser.add_argument("--spp", type=int, default=4, help="samples per pixel (default: 4)")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per measurement")
    parser.add_argument("--json", type=Path, help="also write the numbers here")
    args = parser.parse_args()
    if args.spp < 1 or args.repeats < 1:
        parser.error("--spp and --repeats must be >= 1")

    variant = gdpt.set_variant()
    from gdpt.backend import torch_device

    device = torch_device()
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_name()
    width, height = args.size
    print(f"builtin:cbox-demo {width}x{height}, {args.spp} spp, {variant} on {device} ({name})")
    print(f"kernel compilation excluded (one untimed run first); median of {args.repeats}")
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    rows = measure(args.size, args.spp, args.repeats)
    result = {
        "size": [width, height],
        "spp": args.spp,
        "variant": variant,
        "device": f"{device} ({name})",
        "torch": torch.__version__,
        "repeats": args.repeats,
        "methods": rows,
    }
    if device.type == "cuda" and METHODS["oidn"].check() is None:
        result["oidn_on_cuda"] = oidn_on_cuda(args.size, args.spp, args.repeats)
    if device.type == "cuda":
        result["peak_torch_memory_mib"] = torch.cuda.max_memory_allocated(device) / 2**20

    print(f"\n| method | render s ({args.spp} spp) | reconstruct s |")
    print("|---|---:|---:|")
    for method, row in rows.items():
        reconstruct = "-" if method == PLAIN else f"{row['reconstruct']:.3f}"
        print(f"| {method} | {row['render_per_spp'] * args.spp:.3f} | {reconstruct} |")
    if "peak_torch_memory_mib" in result:
        print(f"peak memory allocated by torch: {result['peak_torch_memory_mib']:.0f} MiB")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
