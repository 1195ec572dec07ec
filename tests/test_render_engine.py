"""The LPV GI render engine from the built zip installed in a fresh headless Blender (bpy):
listed, its F12 and animation renders go through Blender's pipeline into multi-layer EXRs
whose passes are the batch CLI's numbers, Ctrl-C stops an animation keeping the finished
frames, the compositor sees the passes, the Rendered viewport's image is the F12 frame of the
same view, Blender's panels show for it, and the main panel warns about left-out light."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

ROOT = Path(__file__).resolve().parents[1]
MODULE = f"bl_ext.user_default.{tomllib.loads((ROOT / 'blender_manifest.toml').read_text())['id']}"
PASSES = ("Combined", "Diffuse Direct", "Diffuse Indirect", "Diffuse Color")
W, H = 64, 48
INTENSITY = {1: 1.0, 2: 2.0, 3: 0.5}  # keyframed Scene.lpv.intensity

SCRIPT = r"""
import importlib, json, os, signal, sys, threading
from types import SimpleNamespace
import bpy, gpu
import numpy as np
from mathutils import Matrix

zip_path, module, tmp, w, h, keys = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), \
    int(sys.argv[5]), json.loads(sys.argv[6])
# Ctrl-C raises KeyboardInterrupt here even where the job runs with SIGINT ignored (a shell's
# background job), which this process would inherit
signal.signal(signal.SIGINT, signal.default_int_handler)
out = {"install": sorted(bpy.ops.extensions.package_install_files(
    filepath=zip_path, repo="user_default", enable_on_install=True))}
sub = lambda name: importlib.import_module(f"{module}.lpv_addon.{name}")
out["engines"] = [getattr(e, "bl_idname", "") for e in bpy.types.RenderEngine.__subclasses__()]
out["compat"] = {p: "LPV_GI" in getattr(bpy.types, p).COMPAT_ENGINES
                 for p in ("DATA_PT_light", "EEVEE_MATERIAL_PT_surface", "RENDER_PT_format",
                           "RENDER_PT_eevee_sampling")}

sub("scene_io.demo").cornell_box("SPOT", resolution=(w, h))
scene = bpy.context.scene
scene.render.engine = "LPV_GI"
scene.lpv.quality = "DRAFT"
for frame, value in keys.items():
    scene.lpv.intensity = value
    scene.keyframe_insert("lpv.intensity", frame=int(frame))
scene.frame_start, scene.frame_end = 1, 3
for name in ("direct", "indirect", "color"):
    setattr(scene.view_layers[0], f"use_pass_diffuse_{name}", True)
im = scene.render.image_settings
if hasattr(im, "media_type"):
    im.media_type = "MULTI_LAYER_IMAGE"
im.file_format, im.color_depth = "OPEN_EXR_MULTILAYER", "32"
scene.frame_set(2)
bpy.ops.wm.save_as_mainfile(filepath=os.path.join(tmp, "scene.blend"))

scene.render.filepath = os.path.join(tmp, "f12", "still.exr")
out["f12"] = sorted(bpy.ops.render.render(write_still=True))
# Output > Render Region, without and with Crop to Render Region
r = scene.render
r.use_border, r.border_min_x, r.border_max_x = True, 0.25, 0.75
r.border_min_y, r.border_max_y = 0.2, 0.8
for crop in (False, True):
    r.use_crop_to_border = crop
    r.filepath = os.path.join(tmp, "border_crop" if crop else "border", "still.exr")
    out["border_crop" if crop else "border"] = sorted(bpy.ops.render.render(write_still=True))
r.use_border = r.use_crop_to_border = False
scene.render.filepath = os.path.join(tmp, "anim", "frame_")
out["anim"] = sorted(bpy.ops.render.render(animation=True))

# Ctrl-C while frame 2 computes: the signal is sent 50 ms after the stats line that comes
# just before the engine waits on the worker, so the main thread meets it in that wait (a
# bigger frame keeps the wait long). Sent later, it could meet the main thread in Blender's
# C code and then surface in a render_stats handler, which Blender's handler call swallows.
def on_stats(text):
    if "propagation" in str(text) and bpy.context.scene.frame_current == 2:
        threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGINT)).start()
