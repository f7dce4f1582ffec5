"""Self-tests of the per-pixel z statistics of :mod:`pixel_stats` on synthetic runs.

Pairs of estimators with shared random numbers: ``test_i = s_i + e_i``, ``ref_i = s_i + f_i``
per pixel-channel, with a common heavy-ish tailed part ``s`` (Student t, 5 degrees of freedom)
and independent parts ``e``, ``f`` (correlation of the two sides about 0.94), 48 runs, 1200
pixel-channels, the decision rule of ``test_gdpt_unbiased`` (at most 1% of ``|z| > 3.29``, max
``|z|`` at most 6).
"""

from __future__ import annotations

import numpy as np
from pixel_stats import Z_OUTLIER, paired_z, pixel_z

RUNS, SHAPE = 48, (20, 20, 3)
MAX_SHARE, MAX_Z = 0.01, 6.0


def _correlated_pair(seed: int, bias: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(test, ref)`` runs (RUNS, *SHAPE) float32; ``test`` has ``bias`` added."""
    rng = np.random.default_rng(seed)
    common = rng.standard_t(5, (RUNS, *SHAPE)) * 3.0
    test = common + rng.standard_normal((RUNS, *SHAPE)) + bias
    ref = common + rng.standard_normal((RUNS, *SHAPE))
    return test.astype(np.float32), ref.astype(np.float32)


def _passes(z) -> bool:
    return z.share <= MAX_SHARE and z.max_abs <= MAX_Z


def test_paired_z_is_standard_normal_without_bias_and_the_unpaired_z_shrinks():
    """Null: the paired z has unit spread and passes the rule (several seeds); the unpaired z
    of the same correlated runs has a spread far below 1 (its standard error is too large)."""
    for seed in range(4):
        test, ref = _correlated_pair(seed)
        paired, unpaired = paired_z(test, ref), pixel_z(test, ref)
        assert _passes(paired), str(paired)
        assert 0.9 < paired.z.std() < 1.1, paired.z.std()
        assert unpaired.z.std() < 0.5, unpaired.z.std()


def test_paired_z_finds_a_bias_the_unpaired_z_misses():
    """A bias of 0.35 standard deviations of one run's difference: the paired z fails the rule,
    the unpaired z (spread inflated by the shared part) passes it."""
    test, ref = _correlated_pair(10, bias=0.5)
    paired, unpaired = paired_z(test, ref), pixel_z(test, ref)
    assert not _passes(paired) and paired.share > 0.1, str(paired)
    assert _passes(unpaired), str(unpaired)


def test_paired_z_edge_cases():
    """Identical sides give z = 0 (a black pixel both see), a constant offset is infinite, and
    unpaired shapes are refused."""
    test, ref = _correlated_pair(20)
    assert paired_z(test, test).max_abs == 0.0
    offset = paired_z(test + 1.0, test)  # difference constant across runs: zero variance
    assert offset.share == 1.0 and offset.max_abs > 1e3 * Z_OUTLIER
    for bad in (ref[:-1], ref[:, :-1]):
        try:
            paired_z(test, bad)
        except ValueError as error:
            assert "equal shapes" in str(error)
        else:
            raise AssertionError("unpaired shapes were accepted")
