"""gdpt.denoise: the method dispatcher (the solvers are tested in tests/reconstruct)."""

from __future__ import annotations

import sys
import types

import gdpt.reconstruct
import pytest
import torch

from gdpt.buffers import GradientBuffers
from gdpt.denoise import METHODS, reconstruct


def make_buffers(gradients: bool = True) -> GradientBuffers:
    t = torch.rand(6, 5, 3)
    return GradientBuffers(primal=t, dx=t if gradients else None, dy=t if gradients else None)


@pytest.fixture
def fake_poisson(monkeypatch):
    calls = []

    def fake(primal, dx, dy, *, method, alpha, **options):
        calls.append((method, alpha, options))
        return primal + 1

    module = types.SimpleNamespace(reconstruct=fake)
    monkeypatch.setitem(sys.modules, "gdpt.reconstruct.poisson", module)
    monkeypatch.setattr(gdpt.reconstruct, "poisson", module, raising=False)
    return calls


@pytest.mark.parametrize("method", ["l1", "l2"])
def test_poisson_methods_dispatch(fake_poisson, method):
    buffers = make_buffers()
    out = reconstruct(buffers, method, alpha=0.5, iterations=3)
    assert torch.equal(out, buffers.primal + 1)
    assert fake_poisson == [(method, 0.5, {"iterations": 3})]


def test_primal_only_is_a_clear_error(fake_poisson):
    with pytest.raises(ValueError, match=r"'l1' needs dx and dy.*primal-only"):
        reconstruct(make_buffers(gradients=False))
    assert fake_poisson == []


def test_unknown_method_lists_valid_ones():
    with pytest.raises(ValueError, match="valid names: " + ", ".join(METHODS)):
        reconstruct(make_buffers(), "bilateral")
