"""Which method pays on *this* scene at *this* budget, without a reference: :func:`advise`.

The candidate methods (study methods of :data:`gdpt.study.methods.EVAL_METHODS`, default
:data:`DEFAULT_METHODS`) get the same wall time on this machine through the study's
cost models (:func:`gdpt.study.calibration.configuration_model`: probed once per scene,
resolution and configuration in a process, up to :data:`gdpt.pipeline.PROBE_FRACTION` of the
budget as ``render_and_denoise(seconds=...)``, refined by each render; shared by methods that
render the same configuration), each renders once per replicate, and one independent plain
render ``P`` per replicate (two folds of two halves: its per-pixel variance and weights)
scores them: the relMSE ratio of each method to the first, with a 95% Fieller interval, from
the reference-free estimator of :mod:`gdpt.reconstruct.reference_free` (``P``'s four
independent quarters scored against in all six pairs, each pair's terms weighted like relMSE by
the other two quarters: unbiased denominators, alike for every method; standard errors from
8 px block sums, replicates pooled)::

    import gdpt

    advice = gdpt.advise("scene.xml", budget=4.0, box_filter=True)
    print(advice)                 # the report, one line per method, then "recommended: ..."
    advice.recommended            # a study method name, e.g. "gdpt+fuse"

Candidates that render the same samples and differ only in their reconstruction
(``pt+oidn-tuned`` and ``pt+oidn``) share one calibration of the render: the later ones take its
seconds per sample and its fixed seconds shifted by the difference of their reconstructions'
seconds (each the median of 3 runs at 1 spp, :meth:`gdpt.cost_model.TimeModel.shifted`),
instead of a calibration of their own (2-3 budgets each, the untimed warm-up renders included).

``P``'s sample count: the plain samples that fill ``plain_budget`` seconds, to three
significant bits (:func:`gdpt.study.estimate.few_pass_sizes`; default: the candidates'
budget, so ``P`` costs about as much as one candidate; with ``spp``, ``plain_spp`` defaults
to that count), at the cost per sample of the first candidate that renders plain
samples (``P`` renders no features and reconstructs nothing, so it takes a little less than
``plain_budget``); only where no candidate renders plain samples is ``pt`` calibrated for it.
``P``'s noise adds to a difference's variance in proportion to ``1 / n``
(:func:`gdpt.reconstruct.reference_free.plain_share`, measured from ``P``'s folds and reported
per method): where it is more than half of it, a larger ``plain_budget`` tightens the interval
most; else more ``replicates`` (each renders every method and ``P`` again).

Bad input fails with a ``ValueError`` of one line before any render (``spp`` and ``budget``
together, an unknown or unavailable method, a scene that does not load), or after the
calibration and before the scored renders (a budget too small for one sample of a method,
named; a ``P`` of fewer than 4 samples, whose folds' variances and weights cannot be
measured). Where the estimator cannot tell (``P`` black or nearly black, non-finite renders,
intervals that include 1, a difference carried by a handful of lit 8 px blocks,
:attr:`~gdpt.reconstruct.reference_free.RatioEstimate.concentrated`), the report says so in one
line each and recommends nothing on it.
"""

from __future__ import annotations

import math
import os
import statistics
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from gdpt.advice_report import MethodAdvice, method_line, recommend, render_command

if TYPE_CHECKING:
    import torch

    from gdpt.cost_model import TimeModel
    from gdpt.seconds_bar import StageBars
    from gdpt.study.methods import EvalMethod
    from gdpt.study.scenes import EvalScene

__all__ = ["DEFAULT_BUDGET", "DEFAULT_METHODS", "Advice", "MethodAdvice", "advise"]

#: The candidates of :func:`advise`, the first the baseline of every ratio.
DEFAULT_METHODS = ("pt+oidn-tuned", "gdpt+fuse", "pt+oidn")

#: Seconds per method when neither ``budget`` nor ``spp`` is given.
DEFAULT_BUDGET = 4.0

#: ``P`` is nearly black when fewer than this share of its pixels are brighter than
#: ``sqrt(eps)`` (where the relMSE weight is half its largest value).
BRIGHT_SHARE = 0.01


