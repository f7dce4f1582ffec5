"""gdpt.io.exr: multi-layer EXR round trips, error messages, atomic and non-clobbering writes."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from gdpt.buffers import CHANNELS, GRADIENT_HALVES, GradientBuffers
from gdpt.io import exr
from gdpt.io.exr import channel_names, load_buffers, load_image, save_buffers, save_image

# (the gradient halves round-trip in test_float_round_trip: with them the property test's
# draws overrun Hypothesis's data budget)
OPTIONAL = [n for n in CHANNELS if n not in ("primal", "dx", "dy", *GRADIENT_HALVES)]


def assert_same(a: GradientBuffers, b: GradientBuffers) -> None:
    assert a.present() == b.present()
    for name, t in a.items():
        torch.testing.assert_close(getattr(b, name), t, rtol=0, atol=0, equal_nan=True)
    assert (a.spp, a.metadata) == (b.spp, b.metadata)


def write_raw(path: Path, channels: dict[str, np.ndarray], **header) -> Path:
    """Write an EXR that gdpt did not produce, with extra ``header`` attributes (to test the
    reader's checks)."""
    header = {"compression": OpenEXR.ZIP_COMPRESSION, **header}
    OpenEXR.File(header, channels).write(str(path))
    return path


def gdpt_channels(h: int = 4, w: int = 3) -> dict[str, np.ndarray]:
    """Zero ``primal``, ``dx`` and ``dy`` channels of an ``h x w`` render."""
    return {f"{n}.{c}": np.zeros((h, w), np.float32) for n in ("primal", "dx", "dy") for c in "RGB"}


def test_float_round_trip_is_bit_exact(tmp_path, random_buffers):
    meta = {"integrator": "gdpt", "seed": 3, "timings": {"render": 1.5}, "tags": ["a", "b"]}
    buffers = random_buffers(spp=64, metadata=meta)
    buffers.primal[0, 0, 0] = float("nan")
    buffers.dx[1, 2, 1] = float("inf")
    buffers.dy[2, 1, 2] = -float("inf")
    buffers.depth[0, 1, 0] = 1e-42  # subnormal
    path = save_buffers(tmp_path / "r.exr", buffers)
    assert_same(buffers, load_buffers(path))


def test_conventional_channel_names_and_header(tmp_path, random_buffers):
    save_buffers(tmp_path / "r.exr", random_buffers(spp=4, metadata={"k": 1}))
    f = OpenEXR.File(str(tmp_path / "r.exr"), separate_channels=True)
    assert len(f.parts) == 1
    rgb = [*(f"{n}{h}" for n in ("primal", "albedo") for h in ("", "_a", "_b")), "dx", "dy"]
    expected = {
        *(f"{n}.{c}" for n in rgb for c in "RGB"),
        *(f"normal{h}.{c}" for h in ("", "_a", "_b") for c in "XYZ"),
        "depth.Y", "depth_a.Y", "depth_b.Y", "var_primal.Y", "var_dx.Y", "var_dy.Y",
        *(f"{n}_{h}.{c}" for n in ("dx", "dy") for h in "ab" for c in "RGB"),
    }  # fmt: skip
    assert set(f.channels()) == expected
    header = f.header()
    assert header["gdpt.spp"] == 4
    assert json.loads(header["gdpt.metadata"]) == {"k": 1}
    assert header["gdpt.formatVersion"] == exr.FORMAT_VERSION
    assert isinstance(header["gdpt.version"], str)
    assert all(c.pixels.dtype == np.float32 for c in f.channels().values())


def test_half_round_trip_within_half_precision(tmp_path, random_buffers):
    buffers = random_buffers()
    path = save_buffers(tmp_path / "h.exr", buffers, half=True)
    f = OpenEXR.File(str(path), separate_channels=True)
    assert all(c.pixels.dtype == np.float16 for c in f.channels().values())
    loaded = load_buffers(path)
    for name, t in buffers.items():
        got = getattr(loaded, name)
        assert got.dtype == torch.float32
        torch.testing.assert_close(got, t.half().float(), rtol=0, atol=0)
        torch.testing.assert_close(got, t, rtol=2**-11, atol=6e-8)
    assert path.stat().st_size < save_buffers(tmp_path / "f.exr", buffers).stat().st_size


def test_primal_only_and_subsets(tmp_path, random_buffers):
    buffers = random_buffers(names=("primal", "depth"), spp=0)
    loaded = load_buffers(save_buffers(tmp_path / "p.exr", buffers))
    assert loaded.present() == ["primal", "depth"] and not loaded.has_gradients
    assert (loaded.spp, loaded.metadata) == (0, {})


def test_missing_primal_names_channel_and_file(tmp_path):
    rgb = {c: np.zeros((4, 3), np.float32) for c in "RGB"}
    path = write_raw(tmp_path / "plain.exr", rgb)
    with pytest.raises(ValueError, match=r"plain\.exr.*'primal\.R'"):
        load_buffers(path)


def test_partial_layer_names_channel_and_file(tmp_path):
    channels = {f"primal.{c}": np.zeros((4, 3), np.float32) for c in "RGB"}
    channels.update({"dx.R": np.zeros((4, 3), np.float32), "dx.B": np.zeros((4, 3), np.float32)})
    path = write_raw(tmp_path / "partial.exr", channels)
    with pytest.raises(ValueError, match=r"partial\.exr.*layer 'dx'.*'dx\.G'"):
        load_buffers(path)


def test_inconsistent_buffers_name_file(tmp_path):
    channels = {f"{n}.{c}": np.zeros((4, 3), np.float32) for n in ("primal", "dx") for c in "RGB"}
    path = write_raw(tmp_path / "nody.exr", channels)
    with pytest.raises(ValueError, match=r"nody\.exr.*'dx' and 'dy'"):
        load_buffers(path)


def test_uint_channel_is_rejected(tmp_path):
    channels = {f"primal.{c}": np.zeros((4, 3), np.uint32) for c in "RGB"}
    with pytest.raises(ValueError, match=r"u\.exr.*'primal\.R'.*uint32"):
        load_buffers(write_raw(tmp_path / "u.exr", channels))


def test_not_an_exr(tmp_path):
    path = tmp_path / "notes.exr"
    path.write_text("hello, not an image\n")
    with pytest.raises(ValueError, match=r"notes\.exr: not an OpenEXR file"):
        load_buffers(path)
    with pytest.raises(ValueError, match=r"notes\.exr: not an OpenEXR file"):
        load_image(path)


@pytest.mark.parametrize("fraction", [0.05, 0.5, 0.95])
def test_truncated_file(tmp_path, fraction, random_buffers):
    path = save_buffers(tmp_path / "full.exr", random_buffers(40, 30))
    data = path.read_bytes()
    cut = tmp_path / "cut.exr"
    cut.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(ValueError, match=r"cut\.exr"):
        load_buffers(cut)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("{not json", r"bad\.exr: header attribute 'gdpt\.metadata' is not valid JSON"),
        ("[1, 2]", r"bad\.exr: header attribute 'gdpt\.metadata' is not a JSON object"),
    ],
)
def test_metadata_that_is_not_a_json_object_names_file_and_attribute(tmp_path, text, match):
    path = write_raw(tmp_path / "bad.exr", gdpt_channels(), **{"gdpt.metadata": text})
    with pytest.raises(ValueError, match=match):
        load_buffers(path)


