"""gdpt.load_buffers on EXRs written by Mitsuba's ``aov`` integrator, and gdpt.io.exr.describe_exr
(``gdpt info``) on every kind of EXR: buffers, reconstructed images, Mitsuba AOV EXRs."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import OpenEXR
import pytest
import torch

import gdpt
from gdpt.io import mitsuba_aov
from gdpt.io.exr import describe_exr, load_buffers, load_image, save_buffers, save_image

#: Mitsuba's documentation example of the aov integrator, with an albedo.
AOVS = "dd.y:depth,nn:sh_normal,albedo:albedo"


@pytest.fixture(scope="module")
def mitsuba_aov_exr(tmp_path_factory):
    """A 24x16 Cornell box rendered by Mitsuba's ``path`` inside ``aov`` (AOVS), written as
    Mitsuba writes it (``film().bitmap().write``), and the ``mi.render`` tensor."""
    import mitsuba as mi

    gdpt.set_variant()
    scene = mi.cornell_box()
    scene["integrator"] = {"type": "aov", "aovs": AOVS, "integrator": {"type": "path"}}
    scene["sensor"]["film"].update(width=24, height=16)
    scene = mi.load_dict(scene)
    image = mi.render(scene, spp=8)
    path = tmp_path_factory.mktemp("aov") / "cbox.exr"
    scene.sensors()[0].film().bitmap().write(str(path))
    return path, image.torch().cpu()


def write_raw(path, channels):
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, channels).write(str(path))
    return path


def aov_channels(h=4, w=3, **extra):
    rng = np.random.default_rng(0)
    names = ["R", "G", "B", "albedo.R", "albedo.G", "albedo.B", "nn.X", "nn.Y", "nn.Z", "dd.T"]
    channels = {n: rng.random((h, w), dtype=np.float32) for n in names}
    return {**channels, **extra}


def test_channel_names_mitsuba_writes(mitsuba_aov_exr):
    path, _ = mitsuba_aov_exr
    names = set(OpenEXR.File(str(path), separate_channels=True).channels())
    expected = {"R", "G", "B", "albedo.R", "albedo.G", "albedo.B", "dd.y.T", "nn.X", "nn.Y"}
    assert expected | {"nn.Z"} <= names


def test_mitsuba_aov_exr_reads_as_buffers(mitsuba_aov_exr):
    path, image = mitsuba_aov_exr
    buffers = load_buffers(path)
    assert buffers.present() == ["primal", "albedo", "normal", "depth"]
    assert not buffers.has_gradients and (buffers.width, buffers.height) == (24, 16)
    assert buffers.metadata["source"] == "mitsuba-aov-exr"
    assert buffers.metadata["aovs"]["depth"] == ["dd.y.T"]
    assert buffers.metadata["aovs"]["normal"] == ["nn.X", "nn.Y", "nn.Z"]
    channels = OpenEXR.File(str(path), separate_channels=True).channels()
    torch.testing.assert_close(buffers.primal[..., 0], torch.from_numpy(channels["R"].pixels))
    torch.testing.assert_close(buffers.depth[..., 0], torch.from_numpy(channels["dd.y.T"].pixels))
    torch.testing.assert_close(buffers.normal[..., 2], torch.from_numpy(channels["nn.Z"].pixels))
    torch.testing.assert_close(buffers.primal, image[..., :3], rtol=1e-5, atol=1e-5)
    assert buffers.depth.max() > 0 and (buffers.normal.norm(dim=-1).max() - 1).abs() < 1e-3


@pytest.mark.parametrize("method", ["oidn", "oidn-tuned"])
def test_mitsuba_aov_exr_is_denoised(mitsuba_aov_exr, method):
    buffers = load_buffers(mitsuba_aov_exr[0])
    image = gdpt.reconstruct_image(buffers, method=method)
    assert image.shape == (16, 24, 3) and bool(torch.isfinite(image).all())
    assert not torch.equal(image, buffers.primal)


def test_gdpt_reconstruct_denoises_an_aov_exr(mitsuba_aov_exr, tmp_path):
    out = tmp_path / "denoised.exr"
    command = ["reconstruct", str(mitsuba_aov_exr[0]), "--method", "oidn-tuned", "-o", str(out)]
    result = subprocess.run(
        [sys.executable, "-m", "gdpt", *command],
        check=False,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    image = load_image(out)
    assert image.shape == (16, 24, 3) and bool(torch.isfinite(image).all())


@pytest.mark.parametrize("method", ["l1", "l1-fast", "l2", "fuse", "oidn-grad"])
def test_gradient_method_on_aov_exr_names_the_gradients(mitsuba_aov_exr, method):
    with pytest.raises(ValueError, match=r"reads the gradients dx/dy, which only a gdpt render"):
        gdpt.reconstruct_image(load_buffers(mitsuba_aov_exr[0]), method=method)


@pytest.mark.parametrize(
    ("method", "match"),
    [("kpcn", r"lack var_primal"), ("nfor", r"'primal_a' \(render with halves")],
)
def test_statistics_methods_on_aov_exr_name_what_is_missing(mitsuba_aov_exr, method, match):
    """KPCN reads the primal's variance, NFOR half-buffers: an AOV EXR has neither."""
    with pytest.raises((KeyError, ValueError), match=match):
        gdpt.reconstruct_image(load_buffers(mitsuba_aov_exr[0]), method=method)


