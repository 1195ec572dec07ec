"""The HDRI sun split (lpv_core sky.split_sun) on ``hdri_yard`` (sky_yard under
tools/make_source_images.hdri's generated image) against Cycles, with the sun left in the map
(before) and split off as a SUN lamp (after): Diffuse Direct over Cycles' lit pixels,
indirect relative RMSE, HDR-FLIP of Combined and the LPV time, as tools/sources_check.

    .venv/bin/python tools/hdri_sun_check.py [--samples 512]   (reference cached in .cache/)
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="lpv_hdri_sun_"))
os.environ.setdefault("LPV_GI_CACHE_DIR", tempfile.mkdtemp(prefix="lpv_hdri_sun_cache_"))

import bpy
import numpy as np

import lpv_addon
import lpv_core as core
from lpv_addon.render.cycles import render_cycles_passes
from lpv_addon.scene_io import world as W
from lpv_addon.scene_io.extract import extract_scene
from lpv_core.render.error import indirect_term, relative_rmse
from tools import make_source_images, report, sources_check

RESOLUTION = (128, 128)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=512)
    args = ap.parse_args(argv)
    lpv_addon.register()
    make_source_images.build("hdri_yard", RESOLUTION)
    exr = ROOT / ".cache" / "hdri_yard" / f"cycles_{args.samples}.exr"
    if not exr.exists():
        exr.parent.mkdir(parents=True, exist_ok=True)
        render_cycles_passes(exr, samples=args.samples, diffuse_bounces=1,
                             resolution=RESOLUTION)
    ref = report._read_exr(exr)
    engine = report._make_engine(core.render.raster.Rasterizer())
    split = core.sky.split_sun
    try:
        for label in ("before", "after"):
            core.sky.split_sun = split if label == "after" else \
                (lambda m: (np.asarray(m, np.float32), None))
            W._MEMORY.clear()
            cs = extract_scene(bpy.context.evaluated_depsgraph_get(), bpy.context.scene,
                               RESOLUTION)
            run = report.run_lpv(cs, dataclasses.replace(cs.settings), engine, 1)
            test = run["passes"]
            print(f"{label}: lamps {[lt.name for lt in cs.lights]}, Diffuse Direct "
                  f"{sources_check.direct_ratio(test, ref):.3f}, indirect "
                  f"{relative_rmse(indirect_term(test), indirect_term(ref)):.3f}, HDR-FLIP "
                  f"{report.hdr_flip(report.combined_term(test), report.combined_term(ref)):.3f}"
                  f", LPV {run['time_s']:.2f} s", flush=True)
    finally:
        core.sky.split_sun = split
    return 0


if __name__ == "__main__":
    sys.exit(main())
