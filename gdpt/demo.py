"""The ``make demo`` job: G-PT + screened Poisson against path tracing at equal time.

Renders the built-in ``cbox-demo`` scene with ``gdpt`` at a low sample count, reconstructs with
L1 (reference preset and the accelerated solver) and L2 screened Poisson, renders plain path tracing (``gdpt`` with ``gradients=False``) with
as many samples as fit in the same wall-clock time, and compares all of them with a cached
high-spp reference. Writes EXR files, PNG previews and a side-by-side montage.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch


@dataclass
class DemoConfig:
    """Options of :func:`run_demo`."""

    out: Path = Path("out/demo")
    scene: str = "cbox-demo"
    resolution: int = 192
    spp: int = 32
    reference_spp: int = 4096
    max_depth: int = 6
    seed: int = 1
    force: bool = False  # overwrite the outputs of an earlier run (the reference cache is kept)


def _relmse(image: torch.Tensor, ref: torch.Tensor) -> float:
    """NGPT relMSE: mean((x - r)^2 / (1e-3 + mean_c(r)^2))."""
    den = 1e-3 + ref.mean(-1, keepdim=True) ** 2
    return float(((image - ref) ** 2 / den).mean())


def _timed_render(scene, **kwargs):
    from gdpt.render import render

    start = time.perf_counter()
    buffers = render(scene, **kwargs)
    return buffers, time.perf_counter() - start


def run_demo(cfg: DemoConfig) -> dict:
    """Run the demo and return its numbers (also written to ``out/results.json``)."""
    from gdpt.exr import load_image, save_image
    from gdpt.images import save_png, side_by_side
    from gdpt.reconstruction import reconstruct
    from gdpt.render import load_scene
    from gdpt.scenes import builtin_scene

    from gdpt.backend import set_variant

    if (cfg.out / "results.json").exists() and not cfg.force:
        raise FileExistsError(f"{cfg.out} holds an earlier demo; pass --force to overwrite it")
    cfg.out.mkdir(parents=True, exist_ok=True)
    set_variant()
    scene = load_scene(builtin_scene(cfg.scene, resolution=(cfg.resolution, cfg.resolution)))
    common = dict(max_depth=cfg.max_depth, features=False)

    ref_path = cfg.out / f"reference-{cfg.scene}-{cfg.resolution}px-{cfg.reference_spp}spp.exr"
    if ref_path.exists():
        reference = load_image(ref_path)
    else:
        print(f"rendering the reference ({cfg.reference_spp} spp, cached in {ref_path})")
        ref_buffers, _ = _timed_render(
            scene, spp=cfg.reference_spp, seed=10_000, gradients=False, progress=True, **common
        )
        reference = ref_buffers.primal.clone()
        save_image(ref_path, reference, force=True)

    # Warm-up renders compile the kernels; the timed runs below exclude compilation.
    _timed_render(scene, spp=1, seed=0, **common)
    _timed_render(scene, spp=1, seed=0, gradients=False, **common)

    gbuf, t_gdpt = _timed_render(scene, spp=cfg.spp, seed=cfg.seed, progress=True, **common)
    images, seconds = {}, {}
    for method in ("l1", "l1-fast", "l2"):
        start = time.perf_counter()
        images[f"gdpt+{method}"] = reconstruct(gbuf, method=method)
        seconds[f"gdpt+{method}"] = t_gdpt + time.perf_counter() - start
    images["gdpt primal"] = gbuf.primal
    seconds["gdpt primal"] = t_gdpt

    # Equal time: measure the cost of one path-traced sample, then fill the G-PT + fast-L1 budget.
    probe_spp = max(1, cfg.spp // 2)
    _, t_probe = _timed_render(scene, spp=probe_spp, seed=cfg.seed + 1, gradients=False, **common)
    pt_spp = max(1, int(probe_spp * seconds["gdpt+l1-fast"] / t_probe))
    pbuf, t_pt = _timed_render(
        scene, spp=pt_spp, seed=cfg.seed + 2, gradients=False, progress=True, **common
    )
    images[f"pt ({pt_spp} spp)"] = pbuf.primal
    seconds[f"pt ({pt_spp} spp)"] = t_pt

    results = {"config": {k: str(v) for k, v in asdict(cfg).items()}, "methods": {}}
    print(f"\n{'method':<16}{'seconds':>10}{'relMSE':>12}")
    for name, image in images.items():
        stem = name.split(" ")[0].replace("+", "_").replace("-", "_")
        save_image(cfg.out / f"{stem}.exr", image, force=True)
        save_png(cfg.out / f"{stem}.png", image, force=True)
        err = _relmse(image, reference)
        results["methods"][name] = {"seconds": seconds[name], "relmse": err}
        print(f"{name:<16}{seconds[name]:>10.2f}{err:>12.4f}")
    side_by_side({"reference": reference, **images}, cfg.out / "side_by_side.png", force=True)
    (cfg.out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"\nwrote {cfg.out}/ (EXR + PNG per method, side_by_side.png, results.json)")
    return results
