"""References in chunks: bit-identical whatever the workers, after a kill, and no slower.

For each scene (default: cornell-box and living-room-2 of ``../shared/scenes``; 128 px;
``--spp`` 2048 in chunks of 256, the study's default chunk; the study's reference seed), four
renders of the same reference, each in a fresh process and its own cache folder under ``--out``:

1. ``one render``: every sample in one ``render`` call (no chunks, no merge): what the samples
   cost on this machine, the floor for any chunking;
2. ``sequential``: ``gdpt evaluate --references-only`` (the chunks one after the other);
3. ``workers 2``: the same with ``--workers 2`` (Ray on this machine: two chunks at a time, each
   task given one core);
4. ``killed``: the sequential run killed (``SIGKILL``) half-way through a chunk once
   ``--kill-after`` chunks are on disk, then run again to the end (the chunks and temporary
   files on disk at the kill and after the resume are recorded).

The merged EXRs of 2-4 must be bit-identical (sha256 of their pixels). Seconds: the
reference's own record for 2-4 (``seconds`` of its sidecar JSON: the wall time of the chunks'
renders and writes, accumulated over the killed run and its resume; loading and the merge
excluded), the render call's for 1 (kernel compilation included in all four: each is one
process's first render). Prints a table and writes ``OUT/summary.md`` / ``summary.json``::

    .venv/bin/python benchmarks/reference_chunks.py --out out/reference-chunks

Run it on an otherwise idle machine (its seconds are compared).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

from render_timing import SHARED

REPO = Path(__file__).resolve().parents[1]
CHUNK_SPP = 256  # the study's reference_chunk_spp


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["cornell-box", "living-room-2"])
    parser.add_argument("--spp", type=int, default=2048)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--kill-after", type=int, default=3, help="chunks on disk before the kill")
    parser.add_argument("--out", type=Path, default=Path("out/reference-chunks"))
    parser.add_argument("--one-render", metavar="SCENE", help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def one_render(args: argparse.Namespace) -> None:
    """Child process of case 1: print the seconds of one render of every sample."""
    from gdpt.study.references import ReferenceChunk, reference_chunks, reference_seed, render_chunk
    from gdpt.study.scenes import SceneSpec, load_eval_scene

    scene = load_eval_scene(
        SceneSpec(args.one_render, str(SHARED / args.one_render / "scene.xml")),
        resolution=args.resolution,
    )
    seed = reference_chunks(args.spp, CHUNK_SPP, reference_seed(0))[0].seed
    start = time.perf_counter()
    render_chunk(scene, ReferenceChunk(0, 1, args.spp, seed))
    print(json.dumps({"seconds": time.perf_counter() - start}))


def evaluate_command(args: argparse.Namespace, scene: str, cache: Path, workers: int = 0) -> list:
    command = [sys.executable, "-m", "gdpt", "evaluate", "--quick", "--references-only"]
    command += ["--scenes", str(SHARED / scene), "--resolution", str(args.resolution)]
    command += ["--reference-spp", str(args.spp), "--references", str(cache)]
    command += ["--out", str(cache / "study"), "--no-progress"]
    return command + (["--workers", str(workers)] if workers else [])


def reference_of(cache: Path) -> tuple[str, float]:
    """``(sha256 of the merged reference's pixels, its recorded seconds)`` in ``cache``."""
    from gdpt.io.exr import load_image

    (sidecar,) = cache.glob("*spp-seed*.json")
    meta = json.loads(sidecar.read_text())
    assert meta.get("complete"), f"{sidecar}: not complete"
    pixels = load_image(sidecar.with_suffix(".exr")).numpy().tobytes()
    return hashlib.sha256(pixels).hexdigest(), float(meta["seconds"])


def run(command: list[str]) -> None:
    status = subprocess.run(command, check=False, cwd=REPO).returncode
    if status != 0:
        raise SystemExit(f"exit status {status}: {' '.join(command)}")


def killed_run(args: argparse.Namespace, scene: str, cache: Path, chunk_seconds: float) -> dict:
    """Start the sequential run, kill it half-way through the chunk after ``--kill-after``
    finished ones, run it again; what was on disk at the kill."""
    process = subprocess.Popen(evaluate_command(args, scene, cache), cwd=REPO)
    while len(list(cache.glob("*.chunk-*.exr"))) < args.kill_after:
        if process.poll() is not None:
            raise SystemExit(f"{scene}: the run ended before {args.kill_after} chunks")
        time.sleep(0.05)
    time.sleep(chunk_seconds / 2)
    process.send_signal(signal.SIGKILL)
    process.wait()
    on_disk = sorted(p.name.split(".chunk-")[1] for p in cache.glob("*.chunk-*.exr"))
    temporary = sorted(p.name for p in cache.glob(".*.tmp"))
    run(evaluate_command(args, scene, cache))
    left = sorted(p.name for p in cache.glob(".*.tmp"))
    return {"chunks_at_kill": on_disk, "temporary_at_kill": temporary, "temporary_after": left}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.one_render:
        one_render(args)
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    rows, numbers = [], {}
    for scene in args.scenes:
        folder = args.out / scene
        if folder.exists():
            raise SystemExit(f"{folder} exists: give another --out (nothing is overwritten)")
        child = [sys.executable, __file__, "--one-render", scene, "--spp", str(args.spp)]
        child += ["--resolution", str(args.resolution)]
        single = json.loads(
            subprocess.run(child, capture_output=True, text=True, check=True, cwd=REPO)
            .stdout.strip()
            .splitlines()[-1]
        )["seconds"]
        cases = {}
        run(evaluate_command(args, scene, folder / "sequential"))
        cases["sequential"] = reference_of(folder / "sequential")
        run(evaluate_command(args, scene, folder / "workers-2", workers=2))
        cases["workers 2"] = reference_of(folder / "workers-2")
        chunks = -(-args.spp // CHUNK_SPP)
        kill = killed_run(args, scene, folder / "killed", cases["sequential"][1] / chunks)
        cases["killed"] = reference_of(folder / "killed")
        identical = len({digest for digest, _ in cases.values()}) == 1
        numbers[scene] = {
            "one_render_seconds": single,
            **{name: {"sha256": d, "seconds": s} for name, (d, s) in cases.items()},
            "identical": identical,
            **kill,
        }
        rows.append(
            f"| {scene} | {single:.1f} | "
            + " | ".join(f"{s:.1f} ({s / single:.2f}x)" for _, s in cases.values())
            + f" | {'yes' if identical else 'NO'} | {len(kill['chunks_at_kill'])} |"
        )
    text = "\n".join(
        [
            f"{args.spp} spp at {args.resolution} px, chunks of {CHUNK_SPP}; seconds (over one "
            "render):",
            "",
            "| scene | one render s | sequential | workers 2 | killed + resumed | identical | "
            "chunks at the kill |",
            "|---|---:|---:|---:|---:|---|---:|",
            *rows,
        ]
    )
    print(text)
    (args.out / "summary.md").write_text(text + "\n")
    commit = subprocess.run(
        ["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True, check=False
    ).stdout.strip()
    record = {"commit": commit, "args": {k: str(v) for k, v in vars(args).items()}, **numbers}
    (args.out / "summary.json").write_text(json.dumps(record, indent=1))
    return 0 if all(n["identical"] for n in numbers.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
