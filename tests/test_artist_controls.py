"""Artist controls measurably work in the renderer: per-light GI intensity and tint, material
bleed colour, caster/receiver/occluder flags, clip and transition areas (core, no bpy), and a
keyframed global intensity across batch-rendered frames (headless bpy)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lpv_core import areas, engine, lookup
from lpv_core.grid import Grid
from lpv_core.render import deferred
from lpv_core.scene import Area, GISettings, Light, Material, make_scene
from tools import core_scenes as demo

# The engine's defaults (the "dom" transport, the model users get) at small sizes; a key
# GISettings lacks raises (GISettings.updated). antialias=1: the tests compare passes pixel by
# pixel with masks of one raster.render.
SETTINGS = GISettings().updated(grid_resolution=16, rsm_resolution=64, shadow_resolution=256,
                                antialias=1)
RES = (48, 48)


@pytest.fixture(scope="module")
def eng():
    return engine.Engine()


def box(base=SETTINGS, **settings) -> object:
    return demo.cornell_box("SPOT", RES, settings=dataclasses.replace(base, **settings))


def render(eng, scene):
    result = eng.update(scene)
    return deferred.render(eng, scene, result), result


def indirect(eng, scene) -> np.ndarray:
    return render(eng, scene)[0]["Diffuse Indirect"]


def with_light(scene, **changes):
    scene.lights = [dataclasses.replace(scene.lights[0], **changes)] + scene.lights[1:]
    return scene


def object_triangles(scene, lo, hi):
    """Triangles whose centroid lies in the box [lo, hi]."""
    c = scene.positions.mean(axis=1)
    return ((c >= np.asarray(lo)) & (c <= np.asarray(hi))).all(axis=1)


# ---------------------------------------------------------------------------- lights


def test_settings_are_the_engines_default_transport():
    assert SETTINGS.angular == GISettings().angular == "dom"


def test_light_gi_intensity_zero_removes_bounce_and_two_doubles_it(eng):
    base = SETTINGS
    base_passes, result = render(eng, box(base))
    ind = base_passes["Diffuse Indirect"]
    assert ind.max() > 0
    zero = render(eng, with_light(box(base), gi_intensity=0.0))
    assert zero[0]["Diffuse Indirect"].max() == 0.0
    assert any(s["reason"] == "GI intensity is 0" for s in zero[1].stats.skipped)
    # Propagation is linear in the injected light, so x2 is a re-combination of the cached
    # per-light grid: the engine's combine() on this result, then the same lookup.
    doubled = with_light(box(base), gi_intensity=2.0)
    result.values = engine.combine(result.grid, result.per_light, doubled.lights, 1.0)
    double = deferred.render(eng, doubled, result)["Diffuse Indirect"]
    lit = ind > 1e-3 * ind.max()
    np.testing.assert_allclose(double[lit], 2.0 * ind[lit], rtol=1e-4)
    # and a full update agrees with the re-combination
    full = indirect(eng, doubled)
    np.testing.assert_allclose(full[lit], 2.0 * ind[lit], rtol=1e-4)
    # Direct light is untouched by GI controls.
    np.testing.assert_array_equal(base_passes["Diffuse Direct"], zero[0]["Diffuse Direct"])


def test_negative_gi_intensity_subtracts_a_lights_bounce(eng):
    scene = box()
    second = Light("Fill", "POINT", demo.light_matrix((0.3, -0.3, 1.2), (0, 0, -1)), power=150.0)
    scene.lights = scene.lights + [second]
    both = indirect(eng, scene)
    scene.lights = [scene.lights[0], dataclasses.replace(second, gi_intensity=-0.5)]
    negative = indirect(eng, scene)
    scene.lights = [scene.lights[0]]
    spot_only = indirect(eng, scene)
    assert negative.sum() < spot_only.sum() < both.sum()
    assert negative.min() >= 0.0  # lookup clamps at zero
    # Linear in the weights: spot - 0.5 fill, the fill's bounce being both - spot; where no
    # term is near the clamp at zero.
    fill = both - spot_only
    expect = spot_only - 0.5 * fill
    m = (expect > 0.2 * expect.max()) & (fill > 0.05 * fill.max())
    assert m.sum() > 200
    np.testing.assert_allclose(negative[m], expect[m], rtol=1e-3)


def test_light_gi_color_tints_its_bounce(eng):
    base = indirect(eng, box())
    red = indirect(eng, with_light(box(), gi_color=np.array([1.0, 0.0, 0.0], np.float32)))
    np.testing.assert_allclose(red[..., 0], base[..., 0], rtol=1e-4, atol=1e-7)
    assert red[..., 1:].max() == 0.0


# ---------------------------------------------------------------------------- materials


def yellow_block_scene(bleed=None):
    """A grey floor lit by a spot, next to a yellow block: what bounces off the block."""
    mats = [Material("grey", np.array([0.5, 0.5, 0.5], np.float32)),
            Material("yellow", np.array([0.8, 0.7, 0.05], np.float32))]
    if bleed is not None:
        mats[1].bleed_color = np.asarray(bleed, np.float32)
    tris = [demo.quad((-2, -2, 0), (2, -2, 0), (2, 2, 0), (-2, 2, 0)),
            demo.box_triangles((-0.4, -0.4, 0.0), (0.4, 0.4, 1.0))]
    mat = [0] * 2 + [1] * 12
    spot = Light("Spot", "SPOT", demo.light_matrix((1.2, 0.0, 2.0), (-0.6, 0.0, -1.0)),
                 power=400.0, spot_size=np.radians(60))
    cam = demo.Camera.look_at((0.0, -4.5, 2.0), (0.0, 0.0, 0.5), resolution=RES)
    return make_scene(np.concatenate(tris), material_index=np.array(mat), materials=mats,
                      lights=[spot], camera=cam, settings=SETTINGS)


def block_bounce(eng, scene):
    """Indirect light the block adds: all casters minus the block as a non-caster."""
    with_block = indirect(eng, scene)
    scene.caster = np.asarray(scene.material_index != 1)
    without = indirect(eng, scene)
    return (with_block - without).reshape(-1, 3).clip(0).sum(axis=0)


def test_green_bleed_colour_turns_a_yellow_objects_bounce_green(eng):
    plain = block_bounce(eng, yellow_block_scene())
    green = block_bounce(eng, yellow_block_scene(bleed=(0.1, 0.7, 0.1)))
    assert plain[0] > 0.8 * plain[1]  # yellow: red about as strong as green
    assert green[1] > 4.0 * green[0]  # green bleed: green dominates
    # Shading (Diffuse Color) is untouched by the bleed colour.
    p1 = render(eng, yellow_block_scene())[0]["Diffuse Color"]
    p2 = render(eng, yellow_block_scene(bleed=(0.1, 0.7, 0.1)))[0]["Diffuse Color"]
    np.testing.assert_array_equal(p1, p2)


def test_bleed_intensity_scales_the_materials_bounce(eng):
    scene = yellow_block_scene()
    scene.materials[1].bleed_intensity = 0.0
    dark = block_bounce(eng, scene)
    assert dark.max() < 1e-6
    base = block_bounce(eng, yellow_block_scene())
    assert base.max() > 0


# ---------------------------------------------------------------------------- flags


def test_non_caster_bounces_nothing_but_still_shadows(eng):
    base_passes, _ = render(eng, box())
    scene = box()
    scene.caster = np.zeros(scene.triangle_count, bool)
    passes, _ = render(eng, scene)
    assert passes["Diffuse Indirect"].max() == 0.0
    np.testing.assert_array_equal(passes["Diffuse Direct"], base_passes["Diffuse Direct"])
    # The red wall as the only non-caster: its red bleed disappears.
    scene = box()
    scene.caster = ~object_triangles(scene, (-1.01, -1.01, -0.01), (-0.99, 1.01, 2.01))
    no_red = indirect(eng, scene)
    base = base_passes["Diffuse Indirect"]
    # Only white (R = G = B) and green (R = B) surfaces bounce now: red equals blue exactly;
    # with the red wall bouncing, red is well above blue.
    np.testing.assert_allclose(no_red[..., 0], no_red[..., 2], rtol=1e-5, atol=1e-7)
    assert base[..., 0].sum() > 1.1 * base[..., 2].sum()
    assert no_red[..., 0].sum() < 0.9 * base[..., 0].sum()


def test_non_receiver_gets_no_indirect(eng):
    scene = box()
    base, _ = render(eng, scene)
    scene.receiver = ~object_triangles(scene, (-1.01, 0.99, -0.01), (1.01, 1.01, 2.01))  # back
    passes, result = render(eng, scene)
    frame = eng.raster.render(scene.camera.view, scene.camera.projection, *RES)
    back = frame.covered & ~frame.receiver
    assert back.sum() > 200
    assert passes["Diffuse Indirect"][back].max() == 0.0
    assert base["Diffuse Indirect"][back].max() > 0.0
    others = frame.covered & frame.receiver
    np.testing.assert_array_equal(passes["Diffuse Indirect"][others],
                                  base["Diffuse Indirect"][others])
    assert any(s["reason"] == "gi_receiver is off" for s in result.stats.skipped)


def test_non_occluder_stops_blocking(eng):
    block = (-0.71, -0.11, -0.01), (-0.09, 0.61, 1.21)  # the tall block
    on = box(SETTINGS, occlusion=True)
    off = box(SETTINGS, occlusion=False)
    free = box(SETTINGS, occlusion=True)
    free.occluder = ~object_triangles(free, *block)
    (a, ra), (b, rb), (c, rc) = (render(eng, sc) for sc in (on, off, free))
    a, b, c = (p["Diffuse Indirect"].astype(np.float64) for p in (a, b, c))
    # The visibility propagation used: the geometry volume of the occluders, none without.
    assert rb.visibility is None
    assert ra.visibility is not None and rc.visibility is not None
    # Fewer occluders block no more anywhere and less around the block; the walls still do.
    assert np.all(rc.visibility >= ra.visibility)
    cell = ra.grid.cell_size
    lo = np.floor((np.asarray(block[0]) - ra.grid.origin_array) / cell).astype(int)
    hi = np.ceil((np.asarray(block[1]) - ra.grid.origin_array) / cell).astype(int)
    near = (slice(None),) + tuple(slice(max(x - 1, 0), y + 1) for x, y in zip(lo, hi))
    opened = rc.visibility[near] - ra.visibility[near]
    assert opened.max() > 0.5, opened.max()  # a face the block closed is open again
    assert rc.visibility.min() < 0.5  # the box's walls and the short block still block
    # The difference the block makes as an occluder is in the image: with it a non-occluder
    # the result moves most of the way towards no occlusion.
    total = b.sum()
    occluding = np.abs(a - b).sum() / total
    # Measured at these settings: occlusion changes 20 % of the indirect light (L1), the block
    # 14 % of it; the geometry volume left out of the propagation (the injection and lookup
    # still use it) leaves 2 %.
    assert occluding > 0.1, occluding
    assert np.abs(c - a).sum() / total > 0.05, np.abs(c - a).sum() / total
    assert np.abs(c - b).sum() < np.abs(a - b).sum()


# ---------------------------------------------------------------------------- areas


def test_clip_visibility_cuts_exactly_the_box_boundary():
    g = Grid((0.0, 0.0, 0.0), 1.0, 6)
    m = np.diag([1.0, 1.0, 1.0, 1.0])
    m[:3, 3] = (2.0, 2.0, 2.0)  # box [1, 3]^3: cells 1 and 2 on each axis
    vis = areas.clip_visibility(g, [Area("c", "CLIP", m)])
    assert vis.shape == (6, 6, 6, 6) and vis.dtype == np.float32
    # +x from cell 2 (inside) to cell 3 (outside) is cut, 1 -> 2 (both inside) is not.
    assert vis[0, 2, 1, 1] == 0.0 and vis[0, 1, 1, 1] == 1.0
    assert vis[1, 1, 1, 1] == 0.0 and vis[1, 2, 1, 1] == 1.0  # -x: 1 -> 0 cut
    assert vis[0, 0, 0, 0] == 1.0  # both outside
    assert vis[0, 0, 1, 1] == 0.0  # outside -> inside cut too
    # Every cut pair of cells straddles the boundary: 6 faces x 4 cells, both directions.
    assert int((vis == 0).sum()) == 2 * 6 * 4
    assert np.array_equal(areas.clip_visibility(g, []), np.ones((6, 6, 6, 6), np.float32))


def two_rooms(clip=None):
    """A 4 m floor with a wall at x = -2 facing +x, lit only at x > 0.6 by a narrow spot."""
    tris = [demo.quad((-2, -1, 0), (2, -1, 0), (2, 1, 0), (-2, 1, 0)),
            demo.quad((-2, -1, 0), (-2, 1, 0), (-2, 1, 1.5), (-2, -1, 1.5))]
    spot = Light("Spot", "SPOT", demo.light_matrix((1.3, 0.0, 1.4), (0, 0, -1)), power=500.0,
                 spot_size=np.radians(40), spot_blend=0.0)
    settings = dataclasses.replace(SETTINGS, grid_resolution=20)
    return make_scene(np.concatenate(tris), lights=[spot], settings=settings,
                      areas=[] if clip is None else [clip])


def clip_box(lo, hi):
    m = np.diag([(hi[i] - lo[i]) / 2 for i in range(3)] + [1.0])
    m[:3, 3] = [(hi[i] + lo[i]) / 2 for i in range(3)]
    return Area("Clip", "CLIP", m)


def probe(result, points, normals):
    return lookup.irradiance(result.grid, result.values, np.asarray(points, float),
                             np.asarray(normals, float))


def test_clip_area_keeps_outside_bounce_out(eng):
    inside_pts = [(-1.9, y, z) for y in (-0.5, 0.0, 0.5) for z in (0.3, 0.7, 1.1)]
    inside_pts += [(-1.3, 0.0, 0.05)]
    normals = [(1, 0, 0)] * 9 + [(0, 0, 1)]
    free = eng.update(two_rooms())
    clipped = eng.update(two_rooms(clip_box((-2.5, -1.5, -0.5), (-0.3, 1.5, 2.5))))
    e_free = probe(free, inside_pts, normals)
    e_clip = probe(clipped, inside_pts, normals)
    assert e_free.min() > 0
    assert e_clip.max() < 1e-3 * e_free.max(), (e_clip.max(), e_free.max())
    assert clipped.stats.info["clip_areas"] == 1
    # Outside the box the bounce is still there.
    lit = probe(clipped, [(1.0, 0.0, 0.6)], [(0, 0, -1)])
    assert lit.min() > 0.5 * probe(free, [(1.0, 0.0, 0.6)], [(0, 0, -1)]).min()


def test_clip_area_keeps_inside_bounce_in(eng):
    # The lit region is inside the box: nothing reaches the far wall outside it.
    clipped = eng.update(two_rooms(clip_box((0.2, -1.5, -0.5), (2.5, 1.5, 2.5))))
    free = eng.update(two_rooms())
    wall = [(-1.9, 0.0, z) for z in (0.3, 0.7, 1.1)]
    e_free = probe(free, wall, [(1, 0, 0)] * 3)
    e_clip = probe(clipped, wall, [(1, 0, 0)] * 3)
    assert e_free.min() > 0 and e_clip.max() < 1e-3 * e_free.max()


def transition(intensity=2.0, tint=(1.0, 0.5, 0.25), falloff=0.4):
    m = np.diag([0.5, 1.2, 2.0, 1.0])
    m[:3, 3] = (0.5, 0.0, 1.0)  # x in [0, 1]
    return Area("Glow", "TRANSITION", m, falloff=falloff, intensity=intensity,
                tint=np.asarray(tint, np.float32))


def test_transition_factor_is_smooth_and_exact_inside():
    area = transition()
    x = np.linspace(-1.0, 0.5, 301)
    pts = np.stack([x, np.zeros_like(x), np.ones_like(x)], axis=1)
    f = areas.transition_factor([area], pts)
    target = np.array([2.0, 1.0, 0.5])
    np.testing.assert_allclose(f[x >= 0], np.broadcast_to(target, f[x >= 0].shape), rtol=1e-6)
    np.testing.assert_allclose(f[x <= -0.4], 1.0)
    ramp = f[(x > -0.4) & (x < 0), 0]
    assert np.all(np.diff(ramp) > 0)  # monotonic towards the box
    # Smooth: no jump anywhere along the line (C1 smoothstep).
    assert np.abs(np.diff(f[:, 0])).max() < 3 * (1.0 / 0.4) * (x[1] - x[0])
    # Rotated and scaled boxes: distance measured in metres.
    rot = np.eye(4)
    c, s = np.cos(0.7), np.sin(0.7)
    rot[:2, :2] = [[c, -s], [s, c]]
    m = rot @ np.diag([2.0, 0.5, 1.0, 1.0])
    d = areas.distance_outside(Area("r", "TRANSITION", m), rot[:3, :3] @ np.array([0, 0.8, 0]))
    assert d[0] == pytest.approx(0.3)


def test_transition_area_scales_gi_inside_with_smooth_falloff(eng):
    base_scene = box()
    base, _ = render(eng, base_scene)
    scene = box()
    scene.areas = [transition()]
    passes, _ = render(eng, scene)
    frame = eng.raster.render(scene.camera.view, scene.camera.projection, *RES)
    m = frame.covered & (base["Diffuse Indirect"][..., 0] > 1e-4)
    # By hand: the box is x in [0, 1], y in [-1.2, 1.2], z in [-1, 3]; at distance d (m) from
    # it the factor blends 1 into intensity x tint = (2, 1, 0.5) with the C1 smoothstep
    # s(t) = 3 t^2 - 2 t^3, t = d / falloff (0.4 m): 1 + (1 - s) ((2, 1, 0.5) - 1).
    p = frame.position[m].astype(np.float64)
    lo, hi = np.array([0.0, -1.2, -1.0]), np.array([1.0, 1.2, 3.0])
    d = np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0), axis=1)
    t = np.clip(d / 0.4, 0.0, 1.0)
    w = 1.0 - t * t * (3.0 - 2.0 * t)
    expect = 1.0 + w[:, None] * (np.array([2.0, 1.0, 0.5]) - 1.0)
    np.testing.assert_allclose(passes["Diffuse Indirect"][m], base["Diffuse Indirect"][m] * expect,
                               rtol=1e-4, atol=1e-7)
    ratio = passes["Diffuse Indirect"][m][:, 0] / base["Diffuse Indirect"][m][:, 0]
    assert (np.abs(ratio - 2.0) < 1e-3).sum() > 50  # pixels inside the box: x2
    assert (np.abs(ratio - 1.0) < 1e-3).sum() > 50  # far outside: unchanged
    between = (ratio > 1.01) & (ratio < 1.99)
    assert between.sum() > 10  # the falloff band
    np.testing.assert_array_equal(passes["Diffuse Direct"], base["Diffuse Direct"])


# ---------------------------------------------------------------------------- keyframes


def test_keyframed_global_intensity_changes_across_batch_frames(tmp_path):
    bpy = pytest.importorskip("bpy")
    from lpv_addon import batch, properties
    from tools import scenes

    registered = hasattr(bpy.types.Scene, "lpv")
    if not registered:
        properties.register()
    try:
        scenes.cornell_box("SPOT", resolution=(32, 32))
        scene = bpy.context.scene
        scene.lpv.intensity = 1.0
        scene.lpv.keyframe_insert("intensity", frame=1)
        scene.lpv.intensity = 3.0
        scene.lpv.keyframe_insert("intensity", frame=3)
        overrides = {"grid_resolution": SETTINGS.grid_resolution,
                     "rsm_resolution": SETTINGS.rsm_resolution}
        rc = batch.render_frames(scene, tmp_path, (1, 3), (32, 32), overrides, quiet=True)
        assert rc == 0
    finally:
        if not registered:
            properties.unregister()
    import json

    from lpv_core.render import exr

    stats = json.loads((tmp_path / "stats.json").read_text())
    got = [f["intensity"] for f in stats["frames"]]
    assert got[0] == pytest.approx(1.0) and got[2] == pytest.approx(3.0)
    assert 1.0 < got[1] < 3.0
    ind = [exr.read_multilayer(tmp_path / f"{f:04d}.exr")["Diffuse Indirect"] for f in (1, 2, 3)]
    assert ind[0].max() > 0
    lit = ind[0] > 1e-3 * ind[0].max()
    for i in (1, 2):
        np.testing.assert_allclose(ind[i][lit] / ind[0][lit], got[i], rtol=2e-3)


BLEND_SCRIPT = r"""
import sys
import bpy
from lpv_addon import properties
from tools import scenes
properties.register()
scenes.cornell_box("SPOT", resolution=(32, 32))
scene = bpy.context.scene
scene.frame_start, scene.frame_end = 1, 2
scene.lpv.grid_resolution = 16
scene.lpv.rsm_resolution = 64
scene.lpv.intensity = 0.5
scene.lpv.keyframe_insert("intensity", frame=1)
scene.lpv.intensity = 1.5
scene.lpv.keyframe_insert("intensity", frame=2)
bpy.data.lights["Spot"].lpv.gi_intensity = 2.0
bpy.ops.wm.save_as_mainfile(filepath=sys.argv[1])
"""


def test_batch_cli_reads_the_blends_gi_settings_and_keyframes(tmp_path):
    """`python -m lpv_addon.batch file.blend` without the add-on enabled still reads
    Scene.lpv (animated), Light.lpv and the other GI properties saved in the file."""
    import json
    import subprocess
    import sys

    from conftest import ROOT

    from lpv_core.render import exr

    pytest.importorskip("bpy")
    blend = tmp_path / "keyed.blend"
    proc = subprocess.run([sys.executable, "-c", BLEND_SCRIPT, str(blend)], cwd=ROOT,
                          capture_output=True, text=True, check=False, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "lpv_addon.batch", str(blend), "--animation",
                           "--out", str(out), "--quiet"], cwd=ROOT, capture_output=True, text=True,
                          check=False, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    stats = json.loads((out / "stats.json").read_text())
    assert stats["settings"]["grid_resolution"] == 16
    assert [f["intensity"] for f in stats["frames"]] == [pytest.approx(0.5), pytest.approx(1.5)]
    a, b = (exr.read_multilayer(out / f"{i:04d}.exr")["Diffuse Indirect"] for i in (1, 2))
    lit = a > 1e-3 * a.max()
    np.testing.assert_allclose(b[lit] / a[lit], 3.0, rtol=2e-3)