def test_newer_format_version_is_refused_with_both_versions(tmp_path):
    newer = exr.FORMAT_VERSION + 1
    header = {"gdpt.formatVersion": newer, "gdpt.version": "99.0", "gdpt.metadata": "{}"}
    path = write_raw(tmp_path / "future.exr", gdpt_channels(), **header)
    expected = (
        rf"future\.exr: gdpt EXR format version {newer} \(written by gdpt 99\.0\); this gdpt "
        rf".* reads format versions up to {exr.FORMAT_VERSION}"
    )
    with pytest.raises(ValueError, match=expected):
        load_buffers(path)
    with pytest.raises(ValueError, match=expected):
        load_image(path, "dx")
    # the current version and files without the attribute (other writers) are read
    header["gdpt.formatVersion"] = exr.FORMAT_VERSION
    assert load_buffers(write_raw(tmp_path / "now.exr", gdpt_channels(), **header)).spp == 0
    assert load_buffers(write_raw(tmp_path / "other.exr", gdpt_channels())).metadata == {}
    header["gdpt.formatVersion"] = "1"
    with pytest.raises(ValueError, match=r"'gdpt\.formatVersion' is '1', not an integer"):
        load_buffers(write_raw(tmp_path / "text.exr", gdpt_channels(), **header))


def test_directory_given_as_a_file(tmp_path):
    folder = tmp_path / "render.exr"
    folder.mkdir()
    for read in (load_buffers, load_image):
        with pytest.raises(IsADirectoryError, match=r"render\.exr: is a directory"):
            read(folder)


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nothing\.exr"):
        load_buffers(tmp_path / "nothing.exr")


