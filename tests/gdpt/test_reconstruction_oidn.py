"""The ``oidn`` reconstruction method, the study's ``pt+oidn``, and ``gdpt.reconstruct_image``
(its deprecated alias ``gdpt.denoise.reconstruct``: ``tests/gdpt/test_deprecated.py``)."""

from __future__ import annotations

import pytest
import torch

import gdpt
from gdpt.cli import main
from gdpt.io.exr import load_image, save_buffers
from gdpt.methods import METHODS, Method, reconstruct_image

try:
    import mitsuba_oidn
except ImportError:  # pragma: no cover - depends on the environment
    mitsuba_oidn = None

needs_oidn = pytest.mark.skipif(mitsuba_oidn is None, reason="mitsuba-oidn is not installed")

pytestmark = pytest.mark.usefixtures("single_thread")

#: The buffers the ``oidn`` method reads.
OIDN_INPUTS = ("primal", "albedo", "normal")


def _oidn(buffers) -> torch.Tensor:
    """The direct call: OIDN's RT filter, HDR, quality high, with albedo and normal."""
    high = mitsuba_oidn.Quality.High
    return mitsuba_oidn.denoise(
        buffers.primal, buffers.albedo, buffers.normal, hdr=True, quality=high
    )


def test_oidn_is_registered_as_a_feature_method_and_as_pt_oidn():
    from gdpt.study.methods import EVAL_METHODS

    assert METHODS["oidn"].needs == {"gradients": False, "features": True}
    assert METHODS["oidn"].sampling(8) == {"gradients": False, "features": True}
    study = EVAL_METHODS["pt+oidn"]
    assert study.description == (
        "path tracing + Intel Open Image Denoise (mitsuba-oidn; albedo + normal, HDR, quality high)"
    )
    assert list(EVAL_METHODS)[:2] == ["pt", "pt+oidn"]
    assert study.check is METHODS["oidn"].check


@needs_oidn
def test_oidn_equals_a_direct_mitsuba_oidn_call(random_buffers):
    buffers = random_buffers(24, 20, names=OIDN_INPUTS, seed=3)
    buffers.primal.mul_(4.0)  # HDR values above 1
    image = reconstruct_image(buffers, method="oidn")
    assert image.shape == (24, 20, 3) and image.dtype == torch.float32
    assert image.device == buffers.device
    assert torch.equal(image, _oidn(buffers))


@needs_oidn
def test_deprecated_pyoidn_backend_warns_and_runs_native(random_buffers):
    buffers = random_buffers(12, 10, names=OIDN_INPUTS, seed=4)
    with pytest.warns(
        DeprecationWarning, match="oidn backend 'pyoidn' is deprecated; use 'native'"
    ):
        old = reconstruct_image(buffers, method="oidn", backend="pyoidn")
    assert torch.equal(old, reconstruct_image(buffers, method="oidn", backend="native"))


@needs_oidn
def test_torch_backend_agrees_with_oidn(random_buffers):
    """The CUDA code path (OIDN's U-Net in torch), run on the CPU: the agreement metric of
    tests/reconstruct/test_oidn_torch.py, max |a - b| / max |b| <= 1e-4."""
    buffers = random_buffers(37, 29, names=OIDN_INPUTS, seed=5)
    ours = reconstruct_image(buffers, method="oidn", backend="torch")
    reference = _oidn(buffers)
    assert ((ours - reference).abs().max() / reference.abs().max()).item() <= 1e-4
    assert not ours.requires_grad


@pytest.mark.parametrize(
    ("names", "missing"),
    [(("primal",), "albedo and normal buffers"), (("primal", "albedo"), "normal buffer;")],
)
def test_missing_features_name_the_buffer_and_the_render_option(random_buffers, names, missing):
    with pytest.raises(ValueError, match=rf"'oidn' needs the {missing}.*features=True"):
        reconstruct_image(random_buffers(names=names), method="oidn")


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"backend": "cuda"}, "oidn backend must be one of auto, native, torch, got 'cuda'"),
        ({"backend": "native", "weights": "w.tza"}, "weights= is an option of the torch backend"),
        ({"model": "x.safetensors"}, "method 'oidn' has no option model"),
    ],
)
def test_bad_options_are_errors(random_buffers, options, match):
    with pytest.raises(ValueError, match=match):
        reconstruct_image(random_buffers(names=OIDN_INPUTS), method="oidn", **options)


@needs_oidn
def test_cli_reconstruct_with_oidn(tmp_path, random_buffers, capsys):
    buffers = random_buffers(16, 12, names=OIDN_INPUTS, seed=7)
    source = save_buffers(tmp_path / "render.exr", buffers)
    output = tmp_path / "oidn.exr"
    assert main(["reconstruct", str(source), "--method", "oidn", "-o", str(output)]) == 0
    assert f"wrote {output}" in capsys.readouterr().out
    assert torch.equal(load_image(output), _oidn(buffers))


def test_cli_reconstruct_with_oidn_without_features(tmp_path, random_buffers, capsys):
    source = save_buffers(tmp_path / "render.exr", random_buffers(names=("primal", "dx", "dy")))
    output = tmp_path / "oidn.exr"
    assert main(["reconstruct", str(source), "--method", "oidn", "-o", str(output)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("gdpt reconstruct: error: method 'oidn' needs the albedo and normal")
    assert not output.exists()


def test_reconstruct_image_is_the_top_level_name():
    assert gdpt.reconstruct_image is reconstruct_image
    assert "reconstruct_image" in gdpt.__all__


@needs_oidn  # the study checks that the real method could run before it renders
def test_pt_oidn_runs_the_registered_method(variant, monkeypatch):
    """The study's ``pt+oidn`` renders features without gradients and reconstructs through
    :data:`gdpt.methods.METHODS` ``oidn`` (replaced here by a stand-in that records its input)."""
    from gdpt.study.methods import EVAL_METHODS
    from gdpt.study.scenes import SceneSpec, load_eval_scene

    seen = []

    def stand_in(buffers, *, alpha, **_):
        seen.append(buffers)
        return torch.full_like(buffers.primal, 7.0)

    monkeypatch.setitem(METHODS, "oidn", Method(stand_in, False, True, "stand-in"))
    scene = load_eval_scene(SceneSpec("cbox", "builtin:cbox-demo"), resolution=16)
    result = EVAL_METHODS["pt+oidn"].run(scene, spp=1, seed=0)
    assert torch.equal(result.image, torch.full((16, 16, 3), 7.0))
    (buffers,) = seen
    assert buffers.dx is None and buffers.albedo is not None and buffers.normal is not None
