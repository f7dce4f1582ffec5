"""GPU readiness in one go (``make test-gpu``, ``pytest -m gpu``): on ``cuda_ad_rgb``, the
zero-copy hand-off from Dr.Jit to torch, a render, every reconstruction method of
:data:`gdpt.methods.METHODS` and a training run.

Each check runs once per variant: ``cuda`` (marked ``gpu``; skipped, with the reason, where
Dr.Jit or torch sees no CUDA device) and its ``llvm`` twin on the CPU (marked ``slow``: the
same checks where they can run anywhere, so that the GPU tests themselves are tested). The
variant active before the module is restored after it, so the rest of a session keeps its own.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

import gdpt
from gdpt.methods import METHODS

SCENE = "builtin:cbox-demo"
SIZE = 32  # pixels on each side of the test renders


def _no_cuda() -> str | None:
    """Why the CUDA checks cannot run here, or ``None``."""
    from gdpt.backend import ensure_libllvm

    ensure_libllvm()
    import drjit as dr

    if not dr.has_backend(dr.JitBackend.CUDA):
        return "no CUDA device: Dr.Jit has no CUDA backend (no NVIDIA GPU or driver)"
    if not torch.cuda.is_available():
        return "Dr.Jit sees a CUDA device but torch does not (a CPU build of torch?)"
    return None


@pytest.fixture(
    scope="module",
    params=[
        pytest.param("cuda_ad_rgb", marks=pytest.mark.gpu, id="cuda"),
        pytest.param("llvm_ad_rgb", marks=pytest.mark.slow, id="llvm"),
    ],
)
def device(request) -> torch.device:
    """The torch device of the variant under test (set for the module, then restored); TF32
    off so that CUDA results compare with the CPU's at float32 precision."""
    if request.param.startswith("cuda") and (reason := _no_cuda()):
        pytest.skip(reason)
    import mitsuba as mi

    from gdpt.backend import torch_device

    previous = mi.variant()
    tf32 = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    gdpt.set_variant(request.param)
    yield torch_device()
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = tf32
    if previous is not None and previous != request.param:
        gdpt.set_variant(previous)


def _scene():
    return gdpt.load_scene(SCENE, long_side=SIZE)


def test_integrator_output_is_handed_to_torch_without_a_copy(device):
    import drjit as dr

    from gdpt.rendering import make_integrator

    scene = _scene()
    out = make_integrator("gdpt", max_depth=4).render(scene, seed=1, spp=1)
    dr.eval(out)
    dr.sync_thread()
    view = out.torch()
    assert view.device == device and view.shape[:2] == (SIZE, SIZE)
    assert view.abs().sum() > 0
    view.zero_()  # written through torch, read back through Dr.Jit: one memory
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    assert np.count_nonzero(out.numpy()) == 0


def test_render(device):
    import mitsuba as mi

    buffers = gdpt.render(_scene(), spp=2, seed=3, max_depth=4, variance=True)
    assert buffers.device == device and (buffers.height, buffers.width) == (SIZE, SIZE)
    assert buffers.present() == [
        "primal",
        "dx",
        "dy",
        "albedo",
        "normal",
        "depth",
        "var_primal",
        "var_dx",
        "var_dy",
    ]
    storage = buffers.primal.untyped_storage().data_ptr()
    for name, tensor in buffers.items():
        assert tensor.untyped_storage().data_ptr() == storage, name  # views of one tensor
        assert torch.isfinite(tensor).all(), name
    assert buffers.primal.mean() > 0
    assert not buffers.dx[:, -1].any() and not buffers.dy[-1].any()  # unused borders
    assert buffers.metadata["variant"] == mi.variant()


@pytest.mark.parametrize("method", list(METHODS))
def test_reconstruction_method(device, method):
    """Each method runs on the render's device; on CUDA it agrees with the same method on the
    same buffers moved to the CPU (max |a - b| <= 1e-3 max |b|, float32 without TF32)."""
    if reason := METHODS[method].check():
        pytest.skip(f"{method}: {reason}")
    buffers = gdpt.render(_scene(), spp=2, seed=5, max_depth=4, **METHODS[method].sampling(2))
    image = gdpt.reconstruct_image(buffers, method=method)
    assert image.device == device and image.dtype == torch.float32
    assert image.shape == (SIZE, SIZE, 3) and torch.isfinite(image).all()
    on_cpu = gdpt.reconstruct_image(buffers.to("cpu"), method=method)
    error = (image.cpu() - on_cpu).abs().max() / on_cpu.abs().max()
    assert error <= 1e-3, f"{method}: {device} vs cpu, relative error {error:.2e}"


def test_training_run(device, tiny_dataset, tiny_run_config, tmp_path):
    from gdpt.training.run_dir import read_jsonl
    from gdpt.training.train import train

    run = tmp_path / "run"
    config = tiny_run_config(tiny_dataset, run, model="fast_xs", loss="l1", device=str(device))
    path = train(config, progress=False)
    log = read_jsonl(run / "log.jsonl")
    assert [r["step"] for r in log] == [1, 2, 3]
    assert all(math.isfinite(r["loss"]) for r in log)
    assert path.is_file() and json.loads((run / "config.json").read_text())["device"] == str(device)


def test_differentiable_render_and_reconstruction(device, monkeypatch):
    """``gdpt.render_differentiable``: the network reads the render on the variant's device
    (a DLPack view, no host copy) and a loss gradient reaches the scene parameter."""
    import drjit as dr
    import mitsuba as mi

    from gdpt import methods

    if reason := METHODS["oidn-tuned"].check():
        pytest.skip(f"oidn-tuned: {reason}")
    seen = []
    reconstruct_image = methods.reconstruct_image

    def spy(buffers, *args, **kwargs):
        seen.append(buffers.primal.device)
        return reconstruct_image(buffers, *args, **kwargs)

    monkeypatch.setattr(methods, "reconstruct_image", spy)
    scene = _scene()
    params = mi.traverse(scene)
    key = "light.emitter.radiance.value"
    dr.enable_grad(params[key])
    params.update()
    image = gdpt.render_differentiable(scene, params, spp=2, seed=3, max_depth=4)
    dr.backward(dr.mean(image, axis=None))
    grad = dr.grad(params[key]).numpy()
    assert seen == [device]
    assert np.isfinite(grad).all() and (grad > 0).all()
