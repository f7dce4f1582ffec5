"""The reconstruction methods' functions: ``f(buffers, *, alpha, **options) -> (H, W, 3)``
float32 tensor on ``buffers.device``, registered in :data:`gdpt.methods.METHODS`.

Each adapts a :class:`~gdpt.buffers.GradientBuffers` to an algorithm of :mod:`gdpt.reconstruct`
(screened Poisson, a trained network, OIDN, the variance-weighted fusion, NFOR) and names what
the buffers lack with the render option that makes it.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from gdpt import checkpoints, oidn_native
from gdpt.oidn import oidn_denoise

if TYPE_CHECKING:
    import torch

    from gdpt.buffers import GradientBuffers
    from gdpt.reconstruct.fuse import FusionStatistics


class MissingBuffersError(ValueError, KeyError):
    """The buffers lack one that a network reads: a ``ValueError`` like the other methods'
    missing buffers, and the ``KeyError`` the networks raise."""

    def __str__(self) -> str:
        return str(self.args[0])


#: Buffer a network reads -> the render option that makes it (``gdpt.render``, ``gdpt render``).
_RENDER_OPTIONS = {
    **dict.fromkeys(("dx", "dy"), "gradients=True (gdpt render without --no-gradients)"),
    **dict.fromkeys(("albedo", "normal", "depth"), "features=True (the default)"),
    **dict.fromkeys(("var_primal", "var_dx", "var_dy"), "variance=True (gdpt render --variance)"),
}

#: Plain path samples pooled per gradient sample in the input of ``fuse`` (as ``oidn-grad``'s
#: card).
FUSE_PRIMAL_SPP_FACTOR = 2.5


def poisson_method(
    buffers: GradientBuffers, *, method: str, alpha: float, **options: Any
) -> torch.Tensor:
    """Screened Poisson reconstruction from ``primal``, ``dx`` and ``dy``
    (:func:`gdpt.reconstruct.poisson.solve` with ``solver=method``); untraced gradients
    (``buffers.gradient_mask``) are missing constraints, without the solvers' warning about
    non-finite inputs (which still comes for the other inputs).

    Raises:
        ValueError: the buffers have no ``dx``/``dy``.
    """
    if buffers.dx is None or buffers.dy is None:
        raise ValueError(
            f"method {method!r} needs dx and dy; this render has none (primal-only mode)"
        )
    from gdpt.reconstruct.poisson import solve

    mask = buffers.gradient_mask
    if mask is None:
        return solve(buffers.primal, buffers.dx, buffers.dy, solver=method, alpha=alpha, **options)
    from gdpt.buffers import fill_untraced
    from gdpt.reconstruct.poisson import NonFiniteInputWarning

    filled = fill_untraced(buffers, math.nan, math.nan)
    with warnings.catch_warnings():
        if _finite_where(buffers, mask):
            warnings.simplefilter("ignore", NonFiniteInputWarning)
        return solve(filled.primal, filled.dx, filled.dy, solver=method, alpha=alpha, **options)


def _finite_where(buffers: GradientBuffers, mask: torch.Tensor) -> bool:
    """Whether the primal and the traced gradients (``mask``, ``(H, W, 2)``) are finite."""
    import torch

    traced_dx = torch.isfinite(buffers.dx).all(-1) | ~mask[..., 0]
    traced_dy = torch.isfinite(buffers.dy).all(-1) | ~mask[..., 1]
    return bool(torch.isfinite(buffers.primal).all() & traced_dx.all() & traced_dy.all())


def network_method(
    buffers: GradientBuffers, *, name: str, alpha: float, model: str | None = None, **_: Any
) -> torch.Tensor:
    """Neural reconstruction with the checkpoint of ``name`` (or ``model``;
    :func:`gdpt.checkpoints.model_path`); ``alpha`` does not apply. A network cannot leave an
    input out: an untraced gradient (``buffers.gradient_mask``) reaches it as the primal's own
    forward difference there, which tells it nothing the primal does not.

    Raises:
        MissingBuffersError: the buffers lack one the model's card lists (named, with the
            render option that makes it), before the model is loaded.
        RuntimeError: the model builds on OIDN's weights and ``mitsuba-oidn`` (whose library
            holds them) is not installed or its weights are not recognised.
    """
    from gdpt.reconstruct.cards import read_card

    path = checkpoints.model_path(name, model).resolve()
    reads = read_card(path)[2].get("features", ())
    if missing := [n for n in reads if getattr(buffers, n, None) is None]:
        options = dict.fromkeys(_RENDER_OPTIONS.get(n, n) for n in missing)
        raise MissingBuffersError(
            f"method {name!r}: the buffers lack {', '.join(missing)}, which its network reads; "
            f"render with {' and '.join(options)}"
        )
    if reason := checkpoints.oidn_weights_missing(name, path):
        raise RuntimeError(reason)
    factor = checkpoints.primal_spp_factor(name, model)
    metadata = getattr(buffers, "metadata", None)
    unpooled = metadata is not None and "primal_spp" not in metadata and buffers.has_gradients
    if factor and unpooled:  # (buffers without gradients fail in the network, by name)
        warnings.warn(
            f"model {path.name} was trained on primals pooled with {factor:g} plain path "
            "samples per gradient sample; these buffers have none (render with "
            f"primal_spp={factor:g} x spp, or 'gdpt render --primal-spp')",
            stacklevel=3,
        )
    if buffers.gradient_mask is not None:
        buffers = _primal_differences_where_untraced(buffers)
    reconstructor = checkpoints.load_reconstructor(path)
    image = oidn_native.reconstruct(reconstructor, buffers)  # OIDN's kernels where they apply
    return reconstructor(buffers) if image is None else image


def _primal_differences_where_untraced(buffers: GradientBuffers) -> GradientBuffers:
    """:func:`gdpt.buffers.fill_untraced` with the primal's forward differences."""
    import torch

    from gdpt.buffers import fill_untraced

    p = buffers.primal
    dx, dy = torch.zeros_like(p), torch.zeros_like(p)
    dx[:, :-1] = p[:, 1:] - p[:, :-1]
    dy[:-1] = p[1:] - p[:-1]
    return fill_untraced(buffers, dx, dy)


