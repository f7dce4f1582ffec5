"""Rendering the training dataset: crops of procedural scenes (``gdpt dataset``).

:func:`build_dataset` renders, for every ``(scene, view)`` pair of :func:`gdpt.scenes.random_scene`,
one *crop* (a small image, 128x128 by default) as in Kettunen et al. 2019 (the paper's
training data, and ``create_dataset/`` of its public code, ``github.com/mkettune/ngpt``):

* ``levels`` (5) noisy gradient-domain inputs (``gdpt`` integrator, gradients and features) at
  sample counts drawn log-uniformly in ``[spp_min, spp_max]``, stratified (one draw in each of
  ``levels`` equal slices of the log range, like the reference's low-discrepancy sequence);
* for each of them a path-traced input (``gradients=False``, features on) at ``pt_factor``
  (2.5) times the samples, the equal-time input of the no-gradient baselines;
* with ``variance`` (the default), each input also stores the variance of its per-pixel mean
  (``var_primal``; ``var_dx``, ``var_dy`` for the G-PT inputs), which KPCN reads (Bako et al.
  2017; :mod:`gdpt.reconstruct.kpcn`); the samples, and so the other buffers, are the same;
* a target: ``target_spp`` samples of ``gdpt``, reconstructed with L1 screened Poisson
  (``alpha = 0.2``), as the paper does (``target="l1"``); or ``target="pt"``: ``target_spp``
  path-traced samples (``gradients=False``), unbiased and cheaper per sample, the choice for
  losses that tolerate zero-mean target noise.

Everything (scene seed, sample counts, render seeds) is a pure function of ``(seed, scene,
view)`` (:func:`plan_crop`), so a dataset can be extended with more scenes or views later and
re-rendered identically. The files, and why a crash never corrupts them, are
:mod:`gdpt.training.manifest`'s; re-running the same command skips the crops listed in the
manifest, so a crash or kill loses at most the crops in flight.

Parallelism: ``workers`` local processes (``spawn`` context; each sets the Mitsuba variant,
uses ``cpu_count // workers`` Dr.Jit threads and ends with the driver, even a killed one), or
Ray tasks (one per crop) when a Ray address is given; results are written by the workers to
``DIR`` (shared storage on a cluster) and the manifest is appended by the driver only.
:mod:`gdpt.training.dataset` reads the crops back.

:mod:`gdpt.scenes` imports Mitsuba, so it is imported inside the functions that use it: a worker
imports this module before it sets the variant, and Dr.Jit must locate libLLVM first
(:mod:`gdpt.backend`).
"""

from __future__ import annotations

import ctypes
import dataclasses
import json
import math
import multiprocessing
import os
import signal
import sys
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm.auto import tqdm

from gdpt.backend import set_variant
from gdpt.io.atomic import atomic_write
from gdpt.io.exr import save_buffers
from gdpt.methods import reconstruct_image
from gdpt.rendering import render
from gdpt.scenes.loading import load_scene
from gdpt.training.config import require_positive
from gdpt.training.manifest import (
    CONFIG_FILE,
    CROPS_DIR,
    DATASET_FORMAT,
    MANIFEST_FILE,
    DatasetWarning,
    append_manifest,
    crop_id,
    read_manifest,
    rewrite_manifest,
)

if TYPE_CHECKING:
    from gdpt.buffers import GradientBuffers
    from gdpt.scenes import RandomSceneConfig

#: Target kinds (:attr:`DatasetConfig.target`).
TARGET_KINDS = ("l1", "pt")

#: Primal estimates of the G-PT inputs (:attr:`DatasetConfig.primal`).
PRIMAL_KINDS = ("base", "mis")

#: Salt separating the render-seed stream of a crop from the scene-seed stream.
_CROP_SALT = 0xC409

#: ``prctl`` option: the signal a process receives when its parent dies (``<linux/prctl.h>``).
_PR_SET_PDEATHSIG = 1


