"""The single entry point that turns gradient-domain buffers into a final image.

:data:`METHODS` is the one registry of reconstruction methods: each :class:`Method` holds the
function and the integrator outputs it reads, so :func:`gdpt.render_and_denoise` renders only
those. Registered:

* ``'l2'`` / ``'l1'`` / ``'l1-fast'``: screened Poisson reconstruction
  (:mod:`gdpt.reconstruct.poisson`, same names): the closed-form L2 solution, the reference
  IRLS L1 preset and the accelerated L1 solver (same or lower L1 energy, fewer CG iterations).
* ``'oidn-grad'`` / ``'oidn-tuned'``: the shipped networks, Intel Open Image Denoise's U-Net
  fine-tuned here (:mod:`gdpt.reconstruct.oidn_finetune`, a delta to Intel's weights read from
  ``mitsuba-oidn``; ``gdpt/models/README.md``): ``oidn-grad`` reads the gradients (pooled primal,
  gated refinement), ``oidn-tuned`` is the same network fine-tuned on the same data without
  them (run by OIDN's own kernels, :func:`gdpt.oidn_native.reconstruct`, unless autograd
  records an input). ``model=PATH`` (or ``$GDPT_OIDN_GRAD_MODEL`` for ``oidn-grad``) runs
  another trained checkpoint instead, e.g. a dense U-Net
  (:mod:`gdpt.reconstruct.dense_unet_reconstructor`). Their former names ``'ngpt'`` /
  ``'ngpt-nograd'`` (and ``$GDPT_NGPT_MODEL``) still work, with a ``DeprecationWarning``.
* ``'kpcn'``: KPCN (Bako et al. 2017, :mod:`gdpt.reconstruct.kpcn`), shipped: per-pixel
  kernels over the path-traced primal, read with albedo, normal, depth and the primal's
  variance (no gradients; ``model=PATH`` runs another KPCN checkpoint).
* ``'nfor'``: NFOR (Bitterli et al. 2016, :mod:`gdpt.reconstruct.nfor`) on the primal's and the
  features' two half-buffers and the primal's variance (no gradients).
* ``'oidn'``: Intel Open Image Denoise on the primal with albedo and normal (no gradients),
  :func:`oidn_denoise`: OIDN itself through ``mitsuba-oidn`` (:mod:`gdpt.oidn_native`) on CPU
  and CUDA tensors, or OIDN's U-Net in torch (:mod:`gdpt.reconstruct.oidn_unet`).

Reconstruct with :func:`reconstruct_image` (``gdpt.reconstruct_image``; :func:`reconstruct` is
its deprecated old name). To add a method, write ``f(buffers, *, alpha, **options) -> (H, W, 3)
tensor`` and ``METHODS.register(name, Method(f, gradients=..., features=...))``, or register a
trained checkpoint with :func:`register_checkpoint`; the CLI, the API and the study
(:mod:`gdpt.study.methods`, :func:`gdpt.study.methods.register_denoiser`) offer every registered
name.

A method marked :attr:`Method.differentiable` passes torch gradients from the image to the
buffers that require them (the Poisson methods by an adjoint solve, the networks by autograd;
``docs/differentiable.md``); :func:`reconstruct_image` refuses such buffers for the others.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache, partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from gdpt.reconstruct.registry import Registry

if TYPE_CHECKING:
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
        differentiable: the image is differentiable in torch w.r.t. the input buffers (the
            Poisson solvers through their adjoint system, :mod:`gdpt.reconstruct.poisson`; L1
            through its last IRLS weights); ``False``: :func:`reconstruct_image` raises when a
            buffer requires gradients.
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


def _poisson(
    buffers: GradientBuffers, *, method: str, alpha: float, **options: Any
) -> torch.Tensor:
    """Screened Poisson reconstruction from ``primal``, ``dx`` and ``dy``."""
    if buffers.dx is None or buffers.dy is None:
        raise ValueError(
            f"method {method!r} needs dx and dy; this render has none (primal-only mode)"
        )
    from gdpt.reconstruct import poisson

    return poisson.solve(
        buffers.primal, buffers.dx, buffers.dy, solver=method, alpha=alpha, **options
    )


#: Folder of the models shipped with the package (``<name>.safetensors`` + ``<name>.json``).
MODEL_DIR = Path(__file__).parent / "models"

#: Environment variable: a checkpoint that replaces the shipped one of ``oidn-grad``.
MODEL_ENV = "GDPT_OIDN_GRAD_MODEL"

#: Deprecated name of :data:`MODEL_ENV` (honoured with a ``DeprecationWarning``).
MODEL_ENV_DEPRECATED = "GDPT_NGPT_MODEL"


def _model_from_environment() -> str | None:
    """``$GDPT_OIDN_GRAD_MODEL``, else ``$GDPT_NGPT_MODEL`` (with a ``DeprecationWarning``), else
    ``None``."""
    if (model := os.environ.get(MODEL_ENV)) is None:
        model = os.environ.get(MODEL_ENV_DEPRECATED)
        if model is not None:
            warnings.warn(
                f"{MODEL_ENV_DEPRECATED} is deprecated; set {MODEL_ENV}",
                DeprecationWarning,
                stacklevel=2,
            )
    return model


def model_path(name: str, model: str | os.PathLike | None = None) -> Path:
    """The checkpoint to use: ``model``, else ``$GDPT_OIDN_GRAD_MODEL`` (for ``oidn-grad``),
    else the shipped ``gdpt/models/<name>.safetensors``.

    Raises:
        FileNotFoundError: no such checkpoint; the message says what to provide.
    """
    if model is None and name == "oidn-grad":
        model = _model_from_environment()
    path = Path(model) if model is not None else MODEL_DIR / f"{name}.safetensors"
    if not path.is_file():
        raise FileNotFoundError(
            f"checkpoint not found: {path}. Pass model=PATH (a checkpoint written by "
            f"'gdpt train'), or set {MODEL_ENV} for 'oidn-grad'"
        )
    return path


@lru_cache(maxsize=4)
def load_reconstructor(path: Path) -> Any:
    """The reconstructor of a checkpoint (cached), built by its network family
    (:func:`gdpt.reconstruct.families.family_of`); it is called with a buffer mapping or
    ``GradientBuffers`` and exposes ``features``.

    Raises:
        FileNotFoundError: a file of the checkpoint is missing.
        ValueError: the card's format is no known family's (the message lists them).
    """
    from gdpt.reconstruct.families import family_of

    return family_of(path).reconstructor(path)


def _network(
    buffers: GradientBuffers, *, name: str, alpha: float, model: str | None = None, **_: Any
) -> torch.Tensor:
    """Neural reconstruction with a trained network (``alpha`` does not apply).

    Raises:
        KeyError: the buffers lack one the model reads (named).
        RuntimeError: the model builds on OIDN's weights and ``mitsuba-oidn`` (whose library
            holds them) is not installed or its weights are not recognised.
    """
    path = model_path(name, model).resolve()
    if reason := _oidn_weights_missing(name, path):
        raise RuntimeError(reason)
    from gdpt import oidn_native

    factor = _network_primal_spp_factor(name, model)
    metadata = getattr(buffers, "metadata", None)
    unpooled = metadata is not None and "primal_spp" not in metadata and buffers.has_gradients
    if factor and unpooled:  # (buffers without gradients fail in the network, by name)
        warnings.warn(
            f"model {path.name} was trained on primals pooled with {factor:g} plain path "
            "samples per gradient sample; these buffers have none (render with "
            f"primal_spp={factor:g} x spp, or 'gdpt render --primal-spp')",
            stacklevel=3,
        )
    reconstructor = load_reconstructor(path)
    image = oidn_native.reconstruct(reconstructor, buffers)
    return reconstructor(buffers) if image is None else image


def _oidn_weights_missing(name: str, path: Path) -> str | None:
    """Why the model at ``path``, when its family builds on OIDN's weights (a fine-tuned OIDN
    network, a combiner's base network), cannot load them, or ``None``.

    Raises:
        FileNotFoundError: a file of the checkpoint is missing.
        ValueError: the card's format is no known family's.
    """
    from gdpt.reconstruct.families import family_of

    if not family_of(path).oidn_weights:
        return None
    if importlib.util.find_spec("mitsuba_oidn") is None:
        return (
            f"method {name!r} fine-tunes Intel Open Image Denoise, whose weights are read from "
            "the 'mitsuba-oidn' package at run time: pip install mitsuba-oidn"
        )
    from gdpt.reconstruct.tza import OIDNWeightsError, builtin_weights

    try:
        builtin_weights()
    except OIDNWeightsError as err:
        return f"method {name!r}: {err}"
    return None


def _network_primal_spp_factor(name: str, model: str | None = None, **_: Any) -> float:
    """The model card's ``sampling.primal_spp_factor`` (0 when the card has none or the
    checkpoint is missing: :func:`_network` reports that)."""
    from gdpt.reconstruct.cards import read_card

    try:
        _, _, card = read_card(model_path(name, model))
    except FileNotFoundError:
        return 0.0
    return float(card.get("sampling", {}).get("primal_spp_factor", 0.0))


def _network_check(name: str) -> str | None:
    """``None`` when the shipped network ``name`` (and what it builds on) can be found, else
    why not."""
    try:
        return _oidn_weights_missing(name, model_path(name))
    except (FileNotFoundError, ValueError) as err:
        return str(err)


#: Backends of :func:`oidn_denoise`.
OIDN_BACKENDS = ("auto", "native", "torch")
#: Former backend names of :func:`oidn_denoise` -> current ones (they warn).
OIDN_BACKEND_ALIASES = {"pyoidn": "native"}


def oidn_check() -> str | None:
    """``None`` when Intel Open Image Denoise (``mitsuba-oidn``, which also holds the weights of
    the torch port) can run here, else why not."""
    from gdpt.oidn_native import check

    return check()


def oidn_denoise(
    primal: torch.Tensor,
    albedo: torch.Tensor,
    normal: torch.Tensor,
    *,
    backend: str = "auto",
    weights: str | os.PathLike | None = None,
) -> torch.Tensor:
    """OIDN's ``RT`` filter, HDR, quality ``high``, with albedo and normal (Intel Open Image
    Denoise, https://github.com/RenderKit/oidn).

    Colour is clamped to >= 0, albedo to [0, 1] and normals to [-1, 1] as OIDN expects.

    Args:
        primal: ``(H, W, 3)`` float32 linear radiance, on the CPU or a CUDA device.
        albedo: ``(H, W, 3)`` float32 albedo, same device.
        normal: ``(H, W, 3)`` float32 normals in [-1, 1], same device.
        backend: ``"native"``: OIDN itself through ``mitsuba-oidn``
            (:func:`gdpt.oidn_native.denoise`) on the tensors' device (CPU, or CUDA), reading
            them in place (copied first only where a pixel's channels are not adjacent) and
            clamping as above;
            ``"torch"``: OIDN's U-Net re-implemented in torch
            (:func:`gdpt.reconstruct.oidn_unet.denoise`, Intel's weights, agrees with OIDN to
            1e-4 relative); ``"auto"``: ``native``, or ``torch`` where ``weights`` is given.
            ``"pyoidn"``, the former name of ``native``, still works with a
            ``DeprecationWarning``.
        weights: the torch port only: a ``.tza`` file of Intel's ``rt_hdr_alb_nrm`` weights
            (from https://github.com/RenderKit/oidn-weights), for machines without
            ``mitsuba-oidn`` (which otherwise supplies them).

    Returns:
        ``(H, W, 3)`` float32 on the device of ``primal``, no gradients.

    Raises:
        ValueError: unknown ``backend``, ``weights`` with ``backend="native"``, or an image
            OIDN cannot read (named with its shape: not ``(H, W, 3)`` float32 like the primal).
        RuntimeError: ``mitsuba-oidn`` is needed (its package or weights) and not installed.
    """
    if backend in OIDN_BACKEND_ALIASES:
        warnings.warn(
            f"oidn backend {backend!r} is deprecated; use {OIDN_BACKEND_ALIASES[backend]!r}",
            DeprecationWarning,
            stacklevel=2,
        )
        backend = OIDN_BACKEND_ALIASES[backend]
    if backend not in OIDN_BACKENDS:
        raise ValueError(f"oidn backend must be one of {', '.join(OIDN_BACKENDS)}, got {backend!r}")
    if backend == "native" and weights is not None:
        raise ValueError("oidn: weights= is an option of the torch backend, not of native OIDN")
    import torch

    if backend == "auto":
        backend = "native" if weights is None else "torch"
    if backend == "torch":
        from gdpt.reconstruct.oidn_unet import denoise

        with torch.no_grad():  # (not inference mode: callers may change the image in place)
            return denoise(primal, albedo, normal, weights=weights, hdr=True, quality="high")
    from gdpt import oidn_native

    images = (primal, albedo, normal)
    return oidn_native.denoise(
        *(
            t.contiguous() if isinstance(t, torch.Tensor) and t.stride(-1) != 1 else t
            for t in images
        )
    )


def _oidn(buffers: GradientBuffers, *, alpha: float, **options: Any) -> torch.Tensor:
    """:func:`oidn_denoise` of a render's primal, albedo and normal (``alpha`` does not apply;
    ``options``: ``backend``, ``weights``).

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


#: Method name -> :class:`Method`, in registration order.
METHODS: Registry[Method] = Registry("reconstruction method")
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
            partial(_poisson, method=_name),
            True,
            False,
            f"screened Poisson, {_detail}",
            differentiable=True,
        ),
    )
