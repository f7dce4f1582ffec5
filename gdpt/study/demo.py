"""The ``make demo`` job: methods on built-in scenes at equal time, both of ``auto``'s routes.

The demo is two small runs of the equal-time study (:func:`gdpt.study.evaluate.evaluate`):

1. every method on ``cbox-demo`` (glass, mirror and rough gold spheres in a Cornell box) at one
   short budget: G-PT reconstructed by ``fuse``, the shipped gradient network ``oidn-grad``, L1
   and L2 screened Poisson; path tracing alone, with Intel Open Image Denoise, and with
   ``oidn-tuned`` (the same network fine-tuned without gradients); ``auto`` takes the plain
   route here (gradients through glass and mirrors do not pay);
2. ``auto``, ``pt+oidn-tuned`` and ``gdpt+fuse`` on ``diffuse-box`` (a diffuse Cornell box) at a
   longer budget, where the gradient samples are enough for ``auto``'s pilot to see ``fuse``'s
   gain (about 130 gradient samples per pixel at 128 px) and ``auto`` takes the gradient route.

Each method's sample count is calibrated by timing so that sampling + reconstruction takes the
budget on this machine (kernel compilation and frozen-pass recording excluded: a run that
recorded passes is run again); errors are measured against a cached high-spp
path-traced reference. Each run writes the study's report (``results.json``, ``results.md``,
``index.html``, crops), an EXR and a PNG per method, and a labelled montage ``side_by_side.png``;
the second run in the subfolder :data:`GRADIENT_ROUTE_FOLDER`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: Methods shown by the demo, best first in the montage.
DEMO_METHODS = (
    "auto",
    "pt+oidn-tuned",
    "pt+oidn",
    "gdpt+fuse",
    "gdpt+oidn-grad",
    "gdpt+l1",
    "gdpt+l2",
    "pt",
)

#: Methods of the demo's second run: ``auto`` and the two methods its routes render.
GRADIENT_ROUTE_METHODS = ("auto", "pt+oidn-tuned", "gdpt+fuse")

#: Subfolder of the demo's output that holds the second run.
GRADIENT_ROUTE_FOLDER = "gradient-route"


@dataclass(frozen=True)
class DemoConfig:
    """Options of :func:`run_demo`.

    Attributes:
        out: output folder (its ``references/`` caches survive ``force``).
        scene: a :func:`gdpt.scenes.builtin_scene` name.
        resolution: film width and height in pixels.
        budget: seconds of sampling + reconstruction per image.
        reference_spp: samples per pixel of the path-traced references.
        max_depth: longest path.
        methods: names from :data:`gdpt.study.methods.EVAL_METHODS`.
        seed: base seed of the study.
        force: overwrite the outputs of an earlier demo.
        gradient_scene, gradient_resolution, gradient_budget, gradient_methods: the second run
            (in ``out / GRADIENT_ROUTE_FOLDER``), where ``auto`` takes the gradient route;
            ``gradient_budget=0`` leaves it out.
    """

    out: Path = Path("out/demo")
    scene: str = "cbox-demo"
    resolution: int = 192
    budget: float = 2.0
    reference_spp: int = 4096
    max_depth: int = 6
    methods: tuple[str, ...] = DEMO_METHODS
    seed: int = 1
    force: bool = False
    gradient_scene: str = "diffuse-box"
    gradient_resolution: int = 128
    gradient_budget: float = 8.0
    gradient_methods: tuple[str, ...] = GRADIENT_ROUTE_METHODS


def run_demo(cfg: DemoConfig, *, progress: bool = True) -> dict[str, dict[str, Any]]:
    """Run the demo, print its tables and return each run's results (``results.json``) by scene.

    Raises:
        ValueError: a negative ``cfg.gradient_budget``.
        FileExistsError: ``cfg.out`` holds an earlier demo and ``cfg.force`` is false.
    """
    if cfg.gradient_budget < 0:
        raise ValueError(f"gradient_budget must be >= 0 seconds, got {cfg.gradient_budget}")
    out = Path(cfg.out)
    runs = [(out, cfg.scene, cfg.resolution, cfg.budget, cfg.methods)]
    if cfg.gradient_budget > 0:
        runs.append(
            (
                out / GRADIENT_ROUTE_FOLDER,
                cfg.gradient_scene,
                cfg.gradient_resolution,
                cfg.gradient_budget,
                cfg.gradient_methods,
            )
        )
    earlier = [folder / "results.json" for folder, *_ in runs if (folder / "results.json").exists()]
    if earlier and not cfg.force:
        raise FileExistsError(f"{out} holds an earlier demo; pass --force to overwrite it")
    for path in earlier:
        path.unlink()  # a fresh study; the reference cache is kept
    return {
        scene: _run_study(cfg, folder, scene, resolution, budget, methods, progress)
        for folder, scene, resolution, budget, methods in runs
    }


def _run_study(
    cfg: DemoConfig,
    out: Path,
    scene: str,
    resolution: int,
    budget: float,
    methods: tuple[str, ...],
    progress: bool,
) -> dict[str, Any]:
    """One equal-time study of the demo in ``out``: run it, print its table (with ``auto``'s
    route) and write its montage."""
    from gdpt.io.exr import load_image
    from gdpt.io.images import side_by_side
    from gdpt.study.config import EvaluateConfig
    from gdpt.study.evaluate import evaluate

    study = EvaluateConfig(
        budgets=(budget,),
        resolution=resolution,
        reference_spp=cfg.reference_spp,
        max_depth=cfg.max_depth,
        metrics=("relmse", "flip_ldr"),
        metric_options={},
        methods=methods,
        seed=cfg.seed,
        profile="demo",
    )
    results = evaluate([f"builtin:{scene}"], out, study, progress=progress, command="gdpt demo")
    entry = results["scenes"][scene]
    if entry.get("status") != "ok":
        raise RuntimeError(f"the demo scene {scene} failed: {entry.get('error')}")

    montage = {"reference": load_image(out / "images" / scene / "reference.exr")}
    print(
        f"\n{scene}, {resolution}x{resolution} px, budget {budget:g} s "
        f"(compilation and pass recording excluded), reference {cfg.reference_spp} spp"
    )
    print(f"{'method':<16}{'spp':>6}{'seconds':>9}{'relMSE':>10}{'FLIP':>8}")
    routes = []
    for name in results["config"]["methods"]:  # current names (a deprecated one is replaced)
        info = entry["methods"].get(name, {})
        cells = list(info.get("cells", {}).values())
        if not cells:
            print(f"{name:<16}  skipped: {info.get('note') or info.get('errors')}")
            continue
        cell, metrics = cells[0], cells[0]["metrics"]
        print(
            f"{name:<16}{cell['spp']:>6}{cell['seconds']:>9.2f}"
            f"{metrics['relmse']:>10.4f}{metrics['flip_ldr']:>8.4f}"
        )
        montage[f"{name} ({cell['spp']} spp)"] = load_image(out / cell["image"])
        route = cell["replicates"][0].get("route")
        if route is not None and "reason" in route:
            routes.append(f"{name}: {route['route']} route ({route['method']}): {route['reason']}")
    for line in routes:
        print(line)
    side_by_side(montage, out / "side_by_side.png", force=True)
    print(f"wrote {out}/: side_by_side.png, index.html, results.md, images/ (EXR + PNG)")
    return results