def test_no_overwrite_without_force(tmp_path, random_buffers):
    path = save_buffers(tmp_path / "r.exr", random_buffers(seed=1))
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match=r"r\.exr"):
        save_buffers(path, random_buffers(seed=2))
    with pytest.raises(FileExistsError, match=r"r\.exr"):
        save_image(path, torch.zeros(2, 2, 3))
    assert path.read_bytes() == before
    save_buffers(path, random_buffers(seed=2), force=True)
    assert_same(random_buffers(seed=2), load_buffers(path))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.exr"]


def test_failed_write_leaves_no_file(tmp_path, monkeypatch, random_buffers):
    class BrokenFile:
        def __init__(self, header, channels):
            pass

        def write(self, filename):
            Path(filename).write_bytes(b"v/1\x01partial")
            raise OSError("disk full")

    monkeypatch.setattr(exr.OpenEXR, "File", BrokenFile)
    with pytest.raises(OSError, match="disk full"):
        save_buffers(tmp_path / "r.exr", random_buffers())
    assert list(tmp_path.iterdir()) == []


def test_unserialisable_metadata_writes_nothing(tmp_path, random_buffers):
    with pytest.raises(TypeError, match="JSON"):
        save_buffers(tmp_path / "r.exr", random_buffers(metadata={"x": object()}))
    assert list(tmp_path.iterdir()) == []


def test_save_and_load_image(tmp_path):
    image = torch.rand(6, 9, 3, dtype=torch.float64)
    path = save_image(tmp_path / "img.exr", image, metadata={"method": "l1"})
    f = OpenEXR.File(str(path), separate_channels=True)
    assert set(f.channels()) == {"R", "G", "B"}
    assert json.loads(f.header()["gdpt.metadata"]) == {"method": "l1"}
    loaded = load_image(path)
    assert loaded.dtype == torch.float32 and loaded.shape == (6, 9, 3)
    assert torch.equal(loaded, image.float())
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        save_image(tmp_path / "bad.exr", np.zeros((4, 4)))


def test_load_image_layers(tmp_path, random_buffers):
    buffers = random_buffers()
    path = save_buffers(tmp_path / "r.exr", buffers)
    assert torch.equal(load_image(path, "dx"), buffers.dx)
    assert torch.equal(load_image(path, "normal"), buffers.normal)
    assert torch.equal(load_image(path, "depth"), buffers.depth)
    with pytest.raises(ValueError, match=r"r\.exr.*missing channel 'R'"):
        load_image(path)
    with pytest.raises(ValueError, match=r"'beauty\.R'"):
        load_image(path, "beauty")


def test_channel_names():
    assert channel_names("normal") == ("normal.X", "normal.Y", "normal.Z")
    assert channel_names("var_dx") == ("var_dx.Y",)
    with pytest.raises(ValueError, match="valid buffers"):
        channel_names("colour")


@st.composite
def buffers_strategy(draw):
    h, w = draw(st.integers(1, 9)), draw(st.integers(1, 9))
    names = ["primal"]
    if draw(st.booleans()):
        names += ["dx", "dy"]
    names += [n for n in OPTIONAL if not n.endswith("_b") and draw(st.booleans())]
    names += [f"{n[:-2]}_b" for n in names if n.endswith("_a")]  # halves come in pairs
    floats = st.floats(width=32, allow_nan=False)
    tensors = {}
    for name in names:
        n = h * w * CHANNELS[name]
        values = draw(st.lists(floats, min_size=n, max_size=n))
        tensors[name] = torch.tensor(values, dtype=torch.float32).reshape(h, w, CHANNELS[name])
    spp = draw(st.integers(0, 2**31 - 1))
    metadata = draw(st.dictionaries(st.text(max_size=5), st.integers() | st.text(), max_size=3))
    return GradientBuffers(**tensors, spp=spp, metadata=metadata)


@settings(max_examples=30, deadline=None)
@given(buffers=buffers_strategy(), half=st.booleans())
def test_property_round_trip(buffers, half):
    with tempfile.TemporaryDirectory() as tmp:
        loaded = load_buffers(save_buffers(Path(tmp) / "r.exr", buffers, half=half))
    if not half:
        assert_same(buffers, loaded)
        return
    assert loaded.present() == buffers.present()
    for name, t in buffers.items():
        with np.errstate(over="ignore"):
            expected = t.numpy().astype(np.float16).astype(np.float32)
        np.testing.assert_array_equal(getattr(loaded, name).numpy(), expected)