METHODS.register(
    "oidn-grad",
    Method(
        partial(_network, name="oidn-grad"),
        True,
        True,
        "OIDN's U-Net fine-tuned to read the gradients (shipped; gated refinement)",
        partial(_network_check, "oidn-grad"),
        partial(_network_primal_spp_factor, "oidn-grad"),
        differentiable=True,
    ),
)
METHODS.register(
    "oidn-tuned",
    Method(
        partial(_network, name="oidn-tuned"),
        False,
        True,
        "OIDN's U-Net fine-tuned on the same data without gradients (shipped; the ablation)",
        partial(_network_check, "oidn-tuned"),
        differentiable=True,
    ),
)
METHODS.alias("ngpt", "oidn-grad")
METHODS.alias("ngpt-nograd", "oidn-tuned")
METHODS.register(
    "kpcn",
    Method(
        partial(_network, name="kpcn"),
        False,
        True,
        "KPCN (Bako et al. 2017), CPU-sized, trained here (shipped): per-pixel 11x11 kernels "
        "over albedo-demodulated log radiance",
        partial(_network_check, "kpcn"),
        variance=True,
    ),
)
METHODS.register(
    "oidn",
    Method(
        _oidn,
        False,
        True,
        "Intel Open Image Denoise (mitsuba-oidn; albedo + normal, HDR, quality high)",
        oidn_check,
    ),
)