# --------------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class DatasetConfig:
    """What :func:`build_dataset` renders.

    Attributes:
        scenes: number of procedural scenes (scene indices ``0 .. scenes-1``).
        views: camera views per scene (view indices ``0 .. views-1``).
        resolution: crop width and height in pixels.
        spp_min: smallest input sample count.
        spp_max: largest input sample count.
        levels: noisy inputs per crop.
        target_spp: samples of the target render.
        pt_factor: path-traced input samples = ``round(pt_factor * spp)`` (equal time).
        max_depth: longest path (integrator ``max_depth``).
        alpha: screened-Poisson data weight of the L1 target reconstruction.
        target: ``"l1"`` (G-PT + L1 Poisson, the paper's) or ``"pt"`` (path tracing).
        variance: store the variance of each input's per-pixel mean (``var_primal``, and
            ``var_dx``, ``var_dy`` of the G-PT inputs); KPCN reads it.
        primal: the ``gdpt`` integrator's ``primal`` property for the G-PT inputs ``in<k>``:
            ``"base"`` (the base path's estimate) or ``"mis"`` (every base and offset path, MIS
            weighted; :mod:`gdpt.integrators.common`); the path-traced inputs and the target do
            not depend on it.
        seed: dataset seed; everything rendered is a function of ``(seed, scene, view)``.
        scene_config: knobs of the scene generator (``None``: its defaults).
    """

    scenes: int = 10
    views: int = 4
    resolution: int = 128
    spp_min: int = 2
    spp_max: int = 256
    levels: int = 5
    target_spp: int = 4096
    pt_factor: float = 2.5
    max_depth: int = 6
    alpha: float = 0.2
    target: str = "l1"
    variance: bool = True
    primal: str = "base"
    seed: int = 0
    scene_config: RandomSceneConfig | None = None

    def __post_init__(self) -> None:
        require_positive(
            self, ("scenes", "views", "resolution", "spp_min", "levels", "target_spp", "max_depth")
        )
        if self.spp_max < self.spp_min:
            raise ValueError(f"spp_max ({self.spp_max}) must be >= spp_min ({self.spp_min})")
        if not (self.pt_factor > 0 and self.alpha > 0):
            raise ValueError("pt_factor and alpha must be > 0")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.target not in TARGET_KINDS:
            raise ValueError(f"target must be one of {TARGET_KINDS}, got {self.target!r}")
        if self.primal not in PRIMAL_KINDS:
            raise ValueError(f"primal must be one of {PRIMAL_KINDS}, got {self.primal!r}")

    def content(self) -> dict[str, Any]:
        """The settings that define the pixels (everything but ``scenes`` and ``views``).

        A dataset directory keeps these in ``dataset.json``; extending it with more scenes or
        views is allowed, changing any of these is not.
        """
        data = dataclasses.asdict(self)
        del data["scenes"], data["views"]
        if data["target"] == "l1":  # the original kind: datasets written before it existed
            del data["target"]
        if not data["variance"]:  # as datasets written before it existed
            del data["variance"]
        if data["primal"] == "base":  # as datasets written before it existed
            del data["primal"]
        if self.scene_config is None:
            from gdpt.scenes import RandomSceneConfig

            data["scene_config"] = dataclasses.asdict(RandomSceneConfig())
        return json.loads(json.dumps(data))  # tuples -> lists, as read back from JSON


@dataclass(frozen=True)
class CropPlan:
    """Everything needed to render one crop (a pure function of the dataset seed and ids).

    Attributes:
        scene: scene index.
        view: view index.
        scene_seed: seed passed to :func:`gdpt.scenes.random_scene`.
        spp: input sample counts, ascending.
        pt_spp: path-traced sample counts (``round(pt_factor * spp)``).
        input_seeds: render seeds of the inputs.
        pt_seeds: render seeds of the path-traced inputs.
        target_seed: render seed of the target.
    """

    scene: int
    view: int
    scene_seed: int
    spp: tuple[int, ...]
    pt_spp: tuple[int, ...]
    input_seeds: tuple[int, ...]
    pt_seeds: tuple[int, ...]
    target_seed: int

    @property
    def crop_id(self) -> str:
        """``s<scene:05d>-v<view:03d>``."""
        return crop_id(self.scene, self.view)


def scene_seed(seed: int, scene: int) -> int:
    """Seed of procedural scene ``scene`` in a dataset with seed ``seed`` (31-bit int)."""
    state = np.random.SeedSequence([seed, scene]).generate_state(1, np.uint32)[0]
    return int(state >> 1)


