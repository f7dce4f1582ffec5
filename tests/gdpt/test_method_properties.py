"""Study methods with integrator properties (``gdpt+fuse@max_depth=4``): one table of the
plugins' properties (:mod:`gdpt.integrators.properties`) checks them for the plugin and the
study alike; cheap (no study runs, one 16 px render)."""

from __future__ import annotations

import dataclasses
import re

import pytest
import torch
from gdpt.integrators import properties

from gdpt.cli import main
from gdpt.study.calibration import calibration_runner, configuration_key
from gdpt.study.methods import EVAL_METHODS


def test_a_method_with_properties_has_its_own_configuration():
    """The name answers as written, is not listed among the registered methods, and its
    properties are part of its render configuration (its own calibration)."""
    name = "gdpt+fuse@max_depth=4,shift_threshold=0.01"
    assert name in EVAL_METHODS and name not in list(EVAL_METHODS)
    assert EVAL_METHODS.resolve(name) == name
    method = EVAL_METHODS[name]
    assert method.name == name
    base = EVAL_METHODS["gdpt+fuse"].configuration()
    assert method.configuration() == {**base, "max_depth": 4, "shift_threshold": 0.01}
    assert configuration_key(method, "total") != configuration_key(
        EVAL_METHODS["gdpt+fuse"], "total"
    )
    assert calibration_runner(method, "total") is method


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("gdpt+fuse@max_dept=4", "unknown gdpt integrator property 'max_dept'; valid: max_depth"),
        ("gdpt+fuse@max_depth=x", "'max_depth' must be -1 \\(unbounded\\) or >= 0, got 'x'"),
        ("gdpt+fuse@max_depth=-2", "'max_depth' must be -1 \\(unbounded\\) or >= 0, got -2"),
        ("gdpt+fuse@freeze=yes", "'freeze' must be true or false, got 'yes'"),
        ("gdpt+fuse@halves=false", "gdpt\\+fuse sets 'halves' itself"),
        ("pt@max_depth=2,max_depth=3", "'max_depth' is given twice"),
        ("pt@max_depth", "expected PROPERTY=VALUE"),
    ],
)
def test_bad_properties_are_refused_by_name(name, message):
    with pytest.raises(ValueError, match=f"method '{re.escape(name)}': .*{message}"):
        EVAL_METHODS.resolve(name)
    assert name not in EVAL_METHODS
    with pytest.raises(ValueError, match=message):
        EVAL_METHODS.check(["pt", name])  # gdpt advise checks its candidates so


def test_a_property_added_to_the_table_is_valid_in_method_names(monkeypatch):
    """The plugin's one table is all a new property needs (e.g. a string with its values)."""
    table = {**properties.PROPERTIES, "toy": properties.Property(str, "one", ("one", "two"))}
    monkeypatch.setattr(properties, "PROPERTIES", table)
    assert EVAL_METHODS["gdpt+fuse@toy=two"].configuration()["toy"] == "two"
    with pytest.raises(ValueError, match="'toy' must be one of 'one', 'two', got 'both'"):
        EVAL_METHODS.resolve("gdpt+fuse@toy=both")


def test_primal_is_a_method_property():
    """``primal`` (the integrators' table) is valid in method names; a bad value is one line."""
    assert EVAL_METHODS["gdpt+fuse@primal=mis"].configuration()["primal"] == "mis"
    with pytest.raises(ValueError, match="'primal' must be one of 'base', 'mis', got 'both'"):
        EVAL_METHODS.resolve("gdpt+fuse@primal=both")


def test_the_properties_reach_the_render(variant):
    """``pt@max_depth=1`` renders what ``pt`` renders on the scene at max_depth 1 (same seed,
    the same bits), unlike ``pt`` at the scene's depth."""
    from gdpt.study.scenes import SceneSpec, load_eval_scene

    scene = load_eval_scene(SceneSpec("cbox", "builtin:cbox-demo"), resolution=16)
    assert scene.max_depth > 1
    with_property = EVAL_METHODS["pt@max_depth=1"].run(scene, spp=2, seed=3).image
    shallow = dataclasses.replace(scene, max_depth=1)
    torch.testing.assert_close(with_property, EVAL_METHODS["pt"].run(shallow, spp=2, seed=3).image)
    assert not torch.equal(with_property, EVAL_METHODS["pt"].run(scene, spp=2, seed=3).image)


def test_the_cli_refuses_a_bad_property_in_one_line(tmp_path, capsys):
    report = tmp_path / "report"
    argv = ["evaluate", "--scenes", "builtin:cbox-demo", "--quick", "--out", str(report)]
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, "--methods", "pt", "gdpt+fuse@max_dept=4"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "unknown gdpt integrator property 'max_dept'" in err[-1] and "Traceback" not in err
    assert not report.exists()
