"""Bit-exact reproduction of ``gdpt``'s buffers at fixed seeds on every built-in scene.

A guard for refactors of the integrator: ``data/gdpt_identity.json`` holds the SHA-256 digest of
every buffer (primal, dx, dy, features, variances: the float32 bytes of each) and the guard
counts of ``gdpt`` on each built-in scene (but ``degenerate``, see ``UNSTABLE``) at 16 x 16
pixels, 2 spp, one seed, plus cases with a ``shift_threshold`` that turns on the half-vector
copy and one without gradients. A change of the arithmetic (operation order, random-number
consumption, a branch) changes some of these floats; a pure restructuring of the code does
not. Digests instead of the buffers keep the references at a few KB (the buffers themselves
take ~390 KB compressed); equal digests mean equal bits, and a failure names the buffers that
differ.

Exactness needs the platform that recorded the references. Dr.Jit's LLVM backend emits
IEEE operations without fast-math flags (no reassociation, no contraction into FMA), so a
kernel gives the same floats however the Python code that traced it is arranged, and the
same run to run. But it compiles for the host CPU (``target-cpu`` native), ``dr.rsqrt`` (also
inside ``dr.normalize``) lowers to the CPU's approximate reciprocal square root (``rsqrtps``;
``vrsqrt14ps`` with AVX-512) refined by one Newton step, whose last bits differ between
vendors and instruction sets, and Embree picks its intersection kernels per instruction set.
Other CPUs, and other Mitsuba or Dr.Jit versions, can therefore give other floats. The
references hold a canary for this: the digest of the same scene rendered by Mitsuba's own
``path`` integrator. Where the canary does not reproduce, the test skips (naming the platform
that recorded the references) instead of comparing with a tolerance: at 2 spp one flipped
discrete decision (a hit, a roulette draw) replaces a whole sample, so no per-pixel tolerance
tells platform noise from a regression. ``test_gdpt_unbiased.py`` checks the integrator's
correctness on any platform.

After an intended change of ``gdpt``'s output, or on a new platform, regenerate the
references with ``python tests/integrators/test_gdpt_identity.py``.
"""

from __future__ import annotations

import hashlib
import json
import platform
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from gdpt.machine import cpu_name

DATA = Path(__file__).resolve().parent / "data" / "gdpt_identity.json"
RESOLUTION, SPP, SEED = (16, 16), 2, 7
#: Integrator settings of every case: every output on, roulette from depth 2.
BASE = {"type": "gdpt", "max_depth": 6, "rr_depth": 2, "variance": True}
#: Settings changed per case (besides the plain ``BASE`` on every built-in scene).
EXTRA = {
    "half": {"shift_threshold": 0.1},  # the half-vector copy on glossy lobes of alpha <= 0.1
    "nograd": {"gradients": False},  # no offsets: phase 1 is skipped
}
#: Built-in scenes with a glossy lobe of alpha in (0.001, 0.1]: ``half`` differs from ``BASE``.
HALF_SCENES = ("near-specular", "principled")
#: Built-in scenes whose renders are not reproducible from one process to the next:
#: ``degenerate`` has coincident faces, where the hit among primitives at equal distance
#: depends on Embree's parallel BVH build (observed: one process in six gave other buffers,
#: for ``path`` as well).
UNSTABLE = ("degenerate",)
#: Cases run in CI (delta and null lobes, the half-vector copy, no gradients, a cone-sampled
#: light); all others are ``slow``.
FAST = {
    ("glass", "base"),
    ("alpha-mask", "base"),
    ("near-specular", "half"),
    ("sphere-light", "base"),
    ("cbox-demo", "nograd"),
}


def _cases() -> list[tuple[str, str]]:
    from gdpt.scenes import builtin_names

    cases = [(name, "base") for name in builtin_names() if name not in UNSTABLE]
    cases += [(name, "half") for name in HALF_SCENES]
    return [*cases, ("cbox-demo", "nograd")]


