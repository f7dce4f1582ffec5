"""Smoke and bad-input tests of the ``make demo`` job on a tiny render."""

from __future__ import annotations

import json

import pytest

from gdpt.study.demo import GRADIENT_ROUTE_FOLDER, GRADIENT_ROUTE_METHODS, DemoConfig, run_demo


def _tiny(out, **kw) -> DemoConfig:
    settings = {"gradient_budget": 0.0, **kw}
    return DemoConfig(
        out=out, resolution=24, budget=0.3, reference_spp=64, methods=("gdpt+l1", "pt"), **settings
    )


@pytest.fixture
def clocked(cost_clock):
    """Both methods' seconds from a cost model, not the wall clock: small sample counts, the
    same on a busy machine."""
    cost_clock("gdpt+l1", 0.05, 0.01)
    cost_clock("pt", 0.01, 0.005)


def test_demo_writes_montage_images_and_table(tmp_path, capsys, clocked):
    results = run_demo(_tiny(tmp_path), progress=False)["cbox-demo"]
    cells = results["scenes"]["cbox-demo"]["methods"]
    assert set(cells) == {"gdpt+l1", "pt"}
    for name in ("gdpt+l1", "pt"):
        (cell,) = cells[name]["cells"].values()
        assert cell["metrics"]["relmse"] > 0 and cell["spp"] >= 1
        assert (tmp_path / cell["image"]).is_file()
        assert (tmp_path / cell["image"]).with_suffix(".png").is_file()
    for name in ("side_by_side.png", "index.html", "results.md", "results.json"):
        assert (tmp_path / name).is_file(), name
    printed = capsys.readouterr().out
    assert "gdpt+l1" in printed and "relMSE" in printed


def test_demo_refuses_to_overwrite_and_force_keeps_reference(tmp_path, clocked):
    run_demo(_tiny(tmp_path), progress=False)
    with pytest.raises(FileExistsError, match="--force"):
        run_demo(_tiny(tmp_path), progress=False)
    references = sorted((tmp_path / "references").glob("*.exr"))
    results = run_demo(_tiny(tmp_path, force=True), progress=False)["cbox-demo"]
    assert sorted((tmp_path / "references").glob("*.exr")) == references
    assert results["scenes"]["cbox-demo"]["reference"]["cached"] is True
    assert len(json.loads((tmp_path / "results.json").read_text())["runs"]) == 1


def test_demo_second_run_shows_autos_route(tmp_path, capsys, clocked, cost_clock):
    """The second run (``auto`` and the methods of its two routes, in its own folder) prints
    the route ``auto`` took with its reason; an earlier second run is not overwritten without
    ``force``."""
    cost_clock("auto", 0.02, 0.005)
    methods = ("auto", "pt")  # cheap stand-ins for GRADIENT_ROUTE_METHODS at 24 px
    cfg = _tiny(tmp_path, gradient_budget=0.3, gradient_resolution=24, gradient_methods=methods)
    results = run_demo(cfg, progress=False)
    assert set(results) == {"cbox-demo", "diffuse-box"}
    second = tmp_path / GRADIENT_ROUTE_FOLDER
    assert (second / "side_by_side.png").is_file() and (second / "results.json").is_file()
    cells = results["diffuse-box"]["scenes"]["diffuse-box"]["methods"]
    assert set(cells) == set(methods) and "auto" in GRADIENT_ROUTE_METHODS
    (auto,) = cells["auto"]["cells"].values()
    reason = auto["replicates"][0]["route"]["reason"]
    assert f"auto: plain route (oidn-tuned): {reason}" in capsys.readouterr().out
    (tmp_path / "results.json").unlink()  # only the second run's results remain
    with pytest.raises(FileExistsError, match="--force"):
        run_demo(cfg, progress=False)


def test_demo_refuses_a_negative_second_budget(tmp_path):
    with pytest.raises(ValueError, match="gradient_budget"):
        run_demo(_tiny(tmp_path, gradient_budget=-1.0), progress=False)
    assert not any(tmp_path.iterdir())
