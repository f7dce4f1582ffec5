"""OIDN's own kernels through ``mitsuba-oidn`` (:mod:`gdpt.oidn_native`): the fine-tuned
``oidn-tuned`` exported to a TZA blob and run natively against its torch path, zero copy, bad
input, and no module importing ``pyoidn``."""

from __future__ import annotations

import copy
import subprocess
import sys
import textwrap
import warnings

import mitsuba_oidn
import pytest
import torch
from gdpt.reconstruct import tza
from gdpt.reconstruct.oidn_finetune import OIDNReconstructor

import gdpt
from gdpt import oidn_native
from gdpt.buffers import GradientBuffers
from gdpt.checkpoints import load_reconstructor, model_path
from gdpt.methods import METHODS, reconstruct_image

pytestmark = pytest.mark.usefixtures("single_thread")

OIDN_INPUTS = ("primal", "albedo", "normal")


@pytest.fixture(scope="module")
def cbox_renders(variant) -> list:
    """Two renders of ``builtin:cbox-demo``, 64x64 at 4 spp and 77x53 (not multiples of OIDN's
    16-pixel alignment) at 32 spp, features, no gradients."""
    import mitsuba as mi

    from gdpt.scenes.loading import generated_scene

    renders = []
    for seed, spp, (width, height) in ((0, 4, (64, 64)), (1, 32, (77, 53))):
        scene = generated_scene("builtin:cbox-demo")
        scene["sensor"]["film"]["width"], scene["sensor"]["film"]["height"] = width, height
        sampling = METHODS["oidn-tuned"].sampling(spp)
        renders.append(gdpt.render(mi.load_dict(scene), spp=spp, seed=seed, **sampling))
    return renders


@pytest.fixture(scope="module")
def tuned() -> OIDNReconstructor:
    return load_reconstructor(model_path("oidn-tuned").resolve())


