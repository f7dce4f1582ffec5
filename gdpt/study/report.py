"""The report of an equal-time evaluation, made from ``results.json`` and the saved images.

:func:`write_report` writes, next to ``results.json``:

* ``results.md``: the headline table (the method with the lowest error at each budget, per
  scene) and one table per scene with every cell (spp, achieved time, metrics);
* ``plots/<scene>.png``: error versus achieved time, log-log, one line per method and one panel
  per metric (the shape of the NGPT paper's equal-time figures);
* ``crops/<scene>.png``: at the largest budget, a crop of the reference and of every method, and
  below each method its per-pixel relMSE map (shared colour scale);
* ``index.html``: all of the above on one page.

Everything is recomputed from ``results.json``, so the report of a resumed or extended study is
always complete.
"""

from __future__ import annotations

import html
import os
import statistics
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

from gdpt.study.estimate import markdown as estimate_markdown

__all__ = ["METRIC_LABELS", "best_methods", "plot_scene", "write_report"]

#: Short column labels of the metrics.
METRIC_LABELS = {
    "relmse": "relMSE",
    "mse": "MSE",
    "smape": "SMAPE",
    "one_minus_ssim": "1-SSIM",
    "flip_hdr": "HDR-FLIP",
    "flip_ldr": "LDR-FLIP",
    "elpips": "E-LPIPS",
}

#: Metrics drawn in the error-versus-time plots (those that were computed).
PLOT_METRICS = ("relmse", "one_minus_ssim", "flip_ldr", "elpips")


def _label(metric: str) -> str:
    return METRIC_LABELS.get(metric, metric)


def _fmt(value: float | None) -> str:
    if value is None:
        return "n/a"
    return f"{value:.4g}" if value >= 1e-3 else f"{value:.3e}"


