"""gdpt.methods: the method dispatcher (the solvers are tested in tests/reconstruct)."""

from __future__ import annotations

import sys
import types

import gdpt.reconstruct
import pytest
import torch

from gdpt.methods import METHODS, reconstruct_image


@pytest.fixture
def fake_poisson(monkeypatch):
    calls = []

    def fake(primal, dx, dy, *, solver, alpha, **options):
        calls.append((solver, alpha, options))
        return primal + 1

    module = types.SimpleNamespace(solve=fake)
    monkeypatch.setitem(sys.modules, "gdpt.reconstruct.poisson", module)
    monkeypatch.setattr(gdpt.reconstruct, "poisson", module, raising=False)
    return calls


@pytest.mark.parametrize("method", ["l1", "l2"])
def test_poisson_methods_dispatch(fake_poisson, method, random_buffers):
    buffers = random_buffers(names=("primal", "dx", "dy"))
    out = reconstruct_image(buffers, method, alpha=0.5, iterations=3)
    assert torch.equal(out, buffers.primal + 1)
    assert fake_poisson == [(method, 0.5, {"iterations": 3})]


def test_primal_only_is_a_clear_error(fake_poisson, random_buffers):
    with pytest.raises(ValueError, match=r"'l1-fast' needs dx and dy.*primal-only"):
        reconstruct_image(random_buffers(names=("primal",)))
    assert fake_poisson == []


def test_unknown_method_lists_valid_ones(random_buffers):
    with pytest.raises(ValueError, match="valid names: " + ", ".join(METHODS)):
        reconstruct_image(random_buffers(), "bilateral")
