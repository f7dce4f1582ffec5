"""Reports on trained reconstruction networks: training curves, the held-out comparison, shipping.

* :func:`plot_training`: training loss and validation relMSE / FLIP over wall-clock time of
  one or more ``gdpt train`` run directories (PNG).
* :func:`compare_models`: every held-out crop and input level of a dataset reconstructed by each
  network (16-channel networks read the G-PT input ``in<k>``, 10-channel ones the path-traced
  input ``pt<k>`` rendered with 2.5x the samples unless their card says they were trained on
  another: :func:`input_kind`), by L1 screened Poisson on ``in<k>`` and, when
  ``mitsuba-oidn`` is installed, by OIDN on ``pt<k>``; mean relMSE and LDR-FLIP per input level,
  with the measured render times of both inputs from the dataset manifest (so the equal-time
  claim of the 2.5x rule can be checked) and the measured reconstruction times.
* :func:`ship_model`: copy a run's final network into ``gdpt/models/<name>`` with a model card
  (data, steps, wall time, the comparison numbers).
* :func:`write_report`: all of these into a report folder (``gdpt model-report --data DIR --run
  oidn-grad=RUN --run oidn-tuned=RUN --out DIR``).
"""

from __future__ import annotations

import json
import math
import statistics
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from gdpt.statistics import mean_interval
from gdpt.training.dataset import CropDataset
from gdpt.training.run_dir import read_jsonl

#: Largest network (float32 weights) shipped inside the package.
MAX_SHIPPED_MIB = 20
#: Scene selection of the held-out set: the same rule as ``gdpt train --holdout-every``.
HOLDOUT_EVERY = 10
#: Labels of the baselines :func:`compare_models` scores beside the networks (``pt+oidn`` when
#: ``mitsuba-oidn`` is installed).
BASELINES = ("gdpt+l1", "pt+oidn", "pt")


def _smooth(values: list[float], window: int) -> list[float]:
    """Centred running mean of ``values`` over ``window`` entries (shorter at the ends)."""
    out, half = [], window // 2
    for i in range(len(values)):
        part = values[max(0, i - half) : i + half + 1]
        out.append(sum(part) / len(part))
    return out


def plot_training(runs: Mapping[str, str | Path], path: str | Path) -> Path:
    """Plot training loss and validation relMSE / FLIP against wall-clock hours.

    Args:
        runs: label -> ``gdpt train`` run directory (``log.jsonl``, ``val.jsonl``).
        path: the PNG to write (overwritten).

    Returns:
        ``path``.

    Raises:
        FileNotFoundError: a run has no ``log.jsonl``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for index, (label, run) in enumerate(runs.items()):
        log = read_jsonl(Path(run) / "log.jsonl")
        if not log:
            raise FileNotFoundError(f"{run}: no log.jsonl (not a gdpt train run directory?)")
        colour = f"C{index}"
        hours = [r["time"] / 3600 for r in log]
        axes[0].plot(hours, [r["loss"] for r in log], color=colour, alpha=0.15, lw=0.5)
        axes[0].plot(hours, _smooth([r["loss"] for r in log], 101), color=colour, label=label)
        val = read_jsonl(Path(run) / "val.jsonl")
        if val:
            vh = [r["time"] / 3600 for r in val]
            for ax, key in ((axes[1], "relmse"), (axes[2], "flip")):
                ax.plot(vh, [r[key] for r in val], "o-", ms=3, color=colour, label=label)
                if f"l1_{key}" not in val[-1]:  # e.g. a combiner: no L1 baseline of its own
                    continue
                ax.axhline(
                    val[-1][f"l1_{key}"],
                    color=colour,
                    ls="--",
                    lw=1,
                    label=f"L1 Poisson on the {label} validation inputs",
                )
    axes[0].set(
        title="training loss (101-step running mean)", xlabel="wall-clock hours", ylabel="loss"
    )
    axes[1].set(title="validation relMSE", xlabel="wall-clock hours", yscale="log")
    axes[2].set(title="validation LDR-FLIP", xlabel="wall-clock hours")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def _timed(fn: Any, *args: Any) -> tuple[torch.Tensor, float]:
    start = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - start


def input_kind(reconstructor: Any) -> str:
    """The dataset input kind a reconstructor reads: the one its card says it was trained on
    (``training.input``: a no-gradient network fine-tuned on the G-PT primal reads ``"gdpt"``),
    else ``"pool"`` when its card pools plain path samples into the primal
    (``sampling.primal_spp_factor``), else ``"gdpt"`` with gradients, else ``"pt-variance"``
    with the primal's variance (KPCN), else ``"pt"``."""
    card = getattr(reconstructor, "card", {}) or {}
    if trained := card.get("training", {}).get("input"):
        return trained
    if card.get("sampling", {}).get("primal_spp_factor"):
        return "pool"
    if "dx" in reconstructor.features:
        return "gdpt"
    return "pt-variance" if "var_primal" in reconstructor.features else "pt"


