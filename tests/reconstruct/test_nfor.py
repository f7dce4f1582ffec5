"""NFOR (Bitterli et al. 2016): the regression against direct solves, exactness on noise-free
affine images, identity at zero variance, borders, bad parameters and non-finite input."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gdpt.reconstruct.nfor import NforConfig, nfor, nlm_filter, regress, weighted_least_squares

#: Largest error of an exact fit allowed: the regression's ridge (``RIDGE``, 1e-5 of a
#: window's weight) biases the corner windows, with fewer and more collinear samples, by up
#: to 3e-4 on values near 1.
RIDGE_BIAS = 1e-3


def _features(h: int, w: int, seed: int = 0) -> list[torch.Tensor]:
    """Smooth albedo (3), normal (3) and depth (1) groups, ``(h, w, c)`` float32."""
    gen = torch.Generator().manual_seed(seed)
    y, x = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    phase = torch.rand(7, generator=gen) * 6
    waves = torch.stack([torch.sin(3 * x + 2 * y + p) for p in phase], dim=-1)
    return [0.5 + 0.4 * waves[..., :3], waves[..., 3:6], 2.0 + waves[..., 6:]]


def test_weighted_least_squares_equals_a_direct_lstsq_solve():
    gen = torch.Generator().manual_seed(1)
    n, k, d, c = 5, 49, 6, 3
    design = torch.cat([torch.ones(n, k, 1), torch.randn(n, k, d - 1, generator=gen)], dim=-1)
    targets = torch.randn(n, k, c, generator=gen)
    weights = torch.rand(n, k, generator=gen)
    beta = weighted_least_squares(torch.cat([design, targets], dim=-1), weights, d)
    for i in range(n):
        sw = np.sqrt(weights[i].double().numpy())[:, None]
        x, y = design[i].double().numpy() * sw, targets[i].double().numpy() * sw
        direct = np.linalg.lstsq(x, y, rcond=None)[0]
        np.testing.assert_allclose(beta[i].numpy(), direct, rtol=2e-3, atol=2e-4)


def test_regression_is_exact_on_an_affine_function_of_the_features():
    feats = torch.cat(_features(24, 30), dim=-1)
    coef = torch.randn(7, 3, generator=torch.Generator().manual_seed(2))
    image = 1.0 + 0.2 * feats @ coef
    var = torch.full((24, 30, 1), 0.05)  # wide weights: every window fits many pixels
    (out,) = regress(image, feats, image, var, radius=4, patch=1, ks=(1.0,))
    torch.testing.assert_close(out, image, rtol=0, atol=RIDGE_BIAS)


def test_nfor_is_exact_on_noise_free_halves_that_are_affine_in_the_features():
    groups = _features(20, 26)
    coef = torch.randn(7, 3, generator=torch.Generator().manual_seed(3))
    image = 1.0 + 0.2 * torch.cat(groups, dim=-1) @ coef
    cfg = NforConfig(radius=4, prefilter_radius=3, error_radius=4)
    out, info = nfor(image, image, torch.full((20, 26, 1), 0.05), groups, groups, cfg)
    torch.testing.assert_close(out, image, rtol=0, atol=RIDGE_BIAS)
    assert info.nonfinite == 0 and abs(sum(info.bandwidth_share) - 1) < 1e-5


def test_nfor_returns_the_input_where_the_variance_is_zero():
    gen = torch.Generator().manual_seed(4)
    image = torch.rand(16, 18, 3, generator=gen)  # not a function of the features
    feats = [torch.rand(16, 18, 3, generator=gen), torch.rand(16, 18, 1, generator=gen)]
    out, _ = nfor(image, image, torch.zeros(16, 18, 1), feats, feats, NforConfig(radius=3))
    torch.testing.assert_close(out, image, rtol=0, atol=1e-6)


def test_nlm_filter_averages_within_a_constant_region_and_keeps_edges():
    image = torch.zeros(12, 12, 1)
    image[:, 6:] = 1.0
    noisy = image + 0.01 * torch.randn(12, 12, 1, generator=torch.Generator().manual_seed(5))
    out = nlm_filter(noisy, image, torch.full((12, 12, 1), 1e-4), radius=3, patch=1, k=0.5)
    assert (out[:, :6] - 0.0).abs().max() < 0.01 and (out[:, 6:] - 1.0).abs().max() < 0.01
    assert (out - image).square().mean() < (noisy - image).square().mean() / 4


@pytest.mark.parametrize("shape", [(1, 1), (7, 3), (3, 7)])
def test_images_smaller_than_the_window_are_handled_at_the_borders(shape):
    gen = torch.Generator().manual_seed(6)
    a = torch.rand(*shape, 3, generator=gen)
    b = a + 0.1 * torch.rand(*shape, 3, generator=gen)
    feats = [torch.rand(*shape, 3, generator=gen)]
    out, _ = nfor(a, b, torch.full((*shape, 1), 0.01), feats, feats)
    assert out.shape == (*shape, 3) and torch.isfinite(out).all()
    # every pixel is a weighted mean of the halves' values (first-order terms aside, small)
    assert out.min() > min(a.min(), b.min()) - 0.2 and out.max() < max(a.max(), b.max()) + 0.2


def test_non_finite_input_gives_finite_output_and_is_counted():
    gen = torch.Generator().manual_seed(7)
    a, b = torch.rand(20, 20, 3, generator=gen), torch.rand(20, 20, 3, generator=gen)
    a[3, 4, 1], b[5, 5, 0] = float("nan"), float("inf")
    feats_a, feats_b = [torch.rand(20, 20, 3, generator=gen)], [torch.rand(20, 20, 3)]
    feats_b[0][1, 1, 2] = float("-inf")
    var = torch.full((20, 20, 1), 0.01)
    var[0, 0, 0] = float("nan")
    out, info = nfor(a, b, var, feats_a, feats_b, NforConfig(radius=3))
    assert torch.isfinite(out).all()
    assert info.nonfinite == 4


@pytest.mark.parametrize(
    ("option", "value"),
    [
        ("radius", 0),
        ("radius", 2.5),
        ("patch", -1),
        ("bandwidths", ()),
        ("bandwidths", (0.5, -1.0)),
        ("final_k", float("nan")),
        ("prefilter_radius", 100),
    ],
)
def test_a_window_or_bandwidth_out_of_range_names_the_parameter(option, value):
    with pytest.raises(ValueError, match=option):
        NforConfig(**{option: value})


def test_mismatched_buffers_are_refused_by_shape():
    a = torch.zeros(4, 4, 3)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        nfor(a, a, torch.zeros(4, 5, 1), [a], [a])
    with pytest.raises(ValueError, match="feature groups"):
        nfor(a, a, torch.zeros(4, 4, 1), [], [])


def test_with_uniform_weights_nlm_filter_is_the_mean_over_the_window_inside_the_image():
    image = torch.rand(9, 11, 2, generator=torch.Generator().manual_seed(8))
    out = nlm_filter(image, image, torch.full((9, 11, 1), 1e8), radius=2, patch=1, k=1.0)
    expected = torch.empty_like(image)
    for i in range(9):
        for j in range(11):
            expected[i, j] = image[max(0, i - 2) : i + 3, max(0, j - 2) : j + 3].mean((0, 1))
    torch.testing.assert_close(out, expected, rtol=1e-5, atol=1e-6)
