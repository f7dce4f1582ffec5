"""Image-quality metrics for evaluating reconstructions against a reference.

Every metric has the signature ``metric(image_test, image_ref, *, option=...) -> float`` and takes
``(H, W, C)`` float images (torch tensors on any device, or numpy arrays) of *linear HDR*
radiance; the test image comes first. Options are keyword-only. Shapes are validated first.

Metrics are registered by name in :data:`METRICS` (``@METRICS.register(name)``);
:func:`compute_metrics` evaluates a list of them and reports metrics whose dependencies are
missing (``flip_evaluator`` not installed, no E-LPIPS weight file) as skipped, with the reason,
instead of failing.

Conventions (apply them to every method that is compared):

* ``relmse``: NGPT's relative MSE, reference *channel-mean* in the denominator, eps = 1e-3.
* ``relmse_trimmed``: ``relmse`` without its 0.1% largest per-pixel terms, the robust companion
  of ``relmse`` for heavy-tailed images (:data:`COMPANIONS`).
* ``smape``: OIDN's symmetric MAPE, eps = 1e-2.
* Display-referred metrics (``one_minus_ssim``, ``flip_ldr``, ``elpips``) see
  ``sRGB(clamp(R(x), 0, 1))`` with NGPT's Reinhard ``R(x) = x / (1 + mean_c |x|)``.
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from gdpt.reconstruct.colour import reinhard, srgb_encode
from gdpt.reconstruct.elpips import (
    ELPIPS,
    ELPIPS_WEIGHTS_ENV,
    ELPIPSConfig,
    ELPIPSWeightsError,
    load_elpips_weights,
)
from gdpt.reconstruct.flip import FLIP_DEFAULT_PPD
from gdpt.reconstruct.losses import ELPIPSLoss
from gdpt.reconstruct.registry import Registry

__all__ = [
    "METRICS",
    "MetricResults",
    "COMPANIONS",
    "MetricUnavailable",
    "compute_metrics",
    "elpips",
    "flip_hdr",
    "flip_ldr",
    "mse",
    "one_minus_ssim",
    "relmse",
    "relmse_trimmed",
    "smape",
]

Image = torch.Tensor | np.ndarray
Metric = Callable[..., float]

#: Registered metrics, name -> function (``METRICS.register(name)`` decorates a new one).
METRICS: Registry[Metric] = Registry("metric")

#: Robust companions of headline metrics, headline name -> (companion name, function): the
#: study records the companion beside the headline (:func:`relmse_trimmed` for ``relmse``).
COMPANIONS: dict[str, tuple[str, Metric]] = {}


class MetricUnavailable(RuntimeError):
    """Raised by a metric that cannot run here (missing package or weights)."""


def _pair(
    metric: str, image_test: Image, image_ref: Image, *, rgb: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate two ``(H, W, C)`` float images and return them as float64 torch tensors.

    Numpy inputs go to the device of a torch partner (else the CPU).

    Raises:
        TypeError: non-float or non-array inputs.
        ValueError: wrong rank, unequal shapes or (``rgb``) ``C != 3``.
    """
    tensors = []
    for label, image in (("image_test", image_test), ("image_ref", image_ref)):
        if isinstance(image, np.ndarray):
            image = torch.from_numpy(image)
        if not isinstance(image, torch.Tensor) or not image.is_floating_point():
            kind = getattr(image, "dtype", type(image).__name__)
            raise TypeError(f"{metric}: {label} must be a float tensor or array, got {kind}")
        tensors.append(image)
    test, ref = tensors
    shapes = f"image_test {tuple(test.shape)} and image_ref {tuple(ref.shape)}"
    if test.ndim != 3 or test.shape != ref.shape:
        raise ValueError(f"{metric}: expected two (H, W, C) images of equal shape, got {shapes}")
    if rgb and test.shape[-1] != 3:
        raise ValueError(f"{metric}: expected (H, W, 3) RGB images, got {shapes}")
    device = test.device if isinstance(image_test, torch.Tensor) else ref.device
    return test.to(device, torch.float64), ref.to(device, torch.float64)


def _display(image: torch.Tensor) -> torch.Tensor:
    """``sRGB(clamp(R(x), 0, 1))`` of an ``(H, W, 3)`` linear image."""
    return srgb_encode(reinhard(image, channel_dim=-1).clamp(0.0, 1.0))