def _spread(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    """(max |a - b| / max |b|, sum |a - b| / sum |b|)."""
    d = (a - b).abs()
    return (d.max() / b.abs().max()).item(), (d.sum() / b.abs().sum()).item()


def test_native_oidn_tuned_matches_the_torch_path_on_the_same_float16_weights(cbox_renders, tuned):
    """OIDN reads only float16 weights: with the torch network's weights rounded the same way,
    the two paths differ by the kernels alone (measured at most 1.2e-5 of the maximum at 53 to
    128 px)."""
    net = copy.deepcopy(tuned.net)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(p.half().float())
    rounded = OIDNReconstructor(net, tuned.design, tuned.card)
    for buffers in cbox_renders:
        native = oidn_native.reconstruct(tuned, buffers)
        assert native is not None and native.shape == buffers.primal.shape
        assert _spread(native, rounded(buffers))[0] <= 1e-4


def test_oidn_tuned_runs_natively_within_the_float16_spread_of_the_torch_path(cbox_renders, tuned):
    """The method ``oidn-tuned`` (native: no input requires gradients) against the shipped
    float32 network in torch: measured at most 2.4e-3 of the maximum, 1.1e-3 mean relative (the
    float16 rounding of the fine-tuned weights)."""
    for buffers in cbox_renders:
        image = reconstruct_image(buffers, "oidn-tuned")
        assert torch.equal(image, oidn_native.reconstruct(tuned, buffers))
        peak, mean = _spread(image, tuned(buffers))
        assert peak <= 5e-3 and mean <= 2.5e-3


def test_autograd_keeps_the_torch_path(cbox_renders, tuned):
    buffers = cbox_renders[0]
    primal = buffers.primal.clone().requires_grad_(True)
    differentiable = buffers.replace(primal=primal)
    assert oidn_native.reconstruct(tuned, differentiable) is None
    image = reconstruct_image(differentiable, "oidn-tuned")
    assert image.requires_grad
    assert torch.equal(image.detach(), tuned(buffers))


def test_networks_with_other_inputs_keep_the_torch_path(cbox_renders):
    grad = load_reconstructor(model_path("oidn-grad").resolve())
    assert oidn_native.network_weights(grad.net) is None
    assert oidn_native.reconstruct(grad, cbox_renders[0]) is None
    assert oidn_native.reconstruct(object(), cbox_renders[0]) is None


def test_a_network_is_exported_once(tuned):
    blob = oidn_native.network_weights(tuned.net)
    assert oidn_native.network_weights(tuned.net) is blob
    assert set(tza.parse_tza(blob)) == set(tuned.net.state_dict())


def test_builtin_weights_given_back_equal_the_default_filter(random_buffers):
    buffers = random_buffers(24, 20, names=OIDN_INPUTS, seed=2)
    blob = tza.write_tza(tza.builtin_weights()[oidn_native.OIDN_WEIGHTS].tensors)
    inputs = (buffers.primal, buffers.albedo, buffers.normal)
    assert torch.equal(oidn_native.denoise(*inputs, weights=blob), oidn_native.denoise(*inputs))


def test_cpu_tensors_are_shared_and_the_output_written_in_place(random_buffers):
    buffers = random_buffers(16, 24, names=OIDN_INPUTS, seed=4)
    device = mitsuba_oidn.Device(mitsuba_oidn.DeviceType.CPU)
    for name in OIDN_INPUTS:
        assert device.can_share(getattr(buffers, name)), name
    output = torch.full_like(buffers.primal, -1.0)
    image = oidn_native.denoise(buffers.primal, buffers.albedo, buffers.normal, output=output)
    assert image is output and image.data_ptr() == output.data_ptr()
    assert (output >= 0).all()
    assert torch.equal(output, reconstruct_image(buffers, "oidn"))


def test_a_renders_buffers_reach_oidn_without_a_copy(cbox_renders):
    """A render's buffers are views of its packed output (pixel stride of more than 3 floats);
    OIDN's CPU device binds them as they are, with the result of packed copies."""
    device = mitsuba_oidn.Device(mitsuba_oidn.DeviceType.CPU)
    buffers = cbox_renders[1]
    images = [getattr(buffers, n) for n in OIDN_INPUTS]
    assert images[0].stride(-2) > 3
    assert all(device.can_share(t) for t in images)
    copies = [t.contiguous() for t in images]
    assert torch.equal(oidn_native.denoise(*images), oidn_native.denoise(*copies))


def test_views_of_packed_render_buffers_are_read_in_place(random_buffers):
    """A render's buffers are views with a pixel stride of more than 3 floats; OIDN binds them
    as they are, with the result of packed copies."""
    buffers = random_buffers(16, 24, names=OIDN_INPUTS, seed=6)
    packed = torch.cat([getattr(buffers, n) for n in OIDN_INPUTS], -1)
    views = [packed[..., 3 * i : 3 * i + 3] for i in range(3)]
    assert views[0].stride() == (24 * 9, 9, 1)
    device = mitsuba_oidn.Device(mitsuba_oidn.DeviceType.CPU)
    assert all(device.can_share(v) for v in views)
    packed_out = oidn_native.denoise(*(v.contiguous() for v in views))
    assert torch.equal(oidn_native.denoise(*views), packed_out)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (
            lambda t: t[..., :2],
            r"the 'albedo' buffer must have shape \(H, W, 3\), got \(8, 10, 2\)",
        ),
        (lambda t: t[:4], r"the 'albedo' buffer has shape \(4, 10, 3\), the colour \(8, 10, 3\)"),
        (
            lambda t: t.double(),
            r"the 'albedo' buffer \(8, 10, 3\) must be float32, got torch.float64",
        ),
        (
            lambda t: t.permute(2, 0, 1).contiguous().permute(1, 2, 0),
            r"the 'albedo' buffer \(8, 10, 3\) has strides \(10, 1, 80\)",
        ),
    ],
)
def test_images_oidn_cannot_bind_are_named_with_their_shape(random_buffers, change, match):
    buffers = random_buffers(8, 10, names=OIDN_INPUTS, seed=1)
    with pytest.raises(ValueError, match=match):
        oidn_native.denoise(buffers.primal, change(buffers.albedo), buffers.normal)


def test_weights_that_do_not_fit_oidn_are_refused_before_filtering(random_buffers, monkeypatch):
    buffers = random_buffers(8, 8, names=OIDN_INPUTS, seed=1)
    inputs = (buffers.primal, buffers.albedo, buffers.normal)
    tensors = dict(tza.builtin_weights()[oidn_native.OIDN_WEIGHTS].tensors)
    wider = dict(tensors, **{"enc_conv0.weight": tensors["enc_conv0.weight"].repeat(2, 1)})
    fewer = {k: v for k, v in tensors.items() if k != "dec_conv0.bias"}
    more = dict(tensors, **{"extra.bias": tensors["dec_conv0.bias"]})
    single = dict(tensors, **{"enc_conv1.bias": tensors["enc_conv1.bias"].astype("float32")})
    monkeypatch.setattr(oidn_native, "_filter", lambda *a: pytest.fail("filtered"))
    for weights, match in (
        (wider, r"tensor 'enc_conv0.weight' has shape \(32, 18, 3, 3\), OIDN's rt_hdr_alb_nrm"),
        (fewer, r"tensor 'dec_conv0.bias' of OIDN's rt_hdr_alb_nrm is missing"),
        (more, r"tensor 'extra.bias' is not in OIDN's rt_hdr_alb_nrm network"),
        (single, r"tensor 'enc_conv1.bias' is float32; OIDN reads float16"),
    ):
        with pytest.raises(ValueError, match=match):
            oidn_native.denoise(*inputs, weights=tza.write_tza(weights))
    with pytest.raises(tza.TZAError, match="bad TZA magic"):
        oidn_native.denoise(*inputs, weights=b"\0" * 64)


