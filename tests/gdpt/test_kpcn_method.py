"""The ``kpcn`` reconstruction method: it renders and reads the primal's variance, runs from the
API and the command line, names a missing buffer, and a registered KPCN checkpoint reads the
variance too."""

from __future__ import annotations

import pytest
import torch
from gdpt.reconstruct.kpcn import KPCN_DESIGNS, KPCNNet, encode_kpcn

from gdpt.cli import main
from gdpt.io.exr import load_image, save_buffers
from gdpt.methods import METHODS, reconstruct_image, register_checkpoint
from gdpt.training.checkpoint import write_checkpoint

pytestmark = pytest.mark.usefixtures("single_thread")


def test_the_method_renders_the_variance_and_no_gradients():
    assert METHODS["kpcn"].sampling(8) == {"gradients": False, "features": True, "variance": True}


def test_the_shipped_network_reconstructs_buffers(random_buffers):
    buffers = random_buffers(16, 12)
    image = reconstruct_image(buffers, method="kpcn")
    assert image.shape == (16, 12, 3) and torch.isfinite(image).all() and (image >= 0).all()
    with pytest.raises(KeyError, match="lack var_primal"):
        reconstruct_image(buffers.replace(var_primal=None), method="kpcn")


def test_the_command_line_reconstructs_with_kpcn(random_buffers, tmp_path):
    render = save_buffers(tmp_path / "render.exr", random_buffers(16, 12))
    out = tmp_path / "kpcn.exr"
    assert main(["reconstruct", str(render), "--method", "kpcn", "-o", str(out)]) == 0
    expected = reconstruct_image(random_buffers(16, 12), method="kpcn")
    torch.testing.assert_close(load_image(out), expected)


def test_a_registered_kpcn_checkpoint_reads_the_variance(tmp_path, random_buffers):
    weights, _ = write_checkpoint(
        tmp_path / "mine", *encode_kpcn(KPCNNet(KPCN_DESIGNS["kpcn"]), "kpcn", {})
    )
    try:
        method = register_checkpoint("mine-kpcn", weights)
        assert method.needs == {"gradients": False, "features": True, "variance": True}
        image = reconstruct_image(random_buffers(8, 8), method="mine-kpcn")
        assert torch.isfinite(image).all()
    finally:
        METHODS.pop("mine-kpcn", None)


def test_pt_kpcn_runs_in_the_study_under_the_default_protocol(tmp_path):
    """``pt+kpcn`` in a tiny study (protocol ``total``): the reconstruction's seconds are part
    of the charged time, and the image is scored."""
    from gdpt.study.config import EvaluateConfig
    from gdpt.study.evaluate import evaluate

    cfg = EvaluateConfig(
        budgets=(0.2,),
        resolution=12,
        reference_spp=32,
        reference_chunk_spp=32,
        metrics=("relmse",),
        metric_options={},
        methods=("pt+kpcn",),
    )
    results = evaluate(["random:3"], tmp_path / "study", cfg, progress=False, report=False)
    cell = results["scenes"]["random-3"]["methods"]["pt+kpcn"]["cells"]["0.2"]
    assert cell["protocol"] == "total" and cell["reconstruct_seconds"] > 0
    assert cell["charged_seconds"] == pytest.approx(cell["seconds"])
    assert cell["metrics"]["relmse"] > 0