def _digest(array: np.ndarray) -> str:
    """SHA-256 (128 bits, hex) of the float32 bytes of ``array``."""
    data = np.ascontiguousarray(array, dtype=np.float32)
    return hashlib.sha256(data.tobytes()).hexdigest()[:32]


def _render(name: str, case: str) -> dict:
    """One case: ``gdpt`` (``buffers``: the digest of each of its named (H, W, C) buffers;
    ``guards``: its guard counts) and the ``path`` canary's digest (``path``)."""
    import mitsuba as mi

    from gdpt.scenes import builtin_scene

    scene = mi.load_dict(builtin_scene(name, resolution=RESOLUTION))
    integrator = mi.load_dict({**BASE, **EXTRA.get(case, {})})
    image = np.array(mi.render(scene, integrator=integrator, spp=SPP, seed=SEED))
    buffers, start = {}, 0
    for buffer, channels in integrator.channels():
        buffers[buffer] = _digest(image[..., start : start + channels])
        start += channels
    assert start == image.shape[-1], (integrator.channels(), image.shape)
    canary = mi.load_dict({"type": "path", "max_depth": BASE["max_depth"]})
    return {
        "buffers": buffers,
        "guards": dict(sorted(integrator.guard_counts.items())),
        "path": _digest(np.array(mi.render(scene, integrator=canary, spp=SPP, seed=SEED))),
    }


def _platform() -> str:
    import drjit as dr
    import mitsuba as mi

    return (
        f"{platform.machine()} '{cpu_name()}' ({_vector_isa()}), mitsuba {mi.__version__}, "
        f"drjit {dr.__version__}"
    )


def _vector_isa() -> str:
    """The widest x86 vector extension the CPU reports (Linux): CPUs of one model name (a
    virtual machine's generic 'AMD EPYC') differ in it, and with it in ``rsqrt``'s last bits."""
    cpuinfo = Path("/proc/cpuinfo")
    flags = set()
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
                break
    for isa in ("avx512f", "avx2", "avx", "sse4_2"):
        if isa in flags:
            return isa
    return "unknown ISA"


@cache
def _references() -> dict:
    return json.loads(DATA.read_text())


@pytest.mark.parametrize(
    ("name", "case"),
    [
        pytest.param(name, case, marks=() if (name, case) in FAST else pytest.mark.slow)
        for name, case in _cases()
    ],
)
def test_gdpt_buffers_are_bit_identical(variant, name, case):
    refs = _references()
    ref = refs["cases"][f"{name}.{case}"]
    got = _render(name, case)
    if got["path"] != ref["path"]:
        pytest.skip(
            f"Mitsuba's path integrator does not reproduce its reference on {name}: this "
            f"platform ({_platform()}) computes other floats than the recording one "
            f"({refs['platform']}); regenerate with "
            "`python tests/integrators/test_gdpt_identity.py`"
        )
    assert got["guards"] == ref["guards"]
    differ = [b for b in ref["buffers"] if got["buffers"].get(b) != ref["buffers"][b]]
    assert got["buffers"].keys() == ref["buffers"].keys()
    assert not differ, f"{name} ({case}): buffers {differ} differ from the reference"


if __name__ == "__main__":
    import gdpt

    gdpt.set_variant("llvm_ad_rgb")
    cases = {}
    for name, case in _cases():
        cases[f"{name}.{case}"] = _render(name, case)
        print(name, case, flush=True)
    settings = {"resolution": RESOLUTION, "spp": SPP, "seed": SEED, "base": BASE, "extra": EXTRA}
    refs = {"platform": _platform(), "settings": settings, "cases": cases}
    DATA.parent.mkdir(exist_ok=True)
    DATA.write_text(json.dumps(refs, indent=1) + "\n")
    print(f"wrote {DATA} ({DATA.stat().st_size} bytes)")
