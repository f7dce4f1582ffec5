"""Tests of the dense U-Net reconstructor: tiling, padding of tiny images, checkpoints and
input errors."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest
import torch
from gdpt.reconstruct import cards, dense_unet_reconstructor
from gdpt.reconstruct.cards import CheckpointMismatchError
from gdpt.reconstruct.dense_unet import DenseUNet, ModelConfig, build_model
from gdpt.reconstruct.dense_unet_reconstructor import DenseUNetReconstructor

from gdpt.training.checkpoint import save_checkpoint

#: A small dense config (radius 28 px) so that tiles are cut well inside the test images.
TINY = ModelConfig(
    growth_rates=(8, 12, 12),
    unit_counts=(2, 1, 1),
    decoder_unit_counts=(2, 1, 1),
    pool_features=(16, 16),
    unpool_features=(8, 16),
)


def _model(config: ModelConfig | str, seed: int = 0) -> DenseUNet:
    torch.manual_seed(seed)
    model = build_model(config) if isinstance(config, str) else DenseUNet(config)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if not name.endswith("weight"):
                p.add_(0.1 * torch.randn_like(p))
    return model


def _buffers(h: int, w: int, seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    image = torch.rand(h, w, 3, generator=gen) * 3
    dx, dy = torch.zeros_like(image), torch.zeros_like(image)
    dx[:, :-1] = image[:, 1:] - image[:, :-1]
    dy[:-1] = image[1:] - image[:-1]
    return {
        "primal": image + 0.3 * torch.randn(h, w, 3, generator=gen),
        "dx": dx,
        "dy": dy,
        "albedo": torch.rand(h, w, 3, generator=gen),
        "normal": torch.rand(h, w, 3, generator=gen) * 2 - 1,
        "depth": torch.rand(h, w, 1, generator=gen) * 10,
    }


@pytest.mark.parametrize(
    ("config", "size", "tile"), [(TINY, (97, 121), 24), ("fast_xs", (100, 90), 56)]
)
def test_tiled_equals_untiled(config, size, tile):
    model = _model(config)
    bufs = _buffers(*size)
    untiled = DenseUNetReconstructor(model, tile_size=None)(bufs)
    tiled_rec = DenseUNetReconstructor(model, tile_size=tile)
    tiled = tiled_rec(bufs)
    assert len(tiled_rec.tiles(size[0] + 24, size[1] + 24)) > 4
    assert tiled.shape == (*size, 3) and tiled.dtype == torch.float32
    assert tiled_rec.overlap >= model.receptive_radius
    torch.testing.assert_close(tiled, untiled, rtol=1e-4, atol=1e-4)


def test_tiny_images_batches_and_nonfinite_inputs():
    rec = DenseUNetReconstructor(_model("fast_xs"))
    bufs = _buffers(3, 5)
    bufs["primal"][1, 1] = float("nan")
    bufs["dx"][0, 0] = float("inf")
    out = rec(bufs)
    assert out.shape == (3, 5, 3) and torch.isfinite(out).all()
    batch = {k: torch.stack([v, v]) for k, v in _buffers(9, 13).items()}
    out = rec(batch)
    assert out.shape == (2, 9, 13, 3)
    torch.testing.assert_close(out[0], out[1])
    # objects with buffer attributes (gdpt.buffers.GradientBuffers) are accepted too
    single = _buffers(9, 13)
    torch.testing.assert_close(rec(SimpleNamespace(**single, var_primal=None)), rec(single))


def test_missing_and_malformed_buffers():
    rec = DenseUNetReconstructor(_model(TINY))
    bufs = _buffers(16, 16)
    del bufs["dy"], bufs["albedo"]
    with pytest.raises(KeyError, match=r"missing feature buffers \['dy', 'albedo'\]"):
        rec(bufs)
    bad = {**_buffers(16, 16), "normal": torch.zeros(16, 16, 2)}
    with pytest.raises(ValueError, match="'normal' must have shape"):
        rec(bad)


def test_checkpoint_round_trip(tmp_path):
    model = _model("nograd")
    card = {
        "training": {"scenes": ["cbox"], "spp": [2, 1024]},
        "steps": 12,
        "validation": {"relmse": 0.125},
    }
    weights, card_path = save_checkpoint(model, tmp_path / "ckpt" / "model.pt", card)
    assert weights.suffix == ".safetensors" and card_path.suffix == ".json"
    stored = json.loads(card_path.read_text())
    assert stored["config_name"] == "nograd" and stored["steps"] == 12
    assert stored["features"] == ["primal", "albedo", "normal", "depth"]
    rec = DenseUNetReconstructor.from_checkpoint(card_path)
    assert rec.features == ("primal", "albedo", "normal", "depth")
    assert rec.card["validation"] == {"relmse": 0.125}
    bufs = _buffers(24, 24)
    del bufs["dx"], bufs["dy"]
    torch.testing.assert_close(rec(bufs), DenseUNetReconstructor(model)(bufs))
    with pytest.raises(ValueError, match="reserved"):
        save_checkpoint(model, tmp_path / "x", {"config": 1})


def test_cards_of_the_former_format_still_load(tmp_path):
    """A card written before the format was renamed (``gdpt-ngpt-checkpoint/1``) is recognised
    as a dense U-Net and loads like a current one; new cards carry the current format."""
    from gdpt.reconstruct.families import FAMILIES, family_of

    model = _model(TINY)
    _, card_path = save_checkpoint(model, tmp_path / "m")
    card = json.loads(card_path.read_text())
    assert card["format"] == dense_unet_reconstructor.CARD_FORMAT == "gdpt-dense-unet-checkpoint/1"
    card["format"] = "gdpt-ngpt-checkpoint/1"
    card_path.write_text(json.dumps(card))
    loaded, stored = dense_unet_reconstructor.load_checkpoint(card_path)
    assert stored["format"] == "gdpt-ngpt-checkpoint/1"
    assert family_of(card_path) is FAMILIES["dense-unet"]
    bufs = _buffers(24, 24)
    expected = DenseUNetReconstructor(model)(bufs)
    torch.testing.assert_close(DenseUNetReconstructor(loaded)(bufs), expected)
    torch.testing.assert_close(DenseUNetReconstructor.from_checkpoint(card_path)(bufs), expected)
    card["format"] = "gdpt-unknown-checkpoint/1"
    card_path.write_text(json.dumps(card))
    with pytest.raises(CheckpointMismatchError, match="this code reads"):
        dense_unet_reconstructor.load_checkpoint(card_path)


def test_checkpoint_mismatch_errors(tmp_path):
    model = _model(TINY)
    model.name = "fast"  # pretend a registered name with a different config
    _, card_path = save_checkpoint(model, tmp_path / "m")
    with pytest.raises(CheckpointMismatchError, match="differs from the code's 'fast'.*growth"):
        dense_unet_reconstructor.load_checkpoint(card_path)
    card = json.loads(card_path.read_text())
    card["config_name"] = None
    card["config"]["growth_rates"] = [8, 12, 16]
    card_path.write_text(json.dumps(card))
    with pytest.raises(CheckpointMismatchError, match="does not match the config.*stored"):
        dense_unet_reconstructor.load_checkpoint(card_path)
    card["config"]["colour"] = 1
    card_path.write_text(json.dumps(card))
    with pytest.raises(CheckpointMismatchError, match="unknown ModelConfig fields"):
        dense_unet_reconstructor.load_checkpoint(card_path)
    with pytest.raises(FileNotFoundError, match="need .safetensors"):
        dense_unet_reconstructor.load_checkpoint(tmp_path / "absent.safetensors")


@pytest.mark.parametrize(
    ("damage", "problem"),
    [
        (lambda data: bytes(range(256)) * 4, "header too large"),
        (lambda data: data[: len(data) // 2], "file not fully covered"),
        (lambda data: b"", "header too small"),
    ],
    ids=["random-bytes", "truncated", "empty"],
)
def test_corrupt_weights_are_a_value_error_naming_the_file(tmp_path, damage, problem):
    """A checkpoint whose ``.safetensors`` is corrupt (its card intact) is refused when its card
    is read, by every reader (and ``gdpt evaluate --model`` before any rendering)."""
    from gdpt.methods import METHODS, register_checkpoint

    weights, card_path = save_checkpoint(_model(TINY), tmp_path / "m")
    weights.write_bytes(damage(weights.read_bytes()))
    expected = rf"m\.safetensors: not a readable safetensors file \(.*{problem}"
    for read in (
        cards.read_card,
        dense_unet_reconstructor.load_checkpoint,
        DenseUNetReconstructor.from_checkpoint,
    ):
        with pytest.raises(ValueError, match=expected):
            read(card_path)
    with pytest.raises(ValueError, match=expected):
        register_checkpoint("corrupt-test", weights)
    assert "corrupt-test" not in METHODS


def test_card_that_is_not_a_json_object_names_the_file(tmp_path):
    _, card_path = save_checkpoint(_model(TINY), tmp_path / "m")
    card_path.write_text("{truncated")
    with pytest.raises(ValueError, match=r"m\.json: model card is not valid JSON"):
        cards.read_card(card_path)
    card_path.write_text("[]")
    with pytest.raises(ValueError, match=r"m\.json: model card is not a JSON object"):
        cards.read_card(card_path)


def test_input_gradients_match_finite_differences():
    """Directional derivatives of ``sum(w * rec(buffers))`` along random directions: autograd
    against central differences. The differences converge to the derivative as the step
    shrinks (at step 1e-2 they were still 16% off for ``dy``: curvature and leaky-ReLU kinks);
    at 3e-4 float32 rounding leaves 0.7-2.4% (measured), hence 5%."""
    rec = DenseUNetReconstructor(_model(TINY), tile_size=None)
    bufs = _buffers(16, 20)
    gen = torch.Generator().manual_seed(1)
    weight = torch.rand(16, 20, 3, generator=gen)
    names = ("primal", "dx", "dy", "albedo")
    leaves = {k: v.clone().requires_grad_(k in names) for k, v in bufs.items()}
    (weight * rec(leaves)).sum().backward()
    assert all(p.grad is None for p in rec._model.parameters())  # frozen weights
    step = 3e-4
    for name in names:
        v = torch.randn(bufs[name].shape, generator=gen)
        with torch.no_grad():
            up = rec({**bufs, name: bufs[name] + step * v})
            down = rec({**bufs, name: bufs[name] - step * v})
        finite = float((weight * (up - down)).sum()) / (2 * step)
        assert float((leaves[name].grad * v).sum()) == pytest.approx(finite, rel=0.05), name


def test_inference_mode_unless_a_buffer_requires_gradients():
    rec = DenseUNetReconstructor(_model(TINY))
    bufs = _buffers(8, 8)
    assert rec(bufs).is_inference()
    bufs["depth"].requires_grad_(True)
    out = rec(bufs)
    assert out.requires_grad and not out.is_inference()
