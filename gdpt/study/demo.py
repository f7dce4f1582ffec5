"""The ``make demo`` job: every method on the built-in ``cbox-demo`` scene at one equal time.

The demo is a one-scene, one-budget run of the equal-time study
(:func:`gdpt.study.evaluate.evaluate`):
G-PT reconstructed by the shipped gradient network ``oidn-grad``, L1 and L2 screened Poisson;
path tracing alone, with Intel Open Image Denoise, and with ``oidn-tuned`` (the same network
fine-tuned without gradients). Each method's sample count is calibrated by timing so that
sampling + reconstruction takes ``budget`` seconds on this machine (kernel compilation and
frozen-pass recording excluded: each timed render follows an untimed one at the same spp);
errors are measured against a cached high-spp path-traced reference. Writes the study's report
(``results.json``, ``results.md``, ``index.html``, crops), an EXR and a PNG per method, and a
labelled montage ``side_by_side.png``.
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


@dataclass(frozen=True)
class DemoConfig:
    """Options of :func:`run_demo`.

    Attributes:
        out: output folder (its ``references/`` cache survives ``force``).
        scene: a :func:`gdpt.scenes.builtin_scene` name.
        resolution: film width and height in pixels.
        budget: seconds of sampling + reconstruction per image.
        reference_spp: samples per pixel of the path-traced reference.
        max_depth: longest path.
        methods: names from :data:`gdpt.study.methods.EVAL_METHODS`.
        seed: base seed of the study.
        force: overwrite the outputs of an earlier demo.
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


def run_demo(cfg: DemoConfig, *, progress: bool = True) -> dict[str, Any]:
    """Run the demo, print its table and return the study's results (``results.json``).

    Raises:
        FileExistsError: ``cfg.out`` holds an earlier demo and ``cfg.force`` is false.
    """
    from gdpt.io.exr import load_image
    from gdpt.io.images import side_by_side
    from gdpt.study.config import EvaluateConfig
    from gdpt.study.evaluate import evaluate

    out = Path(cfg.out)
    results_path = out / "results.json"
    if results_path.exists():
        if not cfg.force:
            raise FileExistsError(f"{out} holds an earlier demo; pass --force to overwrite it")
        results_path.unlink()  # a fresh study; the reference cache is kept
    study = EvaluateConfig(
        budgets=(cfg.budget,),
        resolution=cfg.resolution,
        reference_spp=cfg.reference_spp,
        max_depth=cfg.max_depth,
        metrics=("relmse", "flip_ldr"),
        metric_options={},
        methods=cfg.methods,
        seed=cfg.seed,
        profile="demo",
    )
    results = evaluate([f"builtin:{cfg.scene}"], out, study, progress=progress, command="gdpt demo")
    entry = results["scenes"][cfg.scene]
    if entry.get("status") != "ok":
        raise RuntimeError(f"the demo scene failed: {entry.get('error')}")

    montage = {"reference": load_image(out / "images" / cfg.scene / "reference.exr")}
    print(
        f"\n{cfg.scene}, {cfg.resolution}x{cfg.resolution} px, budget {cfg.budget:g} s "
        f"(compilation and pass recording excluded), reference {cfg.reference_spp} spp"
    )
    print(f"{'method':<16}{'spp':>6}{'seconds':>9}{'relMSE':>10}{'FLIP':>8}")
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
    side_by_side(montage, out / "side_by_side.png", force=True)
    print(f"\nwrote {out}/: side_by_side.png, index.html, results.md, images/ (EXR + PNG)")
    return results
