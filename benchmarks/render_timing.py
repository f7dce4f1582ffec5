"""Timing of Mitsuba renders for the benchmarks that compare integrators or configurations.

:func:`interleaved_rounds` renders every configuration twice untimed (the first render compiles
the kernels, the first two record the frozen passes), then times ``repeats`` rounds with new
seeds, each round rendering every configuration once, back to back: on a shared virtual machine
the speed drifts by 10-20% over tens of seconds, which would bias ratios of configurations timed
one after the other. Imported by the scripts of this folder (run as scripts, so this folder is
on ``sys.path``).
"""

from __future__ import annotations

import time
from pathlib import Path

#: The shared scenes beside the repository (``../shared/scenes``).
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"


def load_shared(name: str, long_side: int):
    """``(scene, (width, height))``: shared scene ``name`` with a box filter at ``long_side``."""
    from gdpt.scenes.loading import load_scene

    scene = load_scene(SHARED / name / "scene.xml", box_filter=True, long_side=long_side)
    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    return scene, (width, height)


def time_render(scene, integrator, spp: int, seed: int) -> float:
    """Seconds of one ``mi.render`` until its image is evaluated and the device is idle."""
    import drjit as dr
    import mitsuba as mi

    start = time.perf_counter()
    image = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
    dr.eval(image)
    dr.sync_thread()
    return time.perf_counter() - start


def interleaved_rounds(
    scene, integrators: dict[str, object], spp: int, repeats: int
) -> tuple[dict[str, float], dict[str, list[float]]]:
    """Time ``integrators`` (label -> integrator) on ``scene`` at ``spp``: two untimed renders
    each (seeds 0 and 1), then ``repeats`` interleaved rounds (seeds 2, 3, ...).

    Returns:
        ``(first, runs)``: the seconds of each configuration's first render (compilation and
        recording included) and its ``repeats`` timed renders, by label.
    """
    first = {}
    for label, integrator in integrators.items():
        first[label] = time_render(scene, integrator, spp, seed=0)
        time_render(scene, integrator, spp, seed=1)
    runs = {label: [] for label in integrators}
    for r in range(repeats):
        for label, integrator in integrators.items():
            runs[label].append(time_render(scene, integrator, spp, seed=2 + r))
    return first, runs