def compare_models(
    data: str | Path,
    models: Mapping[str, str | Path],
    *,
    holdout_every: int = HOLDOUT_EVERY,
    progress: bool = True,
) -> dict[str, Any]:
    """Score networks and baselines on the held-out crops of a dataset.

    Args:
        data: ``gdpt dataset`` directory; scenes with ``index % holdout_every ==
            holdout_every - 1`` are the held-out set (never trained on with the same rule).
        models: method label -> checkpoint (``.safetensors``); the input kind follows the
            network's input channels and card (:func:`input_kind`; a pooled network reads the
            G-PT input with the path-traced input of the same level pooled in, i.e. the render
            time of both).
        holdout_every: see ``data``.
        progress: show a progress bar.

    Returns:
        ``{"crops": n, "resolution": [w, h], "levels": [{"spp", "pt_spp", "render_seconds":
        {"gdpt", "pt"}, "methods": {label: {"relmse", "flip", "seconds"}}}], "mean": {label:
        {...}}, "elements": {"level": [...], label: {"relmse": [...], "flip": [...]}}}`` where
        every number of ``levels`` and ``mean`` is a mean over the held-out crops; ``seconds``
        is the reconstruction time; ``elements`` holds every held-out element's scores in one
        order for all labels (paired comparisons: :func:`paired_comparison`).
    """
    from tqdm.auto import tqdm

    from gdpt.checkpoints import load_reconstructor
    from gdpt.metrics import flip_ldr, relmse
    from gdpt.oidn import oidn_check, oidn_denoise
    from gdpt.reconstruct.poisson import solve as poisson

    held = lambda s: s % holdout_every == holdout_every - 1  # noqa: E731
    nets = {}
    for label, path in models.items():
        rec = load_reconstructor(Path(path).resolve())
        nets[label] = (rec, input_kind(rec))
    kinds = ("gdpt", "pt", *sorted({kind for _, kind in nets.values()} - {"gdpt", "pt"}))
    sets = {kind: CropDataset(data, kind=kind, scenes=held) for kind in kinds}
    methods: dict[str, tuple[str, Any]] = {
        label: (kind, rec) for label, (rec, kind) in nets.items()
    }
    methods["gdpt+l1"] = (
        "gdpt",
        lambda b: poisson(b["primal"], b["dx"], b["dy"], solver="l1", alpha=0.2),
    )
    if oidn_check() is None:
        methods["pt+oidn"] = ("pt", lambda b: oidn_denoise(b["primal"], b["albedo"], b["normal"]))
    methods["pt"] = ("pt", lambda b: b["primal"])

    gdpt_set = sets["gdpt"]
    levels = gdpt_set.levels
    scores: list[dict[str, list[float]]] = [{} for _ in range(levels)]
    elements: dict[str, Any] = {"level": []}
    bar = tqdm(total=len(gdpt_set), unit="element", desc="compare", disable=not progress)
    for index in range(len(gdpt_set)):
        record, level = gdpt_set.element(index)
        items = {kind: sets[kind].load(index) for kind in sets}
        target = items["gdpt"]["target"]
        bucket = scores[level]
        bucket.setdefault("spp", []).append(record["spp"][level])
        bucket.setdefault("pt_spp", []).append(record["pt_spp"][level])
        seconds = record["render_seconds"]
        elements["level"].append(level)
        bucket.setdefault("render_gdpt", []).append(seconds[f"in{level}"])
        bucket.setdefault("render_pt", []).append(seconds[f"pt{level}"])
        for label, (kind, fn) in methods.items():
            with torch.no_grad():
                image, took = _timed(fn, items[kind]["inputs"])
            scored = {"relmse": relmse(image, target), "flip": flip_ldr(image, target)}
            for metric, value in scored.items():
                bucket.setdefault(f"{label}/{metric}", []).append(value)
                elements.setdefault(label, {}).setdefault(metric, []).append(value)
            bucket.setdefault(f"{label}/seconds", []).append(took)
        bar.update(1)
    bar.close()

    def mean(values: list[float]) -> float:
        return float(statistics.fmean(values))

    out_levels = []
    for bucket in scores:
        out_levels.append(
            {
                "spp": mean(bucket["spp"]),
                "pt_spp": mean(bucket["pt_spp"]),
                "render_seconds": {
                    "gdpt": mean(bucket["render_gdpt"]),
                    "pt": mean(bucket["render_pt"]),
                },
                "methods": {
                    label: {m: mean(bucket[f"{label}/{m}"]) for m in ("relmse", "flip", "seconds")}
                    for label in methods
                },
            }
        )
    overall = {
        label: {
            m: mean([lv["methods"][label][m] for lv in out_levels])
            for m in ("relmse", "flip", "seconds")
        }
        for label in methods
    }
    return {
        "data": str(data),
        "holdout_every": holdout_every,
        "crops": len(gdpt_set.crops),
        "resolution": list(gdpt_set.resolution),
        "models": {k: str(v) for k, v in models.items()},
        "inputs": {label: kind for label, (kind, _) in methods.items()},
        "levels": out_levels,
        "mean": overall,
        "elements": elements,
    }


