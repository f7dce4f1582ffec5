"""OIDN's U-Net in torch (:mod:`gdpt.reconstruct.oidn_unet`) against OIDN (``mitsuba-oidn``), and
the TZA reader and writer.

Agreement metric (stated once, used everywhere): for the torch output ``a`` and
``b = mitsuba_oidn.denoise(color, albedo, normal, hdr=True, quality=High)`` (the call gdpt's
``pt+oidn`` makes), ``err = max |a - b| / max |b|`` over all pixels and channels; also the
per-pixel ``max |a - b| / (|b| + 1e-3 max |b|)``. Both must be <= 1e-4.

Buffers are rendered-like: smooth lighting times a piecewise-constant albedo, heavy-tailed
per-pixel noise (fireflies up to ~20x), unit normals of a curved surface.
"""

from __future__ import annotations

import struct

import mitsuba_oidn  # the reference and Intel's weights
import numpy as np
import pytest
import torch
from gdpt.reconstruct import oidn_unet, tza


def _buffers(h: int, w: int, seed: int = 0) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    albedo = torch.stack(
        [0.2 + 0.6 * (xx > 0.5), 0.3 + 0.5 * (yy > 0.3), 0.5 + 0.3 * ((xx + yy) > 1)], -1
    ).float()
    normal = torch.stack([xx - 0.5, yy - 0.5, torch.ones_like(xx)], -1)
    normal = normal / normal.norm(dim=-1, keepdim=True)
    light = 2.0 * torch.exp(-8 * ((xx - 0.3) ** 2 + (yy - 0.4) ** 2))[..., None] + 0.05
    noise = torch.rand(h, w, 3, generator=g) ** 4 * 8
    return (albedo * light * (0.5 + noise)).float(), albedo, normal.float()


