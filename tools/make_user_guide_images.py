"""Pictures and the panel listing of docs/user-guide.md, made headlessly with the bpy module.

    .venv/bin/python tools/make_user_guide_images.py [--out docs/images] [--size 480x360]

What it makes (all from the real add-on, registered from this repository):
- overlay pictures: Blender's own ``gpu`` module draws the LPV overlay (lpv_addon/viewport/overlay.py)
  of the Cornell box into an offscreen buffer, exactly the code the 3D viewport runs; the
  engine runs in the worker process, as in the viewport. The "viewport shading" underneath is
  the direct light of our deferred renderer (the viewport's own EEVEE/Workbench drawing needs a
  window, which headless Blender does not have);
- the Cycles comparison heatmap of ``bpy.ops.lpv.compare_cycles``;
- panel pictures: Blender cannot draw its UI without a window, so the script runs each panel's
  real ``draw()`` against a recording layout and draws what it recorded (labels, values,
  buttons) with ``blf``. They show the layout and the live values, not Blender's widget look.
  The same recording is written as text into the guide between the ``panels`` markers.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="lpv_guide_user_"))

import bpy
import gpu
import numpy as np
from mathutils import Matrix

import lpv_addon
from lpv_addon import operators, ui
from lpv_addon.render import compare
from lpv_addon.viewport import live, overlay
from tools import scenes

GUIDE = ROOT / "docs" / "user-guide.md"
BEGIN, END = "<!-- panels:begin -->", "<!-- panels:end -->"


# ------------------------------------------------------------------------------ pictures


def save_png(path: Path, rgb: np.ndarray) -> None:
    """Write display-referred RGB (H, W, 3) in 0..1, rows top-first, as an 8-bit PNG."""
    h, w = rgb.shape[:2]
    img = bpy.data.images.new(path.stem, w, h, alpha=False)
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = np.clip(rgb, 0.0, 1.0)
    img.pixels.foreach_set(rgba[::-1].ravel())
    img.filepath_raw = str(path)
    img.file_format = "PNG"
    img.save()
    bpy.data.images.remove(img)
    print(f"wrote {path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}")


def to_display(linear: np.ndarray, white: float) -> np.ndarray:
    """Scene-linear -> sRGB with ``white`` mapped to 1 (a plain exposure, no tone curve)."""
    x = np.clip(linear / white, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def warm_up(scene) -> None:
    r = scene.render
    saved = (r.engine, r.resolution_x, r.resolution_y)
    r.engine, r.resolution_x, r.resolution_y = "BLENDER_WORKBENCH", 8, 8
    bpy.ops.render.render(write_still=False)  # creates Blender's GPU context headless
    r.engine, r.resolution_x, r.resolution_y = saved


def camera_matrices(scene, w, h):
    dg = bpy.context.evaluated_depsgraph_get()
    cam = scene.camera.evaluated_get(dg)
    return cam.matrix_world.inverted(), cam.calc_matrix_camera(dg, x=w, y=h)


def _full_screen(texture) -> None:
    from gpu_extras.batch import batch_for_shader

    shader = gpu.shader.from_builtin("IMAGE")
    batch = batch_for_shader(shader, "TRI_FAN", {
        "pos": ((-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)),
        "texCoord": ((0, 0), (1, 0), (1, 1), (0, 1))})
    with gpu.matrix.push_pop(), gpu.matrix.push_pop_projection():
        gpu.matrix.load_identity()
        gpu.matrix.load_projection_matrix(Matrix.Identity(4))
        shader.uniform_sampler("image", texture)
        batch.draw(shader)


def overlay_shot(scene, w, h, mode, background=None, **kw) -> np.ndarray:
    """The overlay in ``mode`` over an optional linear background (H, W, 3), linear RGB."""
    view, proj = camera_matrices(scene, w, h)
    off = gpu.types.GPUOffScreen(w, h, format="RGBA32F")
    with off.bind():
        fb = gpu.state.active_framebuffer_get()
        fb.clear(color=(0.0, 0.0, 0.0, 1.0), depth=1.0)
        if background is not None:
            rgba = np.ones((h, w, 4), np.float32)
            rgba[..., :3] = background[::-1]
            tex = gpu.types.GPUTexture((w, h), format="RGBA32F", data=gpu.types.Buffer(
                "FLOAT", rgba.size, rgba.ravel()))
            _full_screen(tex)
        overlay.draw(view, proj, mode=mode, depth_prepass=True, **kw)
        buf = fb.read_color(0, 0, w, h, 4, 0, "FLOAT")
    off.free()
    buf.dimensions = w * h * 4
    return np.array(buf.to_list(), np.float32).reshape(h, w, 4)[::-1, :, :3]


def build_scene(w: int, h: int):
    scenes.cornell_box("SPOT", resolution=(w, h))
    scene = bpy.context.scene
    # The yellow taxi that bleeds green: a yellow tall block bouncing green light.
    taxi = bpy.data.materials.new("Taxi Yellow")
    taxi.diffuse_color = (0.8, 0.6, 0.02, 1.0)
    taxi.lpv.use_bleed_color = True
    taxi.lpv.bleed_color = (0.05, 0.8, 0.1)
    taxi.lpv.bleed_intensity = 1.5
    return scene, taxi


def make_pictures(out: Path, w: int, h: int) -> dict:
    scene, taxi = build_scene(w, h)
    warm_up(scene)
    live.refresh(scene, wait=True)
    # A first result on a cold kernel cache comes from the numpy reference while the kernels
    # compile in the background: wait for them, so the statistics show the usual timings.
    client, deadline = live.client(), time.monotonic() + 900.0
    while time.monotonic() < deadline and client.wait(client.send("ping"), 60.0).get(
            "kernels", {}).get("state") == "compiling":
        time.sleep(1.0)
    live.refresh(scene, wait=True)
    passes, _ = compare.render_passes(scene, (w, h))
    base = passes["Diffuse Direct"] * passes["Diffuse Color"]
    white = float(np.percentile(base[base > 0], 98)) if (base > 0).any() else 1.0
    pics = {}

    def shot(name, mode, background=None, gain=1.0, **kw):
        img = overlay_shot(scene, w, h, mode, background, **kw)
        save_png(out / f"{name}.png", to_display(img * gain, white))
        pics[name] = img

    save_png(out / "viewport_direct.png", to_display(base, white))
    shot("overlay_add", "ADD", base)
    shot("overlay_indirect", "INDIRECT", gain=3.0)
    for mode in ("CASCADES", "VPLS", "PROBES", "OCCLUSION"):
        dim = base * 0.35
        img = overlay_shot(scene, w, h, mode, dim)
        save_png(out / f"debug_{mode.lower()}.png", to_display(img, white))

    # Art direction, one change at a time (indirect only, x3 so the bounce is visible).
    tall = bpy.data.objects["TallBlock"]
    tall.material_slots[0].link = "OBJECT"
    tall.material_slots[0].material = taxi
    live.mark_dirty("guide")
    live.refresh(scene, wait=True)
    shot("art_bleed_green", "INDIRECT", gain=3.0)
    tall.lpv.gi_caster = False
    live.refresh(scene, wait=True)
    shot("art_non_caster", "INDIRECT", gain=3.0)
    tall.lpv.gi_caster = True
    bpy.data.objects["BackWall"].lpv.gi_receiver = False
    live.refresh(scene, wait=True)
    shot("art_non_receiver", "INDIRECT", gain=3.0)
    bpy.data.objects["BackWall"].lpv.gi_receiver = True
    bpy.data.lights["Spot"].lpv.gi_color = (1.0, 0.45, 0.2)
    live.refresh(scene, wait=True)
    shot("art_light_tint", "INDIRECT", gain=3.0)
    bpy.data.lights["Spot"].lpv.gi_color = (1.0, 1.0, 1.0)
    area = bpy.data.objects.new("LPV Transition Area", None)
    area.empty_display_type = "CUBE"
    area.location, area.scale = (0.6, 0.0, 1.0), (0.4, 1.2, 1.2)
    area.lpv.area_type = "TRANSITION"
    area.lpv.area_intensity, area.lpv.area_falloff = 3.0, 0.3
    area.lpv.area_tint = (0.6, 0.8, 1.0)
    scene.collection.objects.link(area)
    live.refresh(scene, wait=True)
    shot("art_transition", "INDIRECT", gain=3.0)
    area.lpv.area_type = "CLIP"
    live.refresh(scene, wait=True)
    shot("art_clip", "INDIRECT", gain=3.0)
    bpy.data.objects.remove(area)

    # The Cycles comparison heatmap (small and quick, upscaled with nearest pixels).
    live.refresh(scene, wait=True)
    bpy.ops.lpv.compare_cycles(resolution=96, samples=64)
    for name, file in ((operators.IMAGE_ERROR, "compare_heatmap"),
                       (operators.IMAGE_OURS, "compare_lpv"),
                       (operators.IMAGE_CYCLES, "compare_cycles")):
        img = bpy.data.images[name]
        iw, ih = img.size
        px = np.empty(iw * ih * 4, np.float32)
        img.pixels.foreach_get(px)
        rgb = px.reshape(ih, iw, 4)[::-1, :, :3]
        rgb = np.repeat(np.repeat(rgb, 3, axis=0), 3, axis=1)
        save_png(out / f"{file}.png", rgb if file == "compare_heatmap"
                 else to_display(rgb, white / 3.0))
    pics["compare_summary"] = scene.lpv.compare_summary
    return pics


# --------------------------------------------------------------------------------- panels


class Recorder:
    """Records what a panel's draw() puts into its layout (Blender needs a window to draw
    real widgets). Attributes that only style the layout are accepted and ignored."""

    def __init__(self, items: list, depth: int = 0):
        self.items = items
        self.depth = depth
        self.use_property_split = False
        self.use_property_decorate = False
        self.active = True
        self.enabled = True
        self.alignment = "EXPAND"

    def _sub(self, *args, **kw):
        return Recorder(self.items, self.depth + (1 if kw.get("heading") else 0))

    row = column = box = split = column_flow = grid_flow = _sub

    def separator(self, **kw):
        self.items.append(("sep", "", ""))

    def label(self, text="", icon="NONE", **kw):
        self.items.append(("label", text, ""))

    def prop(self, data, name, text=None, **kw):
        rna = data.bl_rna.properties[name]  # KeyError: the panel draws a missing property
        value = getattr(data, name)
        if rna.type == "ENUM":
            value = rna.enum_items[value].name if value in rna.enum_items else value
        elif rna.type == "BOOLEAN":
            value = "[x]" if value else "[ ]"
        elif rna.type == "FLOAT" and getattr(rna, "array_length", 0):
            value = "(" + ", ".join(f"{v:.2f}" for v in value) + ")"
        elif rna.type == "FLOAT":
            value = f"{value:.3g}"
        self.items.append(("prop", rna.name if text is None else text or rna.name, str(value)))

    def operator(self, idname, text=None, icon="NONE", **kw):
        mod, name = idname.split(".")
        op = getattr(getattr(bpy.ops, mod), name)
        label = text or op.get_rna_type().name
        self.items.append(("button", label, idname))
        return SimpleNamespace()

    def operator_menu_enum(self, idname, prop, text="", **kw):
        self.items.append(("button", text, idname))

    def template_list(self, listtype, list_id, data, propname, active_data, active_prop, **kw):
        cls = getattr(bpy.types, listtype)
        items = getattr(data, propname)
        flags, _ = cls.filter_items(SimpleNamespace(bitflag_filter_item=1 << 30), None,
                                    data, propname)
        for ob, flag in zip(items, flags):
            if not flag:
                continue
            if listtype == "LPV_UL_lights":
                lp = ob.data.lpv
                color = ", ".join(f"{c:.2f}" for c in lp.gi_color)
                self.items.append(("list", ob.name, f"GI {lp.gi_intensity:.2f}  tint ({color})"))
            else:
                self.items.append(("list", ob.name, ob.lpv.area_type.title()))


def record_panel(cls, context) -> list:
    items: list = []
    layout = Recorder(items)
    owner = SimpleNamespace(layout=layout)
    if hasattr(cls, "draw_header"):
        header: list = []
        cls.draw_header(SimpleNamespace(layout=Recorder(header)), context)
        items.append(("header", cls.bl_label, header[0][2] if header else ""))
    else:
        items.append(("header", cls.bl_label, ""))
    cls.draw(owner, context)
    return items


def panel_records(scene) -> list[tuple[str, list]]:
    if not any(ob.lpv.area_type != "NONE" for ob in scene.objects):
        area = bpy.data.objects.new("LPV Clip Area", None)
        area.empty_display_type = "CUBE"
        area.lpv.area_type = "CLIP"
        scene.collection.objects.link(area)
        scene.lpv.active_area_index = list(scene.objects).index(area)
    context = SimpleNamespace(
        scene=scene, view_layer=scene.view_layers[0], light=bpy.data.lights["Spot"],
        object=bpy.data.objects["TallBlock"], material=bpy.data.materials["White"])
    out = []
    for cls in ui.CLASSES:
        if not issubclass(cls, bpy.types.Panel):
            continue
        context_names = {"data": "Light (Object Data)", "object": "Object",
                         "material": "Material"}
        where = (f"3D Viewport > Sidebar > {cls.bl_category}" if cls.bl_space_type == "VIEW_3D"
                 else f"Properties > {context_names.get(cls.bl_context, cls.bl_context)}")
        parent = getattr(cls, "bl_parent_id", "")
        if parent:
            where += f" > {getattr(ui, parent).bl_label}"
        out.append((where, record_panel(cls, context)))
    # The area settings as an Empty's Object properties show them.
    context.object = next(ob for ob in scene.objects if ob.lpv.area_type != "NONE")
    out.append(("Properties > Object (an Empty used as a GI area)",
                record_panel(ui.LPV_PT_object, context)))
    return out


def panels_text(records) -> str:
    lines = []
    for where, items in records:
        lines.append(f"{where}")
        for kind, text, value in items:
            if kind == "header":
                lines.append(f"  == {text} ==" + (f"  {value}" if value else ""))
            elif kind == "prop":
                lines.append(f"    {text:<22} {value}")
            elif kind == "button":
                lines.append(f"    [ {text} ]  ({value})")
            elif kind == "list":
                lines.append(f"    | {text:<20} {value}")
            elif kind == "label":
                lines.append(f"    {text}")
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"


def draw_panels(path: Path, records, width: int = 420) -> None:
    """Draw the recorded panels with blf: a picture of the layout and its values."""
    import blf

    rows = sum(len(items) + 2 for _, items in records)
    line = 18
    height = rows * line + 10
    off = gpu.types.GPUOffScreen(width, height)
    from gpu_extras.batch import batch_for_shader

    rect_shader = gpu.shader.from_builtin("UNIFORM_COLOR")

    def rect(x0, y0, x1, y1, color):
        batch = batch_for_shader(rect_shader, "TRI_FAN", {
            "pos": ((x0, y0, 0), (x1, y0, 0), (x1, y1, 0), (x0, y1, 0))})
        rect_shader.uniform_float("color", color)
        batch.draw(rect_shader)

    with off.bind():
        fb = gpu.state.active_framebuffer_get()
        fb.clear(color=(0.16, 0.16, 0.16, 1.0))
        with gpu.matrix.push_pop(), gpu.matrix.push_pop_projection():
            gpu.matrix.load_identity()
            gpu.matrix.load_projection_matrix(Matrix((
                (2 / width, 0, 0, -1), (0, 2 / height, 0, -1), (0, 0, 1, 0), (0, 0, 0, 1))))
            y = height - line
            blf.size(0, 12)
            for where, items in records:
                blf.color(0, 0.6, 0.75, 1.0, 1.0)
                blf.position(0, 6, y, 0)
                blf.draw(0, where)
                y -= line
                for kind, text, value in items:
                    if kind == "header":
                        rect(4, y - 4, width - 4, y + line - 4, (0.24, 0.24, 0.24, 1.0))
                        blf.color(0, 1, 1, 1, 1)
                        blf.position(0, 12, y, 0)
                        blf.draw(0, (value + " " if value else "") + text)
                    elif kind == "button":
                        rect(30, y - 3, width - 30, y + line - 5, (0.33, 0.33, 0.33, 1.0))
                        blf.color(0, 0.95, 0.95, 0.95, 1)
                        blf.position(0, width / 2 - 4 * len(text), y, 0)
                        blf.draw(0, text)
                    else:
                        blf.color(0, 0.85, 0.85, 0.85, 1)
                        blf.position(0, 24, y, 0)
                        blf.draw(0, text)
                        if value:
                            rect(200, y - 3, width - 10, y + line - 5, (0.1, 0.1, 0.1, 1.0))
                            blf.position(0, 206, y, 0)
                            blf.draw(0, value[:36])
                    y -= line
                y -= line // 2
        buf = fb.read_color(0, 0, width, height, 4, 0, "FLOAT")
    off.free()
    buf.dimensions = width * height * 4
    img = np.array(buf.to_list(), np.float32).reshape(height, width, 4)[::-1, :, :3]
    save_png(path, img)


def update_guide(text: str) -> None:
    if not GUIDE.is_file():
        return
    doc = GUIDE.read_text()
    if BEGIN not in doc or END not in doc:
        return
    head, rest = doc.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    GUIDE.write_text(f"{head}{BEGIN}\n```text\n{text}```\n{END}{tail}")
    print(f"updated the panel listing in {GUIDE.relative_to(ROOT)}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "images")
    parser.add_argument("--size", default="480x360", help="overlay picture size WxH")
    args = parser.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    lpv_addon.register()
    try:
        pics = make_pictures(args.out, w, h)
        records = panel_records(bpy.context.scene)
        text = panels_text(records)
        (args.out / "panels.txt").write_text(text)
        sidebar = [r for r in records if r[0].startswith("3D Viewport")]
        props = [r for r in records if not r[0].startswith("3D Viewport")]
        draw_panels(args.out / "panels_sidebar.png", sidebar)
        draw_panels(args.out / "panels_properties.png", props)
        update_guide(text)
        print("comparison:", pics.get("compare_summary", ""))
    finally:
        lpv_addon.unregister()
    return 0


if __name__ == "__main__":
    sys.exit(main())
