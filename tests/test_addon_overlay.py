"""The viewport overlay drawn by Blender's own gpu module into an offscreen buffer, in a child
Blender process (the engine runs in the worker; moderngl never enters the drawing process).

Pixels are checked against the core deferred renderer (Diffuse Indirect x Diffuse Color of
the same camera): the overlay shows indirect light exactly where the LPV says, nothing where
gi_receiver is off, adds onto the viewport in ADD mode, blends old and new results while
fading in, scales inside transition areas, and draws the debug views."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT

pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

W = H = 64

SCRIPT = r"""
import json, os, sys
import bpy, gpu
import numpy as np
import lpv_addon
from lpv_addon import live, overlay, scenes

W = H = int(sys.argv[2])
out = sys.argv[1]
lpv_addon.register()
scenes.cornell_box("SPOT", resolution=(W, H))
scene = bpy.context.scene
scene.lpv.quality = "DRAFT"
scene.lpv.rsm_resolution = 64

def warm_up():
    r = scene.render
    saved = (r.engine, r.resolution_x, r.resolution_y)
    r.engine, r.resolution_x, r.resolution_y = "BLENDER_WORKBENCH", 8, 8
    bpy.ops.render.render(write_still=False)  # creates Blender's GPU context headless
    r.engine, r.resolution_x, r.resolution_y = saved

def matrices():
    dg = bpy.context.evaluated_depsgraph_get()
    cam = scene.camera.evaluated_get(dg)
    return cam.matrix_world.inverted(), cam.calc_matrix_camera(dg, x=W, y=H)

def shot(mode, clear=(0, 0, 0, 0), **kw):
    view, proj = matrices()
    off = gpu.types.GPUOffScreen(W, H, format="RGBA32F")
    with off.bind():
        fb = gpu.state.active_framebuffer_get()
        fb.clear(color=clear, depth=1.0)
        overlay.draw(view, proj, mode=mode, depth_prepass=True, **kw)
        buf = fb.read_color(0, 0, W, H, 4, 0, "FLOAT")
    off.free()
    buf.dimensions = W * H * 4
    return np.array(buf.to_list(), np.float32).reshape(H, W, 4)[::-1]  # top row first

from lpv_core.scene import GISettings
# The fast model for most shots (the overlay's job is the same in every model); each model
# is compared once below.
FAST = {k: v for k, v in (("angular", "sh"), ("direction_groups", 1))
        if k in GISettings.__dataclass_fields__}

def expected(**overrides):
    passes, _ = live.render_passes(scene, (W, H), overrides={**FAST, **overrides})
    return passes["Diffuse Indirect"] * passes["Diffuse Color"]

def refresh():
    live.mark_dirty("test")
    live.refresh(scene, wait=True, overrides=FAST)

warm_up()
res = {}
# Both angular models of the engine ("sh": KD10's clamped SH; "m1": max-entropy lobe), when
# the engine has them: the shader mirrors each lookup.
models = ["sh", "m1"] if "angular" in GISettings.__dataclass_fields__ else []
for model in models:
    live.refresh(scene, wait=True, overrides={**FAST, "angular": model})
    res["model_" + model] = shot("INDIRECT")
    res["expect_model_" + model] = expected(angular=model)
# Two cascades (the inner one follows the camera): every cascade adds its lookup.
scene.lpv.cascades = 2
refresh()
res["levels"] = np.array(1 + len(live.STATE.current.fine))
res["cascaded"] = shot("INDIRECT")
res["expect_cascaded"] = expected()
scene.lpv.cascades = 1
refresh()
base = live.STATE.current
res["indirect"] = shot("INDIRECT")
res["expect"] = expected()
res["add"] = shot("ADD", clear=(0.1, 0.2, 0.3, 1.0))
for mode in ("CASCADES", "VPLS", "PROBES", "OCCLUSION"):
    res[mode.lower()] = shot(mode)
res["has_occlusion"] = np.array(base.visibility is not None)
res["fast"] = np.array(json.dumps(FAST))

# Fade-in: the new result (GI intensity x2, re-combined) half faded over the old one.
bpy.data.lights["Spot"].lpv.gi_intensity = 2.0
refresh()
res["recombined"] = np.array(live.STATE.current.serial == base.serial + 1
                             and live.STATE.previous is base)
res["fade_half"] = shot("INDIRECT", fade=0.5)
res["fade_full"] = shot("INDIRECT", fade=1.0)
bpy.data.lights["Spot"].lpv.gi_intensity = 1.0

# The back wall stops receiving GI.
bpy.data.objects["BackWall"].lpv.gi_receiver = False
refresh()
res["no_back"] = shot("INDIRECT")
res["expect_no_back"] = expected()
bpy.data.objects["BackWall"].lpv.gi_receiver = True

# A transition area over the right half of the box: GI x3 inside.
area = bpy.data.objects.new("Glow", None)
area.empty_display_type = "CUBE"
area.location = (0.75, 0.0, 1.0)
area.scale = (0.25, 1.5, 1.5)
area.lpv.area_type = "TRANSITION"
area.lpv.area_intensity = 3.0
area.lpv.area_falloff = 0.2
scene.collection.objects.link(area)
refresh()
res["transition"] = shot("INDIRECT")
res["expect_transition"] = expected()