def _scenes(results: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    return list(results.get("scenes", {}).items())


def _budgets(results: dict[str, Any]) -> list[str]:
    return [f"{b:g}" for b in results["config"]["budgets"]]


def _ranking_metric(results: dict[str, Any]) -> str:
    return results["config"]["metrics"][0]


def best_methods(results: dict[str, Any]) -> dict[str, dict[str, tuple[str, float] | None]]:
    """For each scene and budget, the method with the lowest value of the ranking metric.

    The ranking metric is the first metric of the config (``relmse`` by default).

    Args:
        results: the content of ``results.json``.

    Returns:
        ``{scene: {budget key: (method, value) or None}}`` for the scenes that rendered.
    """
    metric = _ranking_metric(results)
    out: dict[str, dict[str, tuple[str, float] | None]] = {}
    for scene, entry in _scenes(results):
        if entry.get("status") != "ok":
            continue
        row: dict[str, tuple[str, float] | None] = {}
        for key in _budgets(results):
            candidates = [
                (info["cells"][key]["metrics"].get(metric), name)
                for name, info in entry.get("methods", {}).items()
                if key in info.get("cells", {})
            ]
            candidates = [(v, n) for v, n in candidates if v is not None]
            row[key] = (min(candidates)[1], min(candidates)[0]) if candidates else None
        out[scene] = row
    return out


# ---------------------------------------------------------------------------------- tables
def _headline(results: dict[str, Any]) -> tuple[list[str], list[list[str]]]:
    metric = _label(_ranking_metric(results))
    head = ["scene", *(f"{k} s" for k in _budgets(results))]
    rows = []
    for scene, row in best_methods(results).items():
        rows.append(
            [scene, *(f"{b[0]} ({metric} {_fmt(b[1])})" if b else "n/a" for b in row.values())]
        )
    return head, rows


def _scene_table(
    results: dict[str, Any], entry: dict[str, Any]
) -> tuple[list[str], list[list[str]]]:
    metrics = results["config"]["metrics"]
    shown = [
        m
        for m in metrics
        if any(
            m in cell["metrics"]
            for info in entry.get("methods", {}).values()
            for cell in info.get("cells", {}).values()
        )
    ]
    head = ["method", "budget s", "spp", "time s", "render s", "recon s"]
    head += [_label(m) for m in shown]
    rows = []
    for key in _budgets(results):
        for name, info in entry.get("methods", {}).items():
            cell = info.get("cells", {}).get(key)
            if cell is None:
                continue
            mark = "" if cell["within_tolerance"] else " *"
            rows.append(
                [
                    name,
                    key,
                    str(cell["spp"]),
                    f"{cell['seconds']:.2f}{mark}",
                    _seconds(cell.get("render_seconds")),
                    _seconds(cell.get("reconstruct_seconds")),
                    *(_fmt(cell["metrics"].get(m)) for m in shown),
                ]
            )
    return head, rows


def _seconds(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f}"


def charged(cell: dict[str, Any]) -> float:
    """The seconds of a cell that its study's protocol charged against the budget (studies
    before protocols charged the total)."""
    return cell.get("charged_seconds", cell["seconds"])


def _md_table(head: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def _html_table(head: list[str], rows: list[list[str]]) -> str:
    cells = "".join(f"<th>{html.escape(h)}</th>" for h in head)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>" for row in rows
    )
    return f"<table><thead><tr>{cells}</tr></thead><tbody>{body}</tbody></table>"


def _skips(entry: dict[str, Any]) -> list[str]:
    out = []
    for name, info in entry.get("methods", {}).items():
        if info.get("status") == "skipped":
            out.append(f"{name}: skipped ({info.get('note')})")
        out += [f"{name} at {k} s: failed ({v})" for k, v in info.get("errors", {}).items()]
    return out


def _missed(entry: dict[str, Any]) -> list[str]:
    """One line per replicate kept although it missed its budget after one redo."""
    out = []
    for name, info in entry.get("methods", {}).items():
        for key, cell in info.get("cells", {}).items():
            for index in cell.get("missed_budget", []):
                replicate = cell["replicates"][index]
                redone = replicate.get("redone", {})
                out.append(
                    f"{name} at {key} s, replicate {index}: missed the budget "
                    f"({replicate['charged_seconds']:.2f} s charged, "
                    f"{replicate['relative_error']:+.0%}"
                    + (f"; first run {redone['relative_error']:+.0%}" if redone else "")
                    + f"; load {replicate.get('loadavg_1min')}, CPU/wall "
                    f"{_seconds(replicate.get('cpu_per_wall'))})"
                )
    return out


def _cells_line(results: dict[str, Any]) -> str | None:
    """How the cells ran (studies before cells: ``None``)."""
    threads = results.get("threads")
    if threads is None:
        return None
    hosts = sorted(
        {
            run["worker"]["host"]
            for _, entry in _scenes(results)
            for run in entry.get("cell_runs", {}).values()
        }
    )
    engine = threads.get("engine")
    return (
        "Cells: each (scene, budget, replicate seed) calibrated and ran every method back to "
        "back on one worker, the order reversed on odd replicates; compare timings only within "
        f"a cell (workers may differ in speed). Engine: {engine}"
        + (f", {threads.get('workers')} workers" if threads.get("workers") else "")
        + (f", cluster {threads.get('address')}" if threads.get("address") else "")
        + f"; threads per worker: {threads.get('per_worker')}; hosts: {', '.join(hosts) or 'n/a'}."
    )


#: A study whose render-bound timed runs got less than this share of their Dr.Jit threads' CPU
#: time (median over the replicates; another process took the rest) is reported busy: idle, the
#: 2-core VM's runs got 96-99%, beside one busy loop 60-66%.
BUSY_SHARE = 0.85


def _busy_line(results: dict[str, Any]) -> str | None:
    """A warning where the timed runs shared the machine (:data:`BUSY_SHARE`; over the
    replicates whose render took at least half their seconds, since a reconstruction runs on
    one torch thread), else ``None``."""
    shares = [
        rep["cpu_per_wall"] / threads
        for _, entry in _scenes(results)
        for run in entry.get("cell_runs", {}).values()
        if (threads := run.get("worker", {}).get("threads", {}).get("drjit"))
        for rep in run.get("replicates", {}).values()
        if rep.get("cpu_per_wall") and rep.get("render_seconds", 0) >= 0.5 * rep["seconds"]
    ]
    if not shares or (share := statistics.median(shares)) >= BUSY_SHARE:
        return None
    return (
        f"Busy machine: the timed renders got a median {share:.0%} of their threads' CPU time "
        "(other work took the rest). Each cell's sample counts follow its timings, and beside "
        "other work those vary from cell to cell: a cell's count proportions between methods "
        "can move by 10-20% either way (docs/evaluation.md, beside a busy loop). Compare "
        "methods on an otherwise idle machine."
    )


def _run_summary(results: dict[str, Any]) -> list[str]:
    cfg, machine, versions = results["config"], results["machine"], results["versions"]
    runs = results.get("runs", [])
    command = next((r["command"] for r in reversed(runs) if r.get("command")), None)
    lines = [
        f"Profile `{cfg['profile']}`: budgets {', '.join(_budgets(results))} s, "
        f"{cfg['resolution']} px on the long side, reference {cfg['reference_spp']} spp "
        f"(path tracing), seed {cfg['seed']}, time tolerance {cfg['tolerance']:.0%}.",
        f"Machine: {machine['cpu']}, {machine['usable_cores']} usable cores, "
        f"{machine.get('memory_gib')} GiB; load average at start "
        f"{machine.get('loadavg_at_start')}, at end {machine.get('loadavg_at_end')}.",
        "Versions: " + ", ".join(f"{k} {v}" for k, v in versions.items() if v) + ".",
        "Protocol: " + results.get("protocol", ""),
    ]
    if cells := _cells_line(results):
        lines.append(cells)
    if (cost := (runs[-1].get("cost") if runs else None)) and cost.get("ratio"):
        lines.append(
            f"The study's own cost (last run): {cost['wall_seconds']:.0f} s of wall time for "
            f"{cost['timed_seconds']:.0f} s of timed renders ({cost['ratio']:.1f}x; the rest: "
            "loading, references, compilation, calibration, warm-ups)."
        )
    if busy := _busy_line(results):
        lines.append(busy)
    if command:
        lines.insert(0, f"Command: `{command}`")
    return lines


def _filter_notes(results: dict[str, Any]) -> list[str]:
    return [
        f"{scene}: pixel filter '{e['film_filter']['original']}' replaced by 'box'"
        for scene, e in _scenes(results)
        if e.get("film_filter", {}).get("original") not in (None, "box")
    ]


def _markdown(results: dict[str, Any], plots: dict[str, str], crops: dict[str, str]) -> str:
    metric = _label(_ranking_metric(results))
    out = ["# Equal-time evaluation", ""]
    out += [f"- {line}" for line in _run_summary(results)]
    out += ["", "Metric conventions:", ""]
    out += [f"- `{k}`: {v}" for k, v in results.get("conventions", {}).items()]
    if notes := _filter_notes(results):
        out += ["", "Scene changes (same for the reference and every method):", ""]
        out += [f"- {n}" for n in notes]
    head, rows = _headline(results)
    out += ["", f"## Lowest {metric} at each budget", "", _md_table(head, rows)]
    out += [
        "",
        "`*` after a time: the achieved time misses the budget by more than the "
        "tolerance (usually: the method's fixed cost exceeds the budget even at 1 spp).",
    ]
    for scene, entry in _scenes(results):
        out += ["", f"## {scene}", "", f"Source: `{entry.get('source')}`"]
        if entry.get("status") != "ok":
            out += ["", f"**Failed** at stage `{entry.get('stage')}`: {entry.get('error')}"]
            continue
        ref = entry.get("reference")
        out += [
            "",
            f"{entry['resolution'][0]}x{entry['resolution'][1]} px, "
            + (
                f"reference {ref.get('spp')} spp (seed {ref.get('seed')}, "
                f"{ref.get('seconds', 0):.1f} s). "
                if ref
                else "no reference (--no-reference): the estimate below is the result. "
            )
            + "; ".join(entry.get("notes", []))
            + ".",
        ]
        out += ["", _md_table(*_scene_table(results, entry))]
        if estimates := estimate_markdown(entry):
            out += ["", *estimates]
        if skips := _skips(entry):
            out += [""] + [f"- {s}" for s in skips]
        if missed := _missed(entry):
            out += ["", "Replicates kept although they missed the budget after one redo:", ""]
            out += [f"- {m}" for m in missed]
        for figure in (plots.get(scene), crops.get(scene)):
            if figure:
                out += ["", f"![{scene}]({figure})"]
    return "\n".join(out) + "\n"


def _html(results: dict[str, Any], plots: dict[str, str], crops: dict[str, str]) -> str:
    metric = _label(_ranking_metric(results))
    esc = html.escape
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>gdpt equal-time evaluation"
        "</title><style>body{font-family:sans-serif;max-width:1400px;margin:auto;padding:1em}"
        "table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;"
        "padding:2px 8px;text-align:right}td:first-child,th:first-child{text-align:left}"
        "img{max-width:100%}.failed{color:#b00}</style></head><body>",
        "<h1>Equal-time evaluation</h1><ul>",
        *(f"<li>{esc(line)}</li>" for line in _run_summary(results)),
        "</ul><details><summary>Metric conventions</summary><ul>",
        *(
            f"<li><code>{esc(k)}</code>: {esc(v)}</li>"
            for k, v in results.get("conventions", {}).items()
        ),
        "</ul></details>",
    ]
    if notes := _filter_notes(results):
        parts += [
            "<p>Scene changes (same for the reference and every method):</p><ul>",
            *(f"<li>{esc(n)}</li>" for n in notes),
            "</ul>",
        ]
    parts += [
        f"<h2>Lowest {esc(metric)} at each budget</h2>",
        _html_table(*_headline(results)),
        "<p>* after a time: the achieved time misses the budget by more than the tolerance.</p>",
    ]
    for scene, entry in _scenes(results):
        parts.append(
            f"<h2 id='{esc(scene)}'>{esc(scene)}</h2>"
            f"<p>Source: <code>{esc(str(entry.get('source')))}</code></p>"
        )
        if entry.get("status") != "ok":
            parts.append(
                f"<p class='failed'>Failed at stage {esc(str(entry.get('stage')))}: "
                f"{esc(str(entry.get('error')))}</p>"
            )
            continue
        parts.append(f"<p>{esc('; '.join(entry.get('notes', [])))}</p>")
        parts.append(_html_table(*_scene_table(results, entry)))
        if skips := _skips(entry):
            parts += ["<ul>", *(f"<li>{esc(s)}</li>" for s in skips), "</ul>"]
        if missed := _missed(entry):
            parts += ["<p>Replicates kept although they missed the budget after one redo:</p>"]
            parts += ["<ul>", *(f"<li>{esc(m)}</li>" for m in missed), "</ul>"]
        for figure in (plots.get(scene), crops.get(scene)):
            if figure:
                parts.append(f"<p><img src='{esc(figure)}' alt='{esc(scene)}'></p>")
    parts.append("</body></html>")
    return "\n".join(parts)


