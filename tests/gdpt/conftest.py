"""Fixtures of the dataset, training, fine-tuning, model-report and study tests.

* ``tiny_dataset_config``: a factory of :class:`~gdpt.training.preprocess.DatasetConfig` for
  16x16 crops of one-object scenes (fast kernels): 1 scene, 2 views, 1-4 spp, 8-spp targets,
  depth 4; keyword arguments override fields.
* ``tiny_dataset``: that dataset (``tiny_dataset_config()``, 2 crops), rendered once per
  session. Read-only: tests that change a dataset work on a copy.
* ``pt_dataset``: two 32x32 crops of a one-object scene, 2 levels, with equal-time path-traced
  inputs and 16-spp path-traced targets (``--target pt``), rendered once per session.
  Read-only.
* ``resume_after_a_lost_checkpoint``: a function ``(run, config, train)`` that deletes the
  checkpoint of step 3 (a run killed between steps 2 and 3), resumes with ``train`` and returns
  ``(log, before, after)``: the new log and the training states (``.pt`` payloads: exact
  weights, optimizer state, step) of step 3 from the first run and from the resumed one.
* ``assert_same_state``: a function ``(a, b)`` asserting that two such training states are
  equal bit for bit (every tensor, every number), naming the first entry that differs.
* ``tiny_run_config``: a factory ``(data, out, **changes)`` of
  :class:`~gdpt.training.config.TrainConfig` with a tiny schedule: 3 steps of batch 2, no
  warm-up, decay from step 1 with half-life 2, validation every 2 steps on 2 crops (so at
  steps 2 and 3), a checkpoint every step; ``data`` also validates.
* ``cost_clock``: a function ``(name, fixed, per_spp)`` that makes the study method ``name``
  report ``seconds = fixed + per_spp * spp`` for the rest of the test (it still renders and
  reconstructs): calibrated sample counts that do not depend on the machine's speed or load.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from gdpt.training.config import TrainConfig
    from gdpt.training.preprocess import DatasetConfig


def make_tiny_dataset_config(**changes) -> DatasetConfig:
    """16x16 crops of one-object scenes (fast kernels), a handful of samples."""
    from gdpt.scenes import RandomSceneConfig
    from gdpt.training.preprocess import DatasetConfig

    scene = RandomSceneConfig(
        num_objects=(1, 1), p_extra_light=0.0, p_window=0.0, p_bitmap_env=0.0, p_thinlens=0.0
    )
    settings = dict(
        scenes=1,
        views=2,
        resolution=16,
        spp_min=1,
        spp_max=4,
        target_spp=8,
        max_depth=4,
        scene_config=scene,
    )
    return DatasetConfig(**{**settings, **changes})


@pytest.fixture(scope="session")
def tiny_dataset_config() -> Callable[..., DatasetConfig]:
    """:func:`make_tiny_dataset_config`, as a fixture."""
    return make_tiny_dataset_config


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """The two rendered crops of ``tiny_dataset_config()`` (do not modify)."""
    from gdpt.training.preprocess import build_dataset

    root = tmp_path_factory.mktemp("dataset") / "tiny"
    summary = build_dataset(make_tiny_dataset_config(), root, progress=False)
    assert (summary.rendered, summary.skipped) == (2, 0)
    return root


@pytest.fixture(scope="session")
def pt_dataset(tmp_path_factory) -> Path:
    """Two 32x32 crops with path-traced inputs and targets (do not modify)."""
    from gdpt.training.preprocess import build_dataset

    root = tmp_path_factory.mktemp("pt-dataset") / "data"
    config = make_tiny_dataset_config(resolution=32, levels=2, target_spp=16, target="pt")
    build_dataset(config, root, progress=False)
    return root


def _resume_after_a_lost_checkpoint(
    run: Path, config: TrainConfig, train: Callable
) -> tuple[list[dict], dict, dict]:
    """Delete ``run``'s checkpoint of step 3 (killed before writing it), resume; return the new
    log and the step-3 training states before and after."""
    import torch

    from gdpt.training.run_dir import read_jsonl

    state = run / "checkpoints" / "ckpt-0000003.pt"

    def training_state() -> dict:  # the training time ("elapsed") is not part of it
        payload = torch.load(state, weights_only=True)
        return {k: payload[k] for k in ("step", "model", "optimizer")}

    before = training_state()
    for suffix in (".pt", ".safetensors", ".json"):
        state.with_suffix(suffix).unlink()
    train(config, resume=True, progress=False)
    return read_jsonl(run / "log.jsonl"), before, training_state()


@pytest.fixture(scope="session")
def resume_after_a_lost_checkpoint() -> Callable[..., tuple[list[dict], dict, dict]]:
    """:func:`_resume_after_a_lost_checkpoint`, as a fixture."""
    return _resume_after_a_lost_checkpoint


def _assert_same_state(a: object, b: object, where: str = "state") -> None:
    """Assert that two nested training states (dicts, lists, tensors, numbers) are identical."""
    import torch

    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and torch.equal(a, b), f"{where} differs"
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), f"{where}: keys differ"
        for key in a:
            _assert_same_state(a[key], b[key], f"{where}[{key!r}]")
    elif isinstance(a, list | tuple):
        assert type(a) is type(b) and len(a) == len(b), f"{where}: lengths differ"
        for index, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same_state(x, y, f"{where}[{index}]")
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


@pytest.fixture(scope="session")
def assert_same_state() -> Callable[[object, object], None]:
    """:func:`_assert_same_state`, as a fixture."""
    return _assert_same_state


def make_tiny_run_config(data: Path, out: Path, **changes) -> TrainConfig:
    """A 3-step run on ``data`` (also the validation set) into ``out``; see the module doc."""
    from gdpt.training.config import TrainConfig

    settings = dict(
        data=str(data),
        val_data=str(data),
        out=str(out),
        steps=3,
        batch=2,
        warmup_steps=0,
        decay_start=1,
        half_life=2,
        val_every=2,
        val_crops=2,
        ckpt_every=1,
    )
    return TrainConfig(**{**settings, **changes})


@pytest.fixture(scope="session")
def tiny_run_config() -> Callable[..., TrainConfig]:
    """:func:`make_tiny_run_config`, as a fixture."""
    return make_tiny_run_config


@pytest.fixture(autouse=True)
def fresh_study_cost_models(monkeypatch):
    """Every test starts the study's cells and ``advise`` without cost models
    (:data:`gdpt.study.calibration._MODELS` is per process: a model of another test's clock
    would set this test's counts)."""
    from gdpt.study import calibration

    monkeypatch.setattr(calibration, "_MODELS", {})


@pytest.fixture
def cost_clock(monkeypatch) -> Callable[[str, float, float], None]:
    """A function ``(name, fixed, per_spp)``: the study method ``name``
    (:data:`gdpt.study.methods.EVAL_METHODS`) renders and reconstructs as before but reports
    ``seconds = fixed + per_spp * spp`` (``render_seconds = per_spp * spp``,
    ``reconstruct_seconds = fixed``) instead of its wall time, until the test ends.

    The calibration then finds the same sample counts on any machine under any load (counts
    a test may assert exactly); the wall clock stays in the tests that time real runs (e.g.
    ``tests/gdpt/test_nfor_method.py``).
    """
    from gdpt.study.methods import EVAL_METHODS

    def use(name: str, fixed: float, per_spp: float) -> None:
        method = EVAL_METHODS[name]

        def run(scene, *, spp: int, seed: int):
            result = method.run(scene, spp=spp, seed=seed)
            return dataclasses.replace(
                result,
                seconds=fixed + per_spp * spp,
                render_seconds=per_spp * spp,
                reconstruct_seconds=fixed,
            )

        def render(scene, *, spp: int, seed: int):
            result = method.render(scene, spp=spp, seed=seed)
            seconds = per_spp * spp
            return dataclasses.replace(result, seconds=seconds, render_seconds=seconds)

        replaced = dataclasses.replace(method, run=run, render=method.render and render)
        monkeypatch.setitem(EVAL_METHODS, name, replaced)

    return use
