"""The regime of ``auto``'s tile pilot: how many tiles it sees and how its statistic moves with
the film size and the sample count.

For each scene, long side and plain sample count ``N`` (the budget of a render), over
``--seeds`` pilots (:func:`gdpt.auto_route.run_pilot` only: no main render, no timing): the
tiles of the pilot, its gradient spp ``G``, the tiles' held-out statistic (standard errors;
< -1.645 takes the gradient route) as mean and standard deviation over the seeds, and the share
of seeds that took the gradient route. The pilot's ``G`` depends on ``N`` alone
(:data:`gdpt.auto_route.DEFAULT_COST_RATIO`). Usage::

    .venv/bin/python benchmarks/auto_pilot_power.py [--scenes cornell-box living-room-2]
        [--sizes 128 256] [--spp 150 300 600] [--seeds 4]
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["cornell-box", "living-room-2"])
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    parser.add_argument("--spp", type=int, nargs="+", default=[150, 300, 600])
    parser.add_argument("--seeds", type=int, default=4)
    args = parser.parse_args()

    from gdpt import auto_route
    from gdpt.scenes.loading import DEFAULT_MAX_DEPTH, read_scene

    print("| scene | size | tiles | plain spp | gradient spp | statistic mean (sd) | gradient |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for name in args.scenes:
        xml = SHARED / name / "scene.xml"
        for size in args.sizes:
            loaded = read_scene(xml, long_side=size, box_filter=True)
            scene, (width, height) = loaded.scene, loaded.resolution
            depth = loaded.max_depth or DEFAULT_MAX_DEPTH
            for spp in args.spp:
                values, routes, info = [], [], {}
                for seed in range(args.seeds):
                    choice, _ = auto_route.run_pilot(scene, spp=spp, seed=seed, max_depth=depth)
                    info = choice.pilot
                    if "statistic" in info:
                        values.append(info["statistic"])
                    routes.append(choice.route == "gradient")
                if not values:
                    print(f"| {name} | {width}x{height} | - | {spp} | - | no pilot | - |")
                    continue
                sd = statistics.stdev(values) if len(values) > 1 else 0.0
                print(
                    f"| {name} | {width}x{height} | {info['tiles']} | {spp} | "
                    f"{info['gradient_spp']} | {statistics.mean(values):+.2f} ({sd:.2f}) | "
                    f"{sum(routes)}/{len(routes)} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