# ----------------------------------------------------------------------------------- figures
def plot_scene(results: dict[str, Any], scene: str, entry: dict[str, Any], path: Path) -> bool:
    """Error versus achieved time, log-log, one line per method, one panel per metric.

    Args:
        results: a ``results.json`` content; its ``config`` (``metrics``, ``budgets``,
            ``protocol``) is read.
        scene: the scene's name (the title).
        entry: ``results["scenes"][scene]``: ``resolution`` and per method its ``cells``
            (``seconds`` or ``charged_seconds``, ``metrics``).
        path: the PNG to write.

    Returns:
        Whether a plot was written (``False``: no cell or no plotted metric).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = {n: i.get("cells", {}) for n, i in entry.get("methods", {}).items() if i.get("cells")}
    metrics = [
        m
        for m in PLOT_METRICS
        if m in results["config"]["metrics"]
        and any(c["metrics"].get(m) for cs in cells.values() for c in cs.values())
    ]
    if not cells or not metrics:
        return False
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.2 * len(metrics), 3.6), squeeze=False)
    for ax, metric in zip(axes[0], metrics, strict=False):
        for name, by_budget in cells.items():
            points = sorted((charged(c), c["metrics"].get(metric)) for c in by_budget.values())
            points = [(t, v) for t, v in points if v and v > 0]
            if points:
                ax.plot(*zip(*points, strict=False), marker="o", label=name)
        for budget in results["config"]["budgets"]:
            ax.axvline(budget, color="0.85", lw=0.8, zorder=0)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(
            "achieved render time (s)"
            if results["config"].get("protocol") == "render-time"
            else "achieved time (s)"
        )
        ax.set_ylabel(_label(metric))
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.suptitle(
        f"{scene}: error vs equal time ({entry['resolution'][0]}x{entry['resolution'][1]} px)"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def _relmse_map(image: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Per-pixel relMSE (NGPT convention) of ``(H, W, 3)`` images -> ``(H, W)``."""
    den = 1e-3 + ref.mean(-1, keepdim=True).square()
    return ((image - ref).square() / den).mean(-1).nan_to_num(nan=0.0, posinf=0.0)