def _errors(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    d = (a - b).abs()
    peak = b.abs().max()
    return (d.max() / peak).item(), (d / (b.abs() + 1e-3 * peak)).max().item()


def _reference(color, albedo=None, normal=None) -> torch.Tensor:
    high = mitsuba_oidn.Quality.High
    return mitsuba_oidn.denoise(color, albedo, normal, hdr=True, quality=high)


@pytest.mark.parametrize("size", [(37, 53), (64, 48)])
@pytest.mark.parametrize("features", ["albedo+normal", "colour only"])
def test_matches_oidn(size, features):
    color, albedo, normal = _buffers(*size)
    aux = (albedo, normal) if features == "albedo+normal" else (None, None)
    with torch.no_grad():
        ours = oidn_unet.denoise(color, *aux, hdr=True, quality="high")
    assert ours.shape == color.shape and ours.dtype == torch.float32
    err, err_px = _errors(ours, _reference(color, *aux))
    assert err <= 1e-4 and err_px <= 1e-4, (err, err_px)


def test_zero_extra_channels_reproduce_oidn():
    color, albedo, normal = _buffers(37, 53, seed=1)
    base = oidn_unet.OIDNUNet.from_weights("rt_hdr_alb_nrm")
    net = oidn_unet.OIDNUNet.from_weights("rt_hdr_alb_nrm", extra_channels=6)
    extra = torch.randn(37, 53, 6, generator=torch.Generator().manual_seed(2)) * 10
    with torch.no_grad():
        out = oidn_unet.denoise(color, albedo, normal, weights=net, extra=extra)
        ref = oidn_unet.denoise(color, albedo, normal, weights=base)
    assert torch.equal(out, ref)  # exactly, whatever the extra inputs hold
    assert _errors(out, _reference(color, albedo, normal))[0] <= 1e-4
    # the zero weights are trainable: gradients reach them
    oidn_unet.denoise(color, albedo, normal, weights=net, extra=extra).mean().backward()
    assert net.enc_conv0.weight.grad[:, 9:].abs().sum() > 0
    assert net.dec_conv1a.weight.grad[:, -6:].abs().sum() > 0


@pytest.mark.parametrize("kind", ["small", "large"])
def test_extra_input_masks_cover_exactly_the_weights_reading_the_extra_inputs(kind):
    torch.manual_seed(0)
    net = oidn_unet.OIDNUNet(9, 3, kind, extra_channels=4).eval()
    masks = net.extra_input_masks()
    params = dict(net.named_parameters())
    x = torch.randn(1, 13, 32, 32)
    other = x.clone()
    other[:, 9:] = torch.randn(1, 4, 32, 32)
    with torch.no_grad():
        assert not torch.equal(net(x), net(other))  # random weights read the extra inputs
        for name, mask in masks.items():
            assert mask.shape == params[name].shape
            assert int(mask.sum()) == params[name].shape[0] * 4 * 9
            params[name].mul_(1 - mask)
        assert torch.equal(net(x), net(other))  # and only through the masked weights
        x[:, :9] += 1.0
        assert not torch.equal(net(x), net(other))
    assert oidn_unet.OIDNUNet(9, 3, kind).extra_input_masks() == {}


def test_non_finite_inputs_give_finite_output():
    color, albedo, normal = _buffers(37, 53, seed=3)
    color[3, 4] = float("nan")
    color[5, 6, 1] = float("inf")
    color[7, 8] = -float("inf")
    albedo[1, 1] = float("nan")
    normal[2, 2] = float("inf")
    with torch.no_grad():
        out = oidn_unet.denoise(color, albedo, normal)
    assert torch.isfinite(out).all()
    assert _errors(out, _reference(color, albedo, normal))[0] <= 1e-4
    with torch.no_grad():
        out = oidn_unet.denoise(torch.full((20, 20, 3), float("nan")))
    assert torch.isfinite(out).all()


def test_padding_and_crop():
    color, albedo, normal = _buffers(37, 53)
    x, scale = oidn_unet.encode_inputs(color, albedo, normal)
    assert x.shape == (1, 9, 48, 64) and scale.ndim == 0
    assert (x[..., 37:, :] == 0).all() and (x[..., 53:] == 0).all()  # zeros, as OIDN pads
    net = oidn_unet.OIDNUNet(9, 3, "small")
    with torch.no_grad():
        assert net(x).shape == (1, 3, 48, 64)
        assert oidn_unet.decode_output(net(x), 37, 53, scale).shape == (37, 53, 3)
        out = oidn_unet.denoise(color, albedo, normal, weights=net)
    assert out.shape == (37, 53, 3)
    with pytest.raises(ValueError, match="multiple of 16"):
        net(x[..., :37, :53])


def test_transfer_functions_invert():
    y = torch.logspace(-8, 4.8, 200)
    assert torch.allclose(oidn_unet.pu_inverse(oidn_unet.pu_forward(y)), y, rtol=1e-4)
    assert oidn_unet.pu_forward(torch.tensor(65504.0)).item() == pytest.approx(1.0, rel=1e-6)
    s = torch.linspace(0, 1, 101)
    assert torch.allclose(oidn_unet.srgb_inverse(oidn_unet.srgb_forward(s)), s, atol=1e-6)


# ---------------------------------------------------------------------------------------------
# TZA reader
# ---------------------------------------------------------------------------------------------


def _write_tza(tensors: dict[str, np.ndarray]) -> bytes:
    """A minimal TZA 2.0 writer (OIDN's format, see reconstruct/tza.py), for the tests."""
    out, table = bytearray(struct.pack("<HBBQ", 0x41D7, 2, 0, 0)), []
    for name, arr in tensors.items():
        out += b"\0" * (-len(out) % 64)
        table.append((name, arr, len(out)))
        out += np.ascontiguousarray(arr).tobytes()
    out += b"\0" * (-len(out) % 64)
    struct.pack_into("<Q", out, 4, len(out))
    out += struct.pack("<I", len(table))
    for name, arr, offset in table:
        out += struct.pack("<H", len(name)) + name.encode()
        out += struct.pack(f"<B{arr.ndim}I", arr.ndim, *arr.shape)
        out += ("oihw" if arr.ndim == 4 else "x").encode() + (
            b"h" if arr.dtype == np.float16 else b"f"
        )
        out += struct.pack("<Q", offset)
    return bytes(out)


def _small_state() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    net = oidn_unet.OIDNUNet(3, 3, "small")
    return {k: rng.standard_normal(v.shape).astype(np.float16) for k, v in net.state_dict().items()}


def test_tza_roundtrip_and_corruption(tmp_path):
    state = _small_state()
    blob = _write_tza(state)
    parsed = tza.parse_tza(blob)
    assert parsed.keys() == state.keys()
    assert all(parsed[k].dtype == np.float32 and np.array_equal(parsed[k], state[k]) for k in state)
    path = tmp_path / "w.tza"
    path.write_bytes(blob)
    net = oidn_unet.OIDNUNet.from_weights(path)
    assert net.kind == "small" and net.in_channels == 3
    bad = bytearray(blob)
    bad[0] ^= 0xFF
    with pytest.raises(tza.TZAError, match="magic"):
        tza.parse_tza(bad)
    bad = bytearray(blob)
    struct.pack_into("<Q", bad, 4, len(blob) + 100)
    with pytest.raises(tza.TZAError, match="out of bounds"):
        tza.parse_tza(bad)
    with pytest.raises(tza.TZAError):
        tza.parse_tza(blob[: len(blob) - 5])  # truncated table
    (tmp_path / "bad.tza").write_bytes(bytes(bad))
    with pytest.raises(tza.TZAError, match="bad.tza"):
        oidn_unet.OIDNUNet.from_weights(tmp_path / "bad.tza")
    with pytest.raises(FileNotFoundError, match="missing.tza"):
        oidn_unet.OIDNUNet.from_weights(tmp_path / "missing.tza")
    wrong = _write_tza({"foo.weight": np.zeros((2, 2, 3, 3), np.float32)})
    (tmp_path / "wrong.tza").write_bytes(wrong)
    with pytest.raises(tza.TZAError, match="OIDN U-Net"):
        tza.load_weights(tmp_path / "wrong.tza")


def test_unrecognised_library_and_missing_mitsuba_oidn(tmp_path, monkeypatch):
    # a "library" whose only TZA blob names the wrong layers, and one with a corrupted table
    wrong = _write_tza({"foo.weight": np.zeros((2, 2, 3, 3), np.float32)})
    corrupt = bytearray(_write_tza(_small_state()))
    struct.pack_into("<Q", corrupt, 4, 3)
    for i, blob in enumerate((wrong, bytes(corrupt))):
        lib = tmp_path / f"libOpenImageDenoise_core{i}.so"
        lib.write_bytes(b"\x7fELF" + b"\0" * 60 + blob + b"\0" * 64)
        with pytest.raises(tza.OIDNWeightsError, match=r"not recognised.*\.tza"):
            tza.builtin_weights(lib)
    monkeypatch.setattr(tza.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(tza.OIDNWeightsError, match=r"mitsuba-oidn.*\.tza"):
        tza.load_weights("rt_hdr_alb_nrm")


def test_builtin_blobs_identified():
    by_symbol = tza.builtin_weights()
    assert {"rt_hdr_alb_nrm", "rt_hdr", "rt_ldr_alb_nrm", "rt_hdr_alb_nrm_small"} <= set(by_symbol)
    assert tza.unet_kind(by_symbol["rt_hdr_alb_nrm"].tensors) == ("base", 9)
    assert tza.unet_kind(by_symbol["rt_hdr_alb_nrm_small"].tensors) == ("small", 9)
    if set(by_symbol) == set(tza.BUILTIN_ORDER):  # the link-order fallback agrees
        by_order = tza.builtin_weights(use_symbols=False)
        assert {k: b.offset for k, b in by_order.items()} == {
            k: b.offset for k, b in by_symbol.items()
        }


def test_tza_write_then_read_is_exact():
    gen = np.random.default_rng(3)
    tensors = {
        "enc_conv0.weight": gen.standard_normal((4, 9, 3, 3)).astype(np.float32),
        "enc_conv0.bias": gen.standard_normal(4).astype(np.float32),
        "dec_conv0.weight": gen.standard_normal((3, 4, 3, 3)).astype(np.float16),
        "dec_conv0.bias": np.array([np.inf, -0.0, 6.5e4], np.float16),
    }
    blob = tza.write_tza(tensors)
    back = tza.parse_tza(blob)
    assert list(back) == list(tensors)
    for name, value in tensors.items():
        assert back[name].dtype == np.float32 and back[name].shape == value.shape
        assert np.array_equal(back[name], value.astype(np.float32)), name
    assert struct.unpack_from("<HBBQ", blob)[:2] == (tza.TZA_MAGIC, 2)
    stored = tza.parse_tza(blob, stored_dtype=True)
    for name, value in tensors.items():
        assert stored[name].dtype == value.dtype and np.array_equal(stored[name], value), name
    with pytest.raises(tza.TZAError, match="tensor 'x': 2-d float32 cannot be written"):
        tza.write_tza({"x": np.zeros((2, 2), np.float32)})
    with pytest.raises(tza.TZAError, match="tensor 'x': 1-d float64 cannot be written"):
        tza.write_tza({"x": np.zeros(2)})


def test_tza_writer_reproduces_oidns_own_blob():
    """Written back, OIDN's built-in ``rt_hdr_alb_nrm`` is its library bytes, byte for byte."""
    blob = tza.builtin_weights()["rt_hdr_alb_nrm"]
    stored = blob.library.read_bytes()[blob.offset : blob.offset + blob.size]
    assert tza.write_tza(blob.tensors) == stored
