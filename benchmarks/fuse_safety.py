"""``fuse`` against its own ``D`` on the same renders: the held-out safeguard, measured.

Per scene, gradient sample count and seed: renders ``fuse``'s input (``primal_spp`` 2.5x the
gradient spp pooled in, variances and halves, gradient halves included), then compares on that
one render, by relMSE against a cached path-traced reference:

* ``D``: the primal-only denoise (``oidn-tuned``, else ``oidn``) of the pooled primal;
* ``fuse_old``: the fusion without the safeguard (:func:`gdpt.reconstruct.fuse.fuse_statistics`);
* ``fuse_new``: ``gdpt.reconstruct_image(buffers, "fuse")`` (the held-out choice), and the
  other designs of :func:`gdpt.reconstruct.held_out.choose` computed from the same candidates.

Scenes: ``../shared/scenes`` (cornell-box, sponza, veach-mis, living-room-2, staircase,
matpreview-dof; 128 px long side, box filter) and procedural rooms lit through a window
(``RandomSceneConfig(p_room=1, p_window=1, p_open_side=0)``, seeds ``--rooms``). References:
``--reference-spp`` path samples (``gradients=False``), cached in ``--cache``. No timing (run
it on a busy machine). Usage::

    .venv/bin/python benchmarks/fuse_safety.py [--spp 16 64 256] [--seeds 2]
        [--reference-spp 4096] [--references-only]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch
from gdpt.reconstruct import fuse, held_out

import gdpt
from gdpt.adapters import fusion_statistics_of
from gdpt.methods import METHODS, primal_only
from gdpt.metrics import relmse
from gdpt.scenes import RandomSceneConfig, random_scene
from gdpt.scenes.loading import DEFAULT_MAX_DEPTH, read_scene

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "scenes"
SHARED_SCENES = (
    "cornell-box",
    "sponza",
    "veach-mis",
    "living-room-2",
    "staircase",
    "matpreview-dof",
)
ROOM = RandomSceneConfig(p_room=1.0, p_window=1.0, p_open_side=0.0)


def load(name: str):
    """``(mi.Scene, max_depth)`` of a shared scene name or ``room:SEED``."""
    if name.startswith("room:"):
        source = random_scene(int(name[5:]), resolution=(128, 128), config=ROOM)
        loaded = read_scene(source)  # generated scenes have a box filter
    else:
        loaded = read_scene(SHARED / name / "scene.xml", box_filter=True, long_side=128)
    return loaded.scene, loaded.max_depth or DEFAULT_MAX_DEPTH


def reference(name: str, scene, depth: int, spp: int, cache: Path) -> torch.Tensor:
    """The path-traced reference ``(H, W, 3)``, rendered in 512-spp chunks and cached."""
    path = cache / f"{name.replace(':', '-')}_{spp}spp.pt"
    if path.exists():
        return torch.load(path)
    chunks = max(1, spp // 512)
    total = None
    for k in range(chunks):
        b = gdpt.render(
            scene,
            spp=spp // chunks,
            seed=1000 + k,
            max_depth=depth,
            gradients=False,
            features=False,
        )
        total = b.primal.clone() if total is None else total + b.primal
    ref = total / chunks
    cache.mkdir(parents=True, exist_ok=True)
    torch.save(ref, path)
    return ref


#: The held-out designs compared: name -> options of :func:`gdpt.reconstruct.held_out.choose`.
DESIGNS = {
    "image k2": {"tile": 0, "margin": 2.0},
    "image k1": {"tile": 0, "margin": 1.0},
    "tile32 k2": {"tile": 32, "margin": 2.0, "block": 8},
    "tile16 k1": {"tile": 16, "margin": 1.0, "block": 4},
    "image k2 else tile16 k1": {"tile": 16, "margin": 1.0, "block": 4, "image_margin": 2.0},
    "image k2 else tile16 k2": {"tile": 16, "margin": 2.0, "block": 4, "image_margin": 2.0},
    "image k2 else tile32 k2": {"tile": 32, "margin": 2.0, "block": 8, "image_margin": 2.0},
}


def fuse_input(scene, spp: int, seed: int, depth: int) -> gdpt.GradientBuffers:
    """What ``fuse`` reads, rendered at ``spp`` gradient samples (its pooled plain samples,
    variances and halves: ``METHODS["fuse"].sampling``)."""
    return gdpt.render(scene, spp=spp, seed=seed, max_depth=depth, **METHODS["fuse"].sampling(spp))


def candidates(b: gdpt.GradientBuffers, denoise):
    """``(D, F_old, F_new, terms, nonfinite, info)`` of one render: its denoise, the unchecked
    fusion, ``fuse`` as shipped, and the held-out terms the designs choose from."""
    counts = b.metadata["gradient_half_spp"]
    stats = fusion_statistics_of(b, denoise)
    old, _ = fuse.fuse_statistics(stats, b.dx, b.dy)
    halves = [
        fuse.fuse_statistics(fuse.half_statistics(stats, h, b.spp / counts[h]), gx, gy)[0]
        for h, (gx, gy) in enumerate(((b.dx_a, b.dy_a), (b.dx_b, b.dy_b)))
    ]
    d_a, d_b = stats.denoised_halves
    terms, nonfinite = held_out.held_out_terms(
        halves[0],
        d_a,
        halves[1],
        d_b,
        b.primal_a,
        b.primal_b,
        stats.denoised.mean(-1, keepdim=True),
    )
    new = gdpt.reconstruct_image(b, "fuse")
    return stats.denoised, old, new, terms, nonfinite, b.metadata["fuse"]


def geomean(values: list[float]) -> float:
    return math.exp(sum(math.log(v) for v in values) / len(values))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=[*SHARED_SCENES, "room:202", "room:311"])
    parser.add_argument("--spp", nargs="+", type=int, default=[16, 64, 256])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--reference-spp", type=int, default=4096)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/fuse_safety/refs"))
    parser.add_argument("--references-only", action="store_true")
    parser.add_argument("--save", type=Path, help="folder for each render's D, F, terms, ref")
    args = parser.parse_args()
    gdpt.set_variant()
    name_d, denoise = primal_only()
    print(
        f"D = {name_d} on the pooled primal (2.5 plain spp per gradient spp); references "
        f"{args.reference_spp} spp; ratios relMSE / relMSE(D), geometric mean over "
        f"{args.seeds} seeds"
    )
    columns = ["fuse_new", "fuse_old", *DESIGNS, "oracle"]
    print("| scene | grad spp | " + " | ".join(columns) + " | kept (new) |")
    print("|---|---:|" + "---:|" * (len(columns) + 1))
    for name in args.scenes:
        scene, depth = load(name)
        ref = reference(name, scene, depth, args.reference_spp, args.cache)
        if args.references_only:
            print(f"{name}: reference {tuple(ref.shape)} mean {float(ref.mean()):.3g}")
            continue
        for spp in args.spp:
            ratios = {c: [] for c in columns}
            kept = []
            for seed in range(args.seeds):
                b = fuse_input(scene, spp, seed + 1, depth)
                d, old, new, terms, nonfinite, info = candidates(b, denoise)
                if args.save:
                    args.save.mkdir(parents=True, exist_ok=True)
                    case = {"d": d, "old": old, "new": new, "terms": terms, "ref": ref}
                    torch.save(case, args.save / f"{name.replace(':', '-')}_{spp}_{seed}.pt")
                base = relmse(d, ref)
                ratios["fuse_new"].append(relmse(new, ref) / base)
                ratios["fuse_old"].append(relmse(old, ref) / base)
                for design, options in DESIGNS.items():
                    choice = held_out.choose(terms, nonfinite=nonfinite, **options)
                    ratios[design].append(relmse(held_out.apply(old, d, choice), ref) / base)
                ratios["oracle"].append(min(1.0, ratios["fuse_old"][-1]))
                kept.append(info["held_out"]["kept"])
            cells = " | ".join(f"{geomean(ratios[c]):.3f}" for c in columns)
            print(f"| {name} | {spp} | {cells} | {sum(kept) / len(kept):.2f} |", flush=True)


if __name__ == "__main__":
    main()
