"""The primal from every path (``primal="mis"``) against the base-path primal, at the same count.

Part 1, per-pixel statistics (``--size`` px long side, ``--spp`` gradient samples, ``--seeds``
seeds, the same seeds for both estimators): the per-pixel variance of the primal's luminance over
the seeds, ``mis`` over ``base`` (the ratio of the summed relative variances ``var / (mean^2 +
1e-3)``, and the median of the per-pixel ratios), and the correlation of a pixel's noise with its
right and lower neighbours' across the seeds (independent samples: 0).

Part 2, what is left after a denoiser (``--denoise-size`` px, ``--denoise-seeds`` seeds, against
the cached 8192-spp references of ``--references``, ``gdpt evaluate``'s cache, relMSE): per
estimator, the raw primal of ``--spp`` gradient samples, ``oidn-tuned`` on it, and ``fuse`` on
``fuse``'s input (``2.5x`` the gradient count of plain path samples pooled in, variances and
halves; the plain samples shared by both estimators). As the premise's control, ``oidn-tuned``
on a plain render of ``round(spp / ratio)`` samples (``ratio`` from part 1: independent noise
of the per-pixel variance ``mis`` reaches). Geometric means of the per-seed ratios over the
seeds. No timing (run it at nice 10 on a busy machine). Usage::

    .venv/bin/python benchmarks/primal_mis.py --scenes cornell-box living-room-2 sponza \\
        [--size 64 --spp 16 --seeds 12] [--denoise-size 128 --denoise-seeds 4] \\
        [--references /work/refs128]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch

import gdpt
from gdpt.buffers import pool_primal
from gdpt.io.exr import load_image
from gdpt.metrics import relmse
from gdpt.rendering import PRIMAL_SEED_SALT
from gdpt.scenes.loading import DEFAULT_MAX_DEPTH, read_scene

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "scenes"
ESTIMATORS = ("base", "mis")
#: Plain path samples ``fuse`` pools in per gradient sample (``primal_spp_factor`` of ``fuse``).
FUSE_PLAIN = 2.5


def load(name: str, size: int):
    loaded = read_scene(SHARED / name / "scene.xml", box_filter=True, long_side=size)
    return loaded.scene, loaded.max_depth or DEFAULT_MAX_DEPTH


def luminance(x: torch.Tensor) -> np.ndarray:
    return x.cpu().numpy().mean(-1).astype(np.float64)


def statistics(name: str, size: int, spp: int, seeds: int) -> dict:
    """Part 1: variance ratio ``mis``/``base`` and the neighbours' noise correlation."""
    scene, depth = load(name, size)
    runs = {
        p: np.stack(
            [
                luminance(
                    gdpt.render(
                        scene, spp=spp, seed=s, max_depth=depth, primal=p, features=False
                    ).primal
                )
                for s in range(seeds)
            ]
        )
        for p in ESTIMATORS
    }
    mean = (runs["base"].mean(0) + runs["mis"].mean(0)) / 2
    var = {p: r.var(0, ddof=1) for p, r in runs.items()}
    rel = {p: float((v / (mean**2 + 1e-3)).sum()) for p, v in var.items()}
    ok = var["base"] > 0
    out = {
        "ratio": rel["mis"] / rel["base"],
        "median_ratio": float(np.median(var["mis"][ok] / var["base"][ok])),
    }
    for p, r in runs.items():
        noise = r - r.mean(0)
        corr = []
        for a, b in ((noise[:, :, :-1], noise[:, :, 1:]), (noise[:, :-1], noise[:, 1:])):
            denom = np.sqrt((a**2).sum(0) * (b**2).sum(0))
            good = denom > 0
            corr.append(float(((a * b).sum(0)[good] / denom[good]).mean()))
        out[f"corr_{p}"] = sum(corr) / 2
    return out