def paired_comparison(
    result: Mapping[str, Any], a: str, b: str, metric: str = "relmse"
) -> dict[str, Any]:
    """``a`` against ``b`` on the same held-out elements of a :func:`compare_models` result.

    Per input level and over all levels: the geometric mean of the per-element ratio
    ``metric(a) / metric(b)`` with its 95% Student-t interval (the mean of the per-element log
    ratios, exponentiated), and the share of elements where ``a`` is lower. An interval that
    excludes 1 separates the two; image-wide means can be dominated by a few elements, a ratio
    per element cannot.

    Returns:
        ``{"a", "b", "metric", "levels": [{"spp", "n", "ratio", "low", "high", "a_lower"}],
        "all": {...}}``.

    Raises:
        KeyError: ``a`` or ``b`` has no per-element scores in ``result``.
        ValueError: a score is not positive (no log ratio).
    """
    elements = result["elements"]
    for label in (a, b):
        if label not in elements:
            raise KeyError(f"{label!r} is not in the comparison ({', '.join(result['mean'])})")
    xs, ys = elements[a][metric], elements[b][metric]
    if min(xs + ys) <= 0:
        raise ValueError(f"{metric} of {a} or {b} is not positive on some element")
    logs = [math.log(x / y) for x, y in zip(xs, ys, strict=True)]

    def summary(indices: list[int]) -> dict[str, float]:
        mean, low, high = mean_interval([logs[i] for i in indices])
        lower = sum(logs[i] < 0 for i in indices) / len(indices)
        n = len(indices)
        return {"n": n, "ratio": math.exp(mean), "low": math.exp(low), "high": math.exp(high),
                "a_lower": lower}  # fmt: skip

    levels = []
    for level, info in enumerate(result["levels"]):
        indices = [i for i, lv in enumerate(elements["level"]) if lv == level]
        levels.append({"spp": info["spp"], "pt_spp": info["pt_spp"], **summary(indices)})
    return {"a": a, "b": b, "metric": metric, "levels": levels,
            "all": summary(list(range(len(logs))))}  # fmt: skip


