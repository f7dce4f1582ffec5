"""Ctrl-C and killed drivers: one line saying what was kept, exit status 130, the same command
resumes (and says from where); the workers of a killed ``gdpt dataset --workers 2`` end with it."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

import gdpt.rendering
import gdpt.training.train
from gdpt.cli import main
from gdpt.interrupt import caused_by_interrupt, interrupts_deferred
from gdpt.study.results import cells_done
from gdpt.training.manifest import read_manifest

#: A 3-crop dataset of 16x16 crops with a handful of samples (seconds per crop).
DATASET = ["dataset", "--scenes", "1", "--views", "3", "--resolution", "16"]
DATASET += ["--spp-max", "4", "--target-spp", "8", "--max-depth", "4"]

#: A 2-cell study of one method on a 16x16 procedural scene.
STUDY = ["evaluate", "--scenes", "random:3", "--resolution", "16", "--budgets", "0.1", "0.2"]
STUDY += ["--reference-spp", "4", "--methods", "pt", "--quick", "--no-progress"]


@pytest.fixture(autouse=True)
def sigint_default():
    """Python's own Ctrl-C handler in this process during each test, also where the test run
    itself ignores SIGINT (a non-interactive shell starts background jobs so): the children it
    starts then get SIGINT at its default too (exec resets a caught signal, not an ignored one).
    """
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def gdpt_process(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "gdpt", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def interrupt_when(args: list[str], ready: Callable[[], bool]) -> tuple[int, str]:
    """Run ``gdpt ARGS``, send SIGINT once ``ready()``; ``(exit status, stderr)``."""
    process = gdpt_process(*args)
    deadline = time.monotonic() + 120
    while not ready():
        assert process.poll() is None, f"finished before the signal: {process.stderr.read()}"
        assert time.monotonic() < deadline, "never ready"
        time.sleep(0.01)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=120)
    return process.returncode, err


def run_again(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "gdpt", *args],
        check=False,
        capture_output=True,
        text=True,
        timeout=300,
    )


def last_line(err: str) -> str:
    """The last line of stderr, after checking that no traceback came before it."""
    assert "Traceback" not in err, err
    return err.strip().splitlines()[-1]


def test_a_keyboard_interrupt_is_found_in_an_exception_chain():
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as interrupt:  # as Dr.Jit's frozen-function recorder does
            raise RuntimeError("record(): error encountered") from interrupt
    except RuntimeError as wrapped:
        assert caused_by_interrupt(wrapped)
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise ValueError("while handling it") from None
    except ValueError as context:
        assert caused_by_interrupt(context)  # __context__ is kept, only not shown
    assert caused_by_interrupt(KeyboardInterrupt())
    assert not caused_by_interrupt(RuntimeError("out of memory"))


def test_a_ctrl_c_in_a_plugin_constructor_reported_by_mitsubas_parser_is_recognised(variant):
    """Mitsuba's parser turns a Python plugin's exception into a ``RuntimeError`` carrying the
    traceback as text, with no chain: a Ctrl-C while a scene loads reaches the CLI so."""
    import mitsuba as mi

    class Interrupted(mi.SamplingIntegrator):
        def __init__(self, props):
            super().__init__(props)
            raise KeyboardInterrupt

    mi.register_integrator("gdpt_test_interrupted", Interrupted)
    with pytest.raises(RuntimeError) as raised:
        mi.load_dict({"type": "gdpt_test_interrupted"})
    assert raised.value.__cause__ is None and raised.value.__context__ is None
    assert caused_by_interrupt(raised.value)
    assert not caused_by_interrupt(RuntimeError("Traceback (most recent call last):\nValueError"))


def test_a_ctrl_c_inside_a_deferred_block_is_raised_at_its_end():
    finished = []
    with pytest.raises(KeyboardInterrupt), interrupts_deferred():
        os.kill(os.getpid(), signal.SIGINT)  # (as Mitsuba's module set-up would receive it)
        time.sleep(0.05)
        finished.append(True)
    assert finished == [True]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_ctrl_c_inside_a_dataset_render_says_what_was_kept_and_the_same_command_resumes(
    tmp_path,
):
    out = tmp_path / "data"
    args = [*DATASET, "--out", str(out)]
    # The crop's folder is made just before its first render: the signal lands in its kernels.
    status, err = interrupt_when(args, (out / "crops" / "s00000-v000").is_dir)
    assert status == 130, err
    assert last_line(err) == (
        "gdpt dataset: interrupted after 0 of 3 crops; run the same command to resume"
    )
    status, err = interrupt_when(args, lambda: bool(read_manifest(out)[0]))
    assert status == 130, err
    assert re.fullmatch(
        r"gdpt dataset: interrupted after [12] of 3 crops; run the same command to resume",
        last_line(err),
    )
    done = len(read_manifest(out)[0])
    result = run_again(args)
    assert result.returncode == 0, result.stderr
    assert f"{out}: resuming: {done} of 3 crops done" in result.stderr
    assert f"rendered {3 - done} crops, {done} already done" in result.stdout
    assert len(read_manifest(out)[0]) == 3


def test_ctrl_c_during_a_study_says_what_was_kept_and_the_same_command_resumes(tmp_path):
    out = tmp_path / "study"
    args = [*STUDY, "--out", str(out)]
    # While the scene loads or its reference renders.
    status, err = interrupt_when(args, (out / "images").is_dir)
    assert status == 130, err
    results = out / "results.json"
    assert last_line(err) == (
        f"gdpt evaluate: interrupted with 0 cells done in {results}; run the same command to resume"
    )

    def a_cell_is_done() -> bool:
        try:
            return cells_done(json.loads(results.read_text())) > 0
        except (OSError, ValueError):
            return False

    status, err = interrupt_when(args, a_cell_is_done)
    assert status == 130, err
    done = cells_done(json.loads(results.read_text()))
    assert done in (1, 2)
    assert last_line(err) == (
        f"gdpt evaluate: interrupted with {done} cells done in {results}; "
        "run the same command to resume"
    )
    result = run_again(args)
    assert result.returncode == 0, result.stderr
    assert f"{results}: resuming: {done} of 2 cells done" in result.stderr
    assert cells_done(json.loads(results.read_text())) == 2


def children(pid: int) -> list[int]:
    """Process ids whose parent is ``pid`` (from ``/proc``)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                found.append(int(entry.name))
    return found


