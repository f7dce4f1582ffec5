"""``gdpt.gradient_mask``: a per-tile gradient mask from a pilot render (``"trust"``: the share
of the gradients ``fuse`` keeps; ``"variance"``: the gradient/primal variance ratio), the
masked render that merges the pilot in, and the study methods that time all of it."""

from __future__ import annotations

import time

import pytest
import torch

import gdpt.gradient_mask as gm
from gdpt.buffers import GradientBuffers

SIZE = 32


def _pilot(noisy_right: float = 1e6, size: int = SIZE) -> GradientBuffers:
    """A 4-spp synthetic pilot of a flat grey image whose gradients are near exact in the left
    half and pure noise (variance ``noisy_right``, per sample far above the primal's) in the
    right half."""
    g = torch.Generator().manual_seed(3)
    truth = torch.full((size, size, 3), 0.5)
    halves = [truth + 0.05 * torch.randn(truth.shape, generator=g) for _ in range(2)]
    var = torch.full((size, size, 1), 1e-8)
    var[:, size // 2 :] = noisy_right
    noise = var.sqrt() * torch.randn((size, size, 1), generator=g)
    return GradientBuffers(
        primal=(halves[0] + halves[1]) / 2, dx=noise.expand(-1, -1, 3).clone(),
        dy=noise.expand(-1, -1, 3).clone(), var_primal=torch.full((size, size, 1), 0.05**2 / 2),
        var_dx=var, var_dy=var.clone(), primal_a=halves[0], primal_b=halves[1], spp=4,
        metadata={"half_spp": [2, 2]},
    )  # fmt: skip


def _blur(buffers: GradientBuffers) -> torch.Tensor:
    """A stand-in denoiser: a 5x5 box mean of the primal (error well above the left half's
    gradient variance, far below the right half's)."""
    from gdpt.reconstruct.fuse import box_mean

    return box_mean(buffers.primal, 2)


@pytest.mark.parametrize("design", gm.DESIGNS)
def test_noisy_half_is_left_out_and_exact_half_kept(design):
    mask = gm.pilot_mask(_pilot(), design=design, denoise=_blur, tile=8)
    assert mask.shape == (SIZE, SIZE) and mask.dtype == torch.bool
    assert bool(mask[:, : SIZE // 2].all())
    assert not bool(mask[:, SIZE // 2 :].any())


def test_tiles_are_whole_and_edge_tiles_count_their_own_pixels():
    values = torch.zeros(20, 20)
    values[16:, 16:] = 1.0  # the 4x4 corner tile, full
    sums = gm.tile_sums(values, 16)
    assert sums.tolist() == [[0.0, 0.0], [0.0, 16.0]]
    share = sums / gm.tile_sums(torch.ones(20, 20), 16)
    full = gm.expand_tiles(share >= 1.0, (20, 20), 16)
    assert full.shape == (20, 20) and int(full.sum()) == 16 and bool(full[16:, 16:].all())


def test_trust_share_is_rounded_to_tiles_by_the_vote():
    pilot = _pilot()
    pilot.var_dx[:, 8:12] = 1e6  # a quarter of the first tile column's dx: share 0.75 there
    pilot.var_dy[:, 8:12] = 1e6
    strict = gm.pilot_mask(pilot, denoise=_blur, tile=16, min_share=0.9)
    lenient = gm.pilot_mask(pilot, denoise=_blur, tile=16, min_share=0.5)
    assert not bool(strict[:, :16].any()) and bool(lenient[:, :16].all())


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"design": "tiles"}, r"unknown mask design 'tiles'; valid: trust, variance"),
        ({"tile": 0}, r"tile must be a positive int \(pixels\), got 0"),
        ({"tile": 4.0}, r"tile must be a positive int \(pixels\), got 4.0"),
        ({"tile": 64}, r"tile 64 px is larger than the 32x32 image"),
        ({"min_share": 0.0}, r"min_share must be in \(0, 1\], got 0.0"),
        ({"design": "variance", "max_ratio": 0}, r"max_ratio must be > 0, got 0"),
    ],
)
def test_bad_arguments_are_named(changes, message):
    with pytest.raises(ValueError, match=message):
        gm.pilot_mask(_pilot(), **{"denoise": _blur, **changes})


def test_pilot_without_gradients_is_named():
    plain = _pilot().replace(dx=None, dy=None, var_dx=None, var_dy=None)
    with pytest.raises(ValueError, match="pilot_mask reads the pilot's gradients"):
        gm.pilot_mask(plain, denoise=_blur)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"spp": 0}, "spp must be >= 1, got 0"),
        ({"design": "tiles"}, "unknown mask design 'tiles'"),
        ({"tile": -1}, r"tile must be a positive int \(pixels\), got -1"),
    ],
)
def test_render_masked_rejects_bad_input_before_rendering(monkeypatch, changes, message):
    def no_render(*args, **kwargs):
        raise AssertionError("rendered before checking its arguments")

    monkeypatch.setattr(gm.rendering, "render", no_render)
    with pytest.raises(ValueError, match=message):
        gm.render_masked(object(), **{"spp": 8, **changes})