def paired_markdown(pair: Mapping[str, Any]) -> str:
    """A :func:`paired_comparison` as a Markdown table, one row per input level."""
    a, b, metric = pair["a"], pair["b"], pair["metric"]
    lines = [
        f"| input spp (G-PT / PT) | elements | {metric} {a} / {b} (geometric mean, 95% interval) "
        f"| {a} lower |",
        "|---|---|---|---|",
    ]
    for level in [*pair["levels"], None]:
        row = pair["all"] if level is None else level
        spp = "all" if level is None else f"{level['spp']:.0f} / {level['pt_spp']:.0f}"
        lines.append(
            f"| {spp} | {row['n']} | {row['ratio']:.3f} [{row['low']:.3f}, {row['high']:.3f}] "
            f"| {row['a_lower']:.0%} |"
        )
    return "\n".join(lines) + "\n"


def comparison_markdown(result: Mapping[str, Any]) -> str:
    """The comparison as a Markdown table: one row per input level, relMSE / FLIP per method
    (the lowest relMSE of a row in bold)."""
    labels = list(result["mean"])
    head = ["input spp (G-PT / PT)", "render s (G-PT / PT)"] + labels
    rows = []
    for level in [*result["levels"], None]:
        entry = result["mean"] if level is None else level["methods"]
        best = min(labels, key=lambda k: entry[k]["relmse"])
        cells = [
            f"**{entry[k]['relmse']:.4f}** / {entry[k]['flip']:.3f}"
            if k == best
            else f"{entry[k]['relmse']:.4f} / {entry[k]['flip']:.3f}"
            for k in labels
        ]
        if level is None:
            rows.append(["mean over levels", ""] + cells)
        else:
            rows.append(
                [
                    f"{level['spp']:.0f} / {level['pt_spp']:.0f}",
                    f"{level['render_seconds']['gdpt']:.2f} / {level['render_seconds']['pt']:.2f}",
                ]
                + cells
            )
    size = "x".join(str(v) for v in result["resolution"]) + " px"
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    pooled = [k for k, kind in result.get("inputs", {}).items() if kind == "pool"]
    pooled_note = (
        f"; {', '.join(pooled)} read the gradient-domain input with the path-traced input "
        "pooled into its primal (the render time of both)"
        if pooled
        else ""
    )
    return "\n".join(lines) + (
        f"\n\nrelMSE / LDR-FLIP, means over {result['crops']} held-out crops ({size}) per "
        "level; G-PT methods read the gradient-domain input, PT methods the path-traced input "
        f"with 2.5x the samples{pooled_note}.\n"
    )


def ship_model(
    run: str | Path,
    name: str,
    *,
    comparison: Mapping[str, Any] | None = None,
    dest: str | Path | None = None,
) -> Path:
    """Copy a run's final network into the package as ``<dest>/<name>.safetensors`` + card
    (a network that builds on another checkpoint, a combiner, also writes that one as
    ``<dest>/<name>-base``).

    The card adds to the run's own card: the dataset configuration and size (crops, scenes,
    held-out scenes), the wall-clock training time, the run's config, and ``comparison`` (from
    :func:`compare_models`).

    Args:
        run: ``gdpt train`` run directory holding ``model.safetensors``.
        name: model name (``oidn-grad``, ``oidn-tuned``).
        comparison: held-out comparison to record.
        dest: target folder (default: ``gdpt/models`` of this package).

    Returns:
        The written ``.safetensors`` path.

    Raises:
        FileNotFoundError: the run has no final model.
        ValueError: the final model is of no known network family, or too large.
    """
    from gdpt.checkpoints import MODEL_DIR
    from gdpt.reconstruct.families import family_of
    from gdpt.training.checkpoint import write_checkpoint

    run = Path(run)
    family = family_of(run / "model.json")
    model, design, card = family.load(run / "model.safetensors")
    base_path = family.base(run / "model.json", card)
    log = read_jsonl(run / "log.jsonl")
    config = json.loads((run / "config.json").read_text())
    data = Path(config["data"]) / "dataset.json"
    manifest = read_jsonl(Path(config["data"]) / "manifest.jsonl")
    scenes = sorted({row["scene"] for row in manifest if "scene" in row})
    holdout = config.get("holdout_every") or HOLDOUT_EVERY
    extra = {k: v for k, v in card.items() if k not in family.card_keys}
    extra.update(
        name=name,
        wall_clock_hours=round(log[-1]["time"] / 3600, 3) if log else None,
        train_config=config,
        dataset=json.loads(data.read_text()) if data.is_file() else None,
        dataset_size={
            "crops": len(manifest),
            "scenes": len(scenes),
            "heldout_scenes": [s for s in scenes if s % holdout == holdout - 1]
            if config.get("val_data") is None
            else "separate validation set",
        },
    )
    if comparison is not None:
        extra["heldout_comparison"] = comparison
    size = sum(p.numel() for p in model.state_dict().values()) * 4 / 2**20
    if size > MAX_SHIPPED_MIB:
        raise ValueError(
            f"{run}: a {size:.1f} MiB network exceeds the {MAX_SHIPPED_MIB} MiB "
            "limit of shipped models"
        )
    target = Path(dest or MODEL_DIR) / name
    if base_path is not None:  # shipped next to it, under the name the card gives it
        base_target = target.with_name(f"{name}-base")
        write_checkpoint(
            base_target,
            base_path.with_suffix(".safetensors").read_bytes(),
            base_path.with_suffix(".json").read_text(),
        )
        extra["base_model"] = base_target.name
    weights, _ = write_checkpoint(target, *family.encode(model, design, extra))
    return weights


