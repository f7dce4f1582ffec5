"""One buffer channel table (``gdpt.reconstruct.channels``) seen by the three rooms: the
package's buffers, the networks' input features and the integrators' output."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

from gdpt.reconstruct import channels
from gdpt.reconstruct.transforms import FEATURE_CHANNELS

from gdpt.buffers import CHANNELS, HALVED

ROOT = Path(__file__).resolve().parents[1]


def test_buffers_and_network_features_read_the_table():
    assert CHANNELS is channels.CHANNELS and HALVED is channels.HALVED
    assert list(FEATURE_CHANNELS.items()) == list(CHANNELS.items())[: len(FEATURE_CHANNELS)]


def test_the_integrators_copy_is_generated_from_the_table():
    """``integrators/channels.py`` is the output of ``python -m gdpt.reconstruct.channels``."""
    assert (ROOT / "integrators" / "channels.py").read_text() == channels.integrators_copy()


def test_the_integrators_write_the_table_in_its_order(variant):
    """With every output on, a ``gdpt`` integrator stores exactly the table's buffers, in its
    order and with its channel counts."""
    from gdpt.integrators import channels as copy
    from gdpt.integrators.common import GradientIntegratorBase

    assert copy.CHANNELS == CHANNELS and copy.HALVED == HALVED
    everything = SimpleNamespace(gradients=True, features=True, variance=True, halves=True)
    assert GradientIntegratorBase.channels(everything) == list(CHANNELS.items())
