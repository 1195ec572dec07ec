"""The user guide's pictures of the light sources LPV GI reads (the World's colour, an HDRI,
the Sky Texture, emissive materials, soft lights), made headlessly with the bpy module.

    .venv/bin/python tools/make_source_images.py [--out docs/images] [--size 256x256]
        [--samples 64] [--only sky_room,hdri_yard,sky_yard,panel_room,soft_room]

For each scene (tools/scenes.py; ``hdri_yard`` is sky_yard lit by a generated HDR image
instead of the Sky Texture) it writes ``source_<scene>.png``: on the left the LPV_GI
engine's F12 render (``bpy.ops.render.render`` with the engine, as an artist presses F12), on
the right Cycles with ``--samples`` samples and OpenImageDenoise, one diffuse bounce; both
through Blender's Standard view transform at the same exposure.
"""

from __future__ import annotations

import argparse
import math
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
from lpv_addon.render import cycles
from lpv_core.render import exr
from tools import scenes

SCENES = ("sky_room", "hdri_yard", "sky_yard", "panel_room", "soft_room")
EXPOSURE = {"sky_room": 1.0, "hdri_yard": -1.0, "sky_yard": -1.0, "panel_room": 0.0,
            "soft_room": -2.0}


def hdri(w: int = 256, h: int = 128) -> bpy.types.Image:
    """A float equirect image: a blue sky graded to white at the horizon, a brown ground and a
    small warm sun 30 deg up (about 1000 x the sky) - a stand-in for a photographed HDRI."""
    v = (np.arange(h) + 0.5) / h  # rows bottom-first, as Blender stores them
    u = (np.arange(w) + 0.5) / w
    el = (v - 0.5)[:, None] * math.pi
    phi = (0.5 - u)[None, :] * 2 * math.pi
    sky = np.where(el[..., None] > 0, np.array([0.35, 0.55, 1.0]) * (0.4 + 0.6 * np.exp(
        -4 * el[..., None])), np.array([0.25, 0.18, 0.12]))
    sky = np.broadcast_to(sky, (h, w, 3)).copy()
    d = np.stack([np.cos(el) * np.cos(phi), np.cos(el) * np.sin(phi),
                  np.sin(el) * np.ones_like(phi)], -1)
    sun = np.array([math.cos(math.radians(30)) * math.cos(math.radians(-40)),
                    math.cos(math.radians(30)) * math.sin(math.radians(-40)),
                    math.sin(math.radians(30))])
    sky[(d @ sun) > math.cos(math.radians(2.5))] = (600.0, 520.0, 420.0)
    img = bpy.data.images.new("HDRI", w, h, alpha=True, float_buffer=True)
    rgba = np.concatenate([sky, np.ones((h, w, 1))], -1).astype(np.float32)
    img.pixels.foreach_set(rgba.ravel())
    img.pack()
    return img


def build(name: str, size: tuple[int, int]) -> bpy.types.Scene:
    if name != "hdri_yard":
        scenes.build(name, resolution=size)
        return bpy.context.scene
    scenes.build("sky_yard", resolution=size)
    scene = bpy.context.scene
    tree = scene.world.node_tree
    for node in [n for n in tree.nodes if n.bl_idname == "ShaderNodeTexSky"]:
        tree.nodes.remove(node)
    env = tree.nodes.new("ShaderNodeTexEnvironment")
    env.image = hdri()
    bg = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeBackground")
    tree.links.new(env.outputs["Color"], bg.inputs["Color"])
    bg.inputs["Strength"].default_value = 1.0
    return scene


def make(name: str, out: Path, size: tuple[int, int], samples: int) -> Path:
    scene = build(name, size)
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.exposure = EXPOSURE.get(name, 0.0)
    tmp = Path(tempfile.mkdtemp(prefix="lpv_sources_img_"))
    scene.render.engine = "LPV_GI"
    scene.lpv.enabled = True
    im = scene.render.image_settings
    if hasattr(im, "media_type"):
        im.media_type = "IMAGE"
    im.file_format, im.color_mode = "PNG", "RGB"
    scene.render.filepath = str(tmp / "lpv.png")
    scene.render.use_file_extension = False
    bpy.ops.render.render(write_still=True)
    cycles.render_cycles_passes(tmp / "cycles.exr", samples=samples, denoise=True)
    combined = exr.read_multilayer(tmp / "cycles.exr")["Combined"][..., :3]
    lpv = bpy.data.images.load(str(tmp / "lpv.png"))
    w, h = lpv.size
    left = np.empty(w * h * 4, np.float32)
    lpv.pixels.foreach_get(left)
    left = left.reshape(h, w, 4)  # bottom-first, display-referred
    right = bpy.data.images.new("cycles", w, h, float_buffer=True)
    right.pixels.foreach_set(np.concatenate([combined[::-1], np.ones((h, w, 1), np.float32)],
                                            -1).ravel())
    right.save_render(str(tmp / "cycles.png"), scene=scene)
    right_png = bpy.data.images.load(str(tmp / "cycles.png"))
    rpx = np.empty(w * h * 4, np.float32)
    right_png.pixels.foreach_get(rpx)
    both = np.concatenate([left, np.ones((h, 4, 4), np.float32), rpx.reshape(h, w, 4)], 1)
    img = bpy.data.images.new(f"source_{name}", both.shape[1], h, alpha=False)
    img.pixels.foreach_set(both.ravel())
    path = out / f"source_{name}.png"
    img.filepath_raw = str(path)
    img.file_format = "PNG"
    img.save()
    print(f"wrote {path}", flush=True)
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default=str(ROOT / "docs" / "images"))
    p.add_argument("--size", default="256x256")
    p.add_argument("--samples", type=int, default=64)
    p.add_argument("--only", default=",".join(SCENES))
    args = p.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lpv_addon.register()
    for name in [n for n in args.only.split(",") if n]:
        make(name, out, size, args.samples)
    lpv_addon.unregister()
    return 0


if __name__ == "__main__":
    sys.exit(main())