def _crop_window(errors: list[torch.Tensor], size: int) -> tuple[int, int]:
    """Top-left corner of the ``size``-square window with the largest mean error."""
    mean = torch.stack(errors).mean(0)[None, None].double()
    pooled = F.avg_pool2d(mean.clamp_max(float(mean.quantile(0.99))), size, stride=1)[0, 0]
    index = int(pooled.argmax())
    return divmod(index, pooled.shape[1])


def _crops(
    results: dict[str, Any], scene: str, entry: dict[str, Any], out: Path, path: Path
) -> bool:
    """Reference, each method's image and its error map, cropped, at the largest budget."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from gdpt.io.exr import load_image
    from gdpt.io.images import to_srgb8

    ref_path = out / "images" / scene / "reference.exr"
    budget = _budgets(results)[-1]
    cells = {
        n: i["cells"][budget]
        for n, i in entry.get("methods", {}).items()
        if budget in i.get("cells", {}) and (out / i["cells"][budget]["image"]).is_file()
    }
    if not ref_path.is_file() or not cells:
        return False
    ref = load_image(ref_path)
    images = {n: load_image(out / c["image"]) for n, c in cells.items()}
    errors = {n: _relmse_map(im, ref) for n, im in images.items()}
    h, w = ref.shape[:2]
    size = max(8, min(h, w) // 2)
    y, x = _crop_window(list(errors.values()), size)
    vmax = float(torch.stack(list(errors.values())).flatten().quantile(0.99)) or 1.0

    cols = 1 + len(images)
    fig, axes = plt.subplots(2, cols, figsize=(2.4 * cols, 5.0), squeeze=False)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
    axes[0][0].imshow(to_srgb8(ref[y : y + size, x : x + size]), interpolation="nearest")
    axes[0][0].set_title("reference", fontsize=8)
    axes[1][0].imshow(to_srgb8(ref), interpolation="nearest")
    axes[1][0].add_patch(Rectangle((x - 0.5, y - 0.5), size, size, fill=False, ec="red"))
    axes[1][0].set_title("full reference\n(red: crop)", fontsize=8)
    image = None
    for col, (name, im) in enumerate(images.items(), start=1):
        cell = cells[name]
        axes[0][col].imshow(to_srgb8(im[y : y + size, x : x + size]), interpolation="nearest")
        axes[0][col].set_title(f"{name}\n{cell['spp']} spp, {cell['seconds']:.2f} s", fontsize=8)
        image = axes[1][col].imshow(
            errors[name][y : y + size, x : x + size].numpy(),
            cmap="magma",
            vmin=0.0,
            vmax=vmax,
            interpolation="nearest",
        )
        value = cell["metrics"].get("relmse")
        axes[1][col].set_title(f"relMSE map\n{_fmt(value)} overall", fontsize=8)
    if image is not None:
        fig.colorbar(image, ax=axes[1].tolist(), shrink=0.8, label="per-pixel relMSE")
    fig.suptitle(f"{scene} at {budget} s")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def write_report(results: dict[str, Any], out: str | os.PathLike[str]) -> list[Path]:
    """Write ``results.md``, the plots, the crops and ``index.html`` into ``out``.

    Args:
        results: the content of ``results.json`` (as returned by
            :func:`gdpt.study.evaluate.evaluate`).
        out: the report folder (holding ``results.json`` and ``images/``).

    Returns:
        The files written.
    """
    out = Path(out)
    (out / "plots").mkdir(parents=True, exist_ok=True)
    (out / "crops").mkdir(parents=True, exist_ok=True)
    plots: dict[str, str] = {}
    crops: dict[str, str] = {}
    for scene, entry in _scenes(results):
        if entry.get("status") != "ok":
            continue
        if plot_scene(results, scene, entry, out / "plots" / f"{scene}.png"):
            plots[scene] = f"plots/{scene}.png"
        if _crops(results, scene, entry, out, out / "crops" / f"{scene}.png"):
            crops[scene] = f"crops/{scene}.png"
    (out / "results.md").write_text(_markdown(results, plots, crops))
    (out / "index.html").write_text(_html(results, plots, crops))
    written = [out / "results.md", out / "index.html"]
    return written + [out / p for p in (*plots.values(), *crops.values())]
