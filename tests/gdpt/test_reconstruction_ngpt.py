"""``reconstruct(buffers, method="ngpt")``: checkpoint lookup, inference, errors."""

from __future__ import annotations

import pytest
import torch

from gdpt.buffers import GradientBuffers
from gdpt.denoise import reconstruct


def _buffers(h=13, w=17, gradients=True):
    g = torch.Generator().manual_seed(0)
    rand = lambda c: torch.rand(h, w, c, generator=g)  # noqa: E731
    extra = {"dx": rand(3) - 0.5, "dy": rand(3) - 0.5} if gradients else {}
    return GradientBuffers(
        primal=rand(3), albedo=rand(3), normal=rand(3) * 2 - 1, depth=rand(1), spp=4, **extra
    )


@pytest.fixture
def checkpoint(tmp_path):
    from gdpt.reconstruct.dense_unet import build_model

    from gdpt.training.checkpoint import save_checkpoint

    torch.manual_seed(0)
    path = tmp_path / "tiny.safetensors"
    save_checkpoint(build_model("fast_xs"), path, {"training": "random init (test)"})
    return path


def test_ngpt_with_explicit_checkpoint(checkpoint):
    image = reconstruct(_buffers(), method="ngpt", model=checkpoint)
    assert image.shape == (13, 17, 3) and image.dtype == torch.float32
    assert torch.isfinite(image).all() and (image >= 0).all()  # radiance: clamped at 0


def test_checkpoint_from_environment(checkpoint, monkeypatch):
    monkeypatch.setenv("GDPT_NGPT_MODEL", str(checkpoint))
    assert reconstruct(_buffers(), method="ngpt").shape == (13, 17, 3)


def test_missing_checkpoint_says_what_to_provide(tmp_path, monkeypatch):
    monkeypatch.delenv("GDPT_NGPT_MODEL", raising=False)
    with pytest.raises(FileNotFoundError, match="model=PATH"):
        reconstruct(_buffers(), method="ngpt", model=tmp_path / "none.safetensors")


def test_missing_gradients_named(checkpoint):
    with pytest.raises((KeyError, ValueError), match="dx"):
        reconstruct(_buffers(gradients=False), method="ngpt", model=checkpoint)
