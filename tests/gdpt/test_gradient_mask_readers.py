"""Every reader of gradients skips the untraced ones of a masked render (``gradient_mask``):
garbage there changes nothing."""

from __future__ import annotations

import math
import warnings

import pytest
import torch
from gdpt.reconstruct.fuse import fuse, fuse_checked, fusion_statistics

from gdpt.buffers import fill_untraced
from gdpt.methods import reconstruct_image

H, W = 24, 20


def _mask() -> torch.Tensor:
    """``(H, W, 2)``: the gradients of a block of pixels (the border rule of a render)."""
    pixels = torch.zeros(H, W, dtype=torch.bool)
    pixels[4:18, 3:13] = True
    out = torch.zeros(H, W, 2, dtype=torch.bool)
    out[:, :-1, 0] = pixels[:, :-1] & pixels[:, 1:]
    out[:-1, :, 1] = pixels[:-1] & pixels[1:]
    return out


def _with_garbage(buffers, value: float):
    """``buffers`` with ``value`` in every untraced gradient and in its variance (as a reader
    that ignored the mask would read them)."""
    mask = buffers.gradient_mask
    changes = {}
    for k, axis in enumerate(("dx", "dy")):
        untraced = ~mask[..., k : k + 1]
        for name in (axis, f"{axis}_a", f"{axis}_b"):
            if (t := getattr(buffers, name)) is not None:
                changes[name] = torch.where(untraced, torch.tensor(value), t)
        if (v := getattr(buffers, f"var_{axis}")) is not None:
            small = 1e-12 if math.isfinite(value) else value  # trusted where it is finite
            changes[f"var_{axis}"] = torch.where(untraced, torch.tensor(small), v)
    return buffers.replace(**changes)


@pytest.fixture
def masked(random_buffers):
    """Random buffers of a render that traced the gradients of :func:`_mask` (0 elsewhere,
    infinite variance), with small gradient variances where traced."""
    buffers = random_buffers(H, W, seed=3, metadata={"half_spp": [8, 8], "primal_spp": 40})
    buffers = buffers.replace(
        var_dx=buffers.var_dx * 1e-3, var_dy=buffers.var_dy * 1e-3, gradient_mask=_mask()
    )
    return fill_untraced(buffers, 0.0, 0.0).replace(gradient_mask=_mask())


GARBAGE = [1e6, -3.0, math.nan, math.inf]


@pytest.mark.parametrize("method", ["l2", "l1-fast"])
@pytest.mark.parametrize("garbage", GARBAGE)
def test_poisson_solvers_treat_untraced_gradients_as_missing(masked, method, garbage):
    clean = reconstruct_image(masked, method=method)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning about the untraced gradients
        dirty = reconstruct_image(_with_garbage(masked, garbage), method=method)
    assert torch.equal(clean, dirty)
    read = reconstruct_image(masked.replace(gradient_mask=None), method=method)
    assert not torch.allclose(clean, read)  # the mask changed what was read


def test_poisson_still_warns_about_a_traced_nonfinite_gradient(masked):
    from gdpt.reconstruct.poisson.problem import NonFiniteInputWarning

    dx = masked.dx.clone()
    dx[5, 5] = math.nan  # a traced one
    with pytest.warns(NonFiniteInputWarning, match="1 dx"):
        reconstruct_image(masked.replace(dx=dx), method="l2")


def _statistics(buffers):
    denoised = {"full": buffers.primal.clone(), "a": buffers.primal_a, "b": buffers.primal_b}
    return fusion_statistics(
        lambda part: denoised[part] * 0.9,
        buffers.primal_a,
        buffers.primal_b,
        buffers.var_dx,
        buffers.var_dy,
    )


@pytest.mark.parametrize("garbage", GARBAGE)
def test_fuse_does_not_read_gradients_of_infinite_variance(masked, garbage):
    s = _statistics(masked)
    dirty = _with_garbage(masked, garbage)
    args = (s.denoised, masked.dx, masked.dy, s.var_dx, s.var_dy, s.error)
    clean, info = fuse(*args, error_floor=s.error_floor)
    assert info.trusted > 0  # the traced gradients are used
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # not even read as missing constraints
        again, _ = fuse(*args[:1], dirty.dx, dirty.dy, *args[3:], error_floor=s.error_floor)
    assert torch.equal(clean, again)


@pytest.mark.parametrize("garbage", GARBAGE)
def test_fuse_checked_does_not_read_gradients_of_infinite_variance(masked, garbage):
    def checked(b):
        return fuse_checked(
            _statistics(masked),
            b.dx,
            b.dy,
            ((b.dx_a, b.dy_a), (b.dx_b, b.dy_b)),
            (b.primal_a, b.primal_b),
            (2.0, 2.0),
            image_margin=None,
            margin=0.0,
        )

    clean, info = checked(masked)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # not even read as missing constraints
        dirty, dirty_info = checked(_with_garbage(masked, garbage))
    assert torch.equal(clean, dirty)
    assert info.held_out["difference"] == dirty_info.held_out["difference"]  # the halves' too


@pytest.mark.parametrize("garbage", [1e6, math.nan])
def test_fuse_method_gives_untraced_gradients_zero_weight(masked, garbage, variant):
    """Garbage in an untraced gradient and a small (trusted) variance there: still skipped."""
    clean = reconstruct_image(masked, method="fuse", denoiser="oidn")
    trusted = masked.metadata["fuse"]["trusted"]
    dirty_buffers = _with_garbage(masked, garbage)
    dirty = reconstruct_image(dirty_buffers, method="fuse", denoiser="oidn")
    assert torch.equal(clean, dirty)
    assert dirty_buffers.metadata["fuse"]["trusted"] == trusted


@pytest.mark.parametrize("garbage", [1e6, math.nan])
def test_gradient_network_reads_untraced_gradients_as_primal_differences(
    masked, garbage, variant, monkeypatch
):
    monkeypatch.delenv("GDPT_OIDN_GRAD_MODEL", raising=False)
    clean = reconstruct_image(masked, method="oidn-grad")
    assert torch.equal(clean, reconstruct_image(_with_garbage(masked, garbage), method="oidn-grad"))
    p = masked.primal
    dx, dy = torch.zeros_like(p), torch.zeros_like(p)
    dx[:, :-1], dy[:-1] = p[:, 1:] - p[:, :-1], p[1:] - p[:-1]
    mask = masked.gradient_mask
    explicit = masked.replace(
        dx=torch.where(mask[..., :1], masked.dx, dx),
        dy=torch.where(mask[..., 1:], masked.dy, dy),
        gradient_mask=None,
    )
    assert torch.allclose(clean, reconstruct_image(explicit, method="oidn-grad"))


def test_saved_untraced_gradients_are_missing(masked, tmp_path):
    from gdpt.io.exr import load_buffers, save_buffers

    loaded = load_buffers(save_buffers(tmp_path / "masked.exr", _with_garbage(masked, 5.0)))
    mask = masked.gradient_mask
    for k, axis in enumerate(("dx", "dy")):
        untraced = ~mask[..., k]
        for name in (axis, f"{axis}_a", f"{axis}_b"):
            assert torch.isnan(getattr(loaded, name)[untraced]).all(), name
            assert torch.equal(getattr(loaded, name)[~untraced], getattr(masked, name)[~untraced])
        assert torch.isinf(getattr(loaded, f"var_{axis}")[untraced]).all()
