"""``gdpt render-and-denoise`` and the scene options of ``gdpt render`` (``--box-filter``,
``--long-side``, the scene's own ``max_depth``): tiny renders (32 px, 1-2 spp)."""

from __future__ import annotations

import re

import pytest
import torch

from gdpt import methods
from gdpt.cli import main
from gdpt.io.exr import load_buffers, load_image

pytestmark = pytest.mark.usefixtures("variant", "single_thread")

#: A 64x32 XML scene with Mitsuba's Gaussian filter and a path integrator of max_depth 4.
GAUSSIAN_XML = """<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="4"/></integrator>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/>
        </transform>
        <film type="hdrfilm">
            <integer name="width" value="64"/>
            <integer name="height" value="32"/>
            <rfilter type="gaussian"/>
        </film>
    </sensor>
    <emitter type="constant"/>
    <shape type="sphere"><bsdf type="diffuse"/></shape>
</scene>
"""


@pytest.fixture
def gaussian_scene(tmp_path):
    path = tmp_path / "scene.xml"
    path.write_text(GAUSSIAN_XML)
    return path


def one_line_error(err: str) -> str:
    lines = [line for line in err.splitlines() if line.startswith("gdpt ")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_writes_image_preview_buffers_and_timings(tmp_path, capsys):
    out, saved = tmp_path / "l2.exr", tmp_path / "buffers.exr"
    args = ["builtin:cbox-demo", "--long-side", "32", "--spp", "2", "--method", "l2"]
    assert main(["render-and-denoise", *args, "-o", str(out), "--save-buffers", str(saved)]) == 0
    stdout = capsys.readouterr().out
    assert "builtin:cbox-demo: max_depth 6 (default; the scene sets none)" in stdout
    assert f"wrote {out}" in stdout and f"wrote {saved}" in stdout
    assert "timings: render " in stdout and ", reconstruct " in stdout and ", total " in stdout
    assert out.with_suffix(".png").is_file()
    image, buffers = load_image(out), load_buffers(saved)
    assert image.shape == (32, 32, 3) and torch.isfinite(image).all()
    assert buffers.spp == 2 and buffers.has_gradients and buffers.albedo is None  # what l2 reads
    assert buffers.metadata["max_depth"] == 6
    torch.testing.assert_close(image, methods.reconstruct_image(buffers, "l2"))


def test_creates_the_output_folders_like_render(tmp_path, capsys):
    out, saved = tmp_path / "new" / "l2.exr", tmp_path / "other" / "deep" / "buffers.exr"
    args = ["builtin:cbox-demo", "--long-side", "16", "--spp", "1", "--method", "l2"]
    assert main(["render-and-denoise", *args, "-o", str(out), "--save-buffers", str(saved)]) == 0
    assert out.is_file() and out.with_suffix(".png").is_file() and saved.is_file()


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"-o": "{tmp}/afile/out.exr"}, "--output .*afile/out.exr: a parent of it is a file"),
        ({"-o": "{tmp}/out.png"}, "--output must be an .exr file"),
        ({"--save-buffers": "{tmp}/afile/b.exr"}, "--save-buffers .*: a parent of it is a file"),
        ({"--save-buffers": "{tmp}/out.exr"}, "--save-buffers and --output are the same file"),
        ({"--spp": "0"}, "--spp must be >= 1, got 0"),
        ({"--time": "2"}, "give --spp or --time, not both"),
        ({"--spp": None, "--time": "0"}, "--time must be a finite number of seconds > 0, got 0"),
        ({"--spp": None, "--time": "-1"}, "--time must be a finite number .* got -1"),
        ({"--spp": None, "--time": "nan"}, "--time must be a finite number .* got nan"),
        ({"--alpha": "0"}, "--alpha must be a finite number > 0"),
        ({"--long-side": "0"}, "--long-side must be >= 1"),
        ({"--max-depth": "-2"}, "--max-depth must be -1 .* or >= 0"),
        ({"scene": "{tmp}/none.xml"}, "scene file not found: .*none.xml"),
        ({"scene": "builtin:nope"}, "unknown builtin scene 'nope'"),
        ({"existing": "out.exr"}, "out.exr: file exists .*--force"),
        ({"existing": "out.png"}, "out.png: file exists .*--force"),
    ],
)
def test_bad_options_fail_before_rendering(tmp_path, capsys, monkeypatch, change, match):
    import gdpt.pipeline

    def forbidden(*args, **kwargs):
        raise AssertionError("rendered despite a bad option")

    monkeypatch.setattr(gdpt.pipeline, "render_and_denoise", forbidden)
    options = {"scene": "builtin:cbox-demo", "-o": "{tmp}/out.exr", "--spp": "1", **change}
    (tmp_path / "afile").write_text("a file")
    if existing := options.pop("existing", None):
        (tmp_path / existing).write_text("keep me")
    argv = ["render-and-denoise", options.pop("scene").format(tmp=tmp_path), "--long-side", "16"]
    for key, value in options.items():
        argv += [] if value is None else [key, value.format(tmp=tmp_path)]
    assert main(argv) == 2
    line = one_line_error(capsys.readouterr().err)
    assert line.startswith("gdpt render-and-denoise: error: ")
    assert re.search(match, line), line
    if existing:
        assert (tmp_path / existing).read_text() == "keep me"