def running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="reads /proc (Linux)")
def test_workers_end_with_a_killed_dataset_driver(tmp_path):
    out = tmp_path / "data"
    # Crops of ~10 s each: without their parent, workers would render on for seconds.
    heavy = ["--resolution", "64", "--spp-max", "64", "--target-spp", "1024"]
    process = gdpt_process(*DATASET, *heavy, "--out", str(out), "--workers", "2")
    deadline = time.monotonic() + 120
    workers: list[int] = []
    while len(workers) < 2:  # spawned workers run multiprocessing.spawn
        assert process.poll() is None and time.monotonic() < deadline, process.stderr.read()
        time.sleep(0.05)
        workers = [
            pid
            for pid in children(process.pid)
            if b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes()
        ]
    while not (out / "crops").is_dir():  # the workers are rendering
        assert process.poll() is None and time.monotonic() < deadline, process.stderr.read()
        time.sleep(0.05)
    process.kill()
    process.wait(timeout=60)  # (not communicate: the workers share its stderr pipe)
    killed = time.monotonic()
    while any(running(pid) for pid in workers) and time.monotonic() - killed < 2.0:
        time.sleep(0.05)
    left = [pid for pid in workers if running(pid)]
    for pid in left:  # this test's own processes, so that they do not outlive it either
        os.kill(pid, signal.SIGKILL)
    process.communicate(timeout=60)
    assert not left, "workers outlived their parent by 2 s"


def test_ctrl_c_in_train_and_render_says_what_was_kept(tmp_path, monkeypatch, capsys):
    def interrupted_render(*args, **kwargs):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as interrupt:  # as Dr.Jit's frozen-function recorder does
            raise RuntimeError("record(): error encountered") from interrupt

    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    for step in (2, 3):
        for suffix in (".pt", ".safetensors", ".json"):
            (run / "checkpoints" / f"ckpt-{step:07d}{suffix}").write_bytes(b"")
    monkeypatch.setattr(gdpt.training.train, "train", interrupted_render)
    argv = ["train", "--config", "fast_xs", "--data", str(tmp_path), "--out", str(run)]
    assert main(argv) == 130
    assert capsys.readouterr().err == (
        f"gdpt train: interrupted; step 3 is kept in {run}/checkpoints/ckpt-0000003.*; "
        "run the same command with --resume to continue\n"
    )
    assert main([*argv, "--resume"]) == 130
    assert "; run the same command to continue\n" in capsys.readouterr().err

    monkeypatch.setattr(gdpt.rendering, "render", interrupted_render)
    output = tmp_path / "out" / "render.exr"
    assert main(["render", "builtin:cbox-demo", "--spp", "1", "-o", str(output)]) == 130
    assert capsys.readouterr().err == (
        f"gdpt render: interrupted; nothing written ({output} is written at the end)\n"
    )
    assert not output.exists()
