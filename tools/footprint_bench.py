"""Cost of the Diffuse Color's texture footprint filter (textures.footprint_factor) on
tools.scenes.checker_room: the textured G-buffer of one sample with the filter (a 2x2
antialias sample's half-pixel cell) against the pixel's centre alone, median of 5.

    python -m tools.footprint_bench [--resolution 1920x1080 ...]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import numpy as np


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--resolution", nargs="+", default=["128x128", "1920x1080"])
    args = p.parse_args(argv)
    os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="lpv_fp_"))
    import bpy

    from lpv_addon.scene_io.extract import extract_scene
    from lpv_core import engine
    from lpv_core.engine import Stats
    from tools import scenes

    scenes.checker_room()
    for text in args.resolution:
        w, h = (int(v) for v in text.split("x"))
        s = extract_scene(bpy.context.evaluated_depsgraph_get(), bpy.context.scene, (w, h))
        eng = engine.Engine()
        eng.upload(s, Stats())
        cam = s.camera
        out = {}
        for fp in (0.0, 0.5):
            times = []
            for _ in range(5):
                t0 = time.perf_counter()
                eng.raster.gbuffer(cam.view, cam.projection, w, h, fp)
                times.append(time.perf_counter() - t0)
            out[fp] = float(np.median(times))
        info = eng.raster.surface.info
        covered = int(eng.raster.gbuffer(cam.view, cam.projection, w, h)[0].sum())
        print(f"{w}x{h}: G-buffer one sample {out[0.0] * 1e3:.1f} ms at the centre, "
              f"{out[0.5] * 1e3:.1f} ms filtered (+{(out[0.5] - out[0.0]) * 1e3:.1f} ms); "
              f"{info['footprint_refined']} of {covered} covered pixels refined")
    return 0


if __name__ == "__main__":
    sys.exit(main())