@dataclass
class Advice:
    """What :func:`advise` found.

    Attributes:
        scene: the scene argument.
        resolution: the film's ``(width, height)``.
        max_depth: the longest path rendered.
        budget: seconds per method (``None``: an equal ``spp``).
        methods: the candidates, the baseline first.
        plain_spp: samples per pixel of each plain render ``P``.
        replicates: renders of every method (and ``P``).
        recommended: the recommended study method, ``None`` where nothing can be told.
        lines: the report, one line each (``str(advice)``).
        seconds: wall time of the whole call.
        command: a command that renders the recommended method (``None``: none).
        images: each method's outputs, one per replicate: ``(H, W, 3)`` float32 linear
            radiance on the CPU (empty where the plain render stopped it).
        plains: each plain render ``P`` that scored them, one per replicate
            (:func:`gdpt.study.estimate.plain_render`: ``image``, ``variance`` ``(H, W, 1)``,
            ``counts``, ``folds``).
        calibrations: per candidate, how its sample count was found: ``"calibrated"``
            (probed now), ``"model"`` (the configuration's cost model kept in this process,
            :func:`gdpt.study.calibration.configuration_model`), ``"shared with NAME"`` (the
            same render, its reconstruction timed apart) or ``"spp"`` (given); and ``"P"``:
            the same for ``P``.
        plain_budget: seconds of each ``P`` (``None`` with ``spp``).
        models: the cost model of each candidate timed for its own configuration, refined by
            its renders here.
        stage_seconds: wall seconds of ``calibration``, ``renders`` (the candidates'),
            ``plain`` (``P``) and ``other`` (loading, the rest).
    """

    scene: str
    resolution: tuple[int, int]
    max_depth: int
    budget: float | None
    methods: list[MethodAdvice]
    plain_spp: int
    replicates: int
    recommended: str | None = None
    lines: list[str] = field(default_factory=list)
    seconds: float = 0.0
    command: str | None = None
    images: dict[str, list[torch.Tensor]] = field(default_factory=dict)
    plains: list[dict[str, Any]] = field(default_factory=list)
    calibrations: dict[str, str] = field(default_factory=dict)
    plain_budget: float | None = None
    models: dict[str, TimeModel] = field(default_factory=dict)
    stage_seconds: dict[str, float] = field(default_factory=dict)

    def __str__(self) -> str:
        return "\n".join(self.lines)


def _check_arguments(
    budget: float | None, spp: int | None, methods: tuple[str, ...], replicates: int
) -> tuple[float | None, list[str]]:
    """The budget (default :data:`DEFAULT_BUDGET` without ``spp``) and the current method
    names; ``ValueError`` (one line) for bad input."""
    from gdpt.study.methods import EVAL_METHODS

    if budget is not None and spp is not None:
        raise ValueError("give a time budget or a sample count (spp), not both")
    if spp is None:
        budget = DEFAULT_BUDGET if budget is None else budget
        if not (math.isfinite(budget) and budget > 0):
            raise ValueError(f"the budget must be a positive number of seconds, got {budget}")
    elif spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    if replicates < 1:
        raise ValueError(f"replicates must be >= 1, got {replicates}")
    EVAL_METHODS.check(methods)
    names = [EVAL_METHODS.resolve(m, stacklevel=3) for m in methods]
    if len(set(names)) < 2 or len(set(names)) != len(names):
        raise ValueError(f"give at least two different methods, got {', '.join(names)}")
    for name in names:
        if reason := EVAL_METHODS[name].check():
            raise ValueError(f"method {name} cannot run here: {reason}")
    return budget, names


def _load(scene: Any, long_side: int | None, box_filter: bool, max_depth: int | None):
    """The :class:`~gdpt.study.scenes.EvalScene` of ``scene`` (a source of
    :func:`gdpt.scenes.loading.read_scene`); ``ValueError`` where its film has no box filter
    and ``box_filter`` is off, ``FileNotFoundError``/``ValueError`` where it does not load."""
    from gdpt.scenes.loading import BOX_FILTER, choose_max_depth, read_scene
    from gdpt.study.scenes import EvalScene, resolve_scenes

    if long_side is not None and long_side < 1:
        raise ValueError(f"long_side must be >= 1, got {long_side}")
    if max_depth is not None and max_depth < -1:
        raise ValueError(f"max_depth must be -1 (unbounded) or >= 0, got {max_depth}")
    loaded = read_scene(scene, box_filter=box_filter, long_side=long_side)
    if loaded.original_filter != BOX_FILTER and not box_filter:
        raise ValueError(
            f"{scene}: the film's pixel filter is '{loaded.original_filter}', gradient-domain "
            "rendering needs a box filter: add --box-filter (box_filter=True) to replace it"
        )
    depth, note = choose_max_depth(max_depth, loaded.max_depth)
    name = resolve_scenes([scene])[0].name if isinstance(scene, (str, os.PathLike)) else "scene"
    return EvalScene(name, loaded.scene, depth, loaded.resolution, [*loaded.notes, note])


