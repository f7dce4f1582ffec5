"""The networks shipped in ``gdpt/models``: present, documented, the default, and useful.

The quality checks render the built-in Cornell box at 8 spp and require each shipped network to
reduce the relMSE of its noisy input against a converged reference (networks that paint or blow
up pixels fail it), and to beat L1 screened Poisson on procedural scenes held out of training.
"""

from __future__ import annotations

import json

import pytest
import torch

import gdpt
from gdpt.checkpoints import MODEL_DIR
from gdpt.methods import METHODS, reconstruct_image
from gdpt.metrics import relmse
from gdpt.scenes import builtin_scene
from gdpt.training.model_report import MAX_SHIPPED_MIB

SHIPPED = {"oidn-grad": True, "oidn-tuned": False, "kpcn": False}  # name -> reads gradients
#: The shipped networks that build on Intel's OIDN weights (read from mitsuba-oidn).
ON_OIDN = ("oidn-grad", "oidn-tuned")


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
    monkeypatch.delenv("GDPT_OIDN_GRAD_MODEL", raising=False)
    buffers = gdpt.render(scene, spp=8, seed=1, **METHODS[name].sampling(8))
    return buffers, reconstruct_image(buffers, method=name)


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_model_is_the_default_and_finite(name, cbox, monkeypatch):
    buffers, image = _default_reconstruction(name, cbox[0], monkeypatch)
    explicit = reconstruct_image(buffers, method=name, model=MODEL_DIR / f"{name}.safetensors")
    assert torch.equal(image, explicit)
    assert torch.isfinite(image).all() and (image >= 0).all()


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_model_reduces_error(name, cbox, monkeypatch):
    scene, reference = cbox
    buffers, image = _default_reconstruction(name, scene, monkeypatch)
    assert relmse(image.cpu(), reference) < relmse(buffers.primal.cpu(), reference)


@pytest.fixture(scope="module")
def generated():
    """Two procedural scenes no model was trained on (the training sets use scene seeds drawn
    by ``gdpt.training.preprocess.scene_seed``), 64 px, with 2048-spp path-traced references."""
    gdpt.set_variant("llvm_ad_rgb")
    scenes = []
    for source in ("random:4242", "random:777:1"):
        scene = gdpt.load_scene(source, long_side=64)
        reference = gdpt.render(scene, spp=2048, seed=5, gradients=False, features=False)
        scenes.append((scene, reference.primal.cpu()))
    return scenes


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_model_beats_l1_poisson_on_generated_scenes(name, generated, monkeypatch):
    """Equal time by the training data's rule (a G-PT sample costs 2.5 path samples):
    oidn-tuned and kpcn read 40 path-traced spp against gdpt+l1 at 16 G-PT spp; oidn-grad reads
    16 G-PT spp with 40 plain path spp pooled into the primal (what its card asks for) against
    gdpt+l1 at 32 G-PT spp. Summed relMSE over both scenes."""
    monkeypatch.delenv("GDPT_OIDN_GRAD_MODEL", raising=False)
    ours = l1 = 0.0
    for scene, reference in generated:
        if SHIPPED[name]:
            g = gdpt.render(scene, spp=32, seed=2)
            b = gdpt.render(scene, spp=16, seed=3, **METHODS[name].sampling(16))
            assert b.metadata["primal_spp"] == 56
        else:
            g = gdpt.render(scene, spp=16, seed=2)
            b = gdpt.render(scene, spp=40, seed=3, **METHODS[name].sampling(40))
        l1 += relmse(reconstruct_image(g, method="l1").cpu(), reference)
        ours += relmse(reconstruct_image(b, method=name).cpu(), reference)
    assert ours < l1, (ours, l1)


def test_shipped_gradient_model_names_a_missing_buffer(cbox, monkeypatch):
    monkeypatch.delenv("GDPT_OIDN_GRAD_MODEL", raising=False)
    buffers = gdpt.render(cbox[0], spp=2, seed=1, gradients=False)
    with pytest.raises(KeyError, match="dx"):
        reconstruct_image(buffers, method="oidn-grad")


@pytest.mark.parametrize("name", ON_OIDN)
def test_missing_mitsuba_oidn_is_named_with_the_method(name, cbox, monkeypatch):
    import importlib.util

    monkeypatch.delenv("GDPT_OIDN_GRAD_MODEL", raising=False)
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda n, *a: None if n == "mitsuba_oidn" else find_spec(n, *a)
    )
    reason = METHODS[name].check()
    assert reason is not None and "mitsuba-oidn" in reason and repr(name) in reason
    buffers = gdpt.render(cbox[0], spp=2, seed=1, gradients=SHIPPED[name])
    with pytest.raises(RuntimeError, match="mitsuba-oidn"):
        reconstruct_image(buffers, method=name)