#: Plain path samples pooled per gradient sample in the input of ``fuse`` (as ``oidn-grad``'s
#: card).
FUSE_PRIMAL_SPP_FACTOR = 2.5


def _fuse(
    buffers: GradientBuffers,
    *,
    alpha: float,
    denoiser: str | None = None,
    trust_ratio: float | None = None,
    **_: Any,
) -> torch.Tensor:
    """Denoise the primal and its two halves with a primal-only denoiser, then fuse the result
    with the gradients by variance-weighted screened Poisson
    (:func:`gdpt.reconstruct.fuse.fuse_halves`; ``alpha`` does not apply).
    ``buffers.metadata["fuse"]`` receives the denoiser, the share of gradients used, the solver
    iterations and the guard counts.

    Raises:
        ValueError: the buffers lack gradients, variances or half-buffers (named, with the
            render option that makes them), or ``denoiser`` reads gradients.
    """
    from gdpt.reconstruct.fuse import TRUST_RATIO, fuse_halves

    missing = [
        (name, option)
        for name, option in (
            ("dx", "gradients=True"),
            ("var_dx", "variance=True"),
            ("primal_a", "halves=True"),
        )
        if getattr(buffers, name) is None
    ]
    if missing:
        raise ValueError(
            "method 'fuse' reads "
            + ", ".join(f"'{n}' (render with {o})" for n, o in missing)
            + "; these buffers have none"
        )
    if denoiser is None:
        denoiser = "oidn-tuned" if _network_check("oidn-tuned") is None else "oidn"
    name = METHODS.resolve(denoiser, stacklevel=3)
    METHODS.check([name])
    if METHODS[name].gradients:
        raise ValueError(f"fuse: denoiser {name!r} reads gradients; give a primal-only one")
    plain = buffers.replace(dx=None, dy=None)
    denoised = [reconstruct_image(b, name) for b in (plain, buffers.half("a"), buffers.half("b"))]
    image, info = fuse_halves(
        *denoised,
        buffers.primal_a,
        buffers.primal_b,
        buffers.dx,
        buffers.dy,
        buffers.var_dx,
        buffers.var_dy,
        trust_ratio=TRUST_RATIO if trust_ratio is None else trust_ratio,
    )
    buffers.metadata["fuse"] = {"denoiser": name, **dataclasses.asdict(info)}
    return image