def reference_of(name: str, references: Path, width: int, height: int) -> torch.Tensor:
    """The merged cached reference of ``name`` at ``width`` x ``height``."""
    found = sorted(
        p
        for p in references.glob(f"{name}-{width}x{height}-d*-*spp-*.exr")
        if ".chunk-" not in p.name
    )
    if not found:
        raise SystemExit(f"no reference for {name} at {width}x{height} in {references}")
    return torch.as_tensor(np.asarray(load_image(found[-1]), np.float32))[..., :3]


def denoised(name: str, size: int, spp: int, seeds: int, references: Path, ratio: float) -> dict:
    """Part 2: relMSE per estimator and stage, per seed."""
    scene, depth = load(name, size)
    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    ref = reference_of(name, references, width, height)
    more = max(spp, round(spp / ratio))
    rows: dict[str, list[float]] = {}

    def add(key: str, image: torch.Tensor) -> None:
        rows.setdefault(key, []).append(relmse(image.float().cpu(), ref))

    stats = {"variance": True, "halves": True, "max_depth": depth}
    for seed in range(seeds):
        plain = gdpt.render(
            scene,
            spp=round(FUSE_PLAIN * spp),
            seed=(seed ^ PRIMAL_SEED_SALT) & 0xFFFFFFFF,
            gradients=False,
            **stats,
        )
        for p in ESTIMATORS:
            b = gdpt.render(scene, spp=spp, seed=seed, primal=p, **stats)
            add(f"{p} raw", b.primal)
            add(f"{p} oidn-tuned", gdpt.reconstruct_image(b, "oidn-tuned"))
            add(f"{p} fuse", gdpt.reconstruct_image(pool_primal(b, plain), "fuse"))
        control = gdpt.render(scene, spp=more, seed=500 + seed, gradients=False, max_depth=depth)
        add(f"plain {more} spp raw", control.primal)
        add(f"plain {more} spp oidn-tuned", gdpt.reconstruct_image(control, "oidn-tuned"))
    return rows


def geomean_ratio(a: list[float], b: list[float]) -> float:
    return math.exp(sum(math.log(x / y) for x, y in zip(a, b, strict=True)) / len(a))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["cornell-box", "living-room-2", "sponza"])
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--seeds", type=int, default=12)
    parser.add_argument("--denoise-size", type=int, default=128)
    parser.add_argument("--denoise-seeds", type=int, default=4)
    parser.add_argument("--references", type=Path, default=Path("/work/refs128"))
    parser.add_argument("--skip-denoise", action="store_true")
    args = parser.parse_args()
    gdpt.set_variant()
    for name in args.scenes:
        s = statistics(name, args.size, args.spp, args.seeds)
        print(
            f"{name} {args.size}px {args.spp} gradient spp, {args.seeds} seeds: primal variance "
            f"mis/base {s['ratio']:.3f} (median per pixel {s['median_ratio']:.3f}); neighbour "
            f"noise correlation base {s['corr_base']:+.3f}, mis {s['corr_mis']:+.3f}",
            flush=True,
        )
        if args.skip_denoise:
            continue
        rows = denoised(
            name, args.denoise_size, args.spp, args.denoise_seeds, args.references, s["ratio"]
        )
        means = {k: math.exp(sum(math.log(v) for v in r) / len(r)) for k, r in rows.items()}
        print(
            f"{name} {args.denoise_size}px relMSE (geomean of {args.denoise_seeds} seeds): "
            + "; ".join(f"{k} {v:.4g}" for k, v in means.items()),
            flush=True,
        )
        plain = next(k for k in rows if k.startswith("plain") and k.endswith("oidn-tuned"))
        for stage in ("raw", "oidn-tuned", "fuse"):
            mis, base = rows[f"mis {stage}"], rows[f"base {stage}"]
            per_seed = " ".join(f"{m / b:.3f}" for m, b in zip(mis, base, strict=True))
            r = geomean_ratio(mis, base)
            print(f"  {name} {stage}: mis/base {r:.3f} (per seed {per_seed})", flush=True)
        r = geomean_ratio(rows[plain], rows["base oidn-tuned"])
        print(f"  {name} control: {plain} / base oidn-tuned {r:.3f}", flush=True)


if __name__ == "__main__":
    main()
