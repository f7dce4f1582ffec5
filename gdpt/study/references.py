"""Path-traced references of the study: a sum of independent chunks, cached and resumable.

A reference of ``spp`` samples per pixel is the sample-count-weighted mean of chunks of at most
``chunk_spp`` samples (:func:`reference_chunks`). Chunk ``i`` depends on nothing but its index:
it renders ``min(chunk_spp, spp - i * chunk_spp)`` samples with the seed
``seed * 7919 + i * chunk_spp``, so chunks can be rendered in any order, by any number of
workers, and a render that stops keeps every finished chunk. Each finished chunk is one EXR
written atomically (:func:`gdpt.io.atomic.atomic_path`; a chunk killed while rendering leaves no
file). The merge (:func:`merge_chunks`) sums the chunks in index order in float64, so the
finished reference is bit-identical whatever the number of workers or the order the chunks came
in. Monte Carlo estimates from independent sample sets combine as their sample-count-weighted
mean (Pharr, Jakob and Humphreys, *Physically Based Rendering*, 4th ed., sec. 2.1.4).

The seeds are those of the earlier running-mean reference (chunk ``i`` started at ``i *
chunk_spp`` samples done), so a running-mean partial ``<stem>.partial-<done>.exr`` left by an
older version is read as the first ``done / chunk_spp`` chunks and the render resumes after it.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from gdpt.study.results import write_json
from gdpt.study.scenes import EvalScene

__all__ = [
    "ReferenceChunk",
    "merge_chunks",
    "reference_chunks",
    "reference_seed",
    "reference_stem",
    "render_chunk",
    "render_reference",
]


# --------------------------------------------------------------------------------- reference
def reference_seed(seed: int) -> int:
    """The reference's seed for a study's base ``seed`` (distinct from every cell's seed)."""
    return 1_000_003 + seed


@dataclass(frozen=True)
class ReferenceChunk:
    """One independent chunk of a reference.

    Attributes:
        index: position in the reference (``0 .. count - 1``).
        count: number of chunks of the reference.
        spp: samples per pixel of this chunk.
        seed: its render seed, ``reference seed * 7919 + index * chunk_spp``.
    """

    index: int
    count: int
    spp: int
    seed: int


def reference_chunks(spp: int, chunk_spp: int, seed: int) -> list[ReferenceChunk]:
    """The chunks of a ``spp``-sample reference with seed ``seed``, in index order.

    Raises:
        ValueError: ``spp`` or ``chunk_spp`` below 1.
    """
    if spp < 1 or chunk_spp < 1:
        raise ValueError(f"spp and chunk_spp must be >= 1, got {spp} and {chunk_spp}")
    count = -(-spp // chunk_spp)
    return [
        ReferenceChunk(i, count, min(chunk_spp, spp - i * chunk_spp), seed * 7919 + i * chunk_spp)
        for i in range(count)
    ]


def reference_stem(scene: EvalScene, spp: int, seed: int) -> str:
    """``<scene>-<W>x<H>-d<max depth>-<spp>spp-seed<seed>``: the cache files' common name."""
    width, height = scene.resolution
    return f"{scene.name}-{width}x{height}-d{scene.max_depth}-{spp}spp-seed{seed}"


def render_chunk(scene: EvalScene, chunk: ReferenceChunk) -> torch.Tensor:
    """Render one chunk: plain path tracing (``gdpt``, ``gradients=False``) of ``chunk.spp``
    samples with ``chunk.seed``.

    Returns:
        The chunk's mean radiance, ``(H, W, 3)`` float32 on the CPU.
    """
    from gdpt.rendering import render

    buffers = render(
        scene.scene,
        spp=chunk.spp,
        seed=chunk.seed,
        max_depth=scene.max_depth,
        gradients=False,
        features=False,
    )
    return buffers.primal.to("cpu", torch.float32).contiguous()


def merge_chunks(parts: Iterable[tuple[int, torch.Tensor]]) -> torch.Tensor:
    """The sample-count-weighted mean of ``(spp, (H, W, 3) image)`` parts, summed in the order
    given in float64 (the same order gives the same bits).

    Returns:
        ``(H, W, 3)`` float64.
    """
    total, count = None, 0
    for spp, image in parts:
        term = image.to(torch.float64) * spp
        total = term if total is None else total + term
        count += spp
    assert total is not None and count > 0, "no chunks to merge"
    return total / count


def _chunk_path(cache_dir: Path, stem: str, chunk: ReferenceChunk) -> Path:
    return cache_dir / f"{stem}.chunk-{chunk.index:05d}-of-{chunk.count:05d}.exr"


def _legacy_partial(cache_dir: Path, stem: str, chunk_spp: int) -> tuple[int, Path] | None:
    """The largest running-mean partial of an older version whose samples are whole chunks."""
    found = []
    for path in cache_dir.glob(f"{stem}.partial-*.exr"):
        done = int(path.stem.rsplit("-", 1)[1])
        if done % chunk_spp == 0:
            found.append((done, path))
    return max(found) if found else None


def _same_source(recorded: str | None, source: str) -> bool:
    """Whether a cached reference's recorded source is ``source``: equal, or the same file
    named from another working directory (``../shared/x/scene.xml`` and its absolute path)."""
    if recorded == source:
        return True
    if not recorded or not source or ":" in recorded.split("/")[0] or ":" in source.split("/")[0]:
        return False  # builtin:NAME, random:SEED differ by name
    try:
        return Path(recorded).resolve(strict=True) == Path(source).resolve(strict=True)
    except OSError:
        return False


#: ``run(scene, chunks) -> iterator of (chunk, image)`` in any order: how the chunks that are
#: missing get rendered (default: one after the other in this process).
ChunkRunner = Callable[[EvalScene, list[ReferenceChunk]], Iterator[tuple[ReferenceChunk, Any]]]


def _in_process(scene: EvalScene, chunks: list[ReferenceChunk]) -> Iterator[tuple[Any, Any]]:
    for chunk in chunks:
        yield chunk, render_chunk(scene, chunk)


def render_reference(
    scene: EvalScene,
    cache_dir: Path,
    *,
    spp: int,
    chunk_spp: int,
    seed: int,
    source: str = "",
    progress: Any = None,
    run_chunks: ChunkRunner | None = None,
) -> tuple[torch.Tensor, dict[str, Any]]:
    """The path-traced reference, from the cache or rendered chunk by chunk into it.

    The files are named by ``<stem>`` (:func:`reference_stem`): the finished image
    ``<stem>.exr``, its metadata ``<stem>.json`` (``complete``: true when finished) and, while
    it renders, one ``<stem>.chunk-<i>-of-<n>.exr`` per finished chunk (removed once merged);
    the temporary file of a write that was killed (``.<stem>...tmp``) is removed on the next
    call.
    Cached files of another ``source`` or film filter under the same name are discarded.

    Args:
        scene: the scene.
        cache_dir: folder of cached references (created if needed).
        spp: samples per pixel.
        chunk_spp: samples per chunk (:func:`reference_chunks`).
        seed: reference seed (distinct from the seeds of the evaluated images).
        source: scene source, recorded.
        progress: optional tqdm bar whose postfix shows the reference progress.
        run_chunks: renders the missing chunks, yielding ``(chunk, (H, W, 3) image)`` in any
            order (e.g. as Ray tasks, :mod:`gdpt.study.engine`); default: in this process.

    Returns:
        The ``(H, W, 3)`` float32 reference on the CPU and its metadata.
    """
    from gdpt.io.exr import load_image, save_image

    cache_dir.mkdir(parents=True, exist_ok=True)
    stem = reference_stem(scene, spp, seed)
    final, sidecar = cache_dir / f"{stem}.exr", cache_dir / f"{stem}.json"
    meta = {
        "source": source,
        "scene": scene.name,
        "spp": spp,
        "seed": seed,
        "chunk_spp": chunk_spp,
        "max_depth": scene.max_depth,
        "resolution": list(scene.resolution),
        "film_filter": scene.film_filter,
        "method": "pt (gdpt integrator, gradients=False)",
    }
    old = json.loads(sidecar.read_text()) if sidecar.is_file() else None
    if (
        old is not None
        and _same_source(old.get("source"), source)
        and old.get("film_filter") == meta["film_filter"]
    ):
        if final.is_file() and old.get("complete"):
            return load_image(final), {**old, "path": str(final), "cached": True}
        meta["seconds"] = old.get("seconds", 0.0)
    else:  # nothing cached, or the same name for another scene: start over
        for stale in [final, *cache_dir.glob(f"{stem}.partial-*.exr")]:
            stale.unlink(missing_ok=True)
        for stale in cache_dir.glob(f"{stem}.chunk-*.exr"):
            stale.unlink(missing_ok=True)
        meta["seconds"] = 0.0
    write_json(sidecar, meta)

    for stale in cache_dir.glob(f".{stem}.*.tmp"):  # a write killed mid-way (atomic_path)
        stale.unlink(missing_ok=True)
    chunks = reference_chunks(spp, chunk_spp, seed)
    legacy = _legacy_partial(cache_dir, stem, chunk_spp) if old is not None else None
    first = legacy[0] // chunk_spp if legacy else 0
    todo = [c for c in chunks[first:] if not _chunk_path(cache_dir, stem, c).is_file()]
    done = spp - sum(c.spp for c in todo)
    start = time.perf_counter()
    for chunk, image in (run_chunks or _in_process)(scene, todo):
        chunk_meta = {"scene": scene.name, "chunk": chunk.index, "of": chunk.count}
        chunk_meta.update(spp=chunk.spp, seed=chunk.seed)
        save_image(_chunk_path(cache_dir, stem, chunk), image, metadata=chunk_meta, force=True)
        done += chunk.spp
        meta["seconds"] += time.perf_counter() - start  # wall time of this call
        start = time.perf_counter()
        write_json(sidecar, meta)
        if progress is not None:
            progress.set_postfix_str(f"{scene.name}: reference {done}/{spp} spp")
    parts = [(legacy[0], load_image(legacy[1]))] if legacy else []
    parts += [(c.spp, load_image(_chunk_path(cache_dir, stem, c))) for c in chunks[first:]]
    mean = merge_chunks(parts)
    save_image(final, mean, metadata=meta | {"seconds": None}, force=True)
    write_json(sidecar, {**meta, "complete": True})
    for path in [*cache_dir.glob(f"{stem}.chunk-*.exr"), *cache_dir.glob(f"{stem}.partial-*")]:
        path.unlink(missing_ok=True)
    return mean.float(), {**meta, "path": str(final), "cached": False}