@METRICS.register("mse")
def mse(image_test: Image, image_ref: Image) -> float:
    """Mean squared error ``mean((p - r)^2)`` over pixels and channels.

    Args:
        image_test: ``(H, W, C)`` float linear image (torch, any device, or numpy).
        image_ref: ``(H, W, C)`` float linear reference.

    Returns:
        The MSE.
    """
    test, ref = _pair("mse", image_test, image_ref)
    return float((test - ref).square().mean())


@METRICS.register("relmse")
def relmse(image_test: Image, image_ref: Image, *, eps: float = 1e-3) -> float:
    """Relative MSE with the NGPT convention (greyscale reference in the denominator).

    ``mean_{pixels, c} (p_c - r_c)^2 / (eps + mean_c(r)^2)``: the per-pixel denominator uses the
    channel mean of the reference, not each channel (SBMC's per-channel variant differs).

    Args:
        image_test: ``(H, W, C)`` float linear image (torch, any device, or numpy).
        image_ref: ``(H, W, C)`` float linear reference.
        eps: denominator offset (NGPT: 1e-3).

    Returns:
        The relative MSE.
    """
    test, ref = _pair("relmse", image_test, image_ref)
    denominator = eps + ref.mean(-1, keepdim=True).square()
    return float(((test - ref).square() / denominator).mean())


def relmse_trimmed(
    image_test: Image, image_ref: Image, *, eps: float = 1e-3, trim: float = 1e-3
) -> float:
    """:func:`relmse` without its largest ``trim`` share of pixels: the mean of the per-pixel
    relative squared errors (channel mean) after the ``ceil(trim * pixels)`` largest are left
    out (a trimmed mean). A robust companion of ``relmse`` on heavy-tailed images, where one
    firefly can move the mean several-fold; ``relmse`` stays the headline (not registered in
    :data:`METRICS`: the study records it beside every ``relmse``, as :data:`COMPANIONS`).

    Args:
        image_test: ``(H, W, C)`` float linear image (torch, any device, or numpy).
        image_ref: ``(H, W, C)`` float linear reference.
        eps: denominator offset, as :func:`relmse`.
        trim: share of pixels left out, in ``[0, 1)``.

    Returns:
        The trimmed relative MSE.
    """
    test, ref = _pair("relmse_trimmed", image_test, image_ref)
    denominator = eps + ref.mean(-1, keepdim=True).square()
    per_pixel = ((test - ref).square() / denominator).mean(-1).flatten().double()
    cut = min(math.ceil(trim * per_pixel.numel()), per_pixel.numel() - 1)
    largest = per_pixel.topk(cut).values.sum() if cut else 0.0
    return float((per_pixel.sum() - largest) / (per_pixel.numel() - cut))


COMPANIONS["relmse"] = ("relmse_trimmed", relmse_trimmed)


@METRICS.register("smape")
def smape(image_test: Image, image_ref: Image, *, eps: float = 1e-2) -> float:
    """Symmetric MAPE ``mean(|p - r| / (|p| + |r| + eps))`` (OIDN convention, eps = 1e-2).

    Args:
        image_test: ``(H, W, C)`` float linear image (torch, any device, or numpy).
        image_ref: ``(H, W, C)`` float linear reference.
        eps: denominator offset.

    Returns:
        The SMAPE, in [0, 1).
    """
    test, ref = _pair("smape", image_test, image_ref)
    return float(((test - ref).abs() / (test.abs() + ref.abs() + eps)).mean())


@METRICS.register("one_minus_ssim")
def one_minus_ssim(image_test: Image, image_ref: Image) -> float:
    """``1 - SSIM`` on display-referred images, per RGB channel, averaged.

    SSIM [Wang et al. 2004] with an 11x11 Gaussian window (sigma 1.5), K1 = 0.01, K2 = 0.03 and
    data range 1, evaluated on ``sRGB(clamp(R(x), 0, 1))`` of each channel; the SSIM map is
    averaged over the valid (unpadded) region and the three channels. This equals
    ``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1, channel_axis=-1)``.

    Args:
        image_test: ``(H, W, 3)`` float linear image (torch, any device, or numpy), H, W >= 11.
        image_ref: ``(H, W, 3)`` float linear reference.

    Returns:
        ``1 - SSIM``, in [0, 2].
    """
    test, ref = _pair("one_minus_ssim", image_test, image_ref, rgb=True)
    if min(test.shape[:2]) < 11:
        raise ValueError(f"one_minus_ssim: images must be at least 11x11, got {tuple(test.shape)}")
    x = _display(test).permute(2, 0, 1)[:, None]  # (3, 1, H, W)
    y = _display(ref).permute(2, 0, 1)[:, None]
    g = torch.exp(-(torch.arange(-5, 6, dtype=x.dtype, device=x.device) ** 2) / (2 * 1.5**2))
    g = g / g.sum()

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(t, g.view(1, 1, 1, 11)), g.view(1, 1, 11, 1))

    mu_x, mu_y = blur(x), blur(y)
    var_x, var_y = blur(x * x) - mu_x**2, blur(y * y) - mu_y**2
    cov = blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    ssim = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / (
        (mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2)
    )
    return float(1.0 - ssim.mean())