def oidn_method(buffers: GradientBuffers, *, alpha: float, **options: Any) -> torch.Tensor:
    """:func:`gdpt.oidn.oidn_denoise` of a render's primal, albedo and normal
    (``alpha`` does not apply; ``options``: ``backend``, ``weights``).

    Raises:
        ValueError: an option other than those, or the render has no albedo or normal
            (rendered with ``features=False``).
    """
    if unknown := sorted(set(options) - {"backend", "weights"}):
        raise ValueError(f"method 'oidn' has no option {', '.join(unknown)} (backend, weights)")
    if missing := [n for n in ("albedo", "normal") if getattr(buffers, n) is None]:
        raise ValueError(
            f"method 'oidn' needs the {' and '.join(missing)} buffer{'s' * (len(missing) > 1)}; "
            "this render has none: render with the integrator option features=True "
            "(the default of gdpt.render and 'gdpt render')"
        )
    return oidn_denoise(buffers.primal, buffers.albedo, buffers.normal, **options)


def plain_denoiser() -> str:
    """The primal-only denoiser of ``fuse`` and of ``auto``'s plain route: ``oidn-tuned`` where
    its model and weights are found, else ``oidn``."""
    return "oidn-tuned" if checkpoints.network_check("oidn-tuned") is None else "oidn"


def fusion_statistics_of(
    buffers: GradientBuffers,
    denoise: Callable[[GradientBuffers], torch.Tensor],
    *,
    whole_denoise: bool = True,
) -> FusionStatistics:
    """:func:`gdpt.reconstruct.fuse.fusion_statistics` of a render with variances and halves:
    ``denoise`` runs on the render without its gradients and on its two halves; without
    ``whole_denoise``, the mean of the halves' denoises stands for the whole render's (one
    denoise fewer: enough where only the held-out terms are read, which take from it only the
    relMSE weights' luminance, the statistics' guide and the error floor)."""
    from gdpt.reconstruct.fuse import fusion_statistics

    done: dict[str, torch.Tensor] = {}

    def denoised(name: str) -> torch.Tensor:
        if name == "full" and not whole_denoise:
            return 0.5 * (denoised("a") + denoised("b"))
        if name not in done:
            part = buffers.replace(dx=None, dy=None) if name == "full" else buffers.half(name)
            done[name] = denoise(part)
        return done[name]

    return fusion_statistics(
        denoised, buffers.primal_a, buffers.primal_b, buffers.var_dx, buffers.var_dy
    )


def _fusion_halves(buffers: GradientBuffers) -> tuple[GradientBuffers, tuple[Any, Any, Any]]:
    """``buffers`` with untraced gradients filled (:func:`gdpt.buffers.fill_untraced`: 0 with
    infinite variance) and the halves :func:`gdpt.reconstruct.fuse.fuse_checked` reads:
    ``((dx_a, dy_a), (dx_b, dy_b))``, ``(primal_a, primal_b)`` and the variance scales (the
    render's gradient samples over each half's, ``inf`` for an empty half)."""
    from gdpt.buffers import fill_untraced, gradient_half_count  # (torch: not at import)

    buffers = fill_untraced(buffers, 0.0, 0.0)
    counts = gradient_half_count(buffers)
    return buffers, (
        ((buffers.dx_a, buffers.dy_a), (buffers.dx_b, buffers.dy_b)),
        (buffers.primal_a, buffers.primal_b),
        tuple(buffers.spp / n if n > 0 else math.inf for n in counts),
    )


