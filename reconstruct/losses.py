"""Training losses for the neural (NGPT) reconstruction and their registry :data:`LOSSES`.

Every loss takes ``(pred, target)``: ``(N, 3, H, W)`` float tensors of *linear HDR* radiance on
any one device, and returns a scalar tensor on that device. The perceptual terms see tone-mapped
images (:mod:`gdpt.reconstruct.colour`), as in NGPT [Kettunen et al. 2019, Eq. 6-8]: LDR-FLIP
(:mod:`gdpt.reconstruct.flip`) on ``clamp(R(x), 0, 1)``, E-LPIPS
(:mod:`gdpt.reconstruct.elpips`) on ``sRGB(max(0, R(x)))``.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .colour import check_image_pair, reinhard, srgb_encode
from .elpips import ELPIPS, ELPIPSConfig, load_elpips_weights
from .flip import FLIP_DEFAULT_PPD, check_tonemapper, hdr_flip, ldr_flip
from .registry import Registry

__all__ = [
    "DenseUNetLoss",
    "ELPIPSLoss",
    "FLIPLoss",
    "LOSSES",
    "forward_differences",
    "get_loss",
    "gradient_l1_tonemapped",
    "l1_log",
    "l1_relative",
    "l1_tonemapped",
]


def forward_differences(x: Tensor) -> tuple[Tensor, Tensor]:
    """Forward differences with the gdpt convention (zero last column / row).

    ``dx[..., y, x] = I[..., y, x + 1] - I[..., y, x]``, ``dy[..., y, x] = I[..., y + 1, x] -
    I[..., y, x]``.

    Args:
        x: ``(..., H, W)`` float tensor (e.g. NCHW), any device.

    Returns:
        ``(dx, dy)``, each shaped like ``x``.
    """
    dx = F.pad(x[..., :, 1:] - x[..., :, :-1], (0, 1, 0, 0))
    dy = F.pad(x[..., 1:, :] - x[..., :-1, :], (0, 0, 0, 1))
    return dx, dy


def l1_tonemapped(pred: Tensor, target: Tensor) -> Tensor:
    """NGPT tone-mapped L1: ``mean |R(target) - R(pred)|``.

    Args:
        pred: ``(N, 3, H, W)`` float linear HDR prediction, any device.
        target: ``(N, 3, H, W)`` float linear HDR reference, same device.

    Returns:
        Scalar tensor.
    """
    check_image_pair(pred, target)
    return (reinhard(pred) - reinhard(target)).abs().mean()


def gradient_l1_tonemapped(pred: Tensor, target: Tensor) -> Tensor:
    """NGPT gradient term: ``mean|R(dx_t) - R(dx_p)| + mean|R(dy_t) - R(dy_p)|``.

    The forward differences (:func:`forward_differences`) are taken on the *linear* images and
    then tone-mapped with the odd Reinhard map :func:`reinhard`.

    Args:
        pred: ``(N, 3, H, W)`` float linear HDR prediction, any device.
        target: ``(N, 3, H, W)`` float linear HDR reference, same device.

    Returns:
        Scalar tensor.
    """
    check_image_pair(pred, target)
    loss = pred.new_zeros(())
    for d_pred, d_target in zip(
        forward_differences(pred), forward_differences(target), strict=False
    ):
        loss = loss + (reinhard(d_pred) - reinhard(d_target)).abs().mean()
    return loss


def l1_log(pred: Tensor, target: Tensor) -> Tensor:
    """L1 in the network's output domain: ``mean |log1p(pred) - log1p(target)|``.

    Unlike the Reinhard-mapped terms this does not saturate on bright pixels, so it pins HDR
    magnitudes (emitters, highlights) that the tone-mapped losses cannot tell apart.
    ``pred`` is clamped to ``> -1`` (the output transform's range).

    Args:
        pred: ``(N, 3, H, W)`` float linear HDR prediction, any device.
        target: ``(N, 3, H, W)`` float linear HDR reference (``>= 0``), same device.

    Returns:
        Scalar tensor.
    """
    check_image_pair(pred, target)
    return (torch.log1p(pred.clamp_min(-0.999)) - torch.log1p(target.clamp_min(0.0))).abs().mean()


def l1_relative(pred: Tensor, target: Tensor, *, eps: float = 1e-2) -> Tensor:
    """Relative L1 with the relMSE convention: ``mean |pred - target| / (eps + mean_c target)``.

    The robust (L1) counterpart of the relMSE metric (:func:`gdpt.metrics.relmse` divides by the
    channel mean of the reference too): it weighs colour errors in dark regions and fireflies as
    the metric does, which tone-mapped and perceptual terms barely see.

    Args:
        pred: ``(N, 3, H, W)`` float linear HDR prediction, any device.
        target: ``(N, 3, H, W)`` float linear HDR reference, same device.
        eps: added to the denominator (the metric uses 1e-3 on squared values).

    Returns:
        Scalar tensor.
    """
    check_image_pair(pred, target)
    scale = eps + target.mean(dim=1, keepdim=True).clamp_min(0.0)
    return ((pred - target).abs() / scale).mean()


class FLIPLoss(nn.Module):
    """FLIP as a loss on linear HDR ``(N, 3, H, W)`` tensors.

    ``mode="ldr"``: LDR-FLIP on ``clamp(R(x), 0, 1)`` (NGPT Reinhard, the image E-LPIPS sees
    sRGB-encoded). ``mode="hdr"``: HDR-FLIP on the linear images (exposures from the target;
    costs one LDR-FLIP per exposure, typically 2-15).

    Args:
        mode: ``"ldr"`` or ``"hdr"``.
        ppd: pixels per degree of visual angle.
        tonemapper: HDR-FLIP tone mapper (``mode="hdr"`` only).
    """

    def __init__(
        self, mode: str = "ldr", *, ppd: float = FLIP_DEFAULT_PPD, tonemapper: str = "aces"
    ) -> None:
        super().__init__()
        if mode not in ("ldr", "hdr"):
            raise ValueError(f"mode must be 'ldr' or 'hdr', got {mode!r}")
        self.mode, self.ppd, self.tonemapper = mode, ppd, check_tonemapper(tonemapper)

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        """Mean FLIP error of ``pred`` against ``target`` (``(N, 3, H, W)``) -> scalar."""
        if self.mode == "hdr":
            return hdr_flip(pred, target, ppd=self.ppd, tonemapper=self.tonemapper)
        return ldr_flip(reinhard(pred), reinhard(target), ppd=self.ppd, inputs_srgb=False)


class ELPIPSLoss(nn.Module):
    """E-LPIPS on ``sRGB(max(0, R(x)))`` of linear HDR images, as in NGPT (Eq. 7-8).

    Args:
        elpips: the distance module (e.g. from :func:`load_elpips_weights`).
    """

    def __init__(self, elpips: ELPIPS) -> None:
        super().__init__()
        self.elpips = elpips

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        """Batch-mean E-LPIPS of ``(N, 3, H, W)`` linear HDR ``pred`` vs ``target`` -> scalar."""

        def display(x: Tensor) -> Tensor:
            return srgb_encode(reinhard(x).clamp_min(0.0))

        return self.elpips(display(pred), display(target)).mean()


class DenseUNetLoss(nn.Module):
    """``perceptual + beta L1(R(x), R(y)) + gamma L1(R~(grad x), R~(grad y)) + delta l1_log
    + rho l1_relative``.

    NGPT Eq. 8 with a pluggable perceptual term (Kettunen et al. 2019: E-LPIPS, beta = gamma =
    0.01, delta = rho = 0). ``perceptual=None`` drops the term (NGPT config 102: beta = 1,
    gamma = 0.01). ``delta`` and ``rho`` weigh :func:`l1_log` and :func:`l1_relative`, our
    additions for short training runs (see :data:`LOSSES`).

    Args:
        perceptual: module ``(pred, target) -> scalar`` on linear HDR ``(N, 3, H, W)``, or None.
        beta: weight of :func:`l1_tonemapped`.
        gamma: weight of :func:`gradient_l1_tonemapped`.
        delta: weight of :func:`l1_log`.
        rho: weight of :func:`l1_relative`.
    """

    def __init__(
        self,
        perceptual: nn.Module | None,
        *,
        beta: float = 0.01,
        gamma: float = 0.01,
        delta: float = 0.0,
        rho: float = 0.0,
    ) -> None:
        super().__init__()
        self.perceptual, self.beta, self.gamma = perceptual, beta, gamma
        self.delta, self.rho = delta, rho

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        """Loss of ``(N, 3, H, W)`` linear HDR ``pred`` against ``target`` -> scalar tensor."""
        loss = self.beta * l1_tonemapped(pred, target)
        loss = loss + self.gamma * gradient_l1_tonemapped(pred, target)
        if self.delta:
            loss = loss + self.delta * l1_log(pred, target)
        if self.rho:
            loss = loss + self.rho * l1_relative(pred, target)
        if self.perceptual is not None:
            loss = loss + self.perceptual(pred, target)
        return loss


def _elpips_loss(
    weights: str | os.PathLike[str] | None = None,
    *,
    config: ELPIPSConfig | None = None,
    seed: int | None = None,
) -> DenseUNetLoss:
    """NGPT config 100: E-LPIPS (NGPT training config) + 0.01 L1(R) + 0.01 gradient L1."""
    elpips = load_elpips_weights(weights, config or ELPIPSConfig.for_training(), seed=seed)
    return DenseUNetLoss(ELPIPSLoss(elpips))


#: Loss name -> factory; every factory returns a module ``(pred, target) -> scalar`` on linear
#: HDR ``(N, 3, H, W)`` tensors.
LOSSES: Registry[Callable[..., nn.Module]] = Registry("loss")
LOSSES.register("flip", lambda **kw: DenseUNetLoss(FLIPLoss("ldr", **kw)))
LOSSES.register("flip_hdr", lambda **kw: DenseUNetLoss(FLIPLoss("hdr", **kw)))
LOSSES.register("flip_log", lambda **kw: DenseUNetLoss(FLIPLoss("ldr", **kw), delta=0.1))
LOSSES.register("flip_rel", lambda **kw: DenseUNetLoss(FLIPLoss("ldr", **kw), rho=1.0))
LOSSES.register("elpips", _elpips_loss)
LOSSES.register("l1", lambda **kw: DenseUNetLoss(None, beta=1.0, gamma=0.01, **kw))


def get_loss(name: str, **kwargs: object) -> nn.Module:
    """Build a training loss by name.

    * ``"flip"``: LDR-FLIP on ``clamp(R(x), 0, 1)`` + 0.01 L1(R) + 0.01 gradient L1 (default).
    * ``"flip_hdr"``: HDR-FLIP (ACES, exposures from the target) + the same L1 terms.
    * ``"flip_log"``: ``"flip"`` + 0.1 :func:`l1_log`. Not in the paper: LDR-FLIP and the
      Reinhard L1 saturate on bright pixels, and in CPU-length runs (~1e3 times fewer updates
      than the paper's) networks trained without it put emitters off by orders of magnitude.
    * ``"flip_rel"``: ``"flip"`` + :func:`l1_relative`. Not in the paper: the relMSE metric is
      dominated by dark regions and fireflies, which FLIP and the log term hardly weigh; in
      CPU-length runs networks trained without it tinted dark regions (relMSE worse than
      their noisy input while FLIP improved).
    * ``"elpips"``: NGPT config 100, E-LPIPS (weights from ``weights=`` or
      ``GDPT_ELPIPS_WEIGHTS``; NGPT training config) + the same L1 terms.
    * ``"l1"``: NGPT config 102, L1(R) + 0.01 gradient L1.

    Args:
        name: one of :data:`LOSSES`.
        **kwargs: forwarded to the factory (e.g. ``ppd=``, ``weights=``, ``seed=``).

    Returns:
        Module mapping ``(pred, target)`` ``(N, 3, H, W)`` linear HDR tensors to a scalar.

    Raises:
        KeyError: unknown name (the message lists the valid names).
        ELPIPSWeightsError: ``"elpips"`` without a weight file.
    """
    return LOSSES[name](**kwargs)