def test_pilot_size():
    assert [gm.pilot_spp(n) for n in (1, 2, 3, 8, 9, 100)] == [1, 2, 2, 2, 3, 25]


@pytest.fixture(scope="module")
def scene(variant):
    from gdpt.scenes import builtin_scene
    from gdpt.scenes.loading import load_scene

    return load_scene(builtin_scene("cbox-demo", resolution=(SIZE, SIZE)))


def _left_half(pilot, **_):
    mask = torch.zeros((pilot.height, pilot.width), dtype=torch.bool, device=pilot.device)
    mask[:, : pilot.width // 2] = True
    return mask


def test_masked_render_merges_the_pilot_and_marks_its_gradients_outside(scene, monkeypatch):
    monkeypatch.setattr(gm, "pilot_mask", _left_half)
    merged = gm.render_masked(scene, spp=8, seed=4, design="variance", tile=8, max_depth=3)
    mask = _left_half(merged)
    traced = gm.traced_of(mask)
    assert torch.equal(merged.gradient_mask, traced)
    assert merged.spp == 8 and merged.metadata["merged_spp"][0] > 0  # the pilot's samples kept
    info = merged.metadata["pilot_mask"]
    assert info["share"] == 0.5 and info["pilot_spp"] == 2 and info["tile"] == 8
    outside = ~traced[..., 0]
    assert bool((merged.dx[outside] == 0).all()) and bool(merged.var_dx[outside].isinf().all())
    assert bool(merged.var_dx[traced[..., 0]].isfinite().all())


@pytest.mark.parametrize("fill", [False, True])
def test_empty_and_full_masks_merge(scene, monkeypatch, fill):
    def constant(pilot, **_):
        return torch.full((pilot.height, pilot.width), fill, device=pilot.device)

    monkeypatch.setattr(gm, "pilot_mask", constant)
    merged = gm.render_masked(scene, spp=8, seed=4, design="variance", tile=8, max_depth=3)
    assert merged.metadata["pilot_mask"]["share"] == float(fill)
    if fill:
        assert merged.gradient_mask is None and merged.spp == 8
    else:  # the pilot's gradients, every one marked untraced; the main render plain
        assert merged.spp == 2 and not bool(merged.gradient_mask.any())


def test_study_method_times_the_pilot_and_calibrates_on_its_own(scene, monkeypatch):
    from gdpt.study.calibration import calibration_runner
    from gdpt.study.methods import EVAL_METHODS
    from gdpt.study.scenes import EvalScene

    method = EVAL_METHODS["gdpt+fuse-masked-variance"]
    if reason := method.check():
        pytest.skip(reason)
    assert method.configuration is None  # cheaper per spp than gdpt+fuse: its own calibration
    assert calibration_runner(method, "total") is method
    study_scene = EvalScene("cbox", scene, 3, (SIZE, SIZE))
    method.run(study_scene, spp=4, seed=1)  # warm-up
    real, real_clock = gm.pilot_mask, time.perf_counter
    jump = 1000.0  # seconds the mask "takes": the clock jumps (no sleep: holds under any load)
    skipped = [0.0]

    def slow(pilot, **kwargs):
        skipped[0] += jump
        return real(pilot, **kwargs)

    monkeypatch.setattr(time, "perf_counter", lambda: real_clock() + skipped[0])
    monkeypatch.setattr(gm, "pilot_mask", slow)
    slowed = method.run(study_scene, spp=4, seed=1)
    # the mask's time is charged to the sampling, once, and not to the reconstruction
    assert jump <= slowed.route["pilot_mask"]["mask_seconds"] < 2 * jump
    assert jump <= slowed.render_seconds <= slowed.seconds < 2 * jump
    assert slowed.reconstruct_seconds < jump


@pytest.mark.parametrize(("primal_spp", "masked"), [(16, True), (4, False)])
def test_variance_ratio_is_per_sample(primal_spp, masked):
    """Equal variances of the means, but the primal pools 4x the gradient samples: per sample
    the gradients are 4x less noisy (ratio 0.25, masked); unpooled the ratio is 1 (not)."""
    pilot = _pilot()
    var = torch.full((SIZE, SIZE, 1), 1e-3)
    pilot = pilot.replace(
        var_primal=var, var_dx=var.clone(), var_dy=var.clone(),
        metadata={**pilot.metadata, "primal_spp": primal_spp},
    )  # fmt: skip
    ratio = gm.variance_ratio(pilot, 8)
    assert torch.allclose(ratio, torch.full_like(ratio, 4 / primal_spp))
    assert bool(gm.pilot_mask(pilot, design="variance", tile=8).all()) is masked
