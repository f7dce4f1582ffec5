"""``reconstruct_image(buffers, method="oidn-grad", model=...)`` with a trained checkpoint (a
dense U-Net): checkpoint lookup, inference, errors, and the method's deprecated names."""

from __future__ import annotations

import pytest
import torch
from gdpt.reconstruct.transforms import FEATURES_WITH_GRADIENTS, FEATURES_WITHOUT_GRADIENTS

from gdpt.checkpoints import model_path
from gdpt.methods import reconstruct_image


@pytest.fixture
def dense_unet_buffers(random_buffers):
    """``f(gradients=True)``: 13x17 random dense U-Net input buffers (with or without dx, dy)."""

    def make(gradients: bool = True):
        names = FEATURES_WITH_GRADIENTS if gradients else FEATURES_WITHOUT_GRADIENTS
        return random_buffers(13, 17, names=names)

    return make


@pytest.fixture
def checkpoint(tmp_path):
    from gdpt.reconstruct.dense_unet import build_model

    from gdpt.training.checkpoint import save_checkpoint

    torch.manual_seed(0)
    path = tmp_path / "tiny.safetensors"
    save_checkpoint(build_model("fast_xs"), path, {"training": "random init (test)"})
    return path


def test_network_with_explicit_checkpoint(checkpoint, dense_unet_buffers):
    image = reconstruct_image(dense_unet_buffers(), method="oidn-grad", model=checkpoint)
    assert image.shape == (13, 17, 3) and image.dtype == torch.float32
    assert torch.isfinite(image).all() and (image >= 0).all()  # radiance: clamped at 0


def test_checkpoint_from_environment(checkpoint, monkeypatch, dense_unet_buffers):
    monkeypatch.setenv("GDPT_OIDN_GRAD_MODEL", str(checkpoint))
    assert reconstruct_image(dense_unet_buffers(), method="oidn-grad").shape == (13, 17, 3)


def test_deprecated_environment_variable_is_honoured_with_a_warning(checkpoint, monkeypatch):
    monkeypatch.delenv("GDPT_OIDN_GRAD_MODEL", raising=False)
    monkeypatch.setenv("GDPT_NGPT_MODEL", str(checkpoint))
    message = "GDPT_NGPT_MODEL is deprecated; set GDPT_OIDN_GRAD_MODEL"
    with pytest.warns(DeprecationWarning, match=message):
        assert model_path("oidn-grad") == checkpoint
    monkeypatch.setenv("GDPT_OIDN_GRAD_MODEL", str(checkpoint.parent / "new.safetensors"))
    with pytest.raises(FileNotFoundError, match="new.safetensors"):  # the new variable wins
        model_path("oidn-grad")


def test_deprecated_method_name_warns_and_runs_the_new_method(checkpoint, dense_unet_buffers):
    buffers = dense_unet_buffers()
    with pytest.warns(DeprecationWarning, match="'ngpt' is deprecated; use 'oidn-grad'") as caught:
        old = reconstruct_image(buffers, method="ngpt", model=checkpoint)
    assert caught[0].filename == __file__  # the warning names the caller's line
    new = reconstruct_image(buffers, method="oidn-grad", model=checkpoint)
    torch.testing.assert_close(old, new, rtol=0, atol=0)


def test_missing_checkpoint_says_what_to_provide(tmp_path, monkeypatch, dense_unet_buffers):
    monkeypatch.delenv("GDPT_OIDN_GRAD_MODEL", raising=False)
    with pytest.raises(FileNotFoundError, match="checkpoint not found: .*model=PATH"):
        reconstruct_image(
            dense_unet_buffers(), method="oidn-grad", model=tmp_path / "none.safetensors"
        )


def test_missing_gradients_named(checkpoint, dense_unet_buffers):
    with pytest.raises((KeyError, ValueError), match="dx"):
        reconstruct_image(dense_unet_buffers(gradients=False), method="oidn-grad", model=checkpoint)
