"""The viewport overlay drawn by Blender's own gpu module into an offscreen buffer, in a child
Blender process (the engine runs in the worker; moderngl never enters the drawing process).

Pixels are checked against the core deferred renderer (Diffuse Indirect x Diffuse Color of
the same camera): the overlay shows indirect light exactly where the LPV says, nothing where
gi_receiver is off, adds onto the viewport in ADD mode, blends old and new results while
fading in, scales inside transition areas, and draws the debug views. The overlay shows the
product's transport only: 9-coefficient grids (``angular="dom"``)."""

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
import dataclasses, json, math, os, sys
import bpy, gpu
import numpy as np
import lpv_addon
from lpv_addon.render import compare
from lpv_addon.viewport import live, overlay
from tools import scenes

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

from lpv_core.render import deferred
from lpv_core import cascades, lookup, sh
from lpv_core.grid import Grid
from lpv_core.scene import GISettings
# the default settings: the product's transport, 9 SH coefficients per colour; the expected
# images without the render's contact light (render/contact.py), which the overlay leaves out
FAST = {"contact_light": False}

def expected(**overrides):
    # one sample at each pixel centre, as the overlay draws (renders average antialias^2)
    passes, _ = compare.render_passes(scene, (W, H),
                                      overrides={**FAST, "antialias": 1, **overrides})
    return passes["Diffuse Indirect"] * passes["Diffuse Color"]

def refresh():
    live.mark_dirty("test")
    live.refresh(scene, wait=True, overrides=FAST)