bpy.app.handlers.render_stats.append(on_stats)
scene.render.resolution_percentage = 400
scene.lpv.antialias = 4
scene.render.filepath = os.path.join(tmp, "cancel", "frame_")
try:
    bpy.ops.render.render(animation=True)
    out["cancel"] = "finished"
except RuntimeError as exc:
    out["cancel"] = str(exc)
bpy.app.handlers.render_stats.remove(on_stats)
scene.render.resolution_percentage = 100
scene.lpv.antialias = 2
scene.frame_set(2)
scene.render.filepath = os.path.join(tmp, "after_cancel", "still.exr")
out["after_cancel"] = sorted(bpy.ops.render.render(write_still=True))

# The compositor: a File Output node writes Diffuse Indirect.
tree = bpy.data.node_groups.new("Compositing", "CompositorNodeTree")
scene.compositing_node_group = tree
rl, fo = tree.nodes.new("CompositorNodeRLayers"), tree.nodes.new("CompositorNodeOutputFile")
fo.file_output_items.new("RGBA", "indirect")
fo.directory, fo.file_name = os.path.join(tmp, "comp") + os.sep, "out_"
fo.format.media_type, fo.format.file_format, fo.format.color_depth = "IMAGE", "OPEN_EXR", "32"
out["rl_outputs"] = [o.name for o in rl.outputs]
tree.links.new(rl.outputs["Diffuse Indirect"], fo.inputs["indirect"])
bpy.ops.render.render(write_still=False)
scene.compositing_node_group = None

# The Rendered viewport's image for the camera's matrices, and its drawing.
r = scene.render
r.engine, r.resolution_x, r.resolution_y = "BLENDER_WORKBENCH", 8, 8
bpy.ops.render.render(write_still=False)  # Blender's GPU context, headless
r.engine, r.resolution_x, r.resolution_y = "LPV_GI", w, h
rendered, passes, live = sub("viewport.rendered"), sub("render.passes"), sub("viewport.live")
dg = bpy.context.evaluated_depsgraph_get()
cam = scene.camera.evaluated_get(dg)
view_scene = rendered.view_scene(dg, cam.matrix_world.inverted(),
                                 cam.calc_matrix_camera(dg, x=w, y=h), (w, h))
client = live.client()
view, _ = passes.receive(client, passes.send(client, view_scene, "test"), block=True)
res = {"view_" + k.replace(" ", "_"): v for k, v in view.items()}
scene.lpv.antialias = 1  # F12 with the viewport's one sample per pixel
scene.render.filepath = os.path.join(tmp, "f12_aa1", "still.exr")
bpy.ops.render.render(write_still=True)
def offscreen(draw):  # what draw() draws into a w x h float buffer, top row first
    off = gpu.types.GPUOffScreen(w, h, format="RGBA32F")
    with off.bind():
        fb = gpu.state.active_framebuffer_get()
        fb.clear(color=(0, 0, 0, 0))
        with gpu.matrix.push_pop(), gpu.matrix.push_pop_projection():
            gpu.matrix.load_identity()
            gpu.matrix.load_projection_matrix(Matrix.Translation((-1, -1, 0))
                                              @ Matrix.Diagonal((2 / w, 2 / h, 1, 1)))
            draw()
        buf = fb.read_color(0, 0, w, h, 4, 0, "FLOAT")
    off.free()
    buf.dimensions = w * h * 4
    return np.array(buf.to_list(), np.float32).reshape(h, w, 4)[::-1]
from gpu_extras.presets import draw_texture_2d
res["drawn"] = offscreen(
    lambda: draw_texture_2d(rendered.image_texture(view["Combined"]), (0, 0), w, h))

# View.draw as view_draw calls it, with the region's size and matrices (no window headless)
# and the two RenderEngine methods it uses: request, polled redraws, the image drawn.
import time
class Engine:
    stats = []
    def get_preview_pixel_size(self, scene):
        return 1
    def update_stats(self, stats, info):
        self.stats.append(info)
ctx = SimpleNamespace(region=SimpleNamespace(width=w, height=h), region_data=SimpleNamespace(
    view_matrix=cam.matrix_world.inverted(), window_matrix=cam.calc_matrix_camera(dg, x=w, y=h)))
view_state, engine, requests = rendered.View(), Engine(), []
def view_draw():
    img = offscreen(lambda: view_state.draw(engine, ctx, dg))
    requests.append(view_state.pending is not None)
    return img
