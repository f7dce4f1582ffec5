"""The one buffer format every part of gdpt shares.

A :class:`GradientBuffers` holds what a gradient-domain render produces: the primal image, its
forward-difference gradients and the feature buffers the neural reconstruction reads. All images
are ``torch.float32`` tensors in HWC layout on one device (the CPU for ``llvm_*`` variants, the
CUDA device for ``cuda_*`` variants).

Gradient convention (shared with the integrators and the Poisson solvers)::

    dx[y, x] = I[y, x + 1] - I[y, x]      (last column unused, stored as 0)
    dy[y, x] = I[y + 1, x] - I[y, x]      (last row unused, stored as 0; y grows downward)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from gdpt.reconstruct.channels import CHANNELS, HALVED

#: Buffers every GradientBuffers has; the rest are optional.
REQUIRED = ("primal",)

#: The gradients of the two halves of the samples (the halves of ``primal_a``, ``primal_b``).
GRADIENT_HALVES = ("dx_a", "dx_b", "dy_a", "dy_b")


@dataclass
class GradientBuffers:
    """Primal, gradients, features and metadata of one render.

    Attributes:
        primal: ``(H, W, 3)`` float32 radiance estimate (base-path MIS estimate).
        dx: ``(H, W, 3)`` float32 horizontal forward-difference estimate, or ``None``
            (plain path tracing).
        dy: ``(H, W, 3)`` float32 vertical forward-difference estimate, or ``None``.
        albedo: ``(H, W, 3)`` float32 albedo at the first rough vertex, or ``None``.
        normal: ``(H, W, 3)`` float32 camera-space shading normal facing the camera, or ``None``.
        depth: ``(H, W, 1)`` float32 distance along the camera path to the first rough vertex,
            or ``None``.
        var_primal, var_dx, var_dy: ``(H, W, 1)`` float32 variance of the per-pixel mean
            (luminance-averaged over channels), or ``None``.
        primal_a, primal_b, albedo_a, ..., depth_b: the primal and features of two
            independent halves of the samples (same shapes as the full buffers), or ``None``;
            ``metadata["half_spp"]`` holds their sample counts.
        dx_a, dx_b, dy_a, dy_b: the gradients of the same two halves of the gradient samples
            (``(H, W, 3)``), or ``None``; they count ``metadata["gradient_half_spp"]`` samples
            when the primal was pooled (:func:`pool_primal`), else ``metadata["half_spp"]``.
        gradient_mask: ``(H, W, 2)`` bool, on the buffers' device: which gradients were traced
            (``[..., 0]``: ``dx``, ``[..., 1]``: ``dy``; the last column's ``dx`` and last row's
            ``dy`` are False), or ``None``: all of them (a render without a gradient mask,
            ``gdpt.render(..., gradient_mask=M)``). An untraced gradient is 0 in ``dx``/``dy``
            and their halves and ``inf`` in ``var_dx``/``var_dy``: no measurement, never read
            (:func:`fill_untraced`). Ignored where ``dx``/``dy`` are ``None``.
        spp: samples per pixel behind the estimate.
        metadata: free-form JSON-serialisable render information (integrator, seed, timings...).
    """

    primal: torch.Tensor
    dx: torch.Tensor | None = None
    dy: torch.Tensor | None = None
    albedo: torch.Tensor | None = None
    normal: torch.Tensor | None = None
    depth: torch.Tensor | None = None
    var_primal: torch.Tensor | None = None
    var_dx: torch.Tensor | None = None
    var_dy: torch.Tensor | None = None
    primal_a: torch.Tensor | None = None
    primal_b: torch.Tensor | None = None
    albedo_a: torch.Tensor | None = None
    albedo_b: torch.Tensor | None = None
    normal_a: torch.Tensor | None = None
    normal_b: torch.Tensor | None = None
    depth_a: torch.Tensor | None = None
    depth_b: torch.Tensor | None = None
    dx_a: torch.Tensor | None = None
    dx_b: torch.Tensor | None = None
    dy_a: torch.Tensor | None = None
    dy_b: torch.Tensor | None = None
    gradient_mask: torch.Tensor | None = None
    spp: int = 0
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.validate()

    # ------------------------------------------------------------------ queries
    @property
    def height(self) -> int:
        return int(self.primal.shape[0])

    @property
    def width(self) -> int:
        return int(self.primal.shape[1])

    @property
    def device(self) -> torch.device:
        return self.primal.device

    @property
    def has_gradients(self) -> bool:
        return self.dx is not None and self.dy is not None

    @property
    def has_halves(self) -> bool:
        return self.primal_a is not None and self.primal_b is not None

    @property
    def has_gradient_halves(self) -> bool:
        return all(getattr(self, n) is not None for n in GRADIENT_HALVES)

    def half(self, which: str) -> GradientBuffers:
        """Half ``which`` (``'a'`` or ``'b'``) as buffers of its own: its primal and features
        (the full render's where the half has none), no gradients, no variances;
        ``spp`` and ``metadata["primal_spp"]`` are the half's sample count.

        Raises:
            ValueError: ``which`` is not ``'a'``/``'b'``, or the render has no half-buffers
                (render with ``halves=True``).
        """
        if which not in ("a", "b"):
            raise ValueError(f"half must be 'a' or 'b', got {which!r}")
        if not self.has_halves:
            raise ValueError(
                "these buffers have no half-buffers 'primal_a'/'primal_b'; render with "
                "halves=True (gdpt render --halves)"
            )
        half_spp = self.metadata.get("half_spp", (0, 0))[0 if which == "a" else 1]
        if half_spp < 1:
            raise ValueError(
                f"half {which!r} of these buffers has no samples (half_spp "
                f"{self.metadata.get('half_spp')}); render at least 2 spp"
            )
        fields = {
            n: getattr(self, f"{n}_{which}")
            if getattr(self, f"{n}_{which}") is not None
            else getattr(self, n)
            for n in HALVED
        }
        metadata = {**self.metadata, "primal_spp": int(half_spp), "half": which}
        return GradientBuffers(**fields, spp=int(half_spp), metadata=metadata)

    def present(self) -> list[str]:
        """Names of the buffers that are set, in :data:`CHANNELS` order."""
        return [name for name in CHANNELS if getattr(self, name) is not None]

    def items(self) -> list[tuple[str, torch.Tensor]]:
        """``(name, tensor)`` pairs of the buffers that are set, in :data:`CHANNELS` order."""
        return [(name, getattr(self, name)) for name in self.present()]

    def nonfinite_counts(self) -> dict[str, int]:
        """Number of NaN/Inf values per present buffer."""
        return {n: int((~torch.isfinite(t)).sum()) for n, t in self.items()}

    # ------------------------------------------------------------------ conversions
    def to(self, device: torch.device | str) -> GradientBuffers:
        """A copy with every buffer on ``device``."""
        moved = {n: t.to(device) for n, t in self.items()}
        if self.gradient_mask is not None:
            moved["gradient_mask"] = self.gradient_mask.to(device)
        return dataclasses.replace(self, **moved)

    def replace(self, **changes: Any) -> GradientBuffers:
        """A copy with some fields replaced (validated again)."""
        return dataclasses.replace(self, **changes)

    def crop(self, top: int, left: int, height: int, width: int) -> GradientBuffers:
        """The ``height x width`` window at ``(top, left)`` of every present buffer (clipped to
        the image), as views of the same tensors; the crop's last column has no ``dx`` and its
        last row no ``dy`` (``gradient_mask`` says so where the render has one)."""
        rows, cols = slice(top, top + height), slice(left, left + width)
        crop = {n: t[rows, cols] for n, t in self.items()}
        if self.gradient_mask is not None:
            crop["gradient_mask"] = self.gradient_mask[rows, cols].clone()
            crop["gradient_mask"][:, -1, 0] = False
            crop["gradient_mask"][-1, :, 1] = False
        return self.replace(**crop)

    def centre_crop(self, size: int) -> GradientBuffers:
        """The centre ``size x size`` pixels (each side at most ``size``) of every present
        buffer (:meth:`crop`); ``self`` where the image fits."""
        if self.height <= size and self.width <= size:
            return self
        y0, x0 = max(0, (self.height - size) // 2), max(0, (self.width - size) // 2)
        return self.crop(y0, x0, size, size)

    # ------------------------------------------------------------------ validation
    def validate(self) -> None:
        """Check shapes, dtypes and devices.

        Raises:
            TypeError: a buffer is not a float32 torch tensor.
            ValueError: a buffer has the wrong rank, channel count, size or device.
        """
        h = w = None
        device = None
        for name, t in self.items():
            if not isinstance(t, torch.Tensor):
                raise TypeError(f"buffer '{name}' must be a torch.Tensor, got {type(t).__name__}")
            if t.dtype != torch.float32:
                raise TypeError(f"buffer '{name}' must be float32, got {t.dtype}")
            c = CHANNELS[name]
            if t.dim() != 3 or t.shape[2] != c:
                raise ValueError(
                    f"buffer '{name}' must have shape (H, W, {c}), got {tuple(t.shape)}"
                )
            if h is None:
                h, w, device = t.shape[0], t.shape[1], t.device
            elif (t.shape[0], t.shape[1]) != (h, w):
                raise ValueError(
                    f"buffer '{name}' is {t.shape[0]}x{t.shape[1]} (HxW) but 'primal' is {h}x{w}"
                )
            elif t.device != device:
                raise ValueError(f"buffer '{name}' is on {t.device} but 'primal' is on {device}")
        if h == 0 or w == 0:
            raise ValueError(f"empty image: {h}x{w} (HxW)")
        if (self.dx is None) != (self.dy is None):
            raise ValueError("'dx' and 'dy' must be given together")
        for name in (*HALVED, "dx", "dy"):
            if (getattr(self, f"{name}_a") is None) != (getattr(self, f"{name}_b") is None):
                raise ValueError(f"'{name}_a' and '{name}_b' must be given together")
        mask = self.gradient_mask
        if mask is not None:
            expected = f"a bool tensor of shape (H, W, 2) = ({h}, {w}, 2) on {device}"
            if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
                raise TypeError(f"'gradient_mask' must be {expected}, got {type(mask).__name__}")
            if tuple(mask.shape) != (h, w, 2) or mask.device != device:
                raise ValueError(
                    f"'gradient_mask' must be {expected}, got {tuple(mask.shape)} on {mask.device}"
                )


#: Buffers that are per-pixel sample means and can be pooled across renders of one scene.
POOLED = ("primal", "albedo", "normal", "depth")
#: The feature buffers among them (a gradient render may leave them to the plain render).
FEATURES = ("albedo", "normal", "depth")


def pool_primal(gradient: GradientBuffers, primal_only: GradientBuffers) -> GradientBuffers:
    """Pool an independent primal-only render into a gradient-domain render.

    The primal and the features become the sample-weighted means of both renders, an unbiased
    estimate from ``gradient.spp + primal_only.spp`` samples; ``dx``, ``dy`` and their halves
    stay those of ``gradient``. Features that only ``primal_only`` has are taken from it as they
    are: the plain pass can supply them alone, which spares the gradient pass their cost.
    ``var_primal`` (variance of the mean) pools as ``(n_g^2 v_g + n_p^2 v_p) / (n_g + n_p)^2``.
    This is the input of a reconstruction that spends part of its sampling time on plain path
    samples (about 1x a ``path`` sample) and part on gradient samples (2-3x), see
    ``primal_spp_factor`` in :mod:`gdpt.methods`.

    Args:
        gradient: a render with ``dx``/``dy`` (``spp`` >= 1).
        primal_only: an independent render of the same scene and film without gradients, with
            the feature buffers of ``gradient`` (or more) and ``spp`` >= 1.

    Returns:
        A new :class:`GradientBuffers` on ``gradient.device`` with ``spp = gradient.spp``
        (the gradients' count) and ``metadata["primal_spp"]`` the pooled count (with halves,
        ``metadata["half_spp"]`` the pooled halves' counts and, with gradient halves,
        ``metadata["gradient_half_spp"]`` the gradient halves' counts);
        ``metadata["primal_only"]`` holds the second render's metadata, and
        ``metadata["render_seconds"]`` (when both have one) is the sum of both.

    Raises:
        ValueError: ``gradient`` has no gradients, ``primal_only`` has some, the sizes or
            devices differ, a buffer is present in one render only (features: in ``gradient``
            only), or an ``spp`` is < 1.
    """
    if not gradient.has_gradients:
        raise ValueError("pool_primal: the first render has no dx/dy (render it with gradients)")
    if primal_only.has_gradients:
        raise ValueError("pool_primal: the primal-only render has dx/dy; render it without")
    if (gradient.height, gradient.width) != (primal_only.height, primal_only.width):
        raise ValueError(
            f"pool_primal: renders of {gradient.width}x{gradient.height} and "
            f"{primal_only.width}x{primal_only.height} px cannot be pooled"
        )
    if gradient.device != primal_only.device:
        raise ValueError(
            f"pool_primal: renders on {gradient.device} and {primal_only.device} cannot be pooled"
        )
    n_g, n_p = gradient.spp, primal_only.spp
    if n_g < 1 or n_p < 1:
        raise ValueError(f"pool_primal: both renders need spp >= 1, got {n_g} and {n_p}")
    names = (*POOLED, "var_primal", "primal_a", *(f"{f}_a" for f in FEATURES))
    uneven = [
        n
        for n in names
        if (getattr(gradient, n) is None) != (getattr(primal_only, n) is None)
        and not (n.removesuffix("_a") in FEATURES and getattr(gradient, n) is None)
    ]
    if uneven:
        raise ValueError(
            f"pool_primal: {', '.join(uneven)} present in one render only; render both with "
            "the same features/variance settings"
        )
    w_g, w_p = n_g / (n_g + n_p), n_p / (n_g + n_p)
    pooled: dict[str, torch.Tensor] = {}
    for name in POOLED:
        a, b = getattr(gradient, name), getattr(primal_only, name)
        if a is not None:
            pooled[name] = w_g * a + w_p * b
        elif b is not None:
            pooled[name] = b
    if gradient.var_primal is not None:
        pooled["var_primal"] = w_g**2 * gradient.var_primal + w_p**2 * primal_only.var_primal
    if gradient.has_halves:
        (g_a, g_b), (p_a, p_b) = gradient.metadata["half_spp"], primal_only.metadata["half_spp"]
        for name in POOLED:
            for which, n_gh, n_ph in (("a", g_a, p_a), ("b", g_b, p_b)):
                a = getattr(gradient, f"{name}_{which}")
                b = getattr(primal_only, f"{name}_{which}")
                if a is not None:
                    pooled[f"{name}_{which}"] = (n_gh * a + n_ph * b) / max(n_gh + n_ph, 1)
                elif b is not None:
                    pooled[f"{name}_{which}"] = b
    metadata = {**gradient.metadata, "primal_spp": n_g + n_p, "primal_only": primal_only.metadata}
    if gradient.has_halves:
        metadata["half_spp"] = [g_a + p_a, g_b + p_b]
        if gradient.has_gradient_halves:
            metadata["gradient_half_spp"] = [g_a, g_b]
    seconds = [b.metadata.get("render_seconds") for b in (gradient, primal_only)]
    if None not in seconds:
        metadata["render_seconds"] = sum(seconds)
    return gradient.replace(**pooled, metadata=metadata)


def gradient_half_count(buffers: GradientBuffers) -> tuple[int, int]:
    """Samples per pixel behind the gradient halves ``dx_a``/``dy_a`` and ``dx_b``/``dy_b``:
    ``metadata["gradient_half_spp"]`` of a pooled or merged render, else ``half_spp``."""
    counts = buffers.metadata.get("gradient_half_spp", buffers.metadata.get("half_spp", (0, 0)))
    return int(counts[0]), int(counts[1])


def primal_count(buffers: GradientBuffers) -> int:
    """Samples per pixel behind ``buffers.primal``: the pooled count of a pooled render
    (``metadata["primal_spp"]``), else ``spp``."""
    return int(buffers.metadata.get("primal_spp") or buffers.spp)


def _traced(buffers: GradientBuffers, exists_only: bool = False) -> torch.Tensor:
    """``(H, W, 2)`` bool: the gradients ``buffers`` traced (all without a gradient mask; with
    ``exists_only``, the last column's ``dx`` and last row's ``dy``, which do not exist, are
    left out then)."""
    if buffers.gradient_mask is not None:
        return buffers.gradient_mask
    out = torch.ones((buffers.height, buffers.width, 2), dtype=torch.bool, device=buffers.device)
    if exists_only:
        out[:, -1, 0] = False
        out[-1, :, 1] = False
    return out


def _pool_traced(
    fields: dict[str, torch.Tensor],
    group: Sequence[GradientBuffers],
    traced: Sequence[torch.Tensor],
    axis: int,
    weights: Sequence[float],
    name: str,
    variance: str | None = None,
) -> None:
    """Set ``fields[name]`` to the mean of ``name`` over the renders of ``group`` that traced
    each gradient (``traced[i][..., axis]``), render ``i`` weighted by ``weights[i]``, and
    ``fields[variance]`` to the variance of that mean (``inf`` where none traced it); ``0``
    where none traced it. Left out where a render of ``group`` lacks the buffer."""
    if not group or any(getattr(r, name) is None for r in group):
        return
    w = [wi * t[..., axis : axis + 1].float() for wi, t in zip(weights, traced, strict=True)]
    total = sum(w)
    share = [wi / total.clamp_min(1e-30) for wi in w]
    fields[name] = sum(
        torch.where(si > 0, getattr(r, name), 0.0) * si for r, si in zip(group, share, strict=True)
    )
    if variance is not None and all(getattr(r, variance) is not None for r in group):
        pooled = sum(
            torch.where(si > 0, getattr(r, variance), 0.0) * si.square()
            for r, si in zip(group, share, strict=True)
        )
        fields[variance] = torch.where(total > 0, pooled, torch.inf)


def merge_renders(renders: Sequence[GradientBuffers]) -> GradientBuffers:
    """Merge independent renders of one scene and film into the render of all their samples.

    The primal, the features (:data:`POOLED`) and ``var_primal`` become sample-weighted means
    over every render (:func:`primal_count` samples each); ``dx``/``dy`` and their variances
    gradient by gradient over the renders that traced it (``spp`` samples each, its
    ``gradient_mask``); a variance of a mean pools as ``sum(w_i^2 v_i)``. A buffer some render
    lacks is left out, except that gradients come from the renders that have them; the
    half-buffers pool half by half (``metadata["half_spp"]``) when every render has them, and
    the gradient halves likewise (``metadata["gradient_half_spp"]``). Renders with different
    gradient masks merge when every gradient traced by any of them ends with the same sample
    count (the same mask, or disjoint masks of equal ``spp``: a render completed where another
    traced no offsets); a gradient none traced stays untraced.

    Args:
        renders: at least one render, same size and device, seeds independent.

    Returns:
        New buffers: ``spp`` the gradient samples of each traced gradient when any render has
        gradients (their sum where none was traced; with ``metadata["primal_spp"]`` the
        primal's count), else the primal's count; ``gradient_mask`` the gradients any render
        traced (``None``: all); ``metadata`` that of the last render plus ``merged_spp`` (each
        render's primal count) and ``render_seconds`` summed where every render has one.

    Raises:
        ValueError: no renders, their sizes or devices differ, or the gradients traced end
            with different sample counts.
    """
    if not renders:
        raise ValueError("merge_renders: no renders")
    shapes = {(r.height, r.width, str(r.device)) for r in renders}
    if len(shapes) > 1:
        raise ValueError(f"merge_renders: renders of different sizes or devices: {shapes}")
    counts = [primal_count(r) for r in renders]
    gradient = [r for r in renders if r.has_gradients]
    fields: dict[str, torch.Tensor] = {}
    traced = [_traced(r) for r in gradient]
    pair_spp = sum(r.spp * t for r, t in zip(gradient, traced, strict=True)) if gradient else None
    if gradient:
        exists = _traced(gradient[0].replace(gradient_mask=None), exists_only=True)
        ends = torch.unique(pair_spp[(pair_spp > 0) & exists])
        if ends.numel() > 1:
            raise ValueError(
                "merge_renders: the traced gradients would end with different sample counts "
                f"({', '.join(str(int(n)) for n in ends)}); merge renders of one gradient mask, "
                "or of disjoint masks and equal spp"
            )
        if any(r.gradient_mask is not None for r in gradient):
            fields["gradient_mask"] = pair_spp > 0

    def mean(group: Sequence[GradientBuffers], weights: Sequence[float], name: str) -> None:
        if group and all(getattr(r, name) is not None for r in group) and sum(weights) > 0:
            share = [w / sum(weights) for w in weights]
            fields[name] = sum(s * getattr(r, name) for r, s in zip(group, share, strict=True))

    def pooled_variance(
        group: Sequence[GradientBuffers], weights: Sequence[float], name: str
    ) -> None:
        if group and all(getattr(r, name) is not None for r in group) and sum(weights) > 0:
            share = [w / sum(weights) for w in weights]
            fields[name] = sum(s * s * getattr(r, name) for r, s in zip(group, share, strict=True))

    for name in POOLED:
        mean(renders, counts, name)
    pooled_variance(renders, counts, "var_primal")
    for axis, name in enumerate(("dx", "dy")):
        _pool_traced(fields, gradient, traced, axis, [r.spp for r in gradient], name, f"var_{name}")
    metadata = {**renders[-1].metadata, "merged_spp": counts}
    if all(r.has_halves for r in renders):
        half_spp = [[int(n) for n in r.metadata["half_spp"]] for r in renders]
        for name in POOLED:
            for side, which in enumerate("ab"):
                mean(renders, [max(h[side], 0) for h in half_spp], f"{name}_{which}")
        metadata["half_spp"] = [sum(h[0] for h in half_spp), sum(h[1] for h in half_spp)]
    else:
        metadata.pop("half_spp", None)
    metadata.pop("gradient_half_spp", None)
    if gradient and all(r.has_gradient_halves for r in gradient):
        half_spp = [gradient_half_count(r) for r in gradient]
        for axis, name in enumerate(("dx", "dy")):
            for side, which in enumerate("ab"):
                weights = [max(h[side], 0) for h in half_spp]
                _pool_traced(fields, gradient, traced, axis, weights, f"{name}_{which}")
        metadata["gradient_half_spp"] = [
            int(sum(h[side] * t for h, t in zip(half_spp, traced, strict=True)).max())
            for side in (0, 1)
        ]
    seconds = [r.metadata.get("render_seconds") for r in renders]
    if None not in seconds:
        metadata["render_seconds"] = sum(seconds)
    if gradient:
        metadata["primal_spp"] = sum(counts)
        traced_any = bool((pair_spp > 0).any())  # (none traced: the renders' gradient spp)
        spp = int(pair_spp.max()) if traced_any else sum(r.spp for r in gradient)
    else:
        metadata.pop("primal_spp", None)
        spp = sum(counts)
    return GradientBuffers(**fields, spp=spp, metadata=metadata)


def fill_untraced(
    buffers: GradientBuffers, dx: float | torch.Tensor, dy: float | torch.Tensor
) -> GradientBuffers:
    """``buffers`` with every untraced gradient (``gradient_mask`` False) replaced: ``dx``/``dy``
    and their halves by ``dx``/``dy`` (a number or a tensor broadcastable to ``(H, W, 3)``),
    ``var_dx``/``var_dy`` by ``inf``; the mask dropped. ``buffers`` itself when every gradient
    was traced or there are none. How a reader skips untraced gradients: NaN for the Poisson
    solvers (missing constraints), 0 with infinite variance for ``fuse`` (zero weight)."""
    mask = buffers.gradient_mask
    if mask is None or not buffers.has_gradients:
        return buffers
    traced = {"dx": mask[..., 0:1], "dy": mask[..., 1:2]}
    fills = {"dx": dx, "dy": dy}
    changes: dict[str, Any] = {"gradient_mask": None}
    for axis in ("dx", "dy"):
        for name in (axis, f"{axis}_a", f"{axis}_b"):
            if (t := getattr(buffers, name)) is not None:
                fill = torch.as_tensor(fills[axis], dtype=t.dtype, device=t.device)
                changes[name] = torch.where(traced[axis], t, fill)
        if (v := getattr(buffers, f"var_{axis}")) is not None:
            changes[f"var_{axis}"] = torch.where(traced[axis], v, torch.inf)
    return buffers.replace(**changes)