def synthetic(seed, visibility, gapped=False):
    # The overlay of a made-up grid on a plane z = 0 seen straight on by an orthographic
    # camera (pixel centres are known world points) and lookup.irradiance there: 8 x 8 quads
    # of 8 x 8 pixels, each with its own normal facing the camera, so bands 1 and 2 vary.
    # ``gapped``: made-up cell gaps (geometry_volume.cell_gaps: slab depths in [0, 0.5],
    # mostly 0) that move the sample points (lookup.sample_points).
    rng = np.random.default_rng(seed)
    grid = Grid((-1.2, -1.2, -1.2), 0.3, 8)
    values = rng.normal(0.0, 0.3, (8, 8, 8, 3, sh.BANDS2)).astype(np.float32)
    values[..., 0] = rng.uniform(1.0, 2.0, (8, 8, 8, 3))
    vis = rng.uniform(0.0, 1.0, (6, 8, 8, 8)).astype(np.float32) if visibility else None
    gaps = None
    if gapped:
        gaps = rng.uniform(0.05, 0.5, (6, 8, 8, 8)).astype(np.float32)
        gaps[rng.uniform(0.0, 1.0, gaps.shape) > 0.3] = 0.0
    q = 8
    normals = rng.normal(0.0, 1.0, (q * q, 3))
    normals[:, 2] = np.abs(normals[:, 2]) + 0.3
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    tris, nrms = [], []
    for k in range(q * q):
        x0, y0 = -1.0 + 2.0 * (k % q) / q, -1.0 + 2.0 * (k // q) / q
        x1, y1 = x0 + 2.0 / q, y0 + 2.0 / q
        tris += [[(x0, y0, 0), (x1, y0, 0), (x1, y1, 0)],
                 [(x0, y0, 0), (x1, y1, 0), (x0, y1, 0)]]
        nrms += [[normals[k]] * 3] * 2
    t = len(tris)
    geometry = {"positions": np.array(tris, np.float32), "normals": np.array(nrms, np.float32),
                "albedo": np.ones((t, 3), np.float32), "receiver": np.ones(t, bool)}
    live.STATE.serial += 1
    result = live.LiveResult(
        serial=live.STATE.serial, grid=grid, values=values, per_light={}, lights=[],
        settings=GISettings(), areas=[], geometry=geometry, visibility=vis, gaps={grid: gaps})
    view = np.eye(4)
    view[2, 3] = -5.0  # camera at z = 5 looking down -z
    proj = np.diag([1.0, 1.0, -0.2, 1.0])  # orthographic, x, y in [-1, 1], z in [0, 10]
    proj[2, 3] = -1.0
    off = gpu.types.GPUOffScreen(W, H, format="RGBA32F")
    with off.bind():
        fb = gpu.state.active_framebuffer_get()
        fb.clear(color=(0, 0, 0, 0), depth=1.0)
        overlay.draw(view, proj, mode="INDIRECT", depth_prepass=True, current=result,
                     previous=None)
        buf = fb.read_color(0, 0, W, H, 4, 0, "FLOAT")
    off.free()
    buf.dimensions = W * H * 4
    got = np.array(buf.to_list(), np.float32).reshape(H, W, 4)[::-1, :, :3]
    # pixel centres (top row first), the normal of the quad each lies in
    j, i = np.meshgrid(np.arange(W), np.arange(H))
    x, y = -1.0 + (j + 0.5) * 2.0 / W, 1.0 - (i + 0.5) * 2.0 / H
    quad = np.clip(((y + 1.0) / 2.0 * q).astype(int), 0, q - 1) * q \
        + np.clip(((x + 1.0) / 2.0 * q).astype(int), 0, q - 1)
    pos = np.stack([x, y, np.zeros_like(x)], axis=-1).reshape(-1, 3)
    pos[:, 2] += deferred.VIEWER_NUDGE_CELLS * grid.cell_size  # deferred.toward_viewer
    nrm = normals[quad.ravel()]
    at = lookup.sample_points(grid, pos, nrm, gaps)
    e = lookup.irradiance(grid, values, at, nrm, offset_cells=0.0, angular="dom",
                          visibility=vis)
    # interior pixels of each quad (an edge pixel may go to either neighbour), and with
    # visibility none whose sample lies on a plane where the nearest cell changes (the
    # visible corners jump there: float and double may pick either side)
    inner = ((j % (W // q)) > 0) & ((j % (W // q)) < W // q - 1) \
        & ((i % (H // q)) > 0) & ((i % (H // q)) < H // q - 1)
    c = grid.cell_coords(at)
    tie = (np.abs(c - np.floor(c) - 0.5) < 0.01).any(axis=1).reshape(H, W)
    inner &= ~tie if vis is not None else True
    moved = np.zeros((H, W), bool)
    if gaps is not None:
        # none whose uncorrected point lies near a face plane or a slab's edge either (float
        # and double may test it differently); ``moved``: the gaps moved the sample point
        rel = (pos + nrm * (0.5 * grid.cell_size) - grid.origin_array) / grid.cell_size
        cell = np.floor(rel).astype(int)
        fr = rel - cell
        idx = tuple(np.clip(cell, 0, 7).T)
        near = (fr < 0.01) | (fr > 0.99)
        for a in range(3):
            lo, up = gaps[2 * a + 1][idx], gaps[2 * a][idx]
            near[:, a] |= (lo > 0) & (np.abs(fr[:, a] - lo) < 0.01)
            near[:, a] |= (up > 0) & (np.abs(1.0 - fr[:, a] - up) < 0.01)
        inner &= ~near.any(axis=1).reshape(H, W)
        plain = lookup.irradiance(grid, values, pos, nrm, angular="dom", visibility=vis)
        moved = (np.abs(at - lookup.sample_points(grid, pos, nrm, None)).max(axis=1) > 1e-9) \
            & (np.abs(plain - e).max(axis=1) > 0.05 * e.max())
        moved = moved.reshape(H, W)
    return got, (e / np.pi).reshape(H, W, 3).astype(np.float32), inner, moved

warm_up()
res = {}
# The overlay's shader against lookup.irradiance on made-up 9-coefficient grids (the
# irradiance kernel), with and without propagation visibility; with made-up cell gaps
# (lookup.sample_points moves the sample points).
for name, vis, gapped in (("syn9", True, False), ("syn9_free", False, False),
                          ("syn9_gaps", True, True), ("syn9_free_gaps", False, True)):
    res[name], res[name + "_expect"], res[name + "_inner"], res[name + "_moved"] = \
        synthetic(7, vis, gapped)

# PROBES glyphs of a 9-coefficient cell: the radius follows the function of all 9 coefficients.
g1 = Grid((0.0, 0.0, 0.0), 1.0, 1)
one = np.zeros((1, 1, 1, 3, sh.BANDS2), np.float32)
one[..., :] = sh.evaluate_basis2(np.array([0.0, 0.0, 1.0]))  # a beam along +z
pos9, col9 = overlay.probe_glyphs(g1, one)
res["probe9_pos"], res["probe9_col"] = pos9, col9
low = one.copy()
low[..., 4:] = 0.0  # the same beam in bands 0-1 only
pos4, _ = overlay.probe_glyphs(g1, low)
res["probe4_pos"] = pos4
# Other grid formats (the retired 4-coefficient models) are refused, not drawn wrongly.
refused = []
for fn in (overlay.lpv_textures, overlay.probe_glyphs):
    try:
        fn(g1, np.ascontiguousarray(one[..., :4]))
    except ValueError as exc:
        refused.append("9 expected" in str(exc))
res["refuses_4"] = np.array(refused)
# Two cascades (the inner one follows the camera): every cascade adds its lookup.
scene.lpv.cascades = 2
scene.lpv.cascades_auto = False  # exactly two (the planner would keep one for this view)
refresh()
res["levels"] = np.array(1 + len(live.STATE.current.fine))
# The worker's cell gaps of every cascade, keyed by the result's own Grid objects.
cur = live.STATE.current
cascade_grids = [cur.grid] + [lv[0] for lv in cur.fine]
res["gap_keys_ok"] = np.array(len(cur.gaps) == len(cascade_grids) and all(
    any(k is g for k in cur.gaps) for g in cascade_grids))
res["gap_shapes_ok"] = np.array(all(
    cur.gaps[g] is None or cur.gaps[g].shape == (6,) + (g.resolution,) * 3
    for g in cascade_grids))
res["gap_any"] = np.array(any(cur.gaps[g] is not None and cur.gaps[g].max() > 0
                              for g in cascade_grids))
# The worker's reply carries each coarser cascade made whole (cascades.whole), as it made it.
chain = [lv[0] for lv in cur.fine] + [cur.grid]
made = cascades.whole(chain, [lv[1] for lv in cur.fine] + [cur.values])[1:]
res["whole_ok"] = np.array(len(cur.whole) == len(cur.fine) == len(made) and all(
    np.allclose(a, b, rtol=1e-6, atol=0) and not np.array_equal(a, cur.values)
    for a, b in zip(cur.whole, made)))
res["cascaded"] = shot("INDIRECT")
res["expect_cascaded"] = expected()
scene.lpv.cascades = 1
scene.lpv.cascades_auto = True
refresh()
base = live.STATE.current
res["coefficients"] = np.array(base.values.shape[-1])
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
bpy.data.objects.remove(area)

# A dielectric Principled floor seen at a grazing angle (3 deg down, from 12 cm above it):
# its Diffuse Color over the view angle (Material.diffuse_share) per fragment, as the render's
# gbuffer applies it; "grazing_plain": the same result drawn without the shares.
floor = bpy.data.objects["Floor"]
floor.data.materials[0] = scenes.principled_material("Glaze", (0.8, 0.8, 0.8), roughness=0.5)
scene.camera.location = (0.0, -0.95, 0.12)
scene.camera.rotation_euler = (math.radians(87.0), 0.0, 0.0)
refresh()
cur = live.STATE.current
res["share_rows"] = np.array(int((np.asarray(cur.geometry.get("share", [-1])) >= 0).sum()))
res["grazing"] = shot("INDIRECT")
res["expect_grazing"] = expected()
plain = dataclasses.replace(cur, serial=cur.serial + 1000, geometry={
    k: v for k, v in cur.geometry.items() if k not in ("share", "shares")})
res["grazing_plain"] = shot("INDIRECT", current=plain, previous=None)

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


def test_default_model_draws_nine_coefficients(shots):
    assert int(shots["coefficients"]) == 9  # angular="dom": bands 0-2


@pytest.mark.parametrize("name", ["syn9", "syn9_free", "syn9_gaps", "syn9_free_gaps"])
def test_shader_repeats_lookup_irradiance(shots, name):
    """Per pixel, the fragment shader gives lookup.irradiance / pi of the 9-coefficient grid
    (the irradiance kernel), up to half-float storage; with cell gaps, read at
    lookup.sample_points (the point moved out of the cut-off slabs)."""
    got, expect, inner = shots[name], shots[name + "_expect"], shots[name + "_inner"]
    assert inner.sum() > 0.5 * W * H
    lit = inner & (expect.max(axis=2) > 0.05 * expect.max())
    assert lit.sum() > 0.4 * W * H
    err = np.abs(got[lit] - expect[lit])
    rel = err / expect[lit]
    print(f"\n{name}: median rel {np.median(rel):.2e}, p99 {np.percentile(rel, 99):.2e}, "
          f"max abs / peak {err.max() / expect.max():.2e}")
    assert np.median(rel) < 2e-3
    assert np.percentile(rel, 99) < 2e-2
    assert err.max() < 2e-2 * expect.max()
    # Where the lookup clamps to zero the shader does too.
    dark = inner & (expect.max(axis=2) == 0)
    assert got[dark].max(initial=0.0) < 1e-3 * expect.max()
    if name.endswith("_gaps"):  # the gaps moved many of the compared points, visibly
        assert (lit & shots[name + "_moved"]).sum() > 0.1 * W * H


def test_cascade_gaps_come_from_the_worker(shots):
    """The worker's cell gaps reach the overlay for every cascade, keyed by its Grid."""
    assert shots["gap_keys_ok"] and shots["gap_shapes_ok"]
    assert shots["gap_any"]  # the Cornell box's walls lie off the grid's face planes


def test_probe_glyphs_read_nine_coefficients(shots):
    """A beam along +z in 9 coefficients: its glyph reaches furthest along +z, and its lobe is
    narrower than the same beam's without band 2 (band 2 sharpens it)."""
    pos9, col9, pos4 = shots["probe9_pos"], shots["probe9_col"], shots["probe4_pos"]
    assert pos9.shape[0] > 0 and pos9.shape[0] == col9.shape[0] == pos4.shape[0]
    assert np.isfinite(pos9).all() and np.isfinite(col9).all()
    d9, d4 = pos9 - 0.5, pos4 - 0.5  # the cell centre
    far = d9[np.argmax(np.linalg.norm(d9, axis=1))]
    assert far[2] > 0.99 * np.linalg.norm(far)
    side9 = np.linalg.norm(d9[:, :2], axis=1).max() / np.linalg.norm(d9, axis=1).max()
    side4 = np.linalg.norm(d4[:, :2], axis=1).max() / np.linalg.norm(d4, axis=1).max()
    assert side9 < side4


def test_only_nine_coefficient_grids_are_drawn(shots):
    assert shots["refuses_4"].tolist() == [True, True]


def test_cascades_add_up_like_the_renderer(shots):
    assert int(shots["levels"]) == 2
    assert bool(shots["whole_ok"])  # the receivers outside the finer cascade read it whole
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


def test_principled_share_at_grazing_view_matches_the_renderer(shots):
    """A dielectric Principled floor seen at 3-12 deg: the overlay multiplies the albedo by the
    Diffuse Color's share at each fragment's view angle, as the render does (Diffuse Indirect
    x Diffuse Color); drawn without the shares it is up to ~17 % brighter there."""
    got, expect = shots["grazing"][..., :3], shots["expect_grazing"]
    plain = shots["grazing_plain"][..., :3]
    assert int(shots["share_rows"]) == 2  # the floor quad's two triangles
    m = _mask(expect)
    off = (np.abs(plain - expect) / np.where(m[..., None], expect, 1.0)).max(axis=2)
    sel = m & (off > 0.02)  # where the head-on Diffuse Color is visibly wrong
    assert sel.sum() > 0.15 * W * H
    rel = np.abs(got[sel] - expect[sel]) / expect[sel]
    print(f"\ngrazing floor: without shares median rel {np.median(off[sel]):.3f}, max "
          f"{off[sel].max():.3f}; with: median {np.median(rel):.2e}, "
          f"p95 {np.percentile(rel, 95):.2e}")
    assert np.median(rel) < 0.01
    assert np.percentile(rel, 95) < 0.05  # polygon edges may cover a pixel differently
    assert got[sel].sum() / expect[sel].sum() == pytest.approx(1.0, rel=0.01)


def test_gpu_resources_and_draw_handler_are_released(shots):
    assert int(shots["resources_before"]) > 0
    assert int(shots["resources_after"]) == 0
    assert int(shots["handlers_after"]) == 0
    print(json.dumps({k: int(shots[k]) for k in ("resources_before", "resources_after")}))