def _render_and_score(
    advice: Advice, scene: EvalScene, candidates: list, seed: int, stages: StageBars
) -> None:
    """Render ``P`` and the candidates per replicate, score them and fill ``advice.lines`` and
    ``advice.recommended`` (stops after ``P`` where ``P`` is unusable: one line why)."""
    import torch

    from gdpt.reconstruct.held_out import EPS
    from gdpt.study.estimate import estimate_ratios, plain_render
    from gdpt.study.results import cell_seed, replicate_seed

    budget = f"{advice.budget:g} s each" if advice.budget is not None else "equal spp"
    width, height = scene.resolution
    advice.lines.append(
        f"advise {advice.scene}: {len(candidates)} methods at {budget} ({width}x{height}, "
        f"max_depth {scene.max_depth}), {advice.replicates} replicate(s); P: "
        f"{advice.plain_spp} plain spp"
    )
    plains = []
    for r in range(advice.replicates):
        with stages("plain", f"plain render P {r + 1}/{advice.replicates}", advice.plain_budget):
            plain = plain_render(
                scene, advice.plain_spp, cell_seed(seed, scene.name, "advise-plain", str(r))
            )
        bad = int((~torch.isfinite(plain["image"])).any(-1).sum())
        bright = float((plain["image"].mean(-1) > math.sqrt(EPS)).float().mean())
        if bad:
            advice.lines.append(
                f"cannot tell: P has {bad} non-finite pixels (the scene or its lights)"
            )
        elif bright < BRIGHT_SHARE:
            advice.lines.append(
                f"cannot tell: the image is black or nearly black ({bright:.1%} of P's pixels "
                f"above {math.sqrt(EPS):.3f}): relative errors mean nothing there"
            )
        if bad or bright < BRIGHT_SHARE:
            advice.lines.append("recommended: none (nothing to compare)")
            return
        plains.append(plain)
    advice.plains = plains
    images: list[list[torch.Tensor]] = [[] for _ in candidates]
    for r in range(advice.replicates):
        for m, (method, record) in enumerate(zip(candidates, advice.methods, strict=True)):
            label = f"{method.name} {r + 1}/{advice.replicates} ({record.spp} spp)"
            with stages("renders", label, advice.budget):
                result = method.run(
                    scene, spp=record.spp, seed=replicate_seed(seed, scene.name, "advise", r)
                )
            model = advice.models.get(method.name)
            if model is not None and not result.recorded:  # (a recording is not the samples')
                model.update(record.spp, result.seconds)  # every timed run refines its model
            record.seconds.append(result.seconds)
            record.recorded.append(result.recorded)
            images[m].append(result.image)
            advice.images.setdefault(method.name, []).append(result.image)
            bad = int((~torch.isfinite(result.image)).any(-1).sum())
            if bad and record.note is None:
                record.note = f"{bad} non-finite pixels in its output (its error is infinite)"
    if advice.methods[0].note is not None:
        advice.lines.append(
            f"cannot tell: the baseline {advice.methods[0].name} has {advice.methods[0].note}"
        )
        advice.lines.append("recommended: none (no finite baseline)")
        return
    scored = [m for m, r in enumerate(advice.methods) if m == 0 or r.note is None]
    estimates = estimate_ratios([images[m] for m in scored], plains)
    for m, (estimate, share) in zip(scored[1:], estimates, strict=True):
        advice.methods[m].estimate, advice.methods[m].plain_share = estimate, share
    width = max(len(m.name) for m in advice.methods)
    advice.lines += [method_line(m, advice.methods[0].name, width) for m in advice.methods]
    advice.recommended, lines = recommend(advice.methods)
    advice.lines += lines
    unsure = [m for m in advice.methods[1:] if m.estimate is not None and not m.estimate.separated]
    if unsure:
        plain_heavy = any(m.plain_share > 0.5 for m in unsure)
        advice.lines.append(
            "to tighten: a larger plain budget (P's noise is most of the variance)"
            if plain_heavy
            else "to tighten: more replicates (the methods' own noise is most of the variance)"
        )


def _reconstruction_seconds(
    method: EvalMethod, scene: EvalScene, seed: int, repeats: int = 3
) -> float:
    """The median reconstruction seconds of ``repeats`` runs of ``method`` at 1 spp, after an
    untimed one (its reconstruction's first call: weights loaded, kernels compiled)."""
    method.run(scene, spp=1, seed=seed + repeats)
    return statistics.median(
        method.run(scene, spp=1, seed=seed + i).reconstruct_seconds for i in range(repeats)
    )


