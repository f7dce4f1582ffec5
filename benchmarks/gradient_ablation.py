"""How much a gradient network uses its gradients: held-out error with ``dx``/``dy`` as rendered
and with both set to zero, on the same inputs.

For every fine-tuned OIDN checkpoint given (delta cards of ``gdpt.reconstruct.oidn_finetune``
with gradient inputs), the network alone (no refinement: it reads the gradients as well) is run
on evenly spaced held-out elements of a ``gdpt dataset`` (the input kind of its design, e.g.
pooled), once as is and once with zero gradients, and the mean relMSE and LDR-FLIP of both
against the dataset's targets are printed as a Markdown table. A network that ignores its
gradients scores the same twice.

    .venv/bin/python benchmarks/gradient_ablation.py --data data/oidn-ft-v6 --holdout-every 5 \
        gdpt/models/oidn-grad.safetensors runs/v11-oidn-grad-pool/model.safetensors
"""

from __future__ import annotations

import argparse

import torch
from gdpt.reconstruct.losses import FLIPLoss
from gdpt.reconstruct.oidn_finetune import assemble, load_model, predict

from gdpt.training.dataset import CropDataset
from gdpt.training.validation import held_out_elements, image_metrics


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", nargs="+", help="delta checkpoints (.safetensors or .json)")
    parser.add_argument("--data", required=True, help="dataset directory (gdpt dataset)")
    parser.add_argument("--holdout-every", type=int, default=5, help="as in gdpt train")
    parser.add_argument("--elements", type=int, default=48, help="held-out elements scored")
    args = parser.parse_args()
    every = args.holdout_every
    flip = FLIPLoss("ldr")
    print("| model | relMSE | relMSE, dx = dy = 0 | LDR-FLIP | LDR-FLIP, dx = dy = 0 |")
    print("|---|---|---|---|---|")
    for path in args.models:
        net, design, _ = load_model(path)
        if not design.gradients:
            raise SystemExit(f"{path}: design {design.description!r} reads no gradients")
        held_out = CropDataset(
            args.data, kind=design.input_kind, scenes=lambda s: s % every == every - 1
        )
        sums = {key: 0.0 for key in ("relmse", "relmse0", "flip", "flip0")}
        count = 0
        for inputs, target, _ in held_out_elements(held_out, args.elements, torch.device("cpu")):
            zeroed = {
                **inputs,
                "dx": torch.zeros_like(inputs["dx"]),
                "dy": torch.zeros_like(inputs["dy"]),
            }
            for suffix, given in (("", inputs), ("0", zeroed)):
                x, scale = assemble(given, design)
                with torch.no_grad():
                    scores = image_metrics(predict(net, x, *target.shape[:2], scale), target, flip)
                sums["relmse" + suffix] += scores["relmse"]
                sums["flip" + suffix] += scores["flip"]
            count += 1
        mean = {key: value / count for key, value in sums.items()}
        print(
            f"| {path} | {mean['relmse']:.5f} | {mean['relmse0']:.5f} | {mean['flip']:.4f} | "
            f"{mean['flip0']:.4f} |"
        )


if __name__ == "__main__":
    main()
