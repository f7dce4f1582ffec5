"""``benchmarks/advise_agreement.py``'s correction for the reference's own noise: on synthetic
images with known truth, the corrected ratio against a noisy reference is the ratio against
the truth (the raw one is pulled toward 1)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import advise_agreement as bench  # noqa: E402 (the benchmarks folder is not a package)
from gdpt.reconstruct.reference_free import half_variance  # noqa: E402


def test_reference_spp_from_the_name():
    assert bench.reference_spp("cornell-box-128x128-d6-8192spp-seed1000003.exr") == 8192
    with pytest.raises(ValueError, match="no sample count"):
        bench.reference_spp("cornell-box.exr")


def test_feature_corrected_ratio_is_the_ratio_against_the_truth():
    """Two methods with errors of 0.02 and 0.01 per channel, a reference whose noise (0.02 per
    sample-averaged channel) is as large as the first error, and ``P`` (its halves give the
    per-pixel variance) of the same per-sample spread: the corrected ratio is the true 0.25
    within 2%, the raw one is near 0.6."""
    g = torch.Generator().manual_seed(1)
    size, sigma, n_p, n_r = (256, 256, 3), 0.8, 400, 1600
    truth = 0.5 + torch.rand(size, generator=g)
    normal = lambda scale: scale * torch.randn(size, generator=g)  # noqa: E731
    reference = truth + normal(sigma / n_r**0.5)
    halves = [truth + normal(sigma / (n_p / 2) ** 0.5) for _ in range(2)]
    plain = {
        "image": (halves[0] + halves[1]) / 2,
        "variance": half_variance(*halves, n_p // 2, n_p // 2),
        "counts": [n_p // 2, n_p // 2],
    }
    noise = bench.reference_variance([plain], n_r)
    assert float(noise.mean()) == pytest.approx(sigma**2 / n_r, rel=0.02)
    images = [truth + normal(0.02), truth + normal(0.01)]

    def against(ref, variance=None):
        return bench.ratio([bench.squared_error(x, ref, ref_variance=variance) for x in images])

    exact = against(truth)
    assert exact == pytest.approx(0.25, rel=0.03)
    assert against(reference, noise) == pytest.approx(exact, rel=0.02)
    assert against(reference) > 0.5  # the raw ratio, pulled toward 1
    # the raw form without weights is relmse's sum
    assert bench.squared_error(images[0], reference) == pytest.approx(
        bench.squared_error(images[0], reference, bench.relmse_weights(reference)), rel=1e-5
    )


def test_ratio_without_a_positive_baseline_is_nan():
    assert bench.ratio([0.0, 1.0]) != bench.ratio([0.0, 1.0])
    assert not bench.covers(None, 1.0)


def test_feature_reference_skips_chunks_and_searches_folders_in_order(tmp_path):
    """A reference still rendering (only its chunks) is not taken; the first folder holding a
    finished one gives it; none anywhere names the folders and ``--render-missing``."""
    from gdpt.io.exr import save_image

    first, second = tmp_path / "a", tmp_path / "b"
    first.mkdir()
    second.mkdir()
    stem = "room-16x8-d6-8192spp-seed1000003"
    save_image(first / f"{stem}.chunk-00000-of-00032.exr", torch.zeros(8, 16, 3))
    save_image(second / f"{stem}.exr", torch.ones(8, 16, 3))
    image, name = bench.reference([first, second], "room", (16, 8), 6)
    assert name == f"{stem}.exr" and float(image.mean()) == 1.0
    with pytest.raises(FileNotFoundError, match="render-missing"):
        bench.reference([first], "room", (16, 8), 6)
