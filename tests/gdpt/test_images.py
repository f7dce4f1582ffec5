"""gdpt.io.images: sRGB tone mapping, PNG previews and the labelled montage."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from gdpt.io.images import preview_path, save_png, side_by_side, to_srgb8


def test_srgb_encoding_of_known_values():
    hdr = torch.tensor([[[0.0, 0.0031308, 0.18], [1.0, 2.0, -1.0], [float("nan"), 0.5, 0.0]]])
    out = to_srgb8(hdr)
    assert out.dtype == np.uint8 and out.shape == (1, 3, 3)
    # sRGB: 0 -> 0, linear 0.0031308 -> 0.0404 -> 10, 0.18 -> 118, >= 1 -> 255, < 0 -> 0.
    assert out[0, 0].tolist() == [0, 10, 118]
    assert out[0, 1].tolist() == [255, 255, 0]
    assert out[0, 2].tolist() == [0, 188, 0]  # NaN shows as black


def test_exposure_tonemap_and_gray():
    hdr = np.full((2, 2, 1), 0.5, dtype=np.float32)
    assert to_srgb8(hdr).shape == (2, 2, 3)
    assert to_srgb8(hdr, exposure=1.0)[0, 0, 0] == 255
    assert to_srgb8(hdr * 8, tonemap="reinhard")[0, 0, 0] < 255  # 4 / 5 = 0.8
    with pytest.raises(ValueError, match="reinhard"):
        to_srgb8(hdr, tonemap="aces")
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        to_srgb8(np.zeros((4, 4)))


def test_save_png_and_preview_path(tmp_path):
    path = preview_path(tmp_path / "out" / "render.exr")
    assert path == tmp_path / "out" / "render.png"
    path.parent.mkdir()
    save_png(path, torch.rand(5, 7, 3))
    assert Image.open(path).size == (7, 5)
    with pytest.raises(FileExistsError):
        save_png(path, torch.rand(5, 7, 3))
    save_png(path, torch.rand(5, 7, 3), force=True)


def test_side_by_side(tmp_path):
    images = {"noisy": torch.rand(8, 8, 3), "L1 reconstruction": torch.rand(6, 8, 3)}
    path = side_by_side(images, tmp_path / "m.png", scale=3)
    montage = Image.open(path)
    assert montage.width > 2 * 24 and montage.height > 24
    with pytest.raises(ValueError):
        side_by_side({}, tmp_path / "e.png")
