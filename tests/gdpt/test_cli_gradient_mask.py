"""A user's gradient mask: ``gdpt.io.images.load_mask`` (PNG, EXR), ``--gradient-mask`` of
``gdpt render`` and ``gdpt render-and-denoise``, and ``render_and_denoise(gradient_mask=M)``;
bad input fails before rendering (tiny renders: 16 px, 2 spp)."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
from PIL import Image

from gdpt.cli import main
from gdpt.io.exr import save_image
from gdpt.io.images import load_mask

SIZE = 16


def _left_half() -> np.ndarray:
    mask = np.zeros((SIZE, SIZE), dtype=bool)
    mask[:, : SIZE // 2] = True
    return mask


def _one_line_error(err: str) -> str:
    lines = [line for line in err.splitlines() if line.startswith("gdpt ")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize("kind", ["grey", "rgba", "16bit", "exr"])
def test_load_mask_reads_png_and_exr(tmp_path, kind):
    mask = _left_half()
    path = tmp_path / ("mask.exr" if kind == "exr" else "mask.png")
    if kind == "grey":
        Image.fromarray(np.where(mask, 200, 40).astype(np.uint8)).save(path)
    elif kind == "rgba":  # set by the blue channel only; alpha (opaque everywhere) ignored
        rgba = np.zeros((SIZE, SIZE, 4), np.uint8)
        rgba[..., 2], rgba[..., 3] = np.where(mask, 255, 0), 255
        Image.fromarray(rgba).save(path)
    elif kind == "16bit":
        Image.fromarray(np.where(mask, 60000, 30000).astype(np.uint16)).save(path)
    else:
        save_image(path, torch.from_numpy(np.where(mask, 0.9, 0.1)[..., None].repeat(3, -1)))
    loaded = load_mask(path)
    assert loaded.dtype == bool and np.array_equal(loaded, mask)


def test_load_mask_bad_files(tmp_path):
    with pytest.raises(ValueError, match=r"a mask must be a .png or .exr image, got '.jpg'"):
        load_mask(tmp_path / "mask.jpg")
    with pytest.raises(FileNotFoundError, match="mask file not found: .*none.png"):
        load_mask(tmp_path / "none.png")


@pytest.fixture
def mask_png(tmp_path):
    path = tmp_path / "mask.png"
    Image.fromarray(np.where(_left_half(), 255, 0).astype(np.uint8)).save(path)
    return path


@pytest.mark.usefixtures("variant", "single_thread")
def test_render_and_denoise_with_a_user_mask(tmp_path, mask_png, capsys):
    from gdpt.io.exr import load_buffers

    out, saved = tmp_path / "fuse.exr", tmp_path / "buffers.exr"
    args = ["builtin:cbox-demo", "--long-side", str(SIZE), "--spp", "2", "--method", "fuse"]
    args += ["--gradient-mask", str(mask_png), "-o", str(out), "--save-buffers", str(saved)]
    assert main(["render-and-denoise", *args]) == 0
    buffers = load_buffers(saved)
    assert buffers.metadata["gradient_mask"] == {"share": 0.5}
    assert torch.isfinite(buffers.dx[:, : SIZE // 2 - 1]).all()
    assert not torch.isfinite(buffers.dx[:, SIZE // 2 :]).any()  # untraced: NaN in the EXR


@pytest.mark.parametrize(
    ("command", "extra", "match"),
    [
        ("render-and-denoise", [], r"--gradient-mask .* but --method auto chooses its own route"),
        ("render-and-denoise", ["--method", "oidn"], r"--method oidn reads no gradients"),
        ("render", ["--no-gradients"], r"--gradient-mask .* but --no-gradients is set"),
        ("render", ["--mask-file", "{tmp}/none.png"], r"mask file not found: .*none.png"),
        ("render", ["--mask-file", "{tmp}/mask.txt"], r"a mask must be a .png or .exr image"),
    ],
)
def test_bad_masks_fail_before_rendering(
    tmp_path, mask_png, capsys, monkeypatch, command, extra, match
):
    import gdpt.pipeline
    import gdpt.rendering

    def forbidden(*args, **kwargs):
        raise AssertionError("rendered despite a bad mask")

    monkeypatch.setattr(gdpt.pipeline, "render_and_denoise", forbidden)
    monkeypatch.setattr(gdpt.rendering, "render", forbidden)
    mask = str(mask_png)
    if extra[:1] == ["--mask-file"]:
        mask, extra = extra[1].format(tmp=tmp_path), []
    argv = [command, "builtin:cbox-demo", "--long-side", str(SIZE), "--spp", "1", *extra]
    argv += ["--gradient-mask", mask, "-o", str(tmp_path / "out.exr")]
    assert main(argv) == 2
    line = _one_line_error(capsys.readouterr().err)
    assert re.search(match, line), line


@pytest.mark.usefixtures("variant", "single_thread")
def test_a_mask_of_the_wrong_size_is_named(tmp_path, capsys):
    path = tmp_path / "small.png"
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(path)
    argv = ["render", "builtin:cbox-demo", "--long-side", str(SIZE), "--spp", "1"]
    argv += ["--gradient-mask", str(path), "-o", str(tmp_path / "out.exr")]
    assert main(argv) == 2
    line = _one_line_error(capsys.readouterr().err)
    assert re.search(r"shape \(H, W\) = \(16, 16\).*got shape \(8, 8\)", line), line
    assert not (tmp_path / "out.exr").exists()


def test_render_and_denoise_rejects_a_mask_with_auto():
    import gdpt

    with pytest.raises(ValueError, match="method 'auto' chooses its own route"):
        gdpt.render_and_denoise(object(), spp=4, gradient_mask=torch.ones(2, 2, dtype=torch.bool))