for _ in range(1200):
    res["view_draw"] = view_draw()
    if view_state.image is not None:
        break
    time.sleep(0.05)
res["view_draw"] = view_draw()  # the same view again: no new request
out["view_draw_requests"], out["view_draw_stats"] = requests, engine.stats

# Film > Transparent: alpha 0 where no surface is seen; Workbench's coverage as reference.
scene.render.film_transparent = True
scene.render.filepath = os.path.join(tmp, "transparent", "still.exr")
bpy.ops.render.render(write_still=True)
scene.render.engine = "BLENDER_WORKBENCH"
scene.render.filepath = os.path.join(tmp, "workbench", "still.exr")
bpy.ops.render.render(write_still=True)
scene.render.engine, scene.render.film_transparent = "LPV_GI", False

# The main panel's warnings: the World and an emissive material are modelled (no warning);
# a missing image is approximated, named.
scene.world = scene.world or bpy.data.worlds.new("World")
scene.world.use_nodes = True
bg = scene.world.node_tree.nodes["Background"]
bg.inputs["Color"].default_value, bg.inputs["Strength"].default_value = (0.5, 0.6, 0.8, 1), 1.0
mat = bpy.data.materials.new("Glow")
mat.use_nodes = True
mat.node_tree.nodes["Principled BSDF"].inputs["Emission Strength"].default_value = 5.0
mat.node_tree.nodes["Principled BSDF"].inputs["Emission Color"].default_value = (1, 1, 1, 1)
tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
tex.image = bpy.data.images.new("no_such_image.png", 4, 4)
tex.image.source = "FILE"
tex.image.filepath = os.path.join(tmp, "no_such_image.png")
mat.node_tree.links.new(tex.outputs["Color"],
                        mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
bpy.data.objects["BackWall"].data.materials[0] = mat
scene.lpv.enabled = True
live.refresh(scene, wait=True)
class Recorder:
    def __init__(self):
        self.labels = []
    def label(self, text="", icon="NONE", **_):
        self.labels.append([text, icon])
    def __getattr__(self, name):
        return lambda *a, **k: self
ui = sub("ui")
rec = Recorder()
ui.LPV_PT_main.draw(SimpleNamespace(layout=rec), bpy.context)
out["panel_labels"] = rec.labels
out["warning_lines"] = ui.warning_lines(live.STATE.current.stats)
np.savez(os.path.join(tmp, "view.npz"), **res)
addon_utils = importlib.import_module("addon_utils")
addon_utils.disable(module, default_set=True)
scene.render.engine = "CYCLES"
try:
    scene.render.engine = "LPV_GI"
    out["engine_after"] = True
except TypeError:
    out["engine_after"] = False
out["compat_after"] = "LPV_GI" in bpy.types.DATA_PT_light.COMPAT_ENGINES
print("RESULT=" + json.dumps(out))
"""


def _exr(path: Path) -> dict:
    from lpv_core.render import exr

    return exr.read_multilayer(path)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from tools.build_extension import build_extension

    tmp = tmp_path_factory.mktemp("engine")
    ext_zip = build_extension(tmp_path_factory.mktemp("dist"))
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp / "blender_user"),
               MESA_SHADER_CACHE_DIR=str(tmp / "mesa_cache"))
    env.pop("PYTHONPATH", None)
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(ext_zip), MODULE, str(tmp),
                           str(W), str(H), json.dumps(INTENSITY)], cwd=tmp, env=env,
                          capture_output=True, text=True, check=False, timeout=900)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT=")]
    assert proc.returncode == 0 and lines, (proc.stdout + proc.stderr)[-4000:]
    return tmp, json.loads(lines[-1][len("RESULT="):]), env


@pytest.fixture(scope="module")
def cli(run) -> Path:
    """The batch CLI (from this repository) on the .blend the engine rendered: frames 1-3."""
    tmp, _, env = run
    proc = subprocess.run([sys.executable, "-m", "lpv_addon.batch", str(tmp / "scene.blend"),
                           "--out", str(tmp / "cli"), "--frames", "1-3", "--quiet"], cwd=ROOT,
                          env=dict(env, PYTHONPATH=str(ROOT)), capture_output=True, text=True,
                          check=False, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return tmp / "cli"


def _same(ours: dict, ref: dict, what: str, tol: float = 1e-6) -> None:
    """The four passes equal up to ``tol`` of each pass's peak. Measured between the engine
    and the CLI: Diffuse Direct and Color identical, Indirect (and so Combined) within 1 ulp,
    from the order each process reuses its cached per-light grids across frames."""
    for name in PASSES:
        peak = float(np.abs(ref[name]).max())
        assert ours[name].shape == ref[name].shape and peak > 0, (what, name)
        err = float(np.abs(ours[name] - ref[name]).max())
        assert err <= tol * peak, (what, name, err, peak)


def _cli_frame(folder: Path, frame: int) -> dict:
    (path,) = sorted(folder.glob(f"*{frame:04d}.exr"))
    return _exr(path)


def test_engine_listed_with_blenders_panels(run):
    _, out, _ = run
    assert out["install"] == ["FINISHED"]
    assert "LPV_GI" in out["engines"]
    assert out["compat"] == {"DATA_PT_light": True, "EEVEE_MATERIAL_PT_surface": True,
                             "RENDER_PT_format": True, "RENDER_PT_eevee_sampling": False}
    assert not out["engine_after"] and not out["compat_after"]


def test_f12_exr_passes_equal_the_batch_cli(run, cli):
    tmp, out, _ = run
    assert out["f12"] == ["FINISHED"]
    ours, ref = _exr(tmp / "f12" / "still.exr"), _cli_frame(cli, 2)
    assert set(PASSES) <= set(ours)
    for name in PASSES:
        assert ours[name].shape == (H, W, 4 if name == "Combined" else 3), name
    _same(ours, ref, "F12")


def test_render_region_renders_that_region_of_the_frame(run):
    """Output > Render Region (x 0.25-0.75, y 0.2-0.8 from the bottom): the region holds the
    full F12 frame's pixels there, Crop to Render Region keeps just them (the region's
    result was the whole frame's size, refused, and with Crop Blender crashed)."""
    tmp, out, _ = run
    assert out["border"] == out["border_crop"] == ["FINISHED"]
    full = _exr(tmp / "f12" / "still.exr")
    region = _exr(tmp / "border" / "still.exr")
    crop = _exr(tmp / "border_crop" / "still.exr")
    x0, x1 = int(0.25 * W), int(0.75 * W)
    y0, y1 = H - int(0.8 * H), H - int(0.2 * H)  # rows top-first
    inside = {k: v[y0:y1, x0:x1] for k, v in full.items()}
    assert crop["Combined"].shape[:2] == (y1 - y0, x1 - x0)
    _same(crop, inside, "crop")
    _same({k: v[y0:y1, x0:x1] for k, v in region.items()}, inside, "region")
    outside = np.ones((H, W), bool)
    outside[y0:y1, x0:x1] = False
    assert float(np.abs(region["Diffuse Color"][outside]).max()) == 0.0


def test_animation_renders_three_frames_with_animated_values(run, cli):
    tmp, out, _ = run
    assert out["anim"] == ["FINISHED"]
    files = sorted(p.name for p in (tmp / "anim").iterdir())
    assert files == ["frame_0001.exr", "frame_0002.exr", "frame_0003.exr"]
    frames = {f: _exr(tmp / "anim" / f"frame_{f:04d}.exr") for f in (1, 2, 3)}
    for f, ours in frames.items():
        _same(ours, _cli_frame(cli, f), f"frame {f}")
    # Scene.lpv.intensity scales the indirect light: 1, 2, 0.5 on frames 1, 2, 3.
    base = frames[1]["Diffuse Indirect"].sum()
    for f in (2, 3):
        ratio = frames[f]["Diffuse Indirect"].sum() / base
        assert ratio == pytest.approx(INTENSITY[f] / INTENSITY[1], rel=1e-4), f
        np.testing.assert_array_equal(frames[f]["Diffuse Direct"], frames[1]["Diffuse Direct"])


def test_ctrl_c_keeps_finished_frames_and_writes_no_partial_file(run):
    tmp, out, _ = run
    assert "cancelled" in out["cancel"]
    assert sorted(p.name for p in (tmp / "cancel").iterdir()) == ["frame_0001.exr"]
    first = _exr(tmp / "cancel" / "frame_0001.exr")
    assert first["Combined"].shape == (4 * H, 4 * W, 4) and first["Combined"].max() > 0
    # The engine renders again after a cancel (a new worker), the same numbers.
    assert out["after_cancel"] == ["FINISHED"]
    again, f12 = _exr(tmp / "after_cancel" / "still.exr"), _exr(tmp / "f12" / "still.exr")
    _same(again, f12, "after the cancel")


def test_compositor_file_output_writes_diffuse_indirect(run):
    import OpenEXR

    tmp, out, _ = run
    assert {"Diffuse Direct", "Diffuse Indirect", "Diffuse Color"} <= set(out["rl_outputs"])
    (path,) = sorted((tmp / "comp").glob("*.exr"))
    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.parts[0].channels
        rgb = np.stack([np.asarray(ch[c].pixels) for c in "RGB"], axis=-1)
    f12 = _exr(tmp / "f12" / "still.exr")["Diffuse Indirect"]
    np.testing.assert_allclose(rgb, f12, rtol=1e-6, atol=1e-7)


def test_rendered_viewport_image_matches_f12(run):
    """The view's image for the camera's matrices is F12's frame at one sample per pixel; against
    F12 at the scene's anti-aliasing (2) the overlay's median tolerance holds, the differences
    sit on polygon and shadow edges; the gpu module draws it exactly as computed, upright."""
    tmp, _, _ = run
    shots = np.load(tmp / "view.npz")
    one = _exr(tmp / "f12_aa1" / "still.exr")
    # up to the float noise of the view matrix (inverted here, decomposed by the extraction)
    _same({n: shots["view_" + n.replace(" ", "_")] for n in PASSES}, one, "view", tol=1e-3)
    got, expect = shots["view_Combined"][..., :3], _exr(tmp / "f12" / "still.exr")["Combined"]
    expect = expect[..., :3]
    m = expect.max(axis=2) > 0.01 * expect.max()
    assert m.sum() > 0.4 * W * H
    rel = np.abs(got[m] - expect[m]) / expect[m]
    print(f"\nviewport (1 sample) vs F12 (antialias 2): median rel {np.median(rel):.2e}, "
          f"p80 {np.percentile(rel, 80):.2e}, p95 {np.percentile(rel, 95):.2e}")
    # at 64x48 a fifth of the pixels lie on a polygon or shadow edge, which F12 averages
    assert np.median(rel) < 0.01 and np.percentile(rel, 80) < 0.05
    assert got[m].sum() / expect[m].sum() == pytest.approx(1.0, rel=0.02)
    # (linear texture filtering at the pixel centres: float rounding)
    np.testing.assert_allclose(shots["drawn"], shots["view_Combined"], rtol=1e-4, atol=1e-5)


def test_view_draw_requests_once_and_draws_the_answer(run):
    """View.draw (what view_draw runs): the first draw sends the view to the worker, redraws
    poll until the image arrives and draw it; an unchanged view sends nothing new."""
    tmp, out, _ = run
    shots = np.load(tmp / "view.npz")
    requests, stats = out["view_draw_requests"], out["view_draw_stats"]
    assert requests[0] and not requests[-1] and not requests[-2], requests
    assert requests == sorted(requests, reverse=True)  # one request in flight, then none
    assert stats[0] == "LPV GI: updating" and stats[-1] == "", stats
    np.testing.assert_allclose(shots["view_draw"], shots["view_Combined"], rtol=1e-4, atol=1e-5)


def test_film_transparent_alpha_follows_coverage(run):
    tmp, _, _ = run
    alpha = _exr(tmp / "transparent" / "still.exr")["Combined"][..., 3]
    cover = _exr(tmp / "workbench" / "still.exr")["Combined"][..., 3]
    empty, full = cover < 0.01, cover > 0.99  # (Workbench's pixel filter is wider than 1 px)
    assert empty.sum() > 20 and full.sum() > 0.5 * W * H
    assert (alpha[empty] == 0).all() and (alpha[full] == 1).all()


def test_main_panel_names_approximated_input(run):
    _, out, _ = run
    lines = out["warning_lines"]
    missing = [line for line in lines if line.startswith("approximated: material 'Glow'")
               and "no_such_image.png" in line and "magenta" in line]
    assert missing, lines
    assert not any("world" in line or "emissive" in line for line in lines), lines
    text = " ".join(t for t, _ in out["panel_labels"])
    icons = [i for _, i in out["panel_labels"]]
    assert "no_such_image.png" in text and icons.count("ERROR") >= 1, out