def _flip_evaluator() -> Any:
    """Import ``flip_evaluator`` or raise :class:`MetricUnavailable`."""
    try:
        import flip_evaluator  # noqa: PLC0415 (optional dependency)
    except ImportError as err:
        raise MetricUnavailable(
            "flip_evaluator is not installed (pip install flip-evaluator)"
        ) from err
    return flip_evaluator


def _to_numpy(image: torch.Tensor) -> np.ndarray:
    """``(H, W, 3)`` tensor -> C-contiguous float32 numpy array on the host."""
    return np.ascontiguousarray(image.detach().cpu().numpy(), dtype=np.float32)


@METRICS.register("flip_hdr")
def flip_hdr(
    image_test: Image, image_ref: Image, *, ppd: float = FLIP_DEFAULT_PPD, tonemapper: str = "aces"
) -> float:
    """Mean HDR-FLIP error from NVIDIA's ``flip_evaluator`` (v1.7 defaults).

    Exposures are computed from the reference; negative values are clamped to 0 (the tool
    expects non-negative linear RGB). The tone-mapper name is passed in lower case because the
    tool matches names case-sensitively and silently falls back to ACES otherwise.

    Args:
        image_test: ``(H, W, 3)`` float linear image (torch, any device, or numpy).
        image_ref: ``(H, W, 3)`` float linear reference; must not be black.
        ppd: pixels per degree (tool default 67.02).
        tonemapper: ``"aces"`` (tool default), ``"hable"`` or ``"reinhard"``.

    Returns:
        The mean HDR-FLIP error, in [0, 1].

    Raises:
        ValueError: invalid options or a black reference (the tool would exit the process).
        MetricUnavailable: ``flip_evaluator`` is not installed.
    """
    test, ref = _pair("flip_hdr", image_test, image_ref, rgb=True)
    tonemapper = tonemapper.lower()
    if tonemapper not in ("aces", "hable", "reinhard") or not ppd > 0:
        raise ValueError(f"flip_hdr: invalid tonemapper {tonemapper!r} or ppd {ppd}")
    test, ref = test.clamp_min(0.0), ref.clamp_min(0.0)
    luminance = ref @ ref.new_tensor([0.2126, 0.7152, 0.0722])
    if float(luminance.max()) <= np.finfo(np.float32).eps:
        raise ValueError("flip_hdr: the reference is black; HDR-FLIP exposures are undefined")
    flip = _flip_evaluator()
    params = {"ppd": ppd, "tonemapper": tonemapper}
    _, mean, _ = flip.evaluate(
        _to_numpy(ref), _to_numpy(test), "HDR", applyMagma=False, parameters=params
    )
    return float(mean)


@METRICS.register("flip_ldr")
def flip_ldr(image_test: Image, image_ref: Image, *, ppd: float = FLIP_DEFAULT_PPD) -> float:
    """Mean LDR-FLIP error from ``flip_evaluator`` on Reinhard-tonemapped sRGB images.

    Both images are mapped to ``sRGB(clamp(R(x), 0, 1))`` and passed to the tool as sRGB
    (``inputsRGB=True``, its LDR default).

    Args:
        image_test: ``(H, W, 3)`` float linear image (torch, any device, or numpy).
        image_ref: ``(H, W, 3)`` float linear reference.
        ppd: pixels per degree (tool default 67.02).

    Returns:
        The mean LDR-FLIP error, in [0, 1].

    Raises:
        ValueError: invalid ``ppd``.
        MetricUnavailable: ``flip_evaluator`` is not installed.
    """
    test, ref = _pair("flip_ldr", image_test, image_ref, rgb=True)
    if not ppd > 0:
        raise ValueError(f"flip_ldr: ppd must be positive, got {ppd}")
    flip = _flip_evaluator()
    _, mean, _ = flip.evaluate(
        _to_numpy(_display(ref)),
        _to_numpy(_display(test)),
        "LDR",
        applyMagma=False,
        parameters={"ppd": ppd},
    )
    return float(mean)


