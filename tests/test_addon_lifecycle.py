"""The built extension installed in a fresh headless Blender: enabled and disabled 20 times and
files reloaded, nothing is left behind: no app handler, timer, draw handler, GPU resource,
worker process or registered class. The live engine works from the installed zip (the worker
runs the extension's own lpv_core)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

ROOT = Path(__file__).resolve().parents[1]
MODULE = f"bl_ext.user_default.{tomllib.loads((ROOT / 'blender_manifest.toml').read_text())['id']}"

SCRIPT = r"""
import json, os, sys
import bpy, gpu, addon_utils

zip_path, module, tmp = sys.argv[1], sys.argv[2], sys.argv[3]
HANDLER_LISTS = ("depsgraph_update_post", "frame_change_post", "undo_post", "redo_post",
                 "load_pre", "load_post", "render_pre", "render_post", "save_pre", "save_post")

def ours_in_handlers():
    return sum(1 for name in HANDLER_LISTS for fn in getattr(bpy.app.handlers, name)
               if getattr(fn, "__module__", "").startswith(module))

def sub(name):
    import importlib
    return importlib.import_module(f"{module}.lpv_addon.{name}")

def enabled_state():
    h, ov, lv = sub("viewport.handlers"), sub("viewport.overlay"), sub("viewport.live")
    menu = sum(getattr(f, "__module__", "").startswith(module)
               for f in bpy.types.VIEW3D_MT_add._dyn_ui_initialize())
    return {"handlers": ours_in_handlers(), "timer": bpy.app.timers.is_registered(h.timer),
            "draw": ov.handler_count(), "ours": h.registered_count(), "menu": menu}

out = {"install": sorted(bpy.ops.extensions.package_install_files(
    filepath=zip_path, repo="user_default", enable_on_install=True))}

# GPU context for offscreen drawing (headless).
r = bpy.context.scene.render
r.engine, r.resolution_x, r.resolution_y = "BLENDER_WORKBENCH", 8, 8
bpy.ops.render.render(write_still=False)

def build_scene():
    sub("scene_io.demo").cornell_box("SPOT", resolution=(32, 32))  # the shipped demo
    scene = bpy.context.scene
    scene.lpv.quality = "DRAFT"
    scene.lpv.rsm_resolution = 32
    return scene

def draw_once():
    ov = sub("viewport.overlay")
    off = gpu.types.GPUOffScreen(16, 16)
    with off.bind():
        ov.draw(bpy.context.scene.camera.matrix_world.inverted(),
                bpy.context.scene.camera.calc_matrix_camera(
                    bpy.context.evaluated_depsgraph_get(), x=16, y=16), depth_prepass=True)
    off.free()

cycles = []
timers, procs = [], []
for i in range(20):
    state = enabled_state()
    work = i % 5 == 0
    if work:  # exercise the live engine, the worker and GPU resources before disabling
        scene = build_scene()
        lv = sub("viewport.live")
        lv.refresh(scene, wait=True)
        state["lpv"] = lv.STATE.current is not None and lv.STATE.current.values is not None
        procs.append(lv.STATE.client.proc)
        draw_once()
        state["resources"] = sub("viewport.overlay").resource_count()
    timers.append(sub("viewport.handlers").timer)
    ov_mod, lv_mod = sub("viewport.overlay"), sub("viewport.live")
    addon_utils.disable(module, default_set=True)
    state["after_disable"] = {
        "handlers": ours_in_handlers(),
        "timers": sum(bpy.app.timers.is_registered(t) for t in timers),
        "draw": ov_mod.handler_count(), "resources": ov_mod.resource_count(),
        "worker": lv_mod.STATE.client is not None,
        "procs_alive": sum(p.poll() is None for p in procs),
        "scene_lpv": hasattr(bpy.types.Scene, "lpv"),
        "light_lpv": hasattr(bpy.types.Light, "lpv"),
        "panel": hasattr(bpy.types, "LPV_PT_main"),
        "operator": hasattr(bpy.types, "LPV_OT_update"),
        "menu": any(getattr(f, "__module__", "").startswith(module)
                    for f in bpy.types.VIEW3D_MT_add._dyn_ui_initialize()),
    }
    cycles.append(state)
    addon_utils.enable(module, default_set=True)
