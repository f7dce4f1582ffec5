"""The report of :func:`gdpt.advice.advise`: what it found per candidate (:class:`MethodAdvice`),
one line per candidate (:func:`method_line`), the recommendation and the lines that say why
(:func:`recommend`), and the ``gdpt`` command that renders the recommended method
(:func:`render_command`)."""

from __future__ import annotations

import math
import shlex
import statistics
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from gdpt.reconstruct.reference_free import RatioEstimate

__all__ = ["MethodAdvice", "method_line", "recommend", "render_command"]


@dataclass
class MethodAdvice:
    """One candidate of :func:`gdpt.advice.advise`.

    Attributes:
        name: study method name (:data:`gdpt.study.methods.EVAL_METHODS`).
        spp: its samples per pixel (calibrated to the budget, or the given ``spp``).
        seconds: its measured seconds per replicate (kernel compilation excluded, as in the
            study; the first render at a sample count also records its frozen passes).
        recorded: per replicate, whether its render recorded frozen passes (its seconds then
            hold their tracing).
        estimate: its relMSE ratio to the first method (``None`` for the first, or where it
            cannot be estimated: :attr:`note`).
        plain_share: share of the ratio's variance that ``P``'s noise makes up (``nan``:
            not measured).
        note: why it has no estimate, else ``None``.
    """

    name: str
    spp: int
    seconds: list[float] = field(default_factory=list)
    recorded: list[bool] = field(default_factory=list)
    estimate: RatioEstimate | None = None
    plain_share: float = math.nan
    note: str | None = None


def method_line(method: MethodAdvice, base: str, width: int) -> str:
    """``method``'s line of the report (its name padded to ``width``): its samples per pixel,
    its seconds (the mean over its renders that replayed their frozen passes; where every one
    recorded them, over all, and the line says so) and its relMSE ratio to ``base`` with the
    95% interval and what it means, or why it cannot tell."""
    replayed = [s for s, r in zip(method.seconds, method.recorded, strict=True) if not r]
    timed = replayed or method.seconds  # a recording's seconds hold its tracing
    seconds = statistics.fmean(timed) if timed else 0.0
    said = " (with pass recording)" if timed and not replayed else ""
    head = f"  {method.name:<{width}}  spp {method.spp:>6}  {seconds:6.2f} s{said}"
    if method.name == base:
        return f"{head}  1.00 (the baseline)"
    if method.estimate is None:
        return f"{head}  cannot tell: {method.note}"
    e = method.estimate
    if not e.bounded:
        return f"{head}  cannot tell: {base}'s estimated error is not separated from 0"
    if e.concentrated:
        return (
            f"{head}  cannot tell: {e.ratio:.2f}, but a handful of pixels carry the difference "
            f"(P is lit in {e.lit} of {e.blocks} blocks of 8 px)"
        )
    verdict = (
        ("lower: separated from 1" if e.high < 1 else "higher: separated from 1")
        if e.separated
        else "includes 1: no measurable difference"
    )
    share = (
        f", P's noise {e_share:.0%} of its variance"
        if math.isfinite(e_share := method.plain_share)
        else ""
    )
    return f"{head}  {e.ratio:.2f} [{e.low:.2f}, {e.high:.2f}] {verdict} (z {e.z:+.1f}{share})"


def recommend(methods: list[MethodAdvice]) -> tuple[str | None, list[str]]:
    """The recommended method and the lines that say why (the last starts ``recommended:``)."""
    base = methods[0].name
    scored = [m for m in methods[1:] if m.estimate is not None]
    better = [m for m in scored if m.estimate.separated and m.estimate.high < 1.0]
    if better:
        best = min(better, key=lambda m: m.estimate.ratio)
        e = best.estimate
        return best.name, [
            f"recommended: {best.name} ({e.ratio:.2f}x {base}'s relMSE, 95% interval "
            f"{e.low:.2f}-{e.high:.2f})"
        ]
    lines = []
    unsure = [m.name for m in scored if not m.estimate.separated]
    told = [m.name for m in scored if m.estimate.bounded and not m.estimate.concentrated]
    if unsure:
        why = "the interval includes 1" + ("" if set(unsure) <= set(told) else ", or cannot tell")
        lines.append(f"no measurable difference between {base} and {', '.join(unsure)} ({why})")
    if not scored:
        return None, [f"recommended: none (no method could be compared with {base})"]
    why = "no other method is measurably better" if unsure else "every other method is worse"
    return base, [*lines, f"recommended: {base} ({why})"]


def render_command(
    name: str, spp: int, scene: Any, options: dict[str, Any], out_name: str, budget: float | None
) -> str | None:
    """The ``gdpt`` command that renders study method ``name`` at ``spp``, or in ``budget``
    seconds (``--time``) where one was given and the command takes it (``None``: none)."""
    from gdpt.methods import METHODS

    sampler, _, method = name.partition("+")
    if name == "pt":
        words = ["gdpt", "render", str(scene), "--no-gradients"]
    elif name == "auto" or (sampler in ("pt", "gdpt") and method in METHODS):
        words = ["gdpt", "render-and-denoise", str(scene), "--method", method or name]
        if budget is not None:
            words += ["--time", f"{budget:g}"]
    else:
        return None
    words += [] if "--time" in words else ["--spp", str(spp)]
    for option in ("long_side", "max_depth"):
        if options[option] is not None:
            words += [f"--{option.replace('_', '-')}", str(options[option])]
    words += ["--box-filter"] if options["box_filter"] else []
    return shlex.join([*words, "-o", f"out/{out_name}-{method or name}.exr"])