@functools.lru_cache(maxsize=2)
def _cached_elpips(path: str, mtime_ns: int) -> ELPIPS:
    """Load E-LPIPS weights once per file version (``mtime_ns`` is part of the cache key)."""
    del mtime_ns
    return load_elpips_weights(path)


@METRICS.register("elpips")
def elpips(
    image_test: Image,
    image_ref: Image,
    *,
    weights: str | os.PathLike[str] | None = None,
    samples: int = 200,
    seed: int = 0,
) -> float:
    """E-LPIPS distance, NGPT evaluation protocol, on Reinhard-tonemapped sRGB images.

    The backbone is whatever the weight file holds (NGPT evaluates with VGG16 and trains with
    SqueezeNet); full (non-fast) ensemble, ``max(1, min(H, W) // 64)`` scale levels, ``samples``
    ensemble samples averaged (NGPT: 200). Cost on a CPU: one backbone pass over both images per
    sample.

    Args:
        image_test: ``(H, W, 3)`` float linear image (torch, any device, or numpy), H, W >= 64.
        image_ref: ``(H, W, 3)`` float linear reference.
        weights: weight file (see ``gdpt.reconstruct.elpips.load_elpips_weights``); default: the
            ``GDPT_ELPIPS_WEIGHTS`` environment variable.
        samples: number of ensemble samples averaged.
        seed: seed of the ensemble draws (results are reproducible for equal seeds).

    Returns:
        The E-LPIPS distance.

    Raises:
        MetricUnavailable: no readable weight file.
    """
    test, ref = _pair("elpips", image_test, image_ref, rgb=True)
    path = weights if weights is not None else os.environ.get(ELPIPS_WEIGHTS_ENV)
    try:
        if not path or not Path(path).is_file():
            load_elpips_weights(path)  # raises ELPIPSWeightsError with the full explanation
        base = _cached_elpips(str(Path(path).resolve()), Path(path).stat().st_mtime_ns)
    except ELPIPSWeightsError as err:
        raise MetricUnavailable(str(err)) from err
    config = ELPIPSConfig(average_over=samples, num_scales=max(1, min(test.shape[:2]) // 64))
    loss = ELPIPSLoss(ELPIPS(base.backbone, base.heads, config, seed=seed)).to(test.device)
    with torch.no_grad():
        value = loss(test.float().permute(2, 0, 1)[None], ref.float().permute(2, 0, 1)[None])
    return float(value)


@dataclass
class MetricResults:
    """Outcome of :func:`compute_metrics`.

    Attributes:
        values: metric name -> value, for the metrics that ran.
        skipped: metric name -> reason, for the metrics that could not run here.
    """

    values: dict[str, float] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)


def compute_metrics(
    image_test: Image,
    image_ref: Image,
    names: Iterable[str] | None = None,
    *,
    options: Mapping[str, Mapping[str, Any]] | None = None,
) -> MetricResults:
    """Evaluate several registered metrics on one image pair.

    Args:
        image_test: ``(H, W, C)`` float linear image (torch, any device, or numpy).
        image_ref: ``(H, W, C)`` float linear reference of the same shape.
        names: metric names (default: all registered, in registration order).
        options: per-metric keyword options, e.g. ``{"elpips": {"samples": 20}}``.

    Returns:
        The values, plus the metrics skipped because :class:`MetricUnavailable` was raised.

    Raises:
        KeyError: an unknown name, or options for a metric not requested.
        ValueError, TypeError: invalid images (checked before any metric runs).
    """
    names = list(METRICS if names is None else names)
    metrics = {name: METRICS[name] for name in names}
    options = dict(options or {})
    if unknown := set(options) - set(names):
        raise KeyError(f"options given for metrics not requested: {sorted(unknown)}")
    _pair("compute_metrics", image_test, image_ref)
    results = MetricResults()
    for name, metric in metrics.items():
        try:
            value = metric(image_test, image_ref, **options.get(name, {}))
        except MetricUnavailable as err:
            results.skipped[name] = str(err)
        else:
            results.values[name] = value
    return results
