"""Fixtures shared by the whole suite.

* ``variant`` (session): Mitsuba's ``llvm_ad_rgb`` with the gdpt plugins registered (the same
  contract as ``tests/integrators/conftest.py``'s fixture of that name).
* ``random_buffers``: a factory of random :class:`~gdpt.buffers.GradientBuffers` on the CPU.
* ``single_thread``: one torch intra-op thread during the test (restored after), for tiny
  workloads on shared CPUs (``pytestmark = pytest.mark.usefixtures("single_thread")``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator

import pytest
import torch

from gdpt.buffers import CHANNELS, GradientBuffers


@pytest.fixture(scope="session")
def variant() -> str:
    """Mitsuba's ``llvm_ad_rgb`` variant with the gdpt plugins registered."""
    import gdpt

    return gdpt.set_variant("llvm_ad_rgb")


def make_random_buffers(
    h: int = 12,
    w: int = 10,
    *,
    names: Iterable[str] = tuple(CHANNELS),
    seed: int = 0,
    spp: int = 16,
    metadata: dict | None = None,
) -> GradientBuffers:
    """Buffers ``names`` of ``(h, w, C)`` float32 uniform [0, 1) values (CPU, seeded)."""
    g = torch.Generator().manual_seed(seed)
    tensors = {n: torch.rand(h, w, CHANNELS[n], generator=g) for n in names}
    return GradientBuffers(**tensors, spp=spp, metadata=dict(metadata or {}))


@pytest.fixture
def random_buffers() -> Callable[..., GradientBuffers]:
    """:func:`make_random_buffers`, as a fixture."""
    return make_random_buffers


@pytest.fixture
def single_thread() -> Iterator[None]:
    """One torch intra-op thread during the test (the previous count is restored)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
