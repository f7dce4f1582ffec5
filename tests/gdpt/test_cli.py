"""gdpt.cli: help, ``info``, ``reconstruct`` and one-line user errors with exit status 2."""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys

import OpenEXR
import pytest
import torch

from gdpt import methods
from gdpt.cli import COMMANDS, build_parser, main
from gdpt.cli.config_options import config_from_args
from gdpt.io.exr import load_image, save_buffers


@pytest.fixture
def render(tmp_path, random_buffers):
    buffers = random_buffers(metadata={"scene": "cbox", "seed": 7})
    buffers.dx[0, 0, 0] = float("nan")
    buffers.dy[1, 1, :] = float("inf")
    return save_buffers(tmp_path / "render.exr", buffers)


@pytest.fixture
def fake_l2(monkeypatch):
    """Make ``--method l2`` a cheap stand-in (primal * 2) so CLI plumbing is tested alone."""
    monkeypatch.setitem(
        methods.METHODS,
        "l2",
        methods.Method(lambda buffers, *, alpha, **_: buffers.primal * 2, True, False, "x2"),
    )


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "gdpt", *args],
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
    )


def one_line_error(err: str) -> str:
    lines = [line for line in err.splitlines() if line.startswith("gdpt ")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_help_lists_commands():
    result = run_cli("--help")
    assert result.returncode == 0
    for command in COMMANDS:
        assert command.name in result.stdout
    with pytest.raises(SystemExit) as exit_info:
        main(["reconstruct", "--help"])
    assert exit_info.value.code == 0


def test_help_imports_neither_torch_nor_mitsuba():
    code = (
        "import sys\n"
        "from gdpt.cli import main\n"
        "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
        "print(sorted({'drjit', 'mitsuba', 'torch'} & set(sys.modules)))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], check=True, capture_output=True, text=True, timeout=120
    )
    assert "model-report" in result.stdout and result.stdout.splitlines()[-1] == "[]"


def test_no_command_is_a_usage_error():
    with pytest.raises(SystemExit) as exit_info:
        main([])
    assert exit_info.value.code == 2


def test_info(render, capsys):
    assert main(["info", str(render)]) == 0
    out = capsys.readouterr().out
    assert "10 x 12 (W x H)" in out
    assert "spp:      16" in out
    assert "gradient-domain" in out
    assert "normal.X,normal.Y,normal.Z" in out
    rows = {line.split()[0]: line.split()[-2:] for line in out.splitlines() if line[:2] == "  "}
    assert rows["dx"] == ["1", "0"] and rows["dy"] == ["0", "3"] and rows["primal"] == ["0", "0"]
    assert '"scene": "cbox"' in out


def test_info_describes_the_image_that_reconstruct_writes(render, tmp_path, fake_l2, capsys):
    out = tmp_path / "l2.exr"
    assert main(["reconstruct", str(render), "--method", "l2", "-o", str(out)]) == 0
    capsys.readouterr()
    assert main(["info", str(out)]) == 0
    described = capsys.readouterr().out
    assert "reconstructed image" in described and "10 x 12" in described
    assert '"method": "l2"' in described


def test_reconstruct_writes_exr_and_png(render, tmp_path, fake_l2, capsys, random_buffers):
    out = tmp_path / "sub" / "l2.exr"
    assert main(["reconstruct", str(render), "--method", "l2", "-o", str(out), "--png"]) == 0
    assert out.exists() and out.with_suffix(".png").exists()
    image = load_image(out)
    torch.testing.assert_close(image, random_buffers().primal * 2)
    assert "wrote" in capsys.readouterr().out


def test_reconstruct_refuses_to_overwrite(render, tmp_path, fake_l2, capsys):
    out = tmp_path / "l2.exr"
    args = ["reconstruct", str(render), "--method", "l2", "-o", str(out), "--png"]
    out.with_suffix(".png").write_bytes(b"old preview")
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "l2.png" in one_line_error(err) and "--force" in err
    assert not out.exists()  # checked before any work
    assert main([*args, "--force"]) == 0
    assert out.with_suffix(".png").read_bytes()[:4] == b"\x89PNG"


def test_deprecated_method_name_runs_the_new_method(render, tmp_path, monkeypatch, capsys):
    """``--method ngpt`` (the former name of ``oidn-grad``) runs ``oidn-grad``, warns, and the
    output's metadata names ``oidn-grad``; ``--help`` lists only current names."""
    network = methods.Method(lambda buffers, *, alpha, **_: buffers.primal * 3, True, True, "x3")
    monkeypatch.setitem(methods.METHODS, "oidn-grad", network)
    out = tmp_path / "o.exr"
    with pytest.warns(DeprecationWarning, match="'ngpt' is deprecated; use 'oidn-grad'"):
        assert main(["reconstruct", str(render), "--method", "ngpt", "-o", str(out)]) == 0
    assert json.loads(OpenEXR.File(str(out)).header()["gdpt.metadata"])["method"] == "oidn-grad"
    with pytest.raises(SystemExit):
        main(["reconstruct", "--help"])
    usage = capsys.readouterr().out
    assert "oidn-grad" in usage and "ngpt" not in usage


def test_deprecated_method_name_is_reported_on_stderr(tmp_path):
    missing = tmp_path / "missing.exr"
    result = run_cli("reconstruct", str(missing), "--method", "ngpt", "-o", str(tmp_path / "o.exr"))
    assert "reconstruction method 'ngpt' is deprecated; use 'oidn-grad'" in result.stderr
    assert one_line_error(result.stderr).endswith("missing.exr: no such file")


def test_primal_only_render_is_a_clear_error(tmp_path, capsys, random_buffers):
    path = save_buffers(tmp_path / "pt.exr", random_buffers(names=("primal", "albedo")))
    assert main(["reconstruct", str(path), "-o", str(tmp_path / "o.exr")]) == 2
    line = one_line_error(capsys.readouterr().err)
    assert "needs dx and dy" in line and "primal-only" in line


@pytest.mark.parametrize(
    ("method", "lacking", "option"),
    [
        ("kpcn", {"var_primal": None}, "render with variance=True (gdpt render --variance)"),
        ("oidn-grad", {"dx": None, "dy": None}, "gdpt render without --no-gradients"),
    ],
)
def test_network_without_the_buffers_it_reads_exits_2_naming_the_render_option(
    tmp_path, random_buffers, capsys, method, lacking, option
):
    """``gdpt reconstruct --method kpcn`` on buffers without ``var_primal`` (and a gradient
    network on primal-only buffers): one line naming the buffer and the render option."""
    path = save_buffers(tmp_path / "render.exr", random_buffers().replace(**lacking))
    out = tmp_path / "o.exr"
    assert main(["reconstruct", str(path), "--method", method, "-o", str(out)]) == 2
    line = one_line_error(capsys.readouterr().err)
    assert f"the buffers lack {', '.join(lacking)}" in line and option in line
    assert not out.exists()


@pytest.mark.parametrize(
    ("command", "match"),
    [
        (["info", "{missing}"], "missing.exr: no such file"),
        (["info", "{text}"], "notes.exr: not an OpenEXR file"),
        (["info", "{tmp}"], ": is a directory"),
        (["reconstruct", "{missing}", "-o", "{out}"], "missing.exr: no such file"),
        (["reconstruct", "{text}", "-o", "{out}"], "notes.exr: not an OpenEXR file"),
        (["reconstruct", "{render}", "-o", "{tmp}/o.png"], "must be an .exr"),
        (["reconstruct", "{render}", "--alpha", "-1", "-o", "{out}"], "--alpha must be"),
    ],
)
def test_bad_input_exits_2_with_one_line(tmp_path, render, command, match, capsys):
    text = tmp_path / "notes.exr"
    text.write_text("not an image")
    names = {"missing": tmp_path / "missing.exr", "text": text, "render": render}
    names.update(out=tmp_path / "o.exr", tmp=tmp_path)
    assert main([arg.format(**names) for arg in command]) == 2
    captured = capsys.readouterr()
    assert match in one_line_error(captured.err)
    assert captured.out == ""


def test_entry_point_error_has_no_traceback(tmp_path):
    result = run_cli("info", str(tmp_path / "missing.exr"))
    assert result.returncode == 2
    expected = f"gdpt info: error: {tmp_path / 'missing.exr'}: no such file"
    assert one_line_error(result.stderr) == expected


def test_reconstruct_end_to_end(render, tmp_path):
    out = tmp_path / "l1.exr"
    result = run_cli("reconstruct", str(render), "--method", "l1", "-o", str(out), "--png")
    assert result.returncode == 0, result.stderr
    image = load_image(out)
    assert image.shape == (12, 10, 3) and torch.isfinite(image).all()
    meta = json.loads(OpenEXR.File(str(out)).header()["gdpt.metadata"])
    assert meta["method"] == "l1" and meta["alpha"] == 0.2 and meta["render"]["seed"] == 7


@pytest.mark.parametrize(
    ("command", "match"),
    [
        (["{missing}", "-o", "{out}"], "missing.xml"),
        (["{broken}", "-o", "{out}"], "no_such_plugin"),
        (["builtin:no-such-scene", "-o", "{out}"], "unknown builtin scene 'no-such-scene'"),
        (["builtin:cbox-demo", "-o", "{folder}"], "{folder}: is a directory"),
        (["builtin:cbox-demo", "-o", "{existing}"], "old.exr: file exists"),
        (["builtin:cbox-demo", "-o", "{tmp}/o.png"], "must be an .exr"),
        (["builtin:cbox-demo", "-o", "{out}", "--spp", "0"], "spp must be >= 1"),
        (
            ["builtin:cbox-demo", "-o", "{out}", "--primal-spp", "4", "--no-gradients"],
            "gradients=false",
        ),
    ],
    ids=[
        "missing-scene",
        "broken-xml",
        "unknown-builtin",
        "output-is-a-directory",
        "output-exists",
        "output-not-exr",
        "zero-spp",
        "pooling-without-gradients",
    ],
)
def test_render_bad_input_exits_2_with_one_line(variant, tmp_path, command, match, capsys):
    """``gdpt render``: every bad input is one line naming the problem, exit 2, no output."""
    broken = tmp_path / "broken.xml"
    broken.write_text('<scene version="3.0.0"><shape type="no_such_plugin"/></scene>')
    existing = tmp_path / "old.exr"
    existing.write_bytes(b"an earlier render")
    names = {"missing": tmp_path / "missing.xml", "broken": broken, "existing": existing}
    names.update(out=tmp_path / "o.exr", tmp=tmp_path, folder=tmp_path / "folder.exr")
    names["folder"].mkdir()
    assert main(["render", *(arg.format(**names) for arg in command)]) == 2
    assert match.format(**names) in one_line_error(capsys.readouterr().err)
    assert not (tmp_path / "o.exr").exists() and not (tmp_path / "o.png").exists()
    assert existing.read_bytes() == b"an earlier render"


@pytest.fixture
def corrupt_checkpoint(tmp_path):
    """A dense U-Net checkpoint whose card is intact and whose weights are random bytes."""
    from gdpt.reconstruct.dense_unet import build_model

    from gdpt.training.checkpoint import save_checkpoint

    torch.manual_seed(0)
    weights, _ = save_checkpoint(build_model("fast_xs"), tmp_path / "mine" / "model")
    weights.write_bytes(bytes(range(256)) * 8)
    return weights


def test_corrupt_checkpoint_exits_2_naming_the_file(render, tmp_path, corrupt_checkpoint, capsys):
    """``--model`` with a corrupt ``.safetensors``: one line naming it, before any rendering."""
    expected = f"{corrupt_checkpoint}: not a readable safetensors file"
    out = tmp_path / "o.exr"
    argv = ["reconstruct", str(render), "--method", "oidn-grad", "--model", str(corrupt_checkpoint)]
    assert main([*argv, "-o", str(out)]) == 2
    assert expected in one_line_error(capsys.readouterr().err)
    assert not out.exists()
    report = tmp_path / "report"
    argv = ["evaluate", "--scenes", "builtin:cbox-demo", "--quick", "--methods", "pt"]
    argv += ["--out", str(report), "--model", f"x={corrupt_checkpoint}", "--no-progress"]
    assert main(argv) == 2
    assert expected in one_line_error(capsys.readouterr().err)
    assert not report.exists()  # refused before the reference was rendered


def test_config_options_expose_every_field_with_the_dataclass_defaults(monkeypatch):
    from gdpt.reconstruct.combiner import COMBINER_LOSSES
    from gdpt.reconstruct.losses import LOSSES
    from gdpt.reconstruct.oidn_finetune import FINETUNE_LOSSES

    from gdpt.training.config import TrainConfig
    from gdpt.training.preprocess import DatasetConfig

    parser = build_parser()
    args = parser.parse_args(["train", "--config", "fast_xs", "--data", "d", "--out", "o"])
    assert {f.name for f in dataclasses.fields(TrainConfig)} <= set(vars(args))
    assert config_from_args(TrainConfig, args) == TrainConfig(data="d", out="o")
    args = parser.parse_args(["dataset", "--out", "x", "--scenes", "3", "--views", "2"])
    assert {f.name for f in dataclasses.fields(DatasetConfig)} - set(vars(args)) == {"scene_config"}
    config = config_from_args(DatasetConfig, args, exclude=("scene_config",))
    assert config == DatasetConfig(scenes=3, views=2)
    # the defaults are read from the dataclass, not re-typed
    steps = next(f for f in dataclasses.fields(TrainConfig) if f.name == "steps")
    monkeypatch.setattr(steps, "default", 7)
    args = build_parser().parse_args(["train", "--config", "m", "--data", "d", "--out", "o"])
    assert args.steps == 7
    # --loss offers exactly the registered losses
    train = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    loss = next(a for a in train.choices["train"]._actions if a.dest == "loss")
    assert set(loss.choices) == set(LOSSES) | set(FINETUNE_LOSSES) | set(COMBINER_LOSSES)


def test_config_options_round_trip_and_help(capsys):
    from gdpt.training.config import TrainConfig

    argv = ["train", "--config", "fast_xs", "--data", "d", "--out", "o", "--no-augment"]
    argv += ["--pad", "4", "--vary-padding", "2", "--loss", "l1_rel", "--crop", "32"]
    config = config_from_args(TrainConfig, build_parser().parse_args(argv))
    assert (config.augment, config.pad, config.vary_padding) == (False, 4, 2)
    assert (config.loss, config.crop, config.warmup_steps) == ("l1_rel", 32, None)
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--help"])
    assert exit_info.value.code == 0
    help_text = " ".join(capsys.readouterr().out.split())
    assert "--beta2 BETA2 Adam beta2. (default: 0.99)" in help_text  # from the docstring
    with pytest.raises(SystemExit) as exit_info:
        build_parser().parse_args([*argv[:7], "--loss", "lpips"])
    assert exit_info.value.code == 2


def test_the_default_reconstruction_is_l1_fast_in_the_api_and_the_cli(random_buffers):
    """``l1-fast`` (the same L1 energy as ``l1``, faster) is the default of both entries."""
    import inspect

    import gdpt

    assert inspect.signature(gdpt.reconstruct_image).parameters["method"].default == "l1-fast"
    args = build_parser().parse_args(["reconstruct", "in.exr", "-o", "out.exr"])
    assert args.method == "l1-fast"
    buffers = random_buffers()
    torch.testing.assert_close(
        gdpt.reconstruct_image(buffers), gdpt.reconstruct_image(buffers, "l1-fast")
    )
