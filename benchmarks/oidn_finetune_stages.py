"""Stage timings of the fine-tuned-OIDN reconstructions (``gdpt.reconstruct.oidn_finetune``) next
to OIDN alone, at several image sizes.

Per design (``oidn-grad``, ``oidn-grad-l1``, ``oidn-nograd``) and size: input assembly
(autoexposure, PU encoding, signed-log gradients; for ``oidn-grad-l1`` the 'l1-fast' Poisson
solve is timed as its own stage), the U-Net, the output decoding, and the end-to-end
``OIDNReconstructor`` call (for gradient designs also with the shipped ``oidn-grad``'s gated Poisson
refinement, :mod:`gdpt.reconstruct.refine`: its L1 solve and gate as stages); next to
``mitsuba_oidn.denoise`` (HDR, albedo + normal, quality high) and the torch port of OIDN
(:func:`gdpt.reconstruct.oidn_unet.denoise`). Timings do not depend on
the weights' values, so Intel's weights with zero extra-channel weights are used. Every task is
warmed up once, then timed in ``--repeats`` interleaved rounds; medians are reported, with the
load average (the machine may be shared). Usage::

    .venv/bin/python benchmarks/oidn_finetune_stages.py                 # 128x128 and 1280x720
    .venv/bin/python benchmarks/oidn_finetune_stages.py --sizes 128x128 --repeats 5 \\
        --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
from collections.abc import Callable
from pathlib import Path

import torch
from dense_unet_inference import _time, oidn_task, synthetic_buffers
from gdpt.reconstruct.oidn_finetune import DESIGNS, OIDNReconstructor, assemble, base_model
from gdpt.reconstruct.oidn_unet import decode_output
from gdpt.reconstruct.oidn_unet import denoise as torch_oidn
from gdpt.reconstruct.poisson import solve as poisson
from gdpt.reconstruct.refine import GatedRefinement


def stage_tasks(design_name: str, buffers: dict[str, torch.Tensor]) -> dict[str, Callable]:
    """``stage -> fn`` for one design on ``buffers`` (each fn runs one stage on fixed inputs)."""
    design = DESIGNS[design_name]
    net = base_model(design)
    h, w = buffers["primal"].shape[:2]
    l1 = None
    tasks: dict[str, Callable] = {}
    if design.l1:
        p, dx, dy = buffers["primal"], buffers["dx"], buffers["dy"]
        tasks["l1-fast solve"] = lambda: poisson(p, dx, dy, solver="l1-fast", alpha=0.2)
        l1 = tasks["l1-fast solve"]()
    x, scale = assemble(buffers, design, l1=l1)
    with torch.inference_mode():
        y = net(x)
    tasks["assemble"] = lambda: assemble(buffers, design, l1=l1)
    tasks["network"] = lambda: torch.inference_mode()(net)(x)
    tasks["decode"] = lambda: decode_output(y, h, w, scale)
    rec = OIDNReconstructor(net, design)
    tasks["total"] = lambda: rec(buffers)
    if design.gradients:
        refine = GatedRefinement()
        image = rec(buffers)
        refined = refine.solve(image, buffers["dx"], buffers["dy"])
        tasks["refinement: L1 solve"] = lambda: refine.solve(image, buffers["dx"], buffers["dy"])
        tasks["refinement: gate"] = lambda: refine.gate(refined, image)
        with_refine = OIDNReconstructor(net, design, {"refine": refine.to_dict()})
        tasks["total, refined"] = lambda: with_refine(buffers)
    return tasks


def main() -> None:
    """Parse arguments, measure, print a Markdown table, optionally write JSON."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", nargs="+", default=["128x128", "1280x720"], help="WxH")
    parser.add_argument("--designs", nargs="+", default=list(DESIGNS), choices=list(DESIGNS))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0 = default)")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    results = {"threads": torch.get_num_threads(), "load_before": os.getloadavg(), "sizes": {}}
    for size in args.sizes:
        w, h = (int(v) for v in size.split("x"))
        buffers = synthetic_buffers(h, w)
        tasks: dict[str, Callable] = {"oidn": oidn_task(buffers)}
        b = buffers
        tasks["oidn (torch)"] = lambda b=b: torch.inference_mode()(torch_oidn)(
            b["primal"], b["albedo"], b["normal"]
        )
        for name in args.designs:
            for stage, fn in stage_tasks(name, buffers).items():
                tasks[f"{name}: {stage}"] = fn
        for fn in tasks.values():
            fn()
        rounds = [{k: _time(fn) for k, fn in tasks.items()} for _ in range(args.repeats)]
        med = {k: statistics.median(r[k] for r in rounds) for k in tasks}
        results["sizes"][size] = med
        print(f"\n{size}, {torch.get_num_threads()} threads, median of {args.repeats} rounds\n")
        print("| task | time [s] | / oidn |\n|---|---:|---:|")
        for k, v in med.items():
            print(f"| {k} | {v:.4f} | {v / med['oidn']:.2f} |")
    results["load_after"] = os.getloadavg()
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
