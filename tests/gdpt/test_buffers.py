"""``GradientBuffers`` operations that are not I/O or pooling: the centre crop."""

from __future__ import annotations

import torch


def test_centre_crop_cuts_every_buffer_to_the_same_centre_window(random_buffers):
    buffers = random_buffers(12, 10)
    crop = buffers.centre_crop(4)
    assert (crop.height, crop.width) == (4, 4)
    for name, tensor in buffers.items():
        assert torch.equal(getattr(crop, name), tensor[4:8, 3:7]), name
    assert crop.spp == buffers.spp and crop.metadata == buffers.metadata


def test_centre_crop_keeps_a_side_that_fits_and_an_image_that_fits(random_buffers):
    buffers = random_buffers(12, 3)
    crop = buffers.centre_crop(4)
    assert (crop.height, crop.width) == (4, 3)
    assert torch.equal(crop.primal, buffers.primal[4:8])
    assert buffers.centre_crop(12) is buffers