def plan_crop(config: DatasetConfig, scene: int, view: int) -> CropPlan:
    """Sample counts and seeds of one crop.

    The ``levels`` sample counts are log-uniform in ``[spp_min, spp_max]`` and stratified: draw
    ``k`` lies in the ``k``-th of ``levels`` equal slices of the log range (then rounded).

    Args:
        config: the dataset settings.
        scene: scene index (>= 0).
        view: view index (>= 0).

    Returns:
        The plan; identical for identical arguments.
    """
    rng = np.random.Generator(np.random.PCG64([config.seed, scene, view, _CROP_SALT]))
    lo, hi = math.log(config.spp_min), math.log(config.spp_max)
    u = (np.arange(config.levels) + rng.uniform(size=config.levels)) / config.levels
    spp = np.clip(np.rint(np.exp(lo + u * (hi - lo))), config.spp_min, config.spp_max)
    spp = tuple(int(s) for s in spp)
    seeds = [int(s) for s in rng.integers(0, 2**31, size=2 * config.levels + 1)]
    return CropPlan(
        scene=scene,
        view=view,
        scene_seed=scene_seed(config.seed, scene),
        spp=spp,
        pt_spp=tuple(max(1, round(config.pt_factor * s)) for s in spp),
        input_seeds=tuple(seeds[: config.levels]),
        pt_seeds=tuple(seeds[config.levels : 2 * config.levels]),
        target_seed=seeds[-1],
    )


# ------------------------------------------------------------------------------------ rendering
def _scene_config(content: dict[str, Any]) -> RandomSceneConfig:
    """The scene generator's settings stored in ``content``."""
    from gdpt.scenes import RandomSceneConfig

    fields = {k: tuple(v) if isinstance(v, list) else v for k, v in content["scene_config"].items()}
    return RandomSceneConfig(**fields)


def render_crop(
    plan: CropPlan,
    root: str | os.PathLike[str],
    content: dict[str, Any],
    variant: str | None = None,
) -> dict[str, Any]:
    """Render and store all elements of one crop; returns its manifest record.

    Sets the Mitsuba variant (:func:`gdpt.set_variant`), so it can run in a fresh worker
    process. Existing (partial) shards of the crop are overwritten.

    Args:
        plan: what to render (:func:`plan_crop`).
        root: dataset directory (must exist).
        content: :meth:`DatasetConfig.content` of the dataset.
        variant: Mitsuba variant (``None``: :func:`gdpt.set_variant`'s automatic choice).

    Returns:
        The manifest record (JSON-serialisable dict, see :mod:`gdpt.training.manifest`).
    """
    set_variant(variant)
    from gdpt.scenes import random_scene  # imports Mitsuba: after set_variant (libLLVM first)

    root = Path(root)
    res = int(content["resolution"])
    scene = load_scene(
        random_scene(
            plan.scene_seed, resolution=(res, res), view=plan.view, config=_scene_config(content)
        )
    )
    crop_dir = root / CROPS_DIR / plan.crop_id
    crop_dir.mkdir(parents=True, exist_ok=True)
    files: dict[str, str] = {}
    sizes: dict[str, int] = {}
    seconds: dict[str, float] = {}

    def store(name: str, buffers: GradientBuffers, **extra: Any) -> None:
        metadata = {**buffers.metadata, "crop": plan.crop_id, "element": name, **extra}
        path = save_buffers(
            crop_dir / f"{name}.exr", buffers.replace(metadata=metadata), force=True
        )  # fsync'ed by the atomic write
        files[name] = path.relative_to(root).as_posix()
        sizes[name] = path.stat().st_size
        seconds[name] = round(float(buffers.metadata["render_seconds"]), 4)

    def draw(spp: int, seed: int, gradients: bool, variance: bool, **props: Any) -> GradientBuffers:
        return render(
            scene,
            spp=spp,
            seed=seed,
            integrator="gdpt",
            max_depth=int(content["max_depth"]),
            gradients=gradients,
            features=True,
            variance=variance,
            **props,
        )

    variance = bool(content.get("variance", False))
    for k, (spp, seed) in enumerate(zip(plan.spp, plan.input_seeds, strict=True)):
        store(f"in{k}", draw(spp, seed, True, variance, primal=content.get("primal", "base")))
    for k, (spp, seed) in enumerate(zip(plan.pt_spp, plan.pt_seeds, strict=True)):
        store(f"pt{k}", draw(spp, seed, False, variance))
    path_traced = content.get("target", "l1") == "pt"
    target = draw(int(content["target_spp"]), plan.target_seed, not path_traced, False)
    solve = 0.0
    if path_traced:
        store("target", target, primal="path_traced")
    else:
        start = time.perf_counter()
        image = reconstruct_image(target, method="l1", alpha=float(content["alpha"]))
        solve = time.perf_counter() - start
        store(
            "target",
            target.replace(primal=image.float().contiguous()),
            primal="l1_poisson",
            alpha=float(content["alpha"]),
            solve_seconds=round(solve, 4),
        )
    seconds["total"] = round(sum(seconds.values()) + solve, 4)
    return {
        "crop": plan.crop_id,
        "scene": plan.scene,
        "view": plan.view,
        "scene_seed": plan.scene_seed,
        "resolution": [res, res],
        "spp": list(plan.spp),
        "pt_spp": list(plan.pt_spp),
        "target_spp": int(content["target_spp"]),
        "seeds": {
            "inputs": list(plan.input_seeds),
            "pt": list(plan.pt_seeds),
            "target": plan.target_seed,
        },
        "files": files,
        "bytes": sizes,
        "render_seconds": seconds,
    }