def test_explicit_kinds_resolve_ambiguous_layers(tmp_path):
    extra = {f"gn.{c}": np.zeros((4, 3), np.float32) for c in "XYZ"}
    path = write_raw(tmp_path / "two_normals.exr", aov_channels(**extra))
    with pytest.raises(ValueError, match=r"two_normals\.exr.*layers gn, nn.*--aov normal=LAYER"):
        load_buffers(path)
    buffers = load_buffers(path, aov_kinds={"normal": "nn"})
    channels = OpenEXR.File(str(path), separate_channels=True).channels()
    torch.testing.assert_close(buffers.normal[..., 1], torch.from_numpy(channels["nn.Y"].pixels))
    assert load_buffers(path, aov_kinds={"normal": "gn"}).normal.abs().max() == 0


def test_explicit_primal_layer_and_nested_integrator_layer(tmp_path):
    rgba = {f"integrator.{c}": np.full((4, 3), 2.0, np.float32) for c in "RGBA"}
    channels = {k: v for k, v in aov_channels(**rgba).items() if k not in "RGB"}
    path = write_raw(tmp_path / "no_rgb.exr", channels)
    with pytest.raises(ValueError, match=r"no_rgb\.exr.*no image channels R, G, B.*integrator\.A"):
        load_buffers(path)
    buffers = load_buffers(path, aov_kinds={"primal": "integrator"})
    assert buffers.present() == ["primal", "albedo", "normal", "depth"]
    assert bool((buffers.primal == 2.0).all())


@pytest.mark.parametrize(
    ("kinds", "match"),
    [
        ({"colour": "nn"}, r"unknown AOV kind colour"),
        ({"normal": "missing"}, r"no layer 'missing' for the normal; layers found: \(image\)"),
        ({"depth": "nn"}, r"layer 'nn' given for the depth has nn\.X, nn\.Y, nn\.Z"),
    ],
)
def test_bad_explicit_kinds(tmp_path, kinds, match):
    path = write_raw(tmp_path / "a.exr", aov_channels())
    with pytest.raises(ValueError, match=match):
        load_buffers(path, aov_kinds=kinds)


def test_kinds_are_refused_for_a_gdpt_render(tmp_path, random_buffers):
    path = save_buffers(tmp_path / "g.exr", random_buffers())
    with pytest.raises(ValueError, match=r"g\.exr: a gdpt buffers EXR; aov_kinds"):
        load_buffers(path, aov_kinds={"normal": "nn"})


def test_mismatched_sizes_are_one_line_naming_the_channels(tmp_path, monkeypatch):
    """Channels of different sizes (subsampled EXR channels), as the reader returns them."""
    from gdpt.io import exr

    channels = {**aov_channels(), "dd.T": np.zeros((2, 3), np.float32)}
    path = write_raw(tmp_path / "sizes.exr", aov_channels())
    monkeypatch.setattr(exr, "_read_exr", lambda _path: ({}, channels))
    with pytest.raises(
        ValueError, match=r"sizes\.exr.*different sizes \(W x H\): B 3x4, .*dd\.T 3x2"
    ) as e:
        load_buffers(path)
    assert "\n" not in str(e.value)