METHODS.register(
    "fuse",
    Method(
        _fuse,
        True,
        True,
        "variance-weighted screened Poisson of the gradients around the primal-only network "
        "(oidn-tuned, else OIDN) denoise, per-pixel error from its half-buffer denoises",
        lambda: (
            None
            if oidn_check() is None or _network_check("oidn-tuned") is None
            else ("fuse needs a primal-only denoiser: oidn-tuned or mitsuba-oidn")
        ),
        lambda **_: FUSE_PRIMAL_SPP_FACTOR,
        statistics=True,
    ),
)


def _nfor(buffers: GradientBuffers, *, alpha: float, **options: Any) -> torch.Tensor:
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


METHODS.register(
    "nfor",
    Method(
        _nfor,
        False,
        True,
        "NFOR (Bitterli et al. 2016): first-order regression on the features, cross-filtered "
        "between the render's two half-buffers",
        statistics=True,
    ),
)


#: Network families whose reconstructors run with autograd when an input buffer requires
#: gradients (:mod:`gdpt.reconstruct.dense_unet_reconstructor`,
#: :mod:`gdpt.reconstruct.oidn_finetune`).
DIFFERENTIABLE_FAMILIES = ("dense-unet", "oidn-finetune")


def register_checkpoint(name: str, path: str | os.PathLike) -> Method:
    """Register a checkpoint written by ``gdpt train`` as the reconstruction method ``name``
    (to compare one's own networks with the shipped ones, e.g. ``gdpt evaluate --model``).

    Whether the method reads gradients (``dx``) and variances (``var_primal``) comes from the
    card's ``features``; a pooled design's
    ``sampling.primal_spp_factor`` sets how many plain path samples its renders pool; it is
    differentiable if its family's reconstructor runs with autograd
    (:data:`DIFFERENTIABLE_FAMILIES`).

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
            partial(_network, name=name, model=path),
            "dx" in card.get("features", ()),
            True,
            f"the checkpoint {path} ({card.get('design') or card.get('config_name', 'network')})",
            partial(_oidn_weights_missing, name, path),
            partial(_network_primal_spp_factor, name, path),
            differentiable=family.name in DIFFERENTIABLE_FAMILIES,
            variance="var_primal" in card.get("features", ()),
        ),
    )


def reconstruct_image(
    buffers: GradientBuffers, method: str = "l1", *, alpha: float = 0.2, **options: Any
) -> torch.Tensor:
    """Reconstruct the final image from a render (``gdpt.reconstruct_image``).

    Args:
        buffers (GradientBuffers): the render; the Poisson methods need ``dx`` and ``dy``,
            ``oidn`` and the networks the features.
        method (str): a key of :data:`METHODS` (``'l1'``, ``'l2'``, ``'oidn'``, ...); a
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
    if not METHODS[method].differentiable and records(t for _, t in buffers.items()):
        usable = ", ".join(n for n, m in METHODS.items() if m.differentiable)
        raise ValueError(
            f"method {method!r} is not differentiable w.r.t. its input buffers, and these "
            f"buffers require gradients; differentiable methods: {usable}"
        )
    return METHODS[method].run(buffers, alpha=alpha, **options)


def reconstruct(
    buffers: GradientBuffers, method: str = "l1", *, alpha: float = 0.2, **options: Any
) -> torch.Tensor:
    """Deprecated name of :func:`reconstruct_image` (same arguments and result); warns.

    Raises:
        ValueError: as :func:`reconstruct_image`.
    """
    warnings.warn(
        "gdpt.denoise.reconstruct is deprecated; use gdpt.reconstruct_image (same arguments)",
        DeprecationWarning,
        stacklevel=2,
    )
    return reconstruct_image(buffers, method, alpha=alpha, **options)
