"""The user guide's pictures of the LPV GI render engine, made headlessly with the bpy module.

    .venv/bin/python tools/make_engine_images.py [--out docs/images] [--size 480x360]

engine_f12.png: the Cornell box rendered by ``bpy.ops.render.render(write_still=True)`` with
the LPV_GI engine, written by Blender's own PNG output (Standard view transform, exposure -1).
engine_viewport.png: the Rendered viewport's image of the same view (viewport/rendered.py:
the view's passes from the live worker, one sample per pixel), saved with the same view
transform.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="lpv_guide_user_"))

import bpy
import numpy as np

import lpv_addon
from lpv_addon.render import passes
from lpv_addon.scene_io import demo
from lpv_addon.viewport import live, rendered


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default=str(ROOT / "docs" / "images"))
    p.add_argument("--size", default="480x360")
    args = p.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    out = Path(args.out)
    lpv_addon.register()
    demo.cornell_box("SPOT", resolution=(w, h))
    scene = bpy.context.scene
    scene.render.engine = "LPV_GI"
    scene.view_settings.view_transform, scene.view_settings.exposure = "Standard", -1.0
    im = scene.render.image_settings
    if hasattr(im, "media_type"):
        im.media_type = "IMAGE"
    im.file_format, im.color_mode = "PNG", "RGB"
    scene.render.filepath = str(out / "engine_f12.png")
    bpy.ops.render.render(write_still=True)
    print(f"wrote {scene.render.filepath}")

    dg = bpy.context.evaluated_depsgraph_get()
    cam = scene.camera.evaluated_get(dg)
    view = rendered.view_scene(dg, cam.matrix_world.inverted(),
                               cam.calc_matrix_camera(dg, x=w, y=h), (w, h))
    client = live.client()
    got, _ = passes.receive(client, passes.send(client, view, "guide"), block=True)
    img = bpy.data.images.new("engine_viewport", w, h, float_buffer=True)
    img.pixels.foreach_set(np.ascontiguousarray(got["Combined"][::-1], np.float32).ravel())
    img.save_render(str(out / "engine_viewport.png"), scene=scene)
    print(f"wrote {out / 'engine_viewport.png'}")
    lpv_addon.unregister()
    return 0


if __name__ == "__main__":
    sys.exit(main())