def held_out_fusion_terms_of(
    buffers: GradientBuffers,
    denoise: Callable[[GradientBuffers], torch.Tensor],
    *,
    whole_denoise: bool = True,
) -> tuple[torch.Tensor, int]:
    """:func:`gdpt.reconstruct.fuse.held_out_fusion_terms` of ``fuse``'s input ``buffers``
    (gradients, variances and halves; untraced gradients have no weight) with the denoiser
    ``denoise`` (``whole_denoise``: see :func:`fusion_statistics_of`): ``(H, W, 1)`` per-pixel
    held-out relMSE of the fusion minus the denoise's (< 0: the fusion looks better) and the
    count of non-finite terms."""
    from gdpt.reconstruct.fuse import TRUST_RATIO, held_out_fusion_terms

    buffers, halves = _fusion_halves(buffers)
    statistics = fusion_statistics_of(buffers, denoise, whole_denoise=whole_denoise)
    return held_out_fusion_terms(statistics, *halves, trust_ratio=TRUST_RATIO)


def fuse_method(
    buffers: GradientBuffers,
    *,
    alpha: float,
    primal_only: Callable[[str | None], tuple[str, Callable[[GradientBuffers], torch.Tensor]]],
    denoiser: str | None = None,
    trust_ratio: float | None = None,
    **_: Any,
) -> torch.Tensor:
    """Denoise the primal and its two halves with a primal-only denoiser, fuse the result with
    the gradients by variance-weighted screened Poisson, and keep the fusion only where the
    two halves' own fusions beat their denoises on held-out data, else the denoise
    (:func:`gdpt.reconstruct.fuse.fuse_checked`; ``alpha`` does not apply).
    ``primal_only(denoiser)`` returns the denoiser's name and function
    (:func:`gdpt.methods.primal_only`). ``buffers.metadata["fuse"]`` receives the denoiser,
    the share of gradients used, the solver iterations, the guard counts and the held-out
    choice (``held_out``). Untraced gradients (``buffers.gradient_mask``) get zero weight
    (:func:`gdpt.buffers.fill_untraced`: infinite variance).

    Raises:
        ValueError: the buffers lack gradients, variances or half-buffers (the gradients'
            included; named, with the render option that makes them), or ``denoiser`` reads
            gradients.
    """
    from gdpt.reconstruct.fuse import TRUST_RATIO, fuse_checked

    missing = [
        (name, option)
        for name, option in (
            ("dx", "gradients=True"),
            ("var_dx", "variance=True"),
            ("primal_a", "halves=True"),
            ("dx_a", "gradients=True, halves=True"),
        )
        if getattr(buffers, name) is None
    ]
    if missing:
        raise ValueError(
            "method 'fuse' reads "
            + ", ".join(f"'{n}' (render with {o})" for n, o in missing)
            + "; these buffers have none"
        )
    name, denoise = primal_only(denoiser)
    buffers, halves = _fusion_halves(buffers)
    image, info = fuse_checked(
        fusion_statistics_of(buffers, denoise),
        buffers.dx,
        buffers.dy,
        *halves,
        trust_ratio=TRUST_RATIO if trust_ratio is None else trust_ratio,
    )
    buffers.metadata["fuse"] = {"denoiser": name, **dataclasses.asdict(info)}
    return image


def nfor_method(buffers: GradientBuffers, *, alpha: float, **options: Any) -> torch.Tensor:
    """NFOR (Bitterli et al. 2016; :func:`gdpt.reconstruct.nfor.nfor`) on the render's two
    half-buffers of primal and features and the primal's variance (``alpha`` does not
    apply). ``options`` are :class:`gdpt.reconstruct.nfor.NforConfig` fields;
    ``buffers.metadata["nfor"]`` receives the non-finite input count and the bandwidths'
    shares.

    Raises:
        ValueError: the buffers lack the half-buffers, the features or the variance (named,
            with the render option that makes them), or an option is out of range (named).
    """
    from gdpt.reconstruct.nfor import NforConfig, nfor

    needs = [("primal_a", "halves=True"), ("var_primal", "variance=True")]
    needs += [(f"{f}_a", "features=True, halves=True") for f in ("albedo", "normal", "depth")]
    missing = [(n, o) for n, o in needs if getattr(buffers, n) is None]
    if missing:
        raise ValueError(
            "method 'nfor' reads "
            + ", ".join(f"'{n}' (render with {o})" for n, o in missing)
            + "; these buffers have none"
        )
    known = [f.name for f in dataclasses.fields(NforConfig)]
    if unknown := sorted(set(options) - set(known)):
        raise ValueError(f"method 'nfor': unknown options {unknown}; valid: {', '.join(known)}")
    config = NforConfig(**options)
    halves = [[getattr(buffers, f"{f}_{h}") for f in ("albedo", "normal", "depth")] for h in "ab"]
    image, info = nfor(
        buffers.primal_a, buffers.primal_b, buffers.var_primal, halves[0], halves[1], config
    )
    buffers.metadata["nfor"] = dataclasses.asdict(info)
    if info.nonfinite:
        warnings.warn(
            f"nfor: {info.nonfinite} non-finite input values were replaced by 0", stacklevel=3
        )
    return image
