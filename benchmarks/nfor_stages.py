"""Stage timings of NFOR (:mod:`gdpt.reconstruct.nfor`) next to OIDN, at 128x128 and 1280x720.

Stages, with NFOR's default parameters (:class:`gdpt.reconstruct.nfor.NforConfig`): the feature
prefilter (one NL-means filter per feature group and half: 6 calls), one first-pass regression
(one half, both bandwidths; the pass runs two), one error-smoothing NL-means (the pass runs
four: two error maps, two selection maps), the second-pass regression, and the whole
:func:`~gdpt.reconstruct.nfor.nfor` call; next to ``pyoidn.denoise`` (HDR, albedo + normal,
quality high) on the same buffers as the anchor, measured in the same run. Timings do not
depend on the image content (fixed windows, no early exits), so synthetic buffers are used.
Every task is run once untimed, then timed ``--repeats`` times (median); the load average is
printed (the machine may be shared). The paper (Kettunen et al. 2019, sec. 4.6.2) quotes the
public NFOR implementation at about two minutes per 1280x720 image on an Intel i7 3770K
(4 cores). Usage::

    .venv/bin/python benchmarks/nfor_stages.py                        # 128x128 and 1280x720
    .venv/bin/python benchmarks/nfor_stages.py --sizes 128x128 --repeats 3 --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
from collections.abc import Callable
from pathlib import Path

import torch
from gdpt.reconstruct.nfor import NforConfig, nfor, nlm_filter, regress
from ngpt_inference import _time, oidn_task, synthetic_buffers


def tasks(height: int, width: int) -> dict[str, Callable[[], object]]:
    """``stage -> fn`` on synthetic half-buffers of ``height x width`` pixels."""
    cfg = NforConfig()
    buffers = synthetic_buffers(height, width)
    noise = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(1))
    a, b = buffers["primal"], buffers["primal"] * (0.5 + noise)
    var = (a - b).square().mean(-1, keepdim=True) / 4
    groups = [buffers["albedo"], buffers["normal"], buffers["depth"]]
    feats = torch.cat(groups, dim=-1)
    albedo = buffers["albedo"]
    return {
        "prefilter (x6)": lambda: nlm_filter(
            albedo, albedo, var, radius=cfg.prefilter_radius, patch=cfg.prefilter_patch, k=0.5
        ),
        "first-pass regression (x2)": lambda: regress(
            a, feats, b, 2 * var, radius=cfg.radius, patch=cfg.patch, ks=cfg.bandwidths
        ),
        "error smoothing (x4)": lambda: nlm_filter(
            a, a, var, radius=cfg.error_radius, patch=cfg.error_patch, k=1.0
        ),
        "second-pass regression": lambda: regress(
            a, feats, a, var, radius=cfg.radius, patch=cfg.patch, ks=(cfg.final_k,)
        ),
        "nfor total": lambda: nfor(a, b, var, groups, groups, cfg),
        "pyoidn (anchor)": oidn_task(buffers),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", nargs="+", default=["128x128", "1280x720"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", type=Path, help="also write the timings here")
    args = parser.parse_args()
    print(f"torch threads {torch.get_num_threads()}, load average {os.getloadavg()}")
    results = {}
    for size in args.sizes:
        width, height = (int(v) for v in size.split("x"))
        timings = {}
        for stage, fn in tasks(height, width).items():
            fn()  # untimed: allocations, thread pools
            timings[stage] = statistics.median(_time(fn) for _ in range(args.repeats))
        anchor = timings["pyoidn (anchor)"]
        print(f"\n{size}: stage, seconds, x pyoidn")
        for stage, seconds in timings.items():
            print(f"  {stage:28s} {seconds:9.3f} {seconds / anchor:9.1f}")
        results[size] = timings
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