out["cycles"] = cycles
out["enabled_after_loop"] = enabled_state()

# Reload files: handlers stay exactly once, the live state of the old file is gone.
scene = build_scene()
scene.lpv.intensity = 1.75
sub("viewport.live").refresh(scene, wait=True)
path = os.path.join(tmp, "reload.blend")
bpy.ops.wm.save_as_mainfile(filepath=path)
bpy.ops.wm.open_mainfile(filepath=path)
out["after_reload"] = enabled_state()
out["reload_intensity"] = bpy.context.scene.lpv.intensity
out["reload_result_dropped"] = sub("viewport.live").STATE.current is None
out["reload_worker_stopped"] = sub("viewport.live").STATE.client is None
bpy.ops.wm.read_homefile(use_empty=True)
out["after_homefile"] = enabled_state()
ov_mod, lv_mod = sub("viewport.overlay"), sub("viewport.live")
addon_utils.disable(module, default_set=True)
out["final"] = {"handlers": ours_in_handlers(),
                "timers": sum(bpy.app.timers.is_registered(t) for t in timers),
                "draw": ov_mod.handler_count(), "resources": ov_mod.resource_count(),
                "procs_alive": sum(p.poll() is None for p in procs)}
print("RESULT=" + json.dumps(out))
"""


@pytest.fixture(scope="module")
def ext_zip(tmp_path_factory):
    from tools.build_extension import build_extension

    return build_extension(tmp_path_factory.mktemp("dist"))


@pytest.fixture(scope="module")
def result(ext_zip, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("lifecycle")
    env = dict(os.environ)
    env["BLENDER_USER_RESOURCES"] = str(tmp / "blender_user")
    env["MESA_SHADER_CACHE_DIR"] = str(tmp / "mesa_cache")
    env.pop("PYTHONPATH", None)
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(ext_zip), MODULE, str(tmp)],
                          cwd=tmp, capture_output=True, text=True, check=False, timeout=300,
                          env=env)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT=")]
    assert proc.returncode == 0 and lines, (proc.stdout + proc.stderr)[-4000:]
    return json.loads(lines[-1][len("RESULT="):])


ENABLED = {"handlers": 6, "timer": True, "draw": 1, "ours": 8, "menu": 1}


def test_enable_disable_20_times_leaves_nothing(result):
    assert result["install"] == ["FINISHED"]
    assert len(result["cycles"]) == 20
    for i, c in enumerate(result["cycles"]):
        assert {k: c[k] for k in ENABLED} == ENABLED, (i, c)
        after = c["after_disable"]
        assert after == {"handlers": 0, "timers": 0, "draw": 0, "resources": 0,
                         "worker": False, "procs_alive": 0, "scene_lpv": False,
                         "light_lpv": False, "panel": False, "operator": False,
                         "menu": False}, (i, after)


def test_the_installed_extension_computes_and_draws(result):
    worked = [c for c in result["cycles"] if "lpv" in c]
    assert len(worked) == 4
    assert all(c["lpv"] for c in worked)
    assert all(c["resources"] > 0 for c in worked)


def test_file_reload_keeps_one_set_of_handlers_and_drops_live_state(result):
    assert result["enabled_after_loop"] == ENABLED
    assert result["after_reload"] == ENABLED
    assert result["after_homefile"] == ENABLED
    assert result["reload_intensity"] == pytest.approx(1.75)
    assert result["reload_result_dropped"] and result["reload_worker_stopped"]


def test_final_disable_leaves_nothing(result):
    assert result["final"] == {"handlers": 0, "timers": 0, "draw": 0, "resources": 0,
                               "procs_alive": 0}
