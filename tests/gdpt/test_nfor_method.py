"""The ``nfor`` reconstruction method on real renders: it beats the noisy input and a box filter
of its footprint, names what a render lacks, runs from the CLI on saved buffers, and runs in
the study as ``pt+nfor`` under both protocols."""

from __future__ import annotations

import dataclasses

import pytest
import torch
import torch.nn.functional as F

import gdpt
from gdpt.cli import main
from gdpt.methods import METHODS
from gdpt.study.config import EvaluateConfig
from gdpt.study.evaluate import evaluate

pytestmark = pytest.mark.usefixtures("variant")

SIZE, SPP, REFERENCE_SPP = 32, 8, 1024


def relmse(image: torch.Tensor, reference: torch.Tensor) -> float:
    return float(((image - reference).square() / (reference.square() + 1e-2)).mean())


@pytest.fixture(scope="module")
def cbox():
    """``(buffers, reference)``: ``cbox-demo`` at ``SIZE`` px, ``SPP`` spp with what ``nfor``
    reads, and a ``REFERENCE_SPP`` path-traced reference (another seed)."""
    gdpt.set_variant("llvm_ad_rgb")
    scene = gdpt.load_scene("builtin:cbox-demo", long_side=SIZE)
    buffers = gdpt.render(scene, spp=SPP, seed=1, **METHODS["nfor"].sampling(SPP))
    reference = gdpt.render(scene, spp=REFERENCE_SPP, seed=99, gradients=False, features=False)
    return buffers, reference.primal


def test_nfor_beats_the_noisy_input_and_a_box_filter_of_its_footprint(cbox):
    buffers, reference = cbox
    image = gdpt.reconstruct_image(buffers, method="nfor")
    window = 2 * 9 + 1  # NforConfig().radius
    padded = F.pad(buffers.primal.permute(2, 0, 1)[None], (9,) * 4, mode="replicate")
    box = F.avg_pool2d(padded, window, stride=1)[0].permute(1, 2, 0)
    noisy, boxed, nfor = (relmse(x, reference) for x in (buffers.primal, box, image))
    assert nfor < 0.5 * noisy and nfor < boxed, (noisy, boxed, nfor)
    assert buffers.metadata["nfor"]["nonfinite"] == 0


def test_nfor_names_the_buffers_a_render_lacks_and_their_options(variant):
    scene = gdpt.load_scene("builtin:cbox-demo", long_side=8)
    plain = gdpt.render(scene, spp=2, seed=0, gradients=False)
    with pytest.raises(ValueError, match=r"'primal_a' \(render with halves=True\)"):
        gdpt.reconstruct_image(plain, method="nfor")
    with pytest.raises(ValueError, match=r"'var_primal' \(render with variance=True\)"):
        gdpt.reconstruct_image(plain, method="nfor")


def test_nfor_options_are_checked_by_name(cbox):
    buffers, _ = cbox
    with pytest.raises(ValueError, match=r"unknown options \['radis'\]"):
        gdpt.reconstruct_image(buffers, method="nfor", radis=3)
    with pytest.raises(ValueError, match="radius"):
        gdpt.reconstruct_image(buffers, method="nfor", radius=0)


def test_cli_renders_halves_and_reconstructs_them_with_nfor(variant, tmp_path):
    exr, out = tmp_path / "b.exr", tmp_path / "nfor.exr"
    args = ["render", "builtin:cbox-demo", "--spp", "4", "--long-side", "16", "--no-gradients"]
    assert main([*args, "--variance", "--halves", "-o", str(exr)]) == 0
    assert main(["reconstruct", str(exr), "--method", "nfor", "-o", str(out)]) == 0
    image = gdpt.load_buffers(exr)
    assert image.primal_a is not None and image.albedo_b is not None
    assert out.is_file()


def test_pt_nfor_runs_in_the_study_under_the_papers_protocol(tmp_path):
    """``pt+nfor`` under ``render-time`` (its reconstruction costs more than the budget,
    which pays for sampling only); the folder then refuses a study under ``total``."""
    cfg = EvaluateConfig(
        budgets=(0.05,),
        resolution=12,
        reference_spp=32,
        reference_chunk_spp=32,
        metrics=("relmse",),
        metric_options={},
        methods=("pt+nfor",),
        protocol="render-time",
    )
    results = evaluate(["random:3"], tmp_path / "study", cfg, progress=False, report=True)
    cell = results["scenes"]["random-3"]["methods"]["pt+nfor"]["cells"]["0.05"]
    assert cell["protocol"] == "render-time" and cell["reconstruct_seconds"] > 0
    assert cell["charged_seconds"] == pytest.approx(cell["render_seconds"])
    assert cell["seconds"] > cell["render_seconds"]
    assert "render-time" in results["protocol"]
    assert "recon s" in (tmp_path / "study" / "results.md").read_text()
    total = dataclasses.replace(cfg, protocol="total")
    with pytest.raises(ValueError, match="different settings \\(protocol\\)"):
        evaluate(["random:3"], tmp_path / "study", total, progress=False, report=False)
