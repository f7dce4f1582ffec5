"""Tests of the NGPT transforms, input assembly, padding and gradient-aware augmentation."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gdpt.reconstruct import transforms as T
from hypothesis import given, settings
from hypothesis import strategies as st


def _forward_dx(image: torch.Tensor) -> torch.Tensor:
    """dx[y, x] = I[y, x+1] - I[y, x], last column 0; image (..., H, W, C)."""
    d = torch.zeros_like(image)
    d[..., :, :-1, :] = image[..., :, 1:, :] - image[..., :, :-1, :]
    return d


def _forward_dy(image: torch.Tensor) -> torch.Tensor:
    d = torch.zeros_like(image)
    d[..., :-1, :, :] = image[..., 1:, :, :] - image[..., :-1, :, :]
    return d


def _buffer_set(h: int, w: int, batch: tuple[int, ...] = (), seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    image = torch.rand(*batch, h, w, 3, generator=gen, dtype=torch.float64) * 4
    return {
        "primal": image,
        "dx": _forward_dx(image),
        "dy": _forward_dy(image),
        "var_dx": _forward_dx(image).abs(),
        "albedo": torch.rand(*batch, h, w, 3, generator=gen, dtype=torch.float64),
        "normal": torch.rand(*batch, h, w, 3, generator=gen, dtype=torch.float64) * 2 - 1,
        "depth": torch.rand(*batch, h, w, 1, generator=gen, dtype=torch.float64) + 1,
    }


def test_transform_inverses_exact():
    x = torch.cat([torch.zeros(1), torch.logspace(-6, 4, 500, dtype=torch.float64)])
    torch.testing.assert_close(T.Log1p().inverse(T.Log1p().forward(x)), x, rtol=1e-12, atol=0)
    g = torch.cat([-x, x])
    torch.testing.assert_close(
        T.SignedLog1p().inverse(T.SignedLog1p().forward(g)), g, rtol=1e-12, atol=0
    )
    y = torch.linspace(0, 8, 101, dtype=torch.float64)  # outputs >= 0 round-trip
    torch.testing.assert_close(T.OUTPUT_TRANSFORM.forward(T.OUTPUT_TRANSFORM.inverse(y)), y)
    assert torch.equal(T.Log1p().forward(torch.tensor([-3.0])), torch.tensor([0.0]))


def test_output_transform_never_overflows():
    """A diverging network (log-radiance 100 or inf) must not produce inf or NaN radiance, nor a
    NaN in a squared loss."""
    y = torch.tensor([0.0, 30.0, 100.0, float("inf")])
    out = T.OUTPUT_TRANSFORM.inverse(y)
    assert torch.isfinite(out).all() and torch.isfinite(out.square()).all()
    assert out[1] == torch.expm1(torch.tensor(30.0)) and out[2] == out[3]


@settings(max_examples=50, deadline=None)
@given(st.floats(-1e6, 1e6, allow_nan=False), st.floats(0.1, 1.1))
def test_signed_log_and_depth_properties(value, scale):
    t = torch.tensor([value], dtype=torch.float64)
    f = T.SignedLog1p().forward(t)
    assert torch.equal(T.SignedLog1p().forward(-t), -f)  # odd: commutes with antisym padding
    torch.testing.assert_close(T.SignedLog1p().inverse(f), t, rtol=1e-12, atol=1e-12)
    depth = torch.tensor([[[abs(value) + 1]], [[2.0]]], dtype=torch.float64)
    dn = T.DepthNormalize(scale)
    y = dn.forward(depth)
    assert abs(y.max().item() - scale) < 1e-9
    torch.testing.assert_close(dn.inverse(y, depth.max()), depth)


def test_nonfinite_inputs_become_zero():
    bufs = {k: v.float() for k, v in _buffer_set(6, 7).items()}
    bufs["primal"][0, 0] = float("nan")
    bufs["dx"][1, 1] = float("inf")
    bufs["depth"][2, 2] = float("inf")
    out = T.transform_buffers(bufs, T.FEATURES_WITH_GRADIENTS)
    assert all(torch.isfinite(v).all() for v in out.values())
    assert torch.all(out["primal"][0, 0] == 0) and torch.all(out["dx"][1, 1] == 0)
    assert out["depth"].max() <= 1


def test_input_assembly_and_errors():
    bufs = {k: v.float() for k, v in _buffer_set(5, 9).items()}
    x = T.stack_input(
        T.transform_buffers(bufs, T.FEATURES_WITH_GRADIENTS), T.FEATURES_WITH_GRADIENTS
    )
    assert x.shape == (1, 16, 5, 9)
    torch.testing.assert_close(x[0, 3:6].permute(1, 2, 0), T.SignedLog1p().forward(bufs["dx"]))
    torch.testing.assert_close(x[0, 15], bufs["depth"][..., 0] / (1e-10 + bufs["depth"].max()))
    assert x.is_contiguous(memory_format=torch.channels_last)
    with pytest.raises(KeyError, match=r"\['dx', 'depth'\]"):
        T.transform_buffers(
            {k: v for k, v in bufs.items() if k not in ("dx", "depth")}, T.FEATURES_WITH_GRADIENTS
        )
    with pytest.raises(ValueError, match=r"'albedo' must have shape \(H, W, 3\)"):
        T.transform_buffers(
            {**bufs, "albedo": bufs["albedo"][..., :2]}, T.FEATURES_WITHOUT_GRADIENTS
        )
    with pytest.raises(ValueError, match="'normal' has shape"):
        T.transform_buffers({**bufs, "normal": bufs["normal"][:4]}, T.FEATURES_WITH_GRADIENTS)


def test_padding_for():
    assert T.padding_for(720, 1280, 8) == T.Padding(8, 8, 8, 8)
    assert T.padding_for(9, 13, 8, margin=0) == T.Padding(0, 7, 0, 3)
    p = T.padding_for(3, 5, 16)
    assert (3 + p.top + p.bottom) % 16 == 0 and (5 + p.left + p.right) % 16 == 0


@pytest.mark.parametrize("pad", [(1, 2, 3, 0), (8, 8, 8, 8), (4, 7, 2, 5)])
def test_reflect_and_odd_match_numpy(pad):
    bufs = _buffer_set(11, 10)
    padding = T.Padding(*pad)
    out = T.pad_buffers(bufs, padding)
    width = ((pad[0], pad[1]), (pad[2], pad[3]), (0, 0))
    np.testing.assert_array_equal(
        out["primal"].numpy(), np.pad(bufs["primal"].numpy(), width, "reflect")
    )
    np.testing.assert_allclose(
        out["depth"].numpy(),
        np.pad(bufs["depth"].numpy(), width, "reflect", reflect_type="odd"),
        rtol=1e-12,
    )
    for name in ("primal", "albedo", "normal", "depth"):  # gradients: tested below
        assert torch.equal(T.crop(out[name], padding), bufs[name]), name


def _reference_pad_dx(dx: np.ndarray, pad_x: tuple[int, int], pad_y: tuple[int, int]):
    """The reference's antisymmetric dx padding (HWC), written from its description."""
    d = dx[:, :-1]
    parts = [-d[:, pad_x[0] - 1 :: -1]] if pad_x[0] else []
    parts += [d]
    parts += [-d[:, -1 : -pad_x[1] - 1 : -1]] if pad_x[1] else []
    parts += [np.zeros_like(d[:, :1])]
    return np.pad(np.concatenate(parts, axis=1), (pad_y, (0, 0), (0, 0)), "reflect")