def test_non_finite_pixels_are_counted_and_the_output_is_finite(random_buffers):
    buffers = random_buffers(16, 16, names=OIDN_INPUTS, seed=3)
    clean = reconstruct_image(buffers, "oidn")
    primal = buffers.primal.clone()
    primal[0, 0] = float("nan")
    primal[3, 5, 1] = float("inf")
    normal = buffers.normal.clone()
    normal[7, 7, 2] = float("-inf")
    dirty = buffers.replace(primal=primal, normal=normal)
    with pytest.warns(RuntimeWarning, match="oidn: 5 non-finite input values were replaced by 0"):
        image = reconstruct_image(dirty, "oidn")
    assert torch.isfinite(image).all() and image.shape == clean.shape
    assert torch.isnan(primal[0, 0]).all()  # the caller's buffers are not changed


def test_finite_values_whose_sum_overflows_are_not_counted(random_buffers):
    """The finiteness check sums first; a finite image whose float32 sum overflows is still
    counted value by value (none replaced, no warning)."""
    buffers = random_buffers(16, 16, names=OIDN_INPUTS, seed=4)
    primal = buffers.primal.clone()
    primal[:4] = 3e38
    assert not torch.isfinite(primal.sum())
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        image = reconstruct_image(buffers.replace(primal=primal), "oidn")
    assert torch.isfinite(image).all()


def test_nothing_imports_pyoidn():
    """Every gdpt module imports, and the ``oidn`` and ``oidn-tuned`` methods run, with
    ``import pyoidn`` raising (a meta-path hook in a fresh interpreter)."""
    script = textwrap.dedent(
        """
        import importlib, pkgutil, sys

        class NoPyoidn:
            def find_spec(self, name, path=None, target=None):
                if name == "pyoidn" or name.startswith("pyoidn."):
                    raise ImportError("pyoidn was imported")
                return None

        sys.meta_path.insert(0, NoPyoidn())
        import gdpt
        gdpt.set_variant("llvm_ad_rgb")  # (the plugins of gdpt.integrators need one)
        names = ["gdpt.reconstruct", "gdpt.integrators"]
        for root in (gdpt, *map(importlib.import_module, names)):
            for info in pkgutil.walk_packages(root.__path__, root.__name__ + "."):
                names.append(info.name)
        for name in names:
            if name != "gdpt.__main__":  # (runs the CLI)
                importlib.import_module(name)
        assert len(names) > 60, names
        import torch
        from gdpt.buffers import GradientBuffers
        g = torch.Generator().manual_seed(0)
        r = lambda: torch.rand(16, 16, 3, generator=g)
        b = GradientBuffers(primal=r(), albedo=r(), normal=r() * 2 - 1, spp=4)
        for method in ("oidn", "oidn-tuned"):
            assert torch.isfinite(gdpt.reconstruct_image(b, method)).all()
        assert "pyoidn" not in sys.modules
        print("ok")
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", script], check=False, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().endswith("ok")


@pytest.mark.gpu
def test_cuda_tensors_are_denoised_on_the_gpu_without_a_copy():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device for torch")
    gen = torch.Generator().manual_seed(8)
    cpu = [torch.rand(32, 48, 3, generator=gen) for _ in range(3)]
    cpu[2] = cpu[2] * 2 - 1
    cuda = [t.cuda() for t in cpu]
    device = mitsuba_oidn.Device.cuda(torch.cuda.current_device())
    assert all(device.can_share(t) for t in cuda)
    output = torch.empty_like(cuda[0])
    image = oidn_native.denoise(*cuda, output=output)
    assert image.device == cuda[0].device and image.data_ptr() == output.data_ptr()
    reference = oidn_native.denoise(*cpu)
    assert _spread(image.cpu(), reference)[0] <= 1e-3  # GPU and CPU kernels differ slightly
    buffers = GradientBuffers(primal=cuda[0], albedo=cuda[1], normal=cuda[2], spp=4)
    assert _spread(reconstruct_image(buffers, "oidn"), oidn_native.denoise(*cuda))[0] <= 1e-6
    tuned = load_reconstructor(model_path("oidn-tuned").resolve())
    native = oidn_native.reconstruct(tuned, buffers)
    assert native is not None and native.device == cuda[0].device
    assert _spread(native, tuned(buffers))[0] <= 5e-3
