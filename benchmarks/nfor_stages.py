"""Stage timings of NFOR (:mod:`gdpt.reconstruct.nfor`) next to OIDN, at 128x128 and 1280x720.

Stages, with NFOR's default parameters (:class:`gdpt.reconstruct.nfor.NforConfig`): the feature
prefilter (one NL-means filter per feature group and half: 6 calls), one first-pass regression
(one half, both bandwidths; the pass runs two), one error-smoothing NL-means (the pass runs
four: two error maps, two selection maps), the second-pass regression, and the whole
:func:`~gdpt.reconstruct.nfor.nfor` call; next to ``mitsuba_oidn.denoise`` (HDR, albedo + normal,
quality high) on the same buffers as the anchor, measured in the same run. Timings do not
depend on the image content (fixed windows, no early exits), so synthetic buffers are used.
Every task is run once untimed (``--no-warmup`` skips it: at 1280x720 the one-off allocations
are a negligible part of a call of minutes), then timed ``--repeats`` times (median);
``--stages`` restricts the run to the named tasks; the load average is printed (the machine
may be shared). The paper (Kettunen et al. 2019, sec. 4.6.2) quotes the
public NFOR implementation at about two minutes per 1280x720 image on an Intel i7 3770K
(4 cores). Usage::

    .venv/bin/python benchmarks/nfor_stages.py                        # 128x128 and 1280x720
    .venv/bin/python benchmarks/nfor_stages.py --sizes 128x128 --repeats 3 --json out.json
    .venv/bin/python benchmarks/nfor_stages.py --sizes 1280x720 --repeats 1 --no-warmup \
        --stages "nfor total" "oidn (anchor)"
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
from gdpt.reconstruct.nfor import NforConfig, nfor, nlm_filter, regress


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
        "oidn (anchor)": oidn_task(buffers),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", nargs="+", default=["128x128", "1280x720"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", type=Path, help="also write the timings here")
    parser.add_argument("--stages", nargs="+", help="only these tasks (default: all)")
    parser.add_argument("--no-warmup", dest="warmup", action="store_false")
    args = parser.parse_args()
    known = list(tasks(1, 1))
    if args.stages and (unknown := sorted(set(args.stages) - set(known))):
        parser.error(f"unknown --stages {unknown}; known: {known}")
    if args.stages and "oidn (anchor)" not in args.stages:
        parser.error("--stages must include 'oidn (anchor)': timings are reported against it")
    print(f"torch threads {torch.get_num_threads()}, load average {os.getloadavg()}")
    results = {}
    for size in args.sizes:
        width, height = (int(v) for v in size.split("x"))
        timings = {}
        for stage, fn in tasks(height, width).items():
            if args.stages and stage not in args.stages:
                continue
            if args.warmup:
                fn()  # untimed: allocations, thread pools
            timings[stage] = statistics.median(_time(fn) for _ in range(args.repeats))
        anchor = timings["oidn (anchor)"]
        print(f"\n{size}: stage, seconds, x oidn")
        for stage, seconds in timings.items():
            print(f"  {stage:28s} {seconds:9.3f} {seconds / anchor:9.1f}")
        results[size] = timings
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