def test_no_primal_like_channel_lists_the_channels(tmp_path):
    channels = {f"nn.{c}": np.zeros((4, 3), np.float32) for c in "XYZ"}
    with pytest.raises(ValueError, match=r"nn\.exr.*no image channels.*found: nn: nn\.X"):
        load_buffers(write_raw(tmp_path / "nn.exr", channels))


def test_parse_aov_kinds():
    assert mitsuba_aov.parse_aov_kinds(["normal=nn", "depth=dd.y"]) == {
        "normal": "nn",
        "depth": "dd.y",
    }
    assert mitsuba_aov.parse_aov_kinds(None) == {}
    for bad, match in [
        (["nn"], "KIND=LAYER"),
        (["x=nn"], "unknown kind"),
        (["depth=a"] * 2, "twice"),
    ]:
        with pytest.raises(ValueError, match=match):
            mitsuba_aov.parse_aov_kinds(bad)


# ------------------------------------------------------------------------------- describe_exr
def table(text: str) -> dict[str, list[str]]:
    """``{row name: [channels, NaN, Inf]}`` of a description's buffers/layers table."""
    rows = [line.split() for line in text.splitlines() if line.startswith("  ")]
    return {row[0]: row[1:] for row in rows if len(row) == 4 and row[0] != "name"}


def test_describe_buffers_exr(tmp_path, random_buffers):
    buffers = random_buffers(metadata={"scene": "cbox"})
    buffers.dy[1, 1, :] = float("inf")
    text = describe_exr(save_buffers(tmp_path / "r.exr", buffers))
    assert "kind:     gdpt buffers" in text and "10 x 12 (W x H)" in text
    assert "spp:      16" in text and "gradient-domain" in text
    assert table(text)["dy"] == ["dy.R,dy.G,dy.B", "0", "3"]
    assert table(text)["normal"][0] == "normal.X,normal.Y,normal.Z"
    assert '"scene": "cbox"' in text


def test_describe_reconstructed_image(tmp_path):
    """The EXR ``gdpt reconstruct`` writes (gdpt.io.exr.save_image with its metadata)."""
    image = torch.rand(5, 7, 3)
    image[0, 0, 1] = float("nan")
    metadata = {"source": "r.exr", "method": "l1", "alpha": 0.2, "spp": 16, "render": {}}
    path = save_image(tmp_path / "l1.exr", image, metadata=metadata)
    text = describe_exr(path)
    assert "kind:     reconstructed image (method l1)" in text
    assert "7 x 5 (W x H)" in text and "spp:      16" in text
    assert table(text)["image"] == ["R,G,B", "1", "0"]
    assert '"method": "l1"' in text
    with pytest.raises(ValueError, match=r"l1\.exr.*reconstructed image.*not buffers"):
        load_buffers(path)


def test_describe_mitsuba_aov_exr(mitsuba_aov_exr):
    text = describe_exr(mitsuba_aov_exr[0])
    assert "kind:     Mitsuba AOV EXR (Mitsuba version" in text
    assert "reads primal, albedo, normal, depth" in text and "24 x 16 (W x H)" in text
    rows = table(text)
    assert rows["depth"] == ["dd.y.T", "0", "0"] and rows["normal"][0] == "nn.X,nn.Y,nn.Z"
    assert rows["(unread)"][0].startswith("integrator.A")


def test_describe_other_exr_says_why_it_is_not_read(tmp_path):
    extra = {f"gn.{c}": np.full((4, 3), np.inf, np.float32) for c in "XYZ"}
    text = describe_exr(write_raw(tmp_path / "x.exr", aov_channels(**extra)))
    assert "kind:     EXR that gdpt does not read as buffers (layers gn, nn" in text
    row = [r for r in text.splitlines() if r.startswith("  (unread)    gn.X")][0]
    assert row.split()[-2:] == ["0", "36"]
