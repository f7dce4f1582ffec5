"""gdpt.reconstruct.kernels: per-pixel softmax kernels on known images (one-hot taps, box
filters, the range of the mixed values) and logits of the wrong shape."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from gdpt.reconstruct.kernels import apply_kernels


def one_hot_logits(n: int, k_cand: int, kernel: int, h: int, w: int, index: int) -> torch.Tensor:
    logits = torch.full((n, k_cand * kernel * kernel, h, w), -1e4)
    logits[:, index] = 0.0
    return logits


def test_a_one_hot_kernel_picks_one_candidate_at_one_offset():
    cands = torch.rand(2, 2, 3, 9, 11, generator=torch.Generator().manual_seed(1))
    centre = apply_kernels(cands, one_hot_logits(2, 2, 3, 9, 11, 9 + 4), 3)
    assert torch.equal(centre, cands[:, 1])
    right = apply_kernels(cands, one_hot_logits(2, 2, 3, 9, 11, 5), 3)  # tap (0, +1)
    assert torch.equal(right[..., :-1], cands[:, 0, ..., 1:])
    assert torch.equal(right[..., -1], cands[:, 0, ..., -1])  # edge replicated


def test_uniform_logits_on_one_candidate_are_a_box_filter():
    cands = torch.rand(1, 2, 3, 8, 8, generator=torch.Generator().manual_seed(2))
    logits = torch.full((1, 18, 8, 8), -1e4)
    logits[:, :9] = 0.0
    out = apply_kernels(cands, logits, 3)
    box = F.avg_pool2d(F.pad(cands[:, 0], (1, 1, 1, 1), mode="replicate"), 3, stride=1)
    torch.testing.assert_close(out, box)


def test_output_lies_within_the_range_of_the_mixed_values():
    g = torch.Generator().manual_seed(3)
    cands = torch.rand(1, 2, 3, 8, 8, generator=g)
    out = apply_kernels(cands, torch.randn(1, 18, 8, 8, generator=g) * 3, 3)
    padded = F.pad(cands.flatten(1, 2), (1, 1, 1, 1), mode="replicate").unflatten(1, (2, 3))
    lo = -F.max_pool2d(-padded.amin(1), 3, stride=1)
    hi = F.max_pool2d(padded.amax(1), 3, stride=1)
    assert (out >= lo - 1e-6).all() and (out <= hi + 1e-6).all()


def test_logits_of_the_wrong_shape_are_refused():
    with pytest.raises(ValueError, match="do not fit 2 candidates"):
        apply_kernels(torch.rand(1, 2, 3, 8, 8), torch.rand(1, 9, 8, 8), 3)
