"""OIDN through ``mitsuba-oidn`` next to the shipped ``oidn-tuned`` run by the torch port of
OIDN's U-Net and by OIDN's own kernels (:mod:`gdpt.oidn_native`), at 128x128 and 1280x720, on
1 and 2 threads.

Tasks, on the same synthetic buffers (timings do not depend on the image content):

* ``oidn``: :func:`gdpt.oidn_native.denoise` with OIDN's built-in weights (the ``oidn``
  method; the anchor, measured in the same run);
* ``oidn-tuned, torch``: the shipped checkpoint's
  :class:`~gdpt.reconstruct.oidn_finetune.OIDNReconstructor` (input assembly, the U-Net in
  torch, output decoding);
* ``oidn-tuned, native``: :func:`gdpt.oidn_native.reconstruct` (the same network exported to a
  float16 TZA blob, autoexposure in torch, OIDN's filter), what the method ``oidn-tuned`` runs.

Threads: ``torch.set_num_threads`` and ``drjit.set_thread_count`` (OIDN's CPU device runs on
Dr.Jit's thread pool). Per size and thread count every task is run once untimed (the warm-up:
filter creation, the blob export, oneDNN's kernel set-up; excluded), then timed in
``--repeats`` interleaved rounds; medians are printed with the load average before and after
(the machine may be shared). Usage::

    .venv/bin/python benchmarks/oidn_native.py                        # 128x128 and 1280x720
    .venv/bin/python benchmarks/oidn_native.py --sizes 128x128 --threads 1 --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
from collections.abc import Callable
from pathlib import Path

import drjit as dr
import torch
from dense_unet_inference import _time, synthetic_buffers

from gdpt import oidn_native
from gdpt.checkpoints import load_reconstructor, model_path


def tasks(buffers: dict[str, torch.Tensor]) -> dict[str, Callable[[], object]]:
    """The three timed calls on ``buffers`` (``primal``, ``albedo``, ``normal``)."""
    images = {k: buffers[k].contiguous() for k in ("primal", "albedo", "normal")}
    tuned = load_reconstructor(model_path("oidn-tuned").resolve())
    return {
        "oidn": lambda: oidn_native.denoise(*images.values()),
        "oidn-tuned, torch": lambda: tuned(images),
        "oidn-tuned, native": lambda: oidn_native.reconstruct(tuned, images),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", nargs="+", default=["128x128", "1280x720"], help="WxH")
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args()
    results: dict = {"load_before": os.getloadavg(), "runs": []}
    for size in args.sizes:
        w, h = (int(v) for v in size.split("x"))
        calls = tasks(synthetic_buffers(h, w))
        for threads in args.threads:
            torch.set_num_threads(threads)
            dr.set_thread_count(threads)
            for fn in calls.values():  # warm-up, not timed
                fn()
            rounds = [{k: _time(fn) for k, fn in calls.items()} for _ in range(args.repeats)]
            med = {k: statistics.median(r[k] for r in rounds) for k in calls}
            results["runs"].append({"size": size, "threads": threads, "seconds": med})
            print(
                f"\n{size}, {threads} threads, median of {args.repeats} rounds (warm-up excluded)"
            )
            print("| task | time [s] | / oidn |\n|---|---:|---:|")
            for k, v in med.items():
                print(f"| {k} | {v:.4f} | {v / med['oidn']:.2f} |")
    results["load_after"] = os.getloadavg()
    print(f"\nload average before {results['load_before']}, after {results['load_after']}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
