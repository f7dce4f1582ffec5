"""gdpt.reconstruct.refine: the gate keeps gradient corrections and rejects gradient failures."""

from __future__ import annotations

import math

import pytest
import torch
from gdpt.reconstruct.oidn_finetune import DESIGNS, OIDNReconstructor, base_model
from gdpt.reconstruct.poisson import NonFiniteInputWarning
from gdpt.reconstruct.refine import GatedRefinement


def forward_differences(image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    dx, dy = torch.zeros_like(image), torch.zeros_like(image)
    dx[:, :-1] = image[:, 1:] - image[:, :-1]
    dy[:-1] = image[1:] - image[:-1]
    return dx, dy


@pytest.fixture
def scene() -> tuple[torch.Tensor, torch.Tensor]:
    """``(clean, blurred)``: a 32x32 image with a shadow edge, and a denoiser-like blur of it."""
    clean = torch.full((32, 32, 3), 0.6)
    clean[:, 16:] = 0.15
    kernel = torch.ones(3, 1, 1, 7) / 7
    blurred = torch.nn.functional.conv2d(
        clean.permute(2, 0, 1)[None], kernel, padding=(0, 3), groups=3
    )[0].permute(1, 2, 0)
    blurred[:, :3], blurred[:, -3:] = clean[:, :3], clean[:, -3:]  # no darkening at the border
    return clean, blurred


def test_exact_gradients_restore_the_edge_the_denoiser_blurred(scene):
    clean, blurred = scene
    dx, dy = forward_differences(clean)
    out = GatedRefinement(alpha=0.5, tau=0.5)(blurred, dx, dy)
    assert (out - clean).abs().max() < 0.25 * (blurred - clean).abs().max()


def test_the_gate_rejects_gradients_that_disagree_with_the_image(scene):
    clean, _ = scene
    dx, dy = forward_differences(clean)
    # a region of failed shifts: dense, heavy-tailed, biased gradient noise (L1 ignores sparse
    # outliers, not this)
    g = torch.Generator().manual_seed(0)
    dx[4:20, 2:14] += torch.randn(16, 12, 3, generator=g).exp()
    dy[4:20, 2:14] += torch.randn(16, 12, 3, generator=g).exp()
    refine = GatedRefinement(alpha=0.5, tau=0.02)
    ungated = refine.solve(clean, dx, dy)
    gated = refine(clean, dx, dy)
    assert (ungated - clean).abs().max() > 0.5
    assert (gated - clean).abs().max() < 0.02


def test_an_infinite_tau_is_the_l1_solution_and_round_trips_through_json(scene):
    clean, blurred = scene
    dx, dy = forward_differences(clean)
    refine = GatedRefinement(alpha=0.5, tau=math.inf)
    assert torch.equal(refine(blurred, dx, dy), refine.solve(blurred, dx, dy))
    card = refine.to_dict()
    assert card["tau"] == "inf" and GatedRefinement.from_dict(card) == refine


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"alpha": 0.0}, "alpha"),
        ({"tau": -1.0}, "tau"),
        ({"window": 4}, "window"),
        ({"preset": "slow"}, "unknown L1 preset 'slow'"),
    ],
)
def test_bad_settings_are_named(changes, message):
    with pytest.raises(ValueError, match=message):
        GatedRefinement(**changes)


def test_a_card_refinement_follows_the_network_and_keeps_non_finite_input_finite():
    g = torch.Generator().manual_seed(0)
    b = {
        "primal": torch.rand(20, 27, 3, generator=g),
        "albedo": torch.rand(20, 27, 3, generator=g),
        "normal": torch.nn.functional.normalize(torch.randn(20, 27, 3, generator=g), dim=-1),
        "dx": torch.randn(20, 27, 3, generator=g) * 0.05,
        "dy": torch.randn(20, 27, 3, generator=g) * 0.05,
    }
    design = DESIGNS["oidn-grad"]
    plain = OIDNReconstructor(base_model(design), design)
    refined = OIDNReconstructor(base_model(design), design, {"refine": {"tau": 0.5}})
    assert refined.refine == GatedRefinement(tau=0.5) and plain.refine is None
    expected = GatedRefinement(tau=0.5)(plain(b), b["dx"], b["dy"])
    torch.testing.assert_close(refined(b), expected)
    b["dx"][3, 4] = float("nan")
    with pytest.warns(NonFiniteInputWarning, match="1 dx"):
        out = refined(b)
    assert torch.isfinite(out).all() and (out >= 0).all()


def test_a_refinement_on_a_design_without_gradients_is_refused():
    design = DESIGNS["oidn-nograd"]
    with pytest.raises(ValueError, match="needs gradients"):
        OIDNReconstructor(base_model(design), design, {"refine": {}})
