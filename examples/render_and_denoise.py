"""Render a scene with gradient-domain path tracing and reconstruct it, in one process.

    .venv/bin/python examples/render_and_denoise.py [SCENE.xml] [--spp 64] [--out out/example]

Without a scene file the built-in Cornell box is used. XML scenes get their pixel filter replaced
by a box filter (gradient-domain rendering needs one); the script says so.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gdpt
from gdpt.io.images import save_png
from gdpt.scenes import builtin_scene
from gdpt.scenes.loading import load_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene", nargs="?", help="Mitsuba XML scene (default: built-in cbox)")
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--out", type=Path, default=Path("out/example"))
    args = parser.parse_args()

    gdpt.set_variant()
    if args.scene:
        print(f"{args.scene}: pixel filter replaced by a box filter")
        scene = load_scene(args.scene, box_filter=True, long_side=256)
    else:
        scene = load_scene(builtin_scene("cbox-demo"))

    result = gdpt.render_and_denoise(scene, spp=args.spp, method="l1-fast", progress=True)
    args.out.mkdir(parents=True, exist_ok=True)
    gdpt.save_buffers(args.out / "buffers.exr", result.buffers, force=True)
    save_png(args.out / "primal.png", result.buffers.primal, force=True)
    save_png(args.out / "l1-fast.png", result.image, force=True)
    timings = ", ".join(f"{k} {v:.2f} s" for k, v in result.timings.items())
    print(f"wrote {args.out}/ ({timings})")


if __name__ == "__main__":
    main()
