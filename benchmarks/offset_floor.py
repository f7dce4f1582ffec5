"""The least work four offset paths need, relative to Mitsuba's ``path``: a floor for ``gdpt``.

Whatever the organisation (megakernel or wavefront), every offset of the hybrid shift must at
least find its own primary vertex y_0 and reconnect it twice, to the base's light sample (NEE)
and to the base's next vertex x_1 (BSDF sampling), each with a visibility ray and a BSDF
evaluation at y_0. This script times exactly that, on top of the base path's first vertex, as
one kernel per pass, minus the same kernel without offsets, against ``path`` at the same
resolution, spp and max depth: ``1 + offsets / path`` is a lower bound of ``gdpt`` / ``path``
for four offsets (later offset vertices, emission, MIS and the accumulation come on top).
Compile time is excluded (one warm-up render each), rounds are interleaved and the median of the
per-round ratios is reported. Usage::

    .venv/bin/python benchmarks/offset_floor.py [--scenes veach-mis matpreview-dof]
        [--resolution 128] [--spp 32] [--max-depth 6] [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"


def _floor_pass(scene, sensor, spp: int, seed: int, offsets: bool = True):
    """The floor's work for one pass (evaluated; ``offsets=False``: the base's first vertex
    only); returns a value so that nothing is optimised out."""
    import drjit as dr
    import mitsuba as mi

    film = sensor.film()
    size = film.crop_size()
    n = int(dr.prod(size)) * spp
    sampler = sensor.sampler().clone()
    sampler.set_sample_count(spp)
    sampler.set_samples_per_wavefront(spp)
    sampler.seed(dr.opaque(mi.UInt32, seed), n)
    idx = dr.arange(mi.UInt32, n) // dr.opaque(mi.UInt32, spp)
    pos = mi.Vector2f(mi.Vector2u(idx % size[0], idx // size[0])) + sampler.next_2d()
    aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
    scale = dr.rcp(mi.ScalarVector2f(size))
    ctx = mi.BSDFContext()

    def primary(shift):
        ray, _ = sensor.sample_ray(0.0, 0.5, (pos + mi.Vector2f(shift)) * scale, aperture)
        return scene.ray_intersect(ray, mi.RayFlags.All, True)

    # The base path's first vertex: emitter sample, BSDF sample, next vertex
    x0 = primary((0, 0))
    active = x0.is_valid()
    bsdf = x0.bsdf()
    ds, _ = scene.sample_emitter_direction(x0, sampler.next_2d(), True, active)
    bs, w = bsdf.sample(ctx, x0, sampler.next_1d(), sampler.next_2d(), active)
    x1 = scene.ray_intersect(x0.spawn_ray(x0.to_world(bs.wo)), active)
    total = dr.sum(w) + ds.pdf
    for shift in ((1, 0), (0, 1), (-1, 0), (0, -1)) if offsets else ():
        y0 = primary(shift)
        act = active & y0.is_valid()
        bsdf_y = y0.bsdf()
        vis_light = ~scene.ray_test(y0.spawn_ray_to(ds.p), act)
        vis_next = ~scene.ray_test(y0.spawn_ray_to(x1.p), act & x1.is_valid())
        f_l, p_l = bsdf_y.eval_pdf(ctx, y0, y0.to_local(dr.normalize(ds.p - y0.p)), act)
        f_n, p_n = bsdf_y.eval_pdf(ctx, y0, y0.to_local(dr.normalize(x1.p - y0.p)), act)
        total += dr.select(vis_light, dr.sum(f_l) + p_l, 0)
        total += dr.select(vis_next, dr.sum(f_n) + p_n, 0)
    total = dr.sum(total)
    dr.eval(total)
    return total


def _timed(fn) -> float:
    import drjit as dr

    start = time.perf_counter()
    dr.eval(fn())
    dr.sync_thread()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["veach-mis", "matpreview-dof"])
    parser.add_argument("--resolution", type=int, default=128, help="long side in pixels")
    parser.add_argument("--spp", type=int, default=32)
    parser.add_argument("--max-depth", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    import gdpt

    variant = gdpt.set_variant()
    print(f"\n{variant}, {args.resolution} px, {args.spp} spp, max_depth {args.max_depth}\n")
    print("| scene | path [ms] | 4 offsets' floor [ms] | floor: 1 + offsets / path | gdpt / path |")
    print("|---|---:|---:|---:|---:|")
    for name in args.scenes:
        print(_scene_row(name, args), flush=True)


def _scene_row(name: str, args) -> str:
    """Time path, the floor with and without offsets, and gdpt on one scene: a table row."""
    import mitsuba as mi

    from gdpt.scenes.loading import load_scene

    scene = load_scene(SHARED / name / "scene.xml", box_filter=True, long_side=args.resolution)
    sensor = scene.sensors()[0]
    path = mi.load_dict({"type": "path", "max_depth": args.max_depth})
    ours = mi.load_dict({"type": "gdpt", "max_depth": args.max_depth})
    jobs = {
        "path": lambda seed: mi.render(scene, integrator=path, spp=args.spp, seed=seed),
        "floor": lambda seed: _floor_pass(scene, sensor, args.spp, seed),
        "base": lambda seed: _floor_pass(scene, sensor, args.spp, seed, offsets=False),
        "gdpt": lambda seed: mi.render(scene, integrator=ours, spp=args.spp, seed=seed),
    }
    for job in jobs.values():  # compile (and record the frozen pass) outside the timing
        _timed(lambda job=job: job(0))
        _timed(lambda job=job: job(0))
    runs = {label: [] for label in jobs}
    for r in range(args.repeats):
        for label, job in jobs.items():
            runs[label].append(_timed(lambda job=job, r=r: job(1 + r)))

    def ratio(label: str) -> float:
        return statistics.median(a / b for a, b in zip(runs[label], runs["path"], strict=True))

    offsets = statistics.median(a - b for a, b in zip(runs["floor"], runs["base"], strict=True))
    return (
        f"| {name} | {1e3 * statistics.median(runs['path']):.0f} | {1e3 * offsets:.0f} | "
        f"{1 + ratio('floor') - ratio('base'):.2f} | {ratio('gdpt'):.2f} |"
    )


if __name__ == "__main__":
    main()