def _calibration_plan(
    candidates: list[EvalMethod], plain: bool
) -> tuple[dict[str, EvalMethod], dict[str, str], str | None]:
    """Which configurations :func:`advise` calibrates and which share another's render.

    Returns:
        ``(to_calibrate, shared, plain_key)``: ``to_calibrate`` maps a configuration key
        (:func:`~gdpt.study.calibration.configuration_key`, ``"total"``) to the method timed
        for it; ``shared`` maps the key of a candidate that renders what an earlier one
        renders, with another reconstruction, to that one's key (both can be split into render
        and reconstruction: :attr:`~gdpt.study.methods.EvalMethod.render`); ``plain_key``
        (with ``plain``: ``P``'s count is wanted): the key whose calibration gives ``P``'s
        count, the first candidate rendering plain samples, else ``pt``'s (added to
        ``to_calibrate``).
    """
    from gdpt.study.calibration import calibration_runner, configuration_key
    from gdpt.study.methods import EVAL_METHODS

    to_calibrate: dict[str, EvalMethod] = {}
    shared: dict[str, str] = {}
    by_render: dict[str, str] = {}  # render configuration -> the key calibrated for it
    for method in candidates:
        key = configuration_key(method, "total")
        if key in to_calibrate or key in shared:
            continue
        runner = calibration_runner(method, "total")
        render = configuration_key(runner, "render-time")
        if runner.render is not None and render in by_render:
            shared[key] = by_render[render]
            continue
        to_calibrate[key] = runner
        if runner.render is not None:
            by_render.setdefault(render, key)
    plain_key = None
    if plain:
        plain_key = next(
            (
                key
                for key, runner in to_calibrate.items()
                if runner.configuration is not None
                and runner.configuration().get("gradients") is False
            ),
            None,
        )
        if plain_key is None:
            plain_key = configuration_key(EVAL_METHODS["pt"], "total")
            to_calibrate.setdefault(plain_key, EVAL_METHODS["pt"])
    return to_calibrate, shared, plain_key


