"""Primal-only denoisers on the ``base`` and the ``mis`` primal of held-out dataset crops.

Two ``gdpt dataset`` directories rendered with the same settings and seed but ``--primal base``
and ``--primal mis`` hold the same crops, sample counts, path-traced inputs and targets; only the
primal of the G-PT inputs ``in<k>`` differs. On the held-out scenes (scene index ``%
holdout-every == holdout-every - 1``, as ``gdpt train --holdout-every``), every network of
``--model LABEL=PATH`` (a primal-only checkpoint: ``primal``, ``albedo``, ``normal``) denoises
the G-PT input of both datasets (``--input gdpt``, the primal the denoiser sees in
``gdpt render --method oidn-tuned``), or that primal pooled with the path-traced input of the
same level (``--input pool``, what ``fuse`` denoises); relMSE against the target.
``--pair A B`` prints :func:`gdpt.training.model_report.paired_comparison` of the labels
``A`` and ``B`` (``LABEL@base``, ``LABEL@mis``; ``primal@...``: the input itself): per input
level and overall, the geometric mean of the per-element relMSE ratio with its 95% Student-t
interval. No timing. Usage::

    .venv/bin/python benchmarks/primal_mis_finetune.py --base data/misft-base \\
        --mis data/misft-mis --holdout-every 5 --model shipped=gdpt/models/oidn-tuned.safetensors \\
        --model ft-mis=runs/misft-mis/model.safetensors \\
        --pair shipped@mis shipped@base --pair ft-mis@mis shipped@base [--out out/x.json]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

from gdpt.checkpoints import load_reconstructor
from gdpt.metrics import relmse
from gdpt.training.dataset import CropDataset
from gdpt.training.model_report import paired_comparison, paired_markdown

PRIMALS = ("base", "mis")


def compare(roots: dict[str, Path], models: dict[str, Path], holdout_every: int, kind: str) -> dict:
    """Per held-out element, the relMSE of every model (and of the input) on each primal, in
    :func:`gdpt.training.model_report.compare_models`'s ``elements`` / ``levels`` form.

    Raises:
        ValueError: the datasets are not the same crops with the same targets, or a dataset's
            primal is not the one its role says.
    """
    held = lambda s: s % holdout_every == holdout_every - 1  # noqa: E731
    sets = {}
    for primal, root in roots.items():
        stored = json.loads((root / "dataset.json").read_text())["config"].get("primal", "base")
        if stored != primal:
            raise ValueError(f"{root}: rendered with primal {stored!r}, given as {primal!r}")
        sets[primal] = CropDataset(root, kind=kind, scenes=held)
    if [r["crop"] for r in sets["base"].crops] != [r["crop"] for r in sets["mis"].crops]:
        raise ValueError("the two datasets hold different held-out crops")
    nets = {label: load_reconstructor(path.resolve()) for label, path in models.items()}
    elements: dict = {"level": []}
    spp: dict[int, list[int]] = {}
    for index in range(len(sets["base"])):
        items = {primal: sets[primal].load(index) for primal in PRIMALS}
        target = items["base"]["target"]
        if not torch.equal(target, items["mis"]["target"]):
            raise ValueError(f"crop {items['base']['crop']}: the two targets differ")
        level = items["base"]["level"]
        elements["level"].append(level)
        spp.setdefault(level, []).append(items["base"]["spp"])
        for primal, item in items.items():
            with torch.no_grad():
                images = {"primal": item["inputs"]["primal"]}
                images |= {label: net(item["inputs"]) for label, net in nets.items()}
            for label, image in images.items():
                scores = elements.setdefault(f"{label}@{primal}", {"relmse": []})
                scores["relmse"].append(relmse(image, target))
    levels = [
        {"spp": sum(spp[k]) / len(spp[k]), "pt_spp": math.nan, "n": len(spp[k])}
        for k in sorted(spp)
    ]
    return {"crops": len(sets["base"].crops), "input": kind, "levels": levels, "elements": elements}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", type=Path, required=True, help="dataset with --primal base")
    parser.add_argument("--mis", type=Path, required=True, help="the same with --primal mis")
    parser.add_argument("--model", action="append", default=[], metavar="LABEL=PATH")
    parser.add_argument("--pair", nargs=2, action="append", default=[], metavar=("A", "B"))
    parser.add_argument("--holdout-every", type=int, default=5)
    parser.add_argument("--input", choices=("gdpt", "pool"), default="gdpt")
    parser.add_argument("--out", type=Path, default=None, help="JSON of every score")
    args = parser.parse_args()
    models = dict(entry.split("=", 1) for entry in args.model)
    result = compare(
        {"base": args.base, "mis": args.mis},
        {label: Path(path) for label, path in models.items()},
        args.holdout_every,
        args.input,
    )
    print(f"{result['crops']} held-out crops, input {args.input}")
    for label, scores in result["elements"].items():
        if label != "level":
            logs = [math.log(v) for v in scores["relmse"]]
            print(f"  {label}: relMSE geometric mean {math.exp(sum(logs) / len(logs)):.5f}")
    pairs = [paired_comparison(result, a, b) for a, b in args.pair]
    for pair in pairs:
        print(f"\n{pair['a']} / {pair['b']}\n" + paired_markdown(pair).replace(" / nan", ""))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({**result, "pairs": pairs}, indent=1) + "\n")


if __name__ == "__main__":
    main()