res["resources_before"] = np.array(overlay.resource_count())
lpv_addon.unregister()
res["resources_after"] = np.array(overlay.resource_count())
res["handlers_after"] = np.array(overlay.handler_count())
np.savez(out, **res)
print("DONE")
"""


@pytest.fixture(scope="module")
def shots(tmp_path_factory):
    out = tmp_path_factory.mktemp("overlay") / "shots.npz"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(out), str(W)], cwd=ROOT,
                          capture_output=True, text=True, check=False, timeout=300, env=env)
    assert proc.returncode == 0 and "DONE" in proc.stdout, proc.stderr[-3000:]
    return dict(np.load(out))


def _mask(expect):
    return expect.max(axis=2) > 0.01 * expect.max()


def test_indirect_only_matches_the_deferred_lookup(shots):
    got, expect = shots["indirect"][..., :3], shots["expect"]
    m = _mask(expect)
    assert m.sum() > 0.4 * W * H
    rel = np.abs(got[m] - expect[m]) / expect[m]
    print(f"\noverlay vs deferred: median rel {np.median(rel):.2e}, "
          f"p95 {np.percentile(rel, 95):.2e}")
    assert np.median(rel) < 0.01
    assert np.percentile(rel, 95) < 0.05  # polygon edges may cover a pixel differently
    assert got[m].sum() / expect[m].sum() == pytest.approx(1.0, rel=0.01)
    # Nothing where the renderer has no indirect light (background, unlit corners).
    assert got[expect.max(axis=2) == 0].max() < 1e-6


@pytest.mark.parametrize("model", ["sh", "m1"])
def test_both_angular_models_match(shots, model):
    if f"model_{model}" not in shots:
        pytest.skip(f"the engine has no angular model {model!r}")
    got, expect = shots[f"model_{model}"][..., :3], shots[f"expect_model_{model}"]
    m = _mask(expect)
    rel = np.abs(got[m] - expect[m]) / expect[m]
    assert np.median(rel) < 0.01 and np.percentile(rel, 95) < 0.05, model


def test_cascades_add_up_like_the_renderer(shots):
    if int(shots["levels"]) < 2:
        pytest.skip("the engine placed one cascade only")
    got, expect = shots["cascaded"][..., :3], shots["expect_cascaded"]
    m = _mask(expect)
    rel = np.abs(got[m] - expect[m]) / expect[m]
    assert np.median(rel) < 0.01 and np.percentile(rel, 95) < 0.05
    assert not np.allclose(expect, shots["expect"], rtol=0.01)  # the cascade changed the GI


def _erode(mask):
    """Pixels whose 8 neighbours are in ``mask`` too (the two rasterisers may give a pixel on
    a polygon edge to different triangles)."""
    out = mask.copy()
    padded = np.pad(mask, 1)
    h, w = mask.shape
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            out &= padded[dy:dy + h, dx:dx + w]
    return out


def test_non_receivers_get_nothing(shots):
    got, expect = shots["no_back"][..., :3], shots["expect_no_back"]
    # Clearly lit before, nothing now: the back wall (pixels whose light is ~0 either way can
    # flip between the two renders when the worker picks another compute backend).
    before = shots["expect"].max(axis=2)
    back = _erode((before > 1e-3 * before.max()) & (expect.max(axis=2) == 0))
    assert back.sum() > 300  # the back wall fills a good part of the view
    assert got[back].max() == 0.0
    keep = _mask(expect)
    np.testing.assert_allclose(got[keep], shots["indirect"][..., :3][keep], rtol=1e-5,
                               atol=1e-7)


def test_add_mode_adds_onto_the_viewport(shots):
    add, ind = shots["add"], shots["indirect"]
    bg = np.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose(add[..., :3], bg + ind[..., :3], rtol=1e-5, atol=1e-6)


def test_new_results_fade_in(shots):
    assert shots["recombined"]
    base, full, half = shots["indirect"][..., :3], shots["fade_full"], shots["fade_half"]
    m = _mask(shots["expect"])
    np.testing.assert_allclose(full[..., :3][m], 2.0 * base[m], rtol=1e-3)
    np.testing.assert_allclose(half[..., :3][m], 1.5 * base[m], rtol=1e-3)


def test_transition_area_scales_the_overlay_like_the_renderer(shots):
    got, expect, base = shots["transition"][..., :3], shots["expect_transition"], shots["expect"]
    m = _mask(base)
    ratio_renderer = expect[m].mean(axis=1) / base[m].mean(axis=1)
    ratio_overlay = got[m].mean(axis=1) / base[m].mean(axis=1)
    inside = ratio_renderer > 2.999
    assert inside.sum() > 100
    # Deep inside the box the overlay's per-cell factor is exact too.
    assert np.median(ratio_overlay[inside]) == pytest.approx(3.0, rel=0.02)
    outside = ratio_renderer < 1.0001
    assert np.median(ratio_overlay[outside]) == pytest.approx(1.0, rel=0.02)


def _quadrants(lit):
    h, w = lit.shape
    return sum(bool(lit[y:y + h // 2, x:x + w // 2].any()) for y in (0, h // 2) for x in (0, w // 2))


def test_debug_views_draw(shots):
    lit = {m: shots[m][..., :3].max(axis=2) > 0 for m in ("cascades", "vpls", "probes",
                                                          "occlusion")}
    assert lit["cascades"].sum() > 20
    # Points and glyphs spread over the box (not collapsed to a line or a corner).
    assert lit["vpls"].sum() > 150 and _quadrants(lit["vpls"]) == 4
    assert lit["probes"].sum() > 150 and _quadrants(lit["probes"]) >= 3
    if shots["has_occlusion"]:
        assert lit["occlusion"].sum() > 300 and _quadrants(lit["occlusion"]) == 4
    else:
        assert shots["occlusion"][..., :3].max() == 0  # nothing blocks: nothing drawn


def test_gpu_resources_and_draw_handler_are_released(shots):
    assert int(shots["resources_before"]) > 0
    assert int(shots["resources_after"]) == 0
    assert int(shots["handlers_after"]) == 0
    print(json.dumps({k: int(shots[k]) for k in ("resources_before", "resources_after")}))
