"""The registry of reconstruction methods and the one call that runs them.

:data:`METHODS` holds every method as a :class:`Method`: its function (:mod:`gdpt.adapters`) and
the integrator outputs it reads, so :func:`gdpt.render_and_denoise` renders only those.
Registered:

* ``'l2'`` / ``'l1'`` / ``'l1-fast'``: screened Poisson reconstruction
  (:mod:`gdpt.reconstruct.poisson`, same names).
* ``'oidn-grad'`` / ``'oidn-tuned'``: the shipped networks, Intel Open Image Denoise's U-Net
  fine-tuned here (:mod:`gdpt.reconstruct.oidn_finetune`; ``gdpt/models/README.md``), with and
  without the gradients; ``model=PATH`` (or ``$GDPT_OIDN_GRAD_MODEL`` for ``oidn-grad``) runs
  another checkpoint (:mod:`gdpt.checkpoints`).
* ``'kpcn'``: KPCN (Bako et al. 2017, :mod:`gdpt.reconstruct.kpcn`), shipped.
* ``'nfor'``: NFOR (Bitterli et al. 2016, :mod:`gdpt.reconstruct.nfor`).
* ``'oidn'``: Intel Open Image Denoise (:func:`gdpt.oidn.oidn_denoise`).
* ``'fuse'``: a primal-only denoise fused with the gradients (:mod:`gdpt.reconstruct.fuse`).

Deprecated names (``'ngpt'``, ``'ngpt-nograd'``) resolve with a ``DeprecationWarning``
(:mod:`gdpt.deprecated`). To add a method, write ``f(buffers, *, alpha, **options) -> (H, W, 3)
tensor`` and ``METHODS.register(name, Method(f, gradients=..., features=...))``, or register a
trained checkpoint with :func:`register_checkpoint`; the CLI, the API and the study
(:mod:`gdpt.study.methods`) offer every registered name.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gdpt.adapters import (
    FUSE_PRIMAL_SPP_FACTOR,
    fuse_method,
    network_method,
    nfor_method,
    oidn_method,
    plain_denoiser,
    poisson_method,
)
from gdpt.checkpoints import network_check, oidn_weights_missing, primal_spp_factor
from gdpt.deprecated import METHOD_ALIASES
from gdpt.io.mitsuba_aov import SOURCE as MITSUBA_AOV_SOURCE
from gdpt.oidn import oidn_check
from gdpt.reconstruct.registry import Registry

if TYPE_CHECKING:
    import os

    import torch

    from gdpt.buffers import GradientBuffers


@dataclass(frozen=True)
class Method:
    """A reconstruction method and the buffers it reads.

    Attributes:
        run: ``f(buffers, *, alpha, **options) -> (H, W, 3)`` float32 tensor on
            ``buffers.device``.
        gradients: reads ``dx``/``dy`` (``gdpt`` property ``gradients``).
        features: reads albedo, normal and depth (``gdpt`` property ``features``).
        description: one line for reports (what follows "path tracing + ").
        check: returns ``None`` when the method can run here, else the reason it cannot.
        primal_spp_factor: ``f(**options) -> float``: plain path samples per gradient sample
            that the method's input pools into its primal (0: none; see
            :func:`gdpt.buffers.pool_primal`); a trained network reads it from its card.
        statistics: reads the variances of the means and the half-buffers.
        differentiable: the image is differentiable in torch w.r.t. the input buffers;
            ``False``: :func:`reconstruct_image` raises when a buffer requires gradients.
        variance: reads ``var_primal``, the variance of the primal's mean (``gdpt`` property
            ``variance``).
    """

    run: Callable[..., torch.Tensor]
    gradients: bool
    features: bool
    description: str
    check: Callable[[], str | None] = lambda: None
    primal_spp_factor: Callable[..., float] = lambda **_: 0.0
    statistics: bool = False
    differentiable: bool = False
    variance: bool = False

    @property
    def needs(self) -> dict[str, bool]:
        """The ``gdpt`` integrator properties that render what this method reads
        (``statistics``: the variances and half-buffers, ``variance`` and ``halves``;
        ``variance``: the variances)."""
        needs = {"gradients": self.gradients, "features": self.features}
        if self.variance:
            needs["variance"] = True
        return {**needs, "variance": True, "halves": True} if self.statistics else needs

    def sampling(self, spp: int, **options: Any) -> dict[str, Any]:
        """Keyword arguments of :func:`gdpt.render` that render this method's input with
        ``spp`` gradient samples per pixel: :attr:`needs`, and ``primal_spp`` (rounded
        ``primal_spp_factor * spp``) when the method pools plain path samples."""
        factor = self.primal_spp_factor(**options) if self.gradients else 0.0
        extra = round(factor * spp)
        return {**self.needs, "primal_spp": extra} if extra else dict(self.needs)


#: Method name -> :class:`Method`, in registration order.
METHODS: Registry[Method] = Registry("reconstruction method")

#: Network families whose reconstructors run with autograd when an input buffer requires
#: gradients (:mod:`gdpt.reconstruct.dense_unet_reconstructor`, :mod:`.oidn_finetune`).
DIFFERENTIABLE_FAMILIES = ("dense-unet", "oidn-finetune")


def reconstruct_image(
    buffers: GradientBuffers, method: str = "l1-fast", *, alpha: float = 0.2, **options: Any
) -> torch.Tensor:
    """Reconstruct the final image from a render (``gdpt.reconstruct_image``).

    Args:
        buffers (GradientBuffers): the render; the Poisson methods need ``dx`` and ``dy``,
            ``oidn`` and the networks the features.
        method (str): a key of :data:`METHODS` (``'l1-fast'``, ``'l2'``, ``'oidn'``, ...); a
            deprecated name (``'ngpt'``) runs its new one (``'oidn-grad'``) with a
            ``DeprecationWarning``.
        alpha (float): weight of the primal term relative to the gradient terms (screened
            Poisson); methods that have no such weight ignore it.
        **options: method-specific options, passed through unchanged (``model=PATH`` for a
            network, ``backend=`` for ``oidn``, solver options for the Poisson methods).

    Returns:
        ``(H, W, 3)`` float32 tensor on ``buffers.device``; differentiable w.r.t. the buffers
        that require gradients (in torch's gradient mode) for a :attr:`Method.differentiable`
        method.

    Raises:
        ValueError: unknown ``method``, the buffers lack what the method needs, or a buffer
            requires gradients and the method is not differentiable (named, with the ones
            that are).
    """
    from gdpt.reconstruct.autograd import records

    method = METHODS.resolve(method, stacklevel=2)
    METHODS.check([method])
    if METHODS[method].gradients and buffers.metadata.get("source") == MITSUBA_AOV_SOURCE:
        raise ValueError(
            f"method {method!r} reads the gradients dx/dy, which only a gdpt render makes "
            "(gdpt.render, 'gdpt render' or <integrator type=\"gdpt\">); these buffers come "
            "from a Mitsuba AOV EXR: use a method without gradients (oidn, oidn-tuned)"
        )
    if not METHODS[method].differentiable and records(t for _, t in buffers.items()):
        usable = ", ".join(n for n, m in METHODS.items() if m.differentiable)
        raise ValueError(
            f"method {method!r} is not differentiable w.r.t. its input buffers, and these "
            f"buffers require gradients; differentiable methods: {usable}"
        )
    return METHODS[method].run(buffers, alpha=alpha, **options)


def primal_only(
    name: str | None = None,
) -> tuple[str, Callable[[GradientBuffers], torch.Tensor]]:
    """The primal-only method ``name`` (default :func:`gdpt.adapters.plain_denoiser`) and
    ``f(buffers) -> image`` that reconstructs with it (the denoiser of ``fuse`` and ``auto``).

    Raises:
        ValueError: ``name`` is unknown, cannot run here, or reads gradients.
    """
    name = METHODS.resolve(name or plain_denoiser(), stacklevel=4)
    METHODS.check([name])
    if METHODS[name].gradients:
        raise ValueError(f"fuse: denoiser {name!r} reads gradients; give a primal-only one")
    return name, lambda buffers: reconstruct_image(buffers, name)


def register_checkpoint(name: str, path: str | os.PathLike) -> Method:
    """Register a checkpoint written by ``gdpt train`` as the reconstruction method ``name``.

    Whether the method reads gradients (``dx``) and variances (``var_primal``) comes from the
    card's ``features``, the plain path samples its renders pool from the card's
    ``sampling.primal_spp_factor``; it is differentiable if its family's reconstructor runs
    with autograd (:data:`DIFFERENTIABLE_FAMILIES`).

    Args:
        name: the new method's name (not yet in :data:`METHODS`).
        path: the checkpoint's ``.safetensors`` (its ``.json`` card next to it).

    Returns:
        The registered :class:`Method`.

    Raises:
        FileNotFoundError: either file of the checkpoint is missing.
        ValueError: ``name`` is already registered, or the checkpoint is unreadable or of no
            known network family (:func:`gdpt.reconstruct.families.family_of`).
    """
    from gdpt.reconstruct.cards import read_card
    from gdpt.reconstruct.families import family_of

    path = Path(path)
    _, _, card = read_card(path)
    family = family_of(path)
    return METHODS.register(
        name,
        Method(
            partial(network_method, name=name, model=path),
            "dx" in card.get("features", ()),
            True,
            f"the checkpoint {path} ({card.get('design') or card.get('config_name', 'network')})",
            partial(oidn_weights_missing, name, path),
            partial(primal_spp_factor, name, path),
            differentiable=family.name in DIFFERENTIABLE_FAMILIES,
            variance="var_primal" in card.get("features", ()),
        ),
    )


for _name, _detail in (
    ("l2", "L2 (alpha 0.2)"),
    ("l1", "L1 (alpha 0.2, reference IRLS schedule)"),
    (
        "l1-fast",
        "L1 (alpha 0.2, DCT-preconditioned IRLS preset 'fast': same final energy, about 3x faster)",
    ),
):
    METHODS.register(
        _name,
        Method(
            partial(poisson_method, method=_name),
            True,
            False,
            f"screened Poisson, {_detail}",
            differentiable=True,
        ),
    )
METHODS.register(
    "oidn-grad",
    Method(
        partial(network_method, name="oidn-grad"),
        True,
        True,
        "OIDN's U-Net fine-tuned to read the gradients (shipped; gated refinement)",
        partial(network_check, "oidn-grad"),
        partial(primal_spp_factor, "oidn-grad"),
        differentiable=True,
    ),
)
METHODS.register(
    "oidn-tuned",
    Method(
        partial(network_method, name="oidn-tuned"),
        False,
        True,
        "OIDN's U-Net fine-tuned on the same data without gradients (shipped; the ablation)",
        partial(network_check, "oidn-tuned"),
        differentiable=True,
    ),
)
for _old, _new in METHOD_ALIASES.items():
    METHODS.alias(_old, _new)
METHODS.register(
    "kpcn",
    Method(
        partial(network_method, name="kpcn"),
        False,
        True,
        "KPCN (Bako et al. 2017), CPU-sized, trained here (shipped): per-pixel 11x11 kernels "
        "over albedo-demodulated log radiance",
        partial(network_check, "kpcn"),
        variance=True,
    ),
)
METHODS.register(
    "oidn",
    Method(
        oidn_method,
        False,
        True,
        "Intel Open Image Denoise (mitsuba-oidn; albedo + normal, HDR, quality high)",
        oidn_check,
    ),
)
METHODS.register(
    "fuse",
    Method(
        partial(fuse_method, primal_only=primal_only),
        True,
        True,
        "variance-weighted screened Poisson of the gradients around the primal-only network "
        "(oidn-tuned, else OIDN) denoise, per-pixel error from its half-buffer denoises",
        lambda: (
            None
            if oidn_check() is None or network_check("oidn-tuned") is None
            else ("fuse needs a primal-only denoiser: oidn-tuned or mitsuba-oidn")
        ),
        lambda **_: FUSE_PRIMAL_SPP_FACTOR,
        statistics=True,
    ),
)
METHODS.register(
    "nfor",
    Method(
        nfor_method,
        False,
        True,
        "NFOR (Bitterli et al. 2016): first-order regression on the features, cross-filtered "
        "between the render's two half-buffers",
        statistics=True,
    ),
)