@pytest.mark.parametrize("shape", [(11, 10), (7, 13), (2, 3), (1, 1)])
@pytest.mark.parametrize("pad", [(1, 2, 3, 1), (8, 8, 8, 8), (0, 5, 0, 6)])
def test_antisymmetric_padding_is_difference_of_reflect_padding(shape, pad):
    bufs = _buffer_set(*shape)
    padding = T.Padding(*pad)
    out = T.pad_buffers(bufs, padding)
    image = T.pad_buffers({"primal": bufs["primal"]}, padding)["primal"]
    torch.testing.assert_close(out["dx"], _forward_dx(image), rtol=0, atol=1e-12)
    torch.testing.assert_close(out["dy"], _forward_dy(image), rtol=0, atol=1e-12)
    torch.testing.assert_close(out["var_dx"], _forward_dx(image).abs(), rtol=0, atol=1e-12)
    h, w = shape
    if max(pad[2:]) <= w - 1 and max(pad[:2]) <= h - 1:  # the reference handles only these
        ref = _reference_pad_dx(bufs["dx"].numpy(), pad[2:], pad[:2])
        np.testing.assert_array_equal(out["dx"].numpy(), ref)
    for name, t in out.items():
        if name in ("primal", "dx", "dy"):
            assert torch.equal(
                T.crop(t, padding)[..., : h - 1, : w - 1, :], bufs[name][..., : h - 1, : w - 1, :]
            ), name


@pytest.mark.parametrize("batch", [(), (2,)])
@pytest.mark.parametrize("op", ["flip_x", "flip_y", "transpose"])
def test_geometry_ops_map_gradients_to_gradients(op, batch):
    bufs = _buffer_set(6, 9, batch)
    out = T.AUGMENTATIONS[op](bufs)
    image = out["primal"]
    torch.testing.assert_close(out["dx"], _forward_dx(image), rtol=0, atol=1e-12)
    torch.testing.assert_close(out["dy"], _forward_dy(image), rtol=0, atol=1e-12)
    torch.testing.assert_close(
        out["var_dx" if op != "transpose" else "var_dy"],
        (_forward_dx if op != "transpose" else _forward_dy)(image).abs(),
        rtol=0,
        atol=1e-12,
    )
    n, nn_ = bufs["normal"], out["normal"]
    if op == "flip_x":
        torch.testing.assert_close(nn_, n.flip(-2) * torch.tensor([-1.0, 1, 1], dtype=n.dtype))
        torch.testing.assert_close(out["primal"], bufs["primal"].flip(-2))
    elif op == "flip_y":
        torch.testing.assert_close(nn_, n.flip(-3) * torch.tensor([1.0, -1, 1], dtype=n.dtype))
    else:
        torch.testing.assert_close(nn_, n.transpose(-3, -2)[..., [1, 0, 2]])
        assert out["depth"].shape[-3:] == (9, 6, 1)
    again = T.AUGMENTATIONS[op](out)
    for name, t in bufs.items():
        torch.testing.assert_close(again[name], t, rtol=0, atol=1e-12)
