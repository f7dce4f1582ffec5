"""Tests of gdpt.reconstruct.colour: sRGB transfer functions and NGPT's Reinhard tone map."""

from __future__ import annotations

import colour
import numpy as np
import pytest
import torch
from gdpt.reconstruct.colour import check_image_pair, reinhard, srgb_decode, srgb_encode

pytestmark = pytest.mark.usefixtures("single_thread")


def test_srgb_matches_colour_science() -> None:
    x = np.concatenate([np.linspace(-0.1, 2.0, 1001), [0.0031308, 0.04045, 1.0]])
    encoded = srgb_encode(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(encoded, colour.cctf_encoding(x, function="sRGB"), atol=1e-12)
    y = np.linspace(-0.1, 1.5, 1001)
    decoded = srgb_decode(torch.from_numpy(y)).numpy()
    np.testing.assert_allclose(decoded, colour.cctf_decoding(y, function="sRGB"), atol=1e-12)
    np.testing.assert_allclose(srgb_decode(srgb_encode(torch.from_numpy(x))).numpy(), x, atol=1e-12)


def test_srgb_and_reinhard_gradcheck() -> None:
    x = torch.linspace(-0.5, 2.0, 24, dtype=torch.float64).view(2, 3, 2, 2).requires_grad_()
    assert torch.autograd.gradcheck(srgb_encode, (x,))
    assert torch.autograd.gradcheck(srgb_decode, (x,))
    assert torch.autograd.gradcheck(reinhard, (x,))
    zero = torch.zeros(3, requires_grad=True)
    srgb_encode(zero).sum().backward()
    assert torch.isfinite(zero.grad).all()


def test_reinhard_values_oddness_and_layouts() -> None:
    x = torch.tensor([1.0, 1.0, 1.0]).view(1, 3, 1, 1)
    assert torch.allclose(reinhard(x), torch.full_like(x, 0.5))
    x = torch.tensor([3.0, -1.0, 2.0]).view(1, 3, 1, 1)  # mean |x| = 2
    assert torch.allclose(reinhard(x), x / 3.0)
    assert torch.equal(reinhard(-x), -reinhard(x))
    hwc = torch.randn(4, 5, 3)
    assert torch.allclose(
        reinhard(hwc, channel_dim=-1), reinhard(hwc.permute(2, 0, 1)).permute(1, 2, 0)
    )


def test_image_pair_check_names_both_shapes() -> None:
    check_image_pair(torch.zeros(2, 3, 4, 5), torch.zeros(2, 3, 4, 5))
    with pytest.raises(ValueError, match=r"pred \(1, 3, 4, 4\) and target \(1, 3, 4, 5\)"):
        check_image_pair(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 5))
    with pytest.raises(ValueError, match="N, 3, H, W"):
        check_image_pair(torch.zeros(3, 4, 4), torch.zeros(3, 4, 4))