def test_a_method_that_cannot_run_here_fails_before_rendering(tmp_path, capsys, monkeypatch):
    unavailable = methods.Method(lambda b, **_: b.primal, True, False, "x", lambda: "no package")
    monkeypatch.setitem(methods.METHODS, "l2", unavailable)
    argv = ["render-and-denoise", "builtin:nope", "--method", "l2", "-o", str(tmp_path / "a.exr")]
    assert main(argv) == 2  # the method is checked before the scene is even loaded
    assert "--method l2 cannot run here: no package" in one_line_error(capsys.readouterr().err)


def test_unknown_method_is_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["render-and-denoise", "builtin:cbox-demo", "--method", "x", "-o", str(tmp_path)])
    assert exit_info.value.code == 2
    assert "invalid choice: 'x'" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["render", "render-and-denoise"])
def test_gaussian_filter_needs_box_filter(gaussian_scene, tmp_path, capsys, command):
    assert main([command, str(gaussian_scene), "-o", str(tmp_path / "out.exr")]) == 2
    line = one_line_error(capsys.readouterr().err)
    assert "pixel filter is 'gaussian'" in line and "add --box-filter" in line
    assert not (tmp_path / "out.exr").exists()


@pytest.mark.parametrize("command", ["render", "render-and-denoise"])
def test_a_medium_on_the_sensor_is_refused(gaussian_scene, tmp_path, capsys, command):
    """A homogeneous medium on the sensor (rendered as vacuum before): one line naming it,
    exit status 2, nothing written, nothing printed before it."""
    fog = '<medium type="homogeneous" id="fog"><float name="scale" value="0.5"/></medium>'
    xml = GAUSSIAN_XML.replace("<sensor", fog + "<sensor", 1)
    scene = tmp_path / "fog.xml"
    scene.write_text(xml.replace("</sensor>", '<ref id="fog"/></sensor>'))
    out = tmp_path / "out" / "out.exr"
    assert main([command, str(scene), "--box-filter", "-o", str(out)]) == 2
    captured = capsys.readouterr()
    line = one_line_error(captured.err)
    assert "participating media are not supported: medium 'fog'" in line and "sensor" in line
    assert captured.out == "" and not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("extra", "depth", "source"),
    [([], 4, "from the scene's integrator"), (["--max-depth", "2"], 2, "--max-depth")],
)
def test_render_box_filter_long_side_and_the_scenes_depth(
    gaussian_scene, tmp_path, capsys, extra, depth, source
):
    out = tmp_path / "buffers.exr"
    argv = ["render", str(gaussian_scene), "--box-filter", "--long-side", "16", "--spp", "1"]
    assert main([*argv, *extra, "-o", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert f"{gaussian_scene}: max_depth {depth} ({source})" in stdout
    assert "film resized from 64x32 to 16x8" in stdout
    assert "pixel filter overridden: 'gaussian' -> 'box'" in stdout
    buffers = load_buffers(out)
    assert (buffers.width, buffers.height) == (16, 8)
    assert buffers.metadata["max_depth"] == depth


def test_timings_line_says_the_budget_the_count_and_what_was_not_timed():
    from types import SimpleNamespace

    from gdpt.cli.render import timings_line

    timings = {"render": 2.5, "reconstruct": 0.55, "total": 3.05, "compile": 0.4, "setup": 9.0}
    result = SimpleNamespace(timings=timings, budget=3.0, spp=27)
    line = timings_line(result, "fuse")
    assert line.startswith("timings: render 2.50 s, reconstruct 0.55 s, total 3.05 s of a 3.00 s ")
    assert "budget (27 gradient spp); not timed: kernel compilation 0.40 s, setup 9.00 s" in line
    counted = timings_line(SimpleNamespace(timings={"total": 1.0}, budget=None, spp=64), "auto")
    assert counted == (
        "timings: total 1.00 s (64 spp, plain samples' worth); not timed: kernel compilation 0.00 s"
    )
