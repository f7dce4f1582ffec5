"""The networks shipped in ``gdpt/models``: present, documented, the default, and useful.

The quality check renders the built-in Cornell box at 8 spp and requires each shipped network to
reduce the relMSE of its noisy input against a converged reference; the current networks fail it
(strict xfail below), as do networks that paint or blow up pixels.
"""

from __future__ import annotations

import json

import pytest
import torch

import gdpt
from gdpt.denoise import MODEL_DIR, reconstruct
from gdpt.metrics import relmse
from gdpt.scenes import builtin_scene
from gdpt.training.model_report import MAX_SHIPPED_MIB

SHIPPED = {"ngpt": True, "ngpt-nograd": False}  # name -> reads gradients


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_model_has_weights_and_card(name):
    weights, card_path = MODEL_DIR / f"{name}.safetensors", MODEL_DIR / f"{name}.json"
    assert weights.is_file() and card_path.is_file(), f"{name} is not shipped in {MODEL_DIR}"
    assert weights.stat().st_size <= MAX_SHIPPED_MIB * 2**20
    card = json.loads(card_path.read_text())
    assert card["name"] == name
    assert card["steps"] > 0 and card["wall_clock_hours"] > 0
    assert card["dataset_size"]["crops"] > 0 and card["train_config"]["loss"]
    assert ("dx" in card["features"]) is SHIPPED[name]
    assert card["heldout_comparison"]["crops"] > 0


@pytest.fixture(scope="module")
def cbox():
    gdpt.set_variant("llvm_ad_rgb")
    scene = builtin_scene("cbox-demo", resolution=(48, 48))
    reference = gdpt.render(scene, spp=2048, seed=99, gradients=False, features=False).primal
    return scene, reference.cpu()


def _default_reconstruction(name, scene, monkeypatch):
    """8-spp buffers of ``scene`` and their reconstruction by ``method=name`` without model=."""
    monkeypatch.delenv("GDPT_NGPT_MODEL", raising=False)
    buffers = gdpt.render(scene, spp=8, seed=1, gradients=SHIPPED[name])
    return buffers, reconstruct(buffers, method=name)


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_model_is_the_default_and_finite(name, cbox, monkeypatch):
    buffers, image = _default_reconstruction(name, cbox[0], monkeypatch)
    explicit = reconstruct(buffers, method=name, model=MODEL_DIR / f"{name}.safetensors")
    assert torch.equal(image, explicit)
    assert torch.isfinite(image).all() and (image >= 0).all()


# Known deficiency, kept visible: the CPU-trained networks (2,500 updates on 40 crops) make
# cbox-demo worse than their own noisy input (README, "Training data ..."). strict: once a
# better-trained model passes, this xfail turns into a failure and must be removed.
@pytest.mark.xfail(
    strict=True,
    reason="shipped CPU-trained networks do not yet beat their noisy input on cbox-demo (issue 5)",
)
@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_model_reduces_error(name, cbox, monkeypatch):
    scene, reference = cbox
    buffers, image = _default_reconstruction(name, scene, monkeypatch)
    assert relmse(image.cpu(), reference) < relmse(buffers.primal.cpu(), reference)