@dataclass(frozen=True)
class Report:
    """What :func:`write_report` wrote.

    Attributes:
        comparison: ``comparison.json``: the :func:`compare_models` result with ``"pairs"``,
            the :func:`paired_comparison` of every pair in relMSE and in LDR-FLIP.
        markdown: ``comparison.md``: :func:`comparison_markdown` and one
            :func:`paired_markdown` table per pair.
        shipped: the ``.safetensors`` files :func:`ship_model` wrote, one per shipped run.
    """

    comparison: dict[str, Any]
    markdown: str
    shipped: tuple[Path, ...]


def write_report(
    data: str | Path,
    runs: Mapping[str, str | Path],
    out: str | Path,
    *,
    models: Mapping[str, str | Path] | None = None,
    holdout_every: int = HOLDOUT_EVERY,
    pairs: Sequence[tuple[str, str]] = (),
    ship: Sequence[str] = (),
    progress: bool = True,
) -> Report:
    """Report on trained networks in ``out``: ``training.png`` (:func:`plot_training` of
    ``runs``), ``comparison.json`` and ``comparison.md`` (the final network of each run and
    each of ``models`` on the held-out crops of ``data``, :func:`compare_models`, with the
    paired comparisons), then ship the runs named in ``ship`` (:func:`ship_model`, with the
    comparison in their card).

    Args:
        data: ``gdpt dataset`` directory.
        runs: name -> ``gdpt train`` run directory holding ``model.safetensors``.
        out: report folder (created; its files are overwritten).
        models: name -> further checkpoint to compare (neither plotted nor shipped); names
            other than those of ``runs``.
        holdout_every: the held-out rule of :func:`compare_models`.
        pairs: ``(a, b)`` labels (of ``runs``, ``models`` or :data:`BASELINES`) to compare
            element by element, in relMSE and in LDR-FLIP.
        ship: names of ``runs`` to ship into ``gdpt/models``.
        progress: show a progress bar.

    Returns:
        What was written.

    Raises:
        FileNotFoundError: a run has no ``log.jsonl`` or a checkpoint is missing.
        KeyError: a label of ``pairs`` or ``ship`` is unknown.
        ValueError: a checkpoint is of no known network family, or a network is too large to
            ship.
    """
    out = Path(out)
    checkpoints = {name: Path(run) / "model.safetensors" for name, run in runs.items()}
    checkpoints.update({name: Path(path) for name, path in (models or {}).items()})
    out.mkdir(parents=True, exist_ok=True)
    plot_training(runs, out / "training.png")
    result = compare_models(data, checkpoints, holdout_every=holdout_every, progress=progress)
    result["pairs"] = [
        paired_comparison(result, a, b, metric) for a, b in pairs for metric in ("relmse", "flip")
    ]
    (out / "comparison.json").write_text(json.dumps(result, indent=2) + "\n")
    markdown = comparison_markdown(result)
    for pair in result["pairs"]:
        markdown += "\n" + paired_markdown(pair)
    (out / "comparison.md").write_text(markdown)
    shipped = tuple(ship_model(runs[name], name, comparison=result) for name in ship)
    return Report(result, markdown, shipped)