def _check_config(root: Path, content: dict[str, Any]) -> None:
    """Write ``dataset.json``, or check that an existing one has the same content settings."""
    path = root / CONFIG_FILE
    if path.exists():
        stored = json.loads(path.read_text())
        old = stored.get("config", {})
        diff = [
            f"{k}: {old.get(k)!r} in {path} vs {content.get(k)!r} requested"
            for k in sorted(set(old) | set(content))
            if old.get(k) != content.get(k)
        ]
        if stored.get("format") != DATASET_FORMAT or diff:
            raise ValueError(
                f"{root} holds a dataset with other settings ({'; '.join(diff) or 'format'}); "
                "use another --out directory or the same settings"
            )
        return
    atomic_write(path, json.dumps({"format": DATASET_FORMAT, "config": content}, indent=2) + "\n")


def _stop_with_parent(parent: int) -> None:
    """Make this worker process end when process ``parent`` does, however it ends.

    Ctrl-C is left to the parent (it ends the pool); on Linux the kernel sends ``SIGKILL``
    when the parent dies (``prctl(PR_SET_PDEATHSIG)``, also after a ``SIGKILL`` of the parent),
    so no orphan keeps rendering.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)


def _init_worker(variant: str | None, threads: int, parent: int | None = None) -> None:
    """Worker-process set-up: stop with process ``parent`` (if given), Mitsuba variant and
    Dr.Jit thread count."""
    if parent is not None:
        _stop_with_parent(parent)
    set_variant(variant)
    import drjit as dr  # (after set_variant: libLLVM located first)

    dr.set_thread_count(threads)


def _render_task(args: tuple[CropPlan, str, dict[str, Any], str | None]) -> dict[str, Any]:
    return render_crop(*args)


def _ray_render_task(
    plan: CropPlan, root: str, content: dict[str, Any], variant: str | None
) -> dict[str, Any]:
    """Ray task body: one crop with one Dr.Jit thread (Ray runs one task per CPU)."""
    _init_worker(variant, 1)
    return render_crop(plan, root, content, variant)


def _run_local(
    plans: list[CropPlan], root: Path, content: dict[str, Any], variant: str | None, workers: int
) -> Iterator[dict[str, Any]]:
    """Render crops in this process (``workers == 1``) or in a spawn pool; yield records."""
    if workers == 1:
        for plan in plans:
            yield render_crop(plan, root, content, variant)
        return
    threads = max(1, (os.cpu_count() or 1) // workers)
    context = multiprocessing.get_context("spawn")
    initargs = (variant, threads, os.getpid())
    with context.Pool(workers, initializer=_init_worker, initargs=initargs) as pool:
        tasks = [(plan, str(root), content, variant) for plan in plans]
        yield from pool.imap_unordered(_render_task, tasks)


def _run_ray(
    plans: list[CropPlan],
    root: Path,
    content: dict[str, Any],
    variant: str | None,
    address: str,
    workers: int,
) -> Iterator[dict[str, Any]]:
    """Render crops as Ray tasks (one per crop, 1 CPU each); yield records as they finish.

    ``address == "local"`` starts a private single-node Ray instance with ``workers`` CPUs;
    any other value is passed to ``ray.init(address=...)`` (e.g. ``auto`` or
    ``ray://head:10001``). ``root`` must be on storage the Ray workers share.
    """
    try:
        import ray
    except ImportError as error:
        raise RuntimeError("--ray needs Ray: pip install 'gdpt[dist]'") from error
    owned = not ray.is_initialized()
    if owned:
        if address == "local":
            ray.init(num_cpus=workers, include_dashboard=False)
        else:
            ray.init(address=address)
    task = ray.remote(num_cpus=1)(_ray_render_task)
    pending = [task.remote(plan, str(root.resolve()), content, variant) for plan in plans]
    try:
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            yield ray.get(ready[0])
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
        if owned:
            ray.shutdown()


@dataclass(frozen=True)
class BuildSummary:
    """What :func:`build_dataset` did.

    Attributes:
        rendered: crops rendered by this call.
        skipped: crops already in the manifest.
        seconds: wall-clock seconds of this call.
    """

    rendered: int
    skipped: int
    seconds: float

    @property
    def crops_per_minute(self) -> float:
        """Throughput of this call."""
        return 60.0 * self.rendered / self.seconds if self.seconds > 0 else 0.0


def build_dataset(
    config: DatasetConfig,
    out: str | os.PathLike[str],
    *,
    workers: int = 1,
    ray_address: str | None = None,
    variant: str | None = None,
    progress: bool = True,
) -> BuildSummary:
    """Render the crops of ``config`` that ``out`` does not hold yet (resumable).

    Args:
        config: what to render.
        out: dataset directory (created if needed).
        workers: local worker processes; with Ray, the CPUs of a ``"local"`` instance.
        ray_address: ``None`` (local processes), ``"local"`` (start a private Ray instance) or
            the address of a Ray cluster.
        variant: Mitsuba variant for every render (``None``: automatic choice).
        progress: show a progress bar with ETA (tqdm).

    Returns:
        Counts and timing of this call. A resumed build says on stderr how many crops were
        done.

    Raises:
        ValueError: ``out`` holds a dataset with other content settings, or ``workers < 1``.
        OSError: writing failed (the manifest stays valid; re-run to continue).
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    start = time.perf_counter()
    root = Path(out)
    root.mkdir(parents=True, exist_ok=True)
    content = config.content()
    _check_config(root, content)
    records, problems = read_manifest(root)
    if problems:
        warnings.warn(
            f"{root}: repairing {MANIFEST_FILE}:\n  " + "\n  ".join(problems),
            DatasetWarning,
            stacklevel=2,
        )
        rewrite_manifest(root, records)
    done = {record["crop"] for record in records}
    ids = [(s, v) for s in range(config.scenes) for v in range(config.views)]
    plans = [plan_crop(config, s, v) for s, v in ids if crop_id(s, v) not in done]
    skipped = len(ids) - len(plans)
    if skipped and plans:
        print(f"{root}: resuming: {skipped} of {len(ids)} crops done", file=sys.stderr, flush=True)
    if ray_address is None:
        results = _run_local(plans, root, content, variant, workers)
    else:
        results = _run_ray(plans, root, content, variant, ray_address, workers)
    rendered = 0
    with tqdm(
        total=len(ids),
        initial=skipped,
        unit="crop",
        desc="dataset",
        disable=not progress,
        dynamic_ncols=True,
    ) as bar:
        for record in results:
            append_manifest(root, record)
            rendered += 1
            bar.update(1)
            bar.set_postfix_str(f"last {record['crop']} {record['render_seconds']['total']:.0f}s")
    return BuildSummary(rendered, skipped, time.perf_counter() - start)
