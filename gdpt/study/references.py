"""Path-traced references of the study: rendered in resumable chunks and cached."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import torch

from gdpt.study.results import write_json
from gdpt.study.scenes import EvalScene


# --------------------------------------------------------------------------------- reference
def reference_seed(seed: int) -> int:
    return 1_000_003 + seed


def render_reference(
    scene: EvalScene,
    cache_dir: Path,
    *,
    spp: int,
    chunk_spp: int,
    seed: int,
    source: str = "",
    progress: Any = None,
) -> tuple[torch.Tensor, dict[str, Any]]:
    """The path-traced reference, from the cache or rendered (resumably) into it.

    The reference is ``gdpt`` with ``gradients=False`` (plain path tracing) at ``spp``,
    rendered in chunks of ``chunk_spp`` with seeds ``seed * 7919 + spp done``. After each chunk
    the running mean is saved as ``<stem>.partial-<spp done>.exr``, from which an interrupted
    render continues. The finished image is ``<stem>.exr`` with its metadata in ``<stem>.json``,
    ``<stem> = <scene>-<W>x<H>-d<max depth>-<spp>spp-seed<seed>``.

    Args:
        scene: the scene.
        cache_dir: folder of cached references (created if needed).
        spp: samples per pixel.
        chunk_spp: samples per chunk.
        seed: reference seed (distinct from the seeds of the evaluated images).
        source: scene source, recorded; cached files of another source with the same name are
            discarded.
        progress: optional tqdm bar whose postfix shows the reference progress.

    Returns:
        The ``(H, W, 3)`` float32 reference on the CPU and its metadata.
    """
    from gdpt.io.exr import load_image, save_image
    from gdpt.rendering import render

    cache_dir.mkdir(parents=True, exist_ok=True)
    width, height = scene.resolution
    stem = f"{scene.name}-{width}x{height}-d{scene.max_depth}-{spp}spp-seed{seed}"
    final, sidecar = cache_dir / f"{stem}.exr", cache_dir / f"{stem}.json"
    meta = {
        "source": source,
        "scene": scene.name,
        "spp": spp,
        "seed": seed,
        "chunk_spp": chunk_spp,
        "max_depth": scene.max_depth,
        "resolution": [width, height],
        "film_filter": scene.film_filter,
        "method": "pt (gdpt integrator, gradients=False)",
    }
    old = json.loads(sidecar.read_text()) if sidecar.is_file() else None
    if old is not None and all(old.get(k) == meta[k] for k in ("source", "film_filter")):
        if final.is_file() and old.get("complete"):
            return load_image(final), {**old, "path": str(final), "cached": True}
        meta["seconds"] = old.get("seconds", 0.0)
    else:  # nothing cached, or the same name for another scene: start over
        for stale in [final, *cache_dir.glob(f"{stem}.partial-*.exr")]:
            stale.unlink(missing_ok=True)
        meta["seconds"] = 0.0
    write_json(sidecar, meta)

    mean, done = None, 0
    partials = sorted(
        cache_dir.glob(f"{stem}.partial-*.exr"), key=lambda p: int(p.stem.rsplit("-", 1)[1])
    )
    if partials:
        mean, done = load_image(partials[-1]).double(), int(partials[-1].stem.rsplit("-", 1)[1])
    while done < spp:
        n = min(chunk_spp, spp - done)
        start = time.perf_counter()
        buffers = render(
            scene.scene,
            spp=n,
            seed=seed * 7919 + done,
            max_depth=scene.max_depth,
            gradients=False,
            features=False,
        )
        chunk = buffers.primal.to("cpu", torch.float64)
        meta["seconds"] += time.perf_counter() - start
        mean = chunk if mean is None else mean + (chunk - mean) * (n / (done + n))
        done += n
        path = cache_dir / f"{stem}.partial-{done}.exr"
        save_image(path, mean, metadata={**meta, "spp_done": done}, force=True)
        write_json(sidecar, meta)
        for older in partials:
            older.unlink(missing_ok=True)
        partials = [path]
        if progress is not None:
            progress.set_postfix_str(f"{scene.name}: reference {done}/{spp} spp")
    save_image(final, mean, metadata=meta, force=True)
    write_json(sidecar, {**meta, "complete": True})
    for older in partials:
        older.unlink(missing_ok=True)
    return mean.float(), {**meta, "path": str(final), "cached": False}