def advise(
    scene: Any,
    *,
    budget: float | None = None,
    spp: int | None = None,
    methods: tuple[str, ...] | list[str] = DEFAULT_METHODS,
    replicates: int = 1,
    plain_budget: float | None = None,
    plain_spp: int | None = None,
    long_side: int | None = None,
    box_filter: bool = False,
    max_depth: int | None = None,
    seed: int = 0,
    progress: bool = True,
) -> Advice:
    """Compare ``methods`` at equal time on ``scene`` without a reference (module docstring).

    Args:
        scene: an XML path, ``builtin:NAME`` or ``random:SEED[:VIEW]``
            (:func:`gdpt.scenes.loading.read_scene`).
        budget: seconds of sampling + reconstruction per method, calibrated on this machine
            (default :data:`DEFAULT_BUDGET` without ``spp``).
        spp: instead of ``budget``: every method renders this many samples per pixel.
        methods: study method names (:data:`gdpt.study.methods.EVAL_METHODS`), the first the
            baseline of every ratio.
        replicates: renders of every method and of ``P`` (their block sums pooled).
        plain_budget: seconds of plain path tracing in each ``P`` (default: ``budget``).
        plain_spp: ``P``'s samples per pixel instead (default with ``spp``: ``spp``).
        long_side: rescale the film to this many pixels on its long side.
        box_filter: replace an XML film's pixel filter by the box filter.
        max_depth: longest path (default: the scene's integrator setting, else 6).
        seed: base seed of the renders.
        progress: a progress bar in seconds per stage (stderr): each calibration (open-ended),
            each candidate's render against ``budget``, each ``P`` against ``plain_budget``.

    Returns:
        The :class:`Advice` (``str(advice)``: the report).

    Raises:
        ValueError: bad input (module docstring), one line.
        FileNotFoundError: the scene file does not exist.
    """
    import drjit as dr

    from gdpt.pipeline import PROBE_FRACTION
    from gdpt.seconds_bar import StageBars
    from gdpt.study.calibration import configuration_key, configuration_model
    from gdpt.study.cells import set_threads, thread_counts
    from gdpt.study.config import EvaluateConfig
    from gdpt.study.estimate import MIN_PLAIN_SPP, few_pass_sizes
    from gdpt.study.evaluate import set_threads_back
    from gdpt.study.methods import EVAL_METHODS
    from gdpt.study.results import cell_seed

    start = time.perf_counter()
    budget, names = _check_arguments(budget, spp, tuple(methods), replicates)
    if plain_budget is not None and plain_spp is not None:
        raise ValueError("give plain_budget or plain_spp, not both")
    loaded = _load(scene, long_side, box_filter, max_depth)
    candidates = [EVAL_METHODS[n] for n in names]
    to_calibrate: dict[str, EvalMethod] = {}
    shared: dict[str, str] = {}
    plain_key = None
    if budget is not None:
        to_calibrate, shared, plain_key = _calibration_plan(candidates, plain_spp is None)
    stages = StageBars(progress)
    history_flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    threads = thread_counts()  # the study's threads: torch's few (small tensors, busy cores)
    set_threads(threads["drjit"])
    try:
        models: dict[str, TimeModel] = {}
        sources: dict[str, str] = {}
        for key, runner in to_calibrate.items():  # the study's models: probed once per process
            with stages("calibration", f"calibration ({runner.name})"):
                models[key], sources[key] = configuration_model(
                    runner,
                    loaded,
                    key,
                    budget=budget,
                    seed=cell_seed(seed, loaded.name, runner.name, "calibration"),
                    probe_fraction=PROBE_FRACTION,  # as render_and_denoise(seconds=)
                )
        runners = {configuration_key(m, "total"): m for m in candidates}
        reconstruction: dict[str, float] = {}
        for key, base in shared.items():  # the same render: only the reconstruction timed
            with stages("calibration", f"timing {runners[key].name}'s reconstruction"):
                for k in (base, key):
                    if k not in reconstruction:
                        runner = to_calibrate.get(k, runners[k])
                        reconstruction[k] = _reconstruction_seconds(
                            runner, loaded, cell_seed(seed, loaded.name, runner.name, "reconstruct")
                        )
            models[key] = models[base].shifted(reconstruction[key] - reconstruction[base])
        for method in candidates:  # each candidate's one sample within the budget
            model = models.get(configuration_key(method, "total"))
            if model is not None and model.fixed + model.per_spp > budget * (
                1 + EvaluateConfig.tolerance
            ):
                raise ValueError(
                    f"a budget of {budget:g} s is too small for one sample of {method.name} "
                    f"(about {model.fixed + model.per_spp:.2f} s here); raise the budget or "
                    "lower the resolution (--long-side)"
                )
        if plain_spp is None:
            filled = spp or models[plain_key].spp_for(plain_budget or budget)
            plain_spp = filled if budget is None else few_pass_sizes(filled)
        calibrations = {"P": "given"}
        for m in candidates:
            key = configuration_key(m, "total")
            calibrations[m.name] = "spp" if budget is None else sources.get(key, "calibrated")
            if key in shared:
                calibrations[m.name] = f"shared with {runners[shared[key]].name}"
        if plain_key is not None:
            calibrations["P"] = (
                f"the cost per sample of {runners.get(plain_key, EVAL_METHODS['pt']).name}"
            )
        advice = Advice(
            str(scene),
            loaded.resolution,
            loaded.max_depth,
            budget,
            [
                MethodAdvice(m.name, spp or models[configuration_key(m, "total")].spp_for(budget))
                for m in candidates
            ],
            plain_spp,
            replicates,
            calibrations=calibrations,
            plain_budget=None if budget is None else plain_budget or budget,
            models={
                m.name: models[configuration_key(m, "total")]
                for m in candidates
                if configuration_key(m, "total") in to_calibrate
            },
        )
        if plain_spp < MIN_PLAIN_SPP:
            raise ValueError(
                f"P would have {plain_spp} sample{'s' if plain_spp != 1 else ''} per pixel: its "
                f"variance and weights cannot be measured; give a larger budget or plain_spp >= "
                f"{MIN_PLAIN_SPP}"
            )  # before any scored render (plain_render says the same)
        _render_and_score(advice, loaded, candidates, seed, stages)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, history_flag)
        set_threads_back(threads)
    advice.seconds = time.perf_counter() - start
    advice.stage_seconds = {
        **stages.seconds,
        "other": advice.seconds - sum(stages.seconds.values()),
    }
    options = {"long_side": long_side, "box_filter": box_filter, "max_depth": max_depth}
    if advice.recommended is not None:
        chosen = next(m for m in advice.methods if m.name == advice.recommended)
        advice.command = render_command(
            chosen.name, chosen.spp, scene, options, loaded.name, budget
        )
    spent = advice.stage_seconds
    advice.lines += [
        f"time: {advice.seconds:.1f} s "
        + (f"({advice.seconds / budget:.1f}x the {budget:g} s budget: " if budget else "(")
        + f"calibration {spent.get('calibration', 0.0):.1f} s, {replicates} x "
        f"{len(candidates)} renders {spent.get('renders', 0.0):.1f} s, {replicates} plain "
        f"render(s) P {spent.get('plain', 0.0):.1f} s, loading and the rest "
        f"{spent['other']:.1f} s)"
    ]
    if advice.command is not None:
        advice.lines.append(f"render it: {advice.command}")
    return advice
