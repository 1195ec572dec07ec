"""Point and spot lights with a radius are Cycles' round emitters (lights.round_geometry): a
disk facing the receiver (Soft Falloff, Blender's default) or a sphere, of radiance
I / (pi r^2), cut at the receiver's horizon. Checked against a numerical integral, the point
limit, the compiled twins, and Cycles with the light's sphere cutting the floor."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import surface_points

from lpv_core import engine, rsm
from lpv_core.render import direct
from lpv_core.runtime import jit
from lpv_core.scene import GISettings
from lpv_core.scene import lights as lights_mod
from tools import core_scenes as demo


def _cone_integral(half_angle: float, tilt: float, n: int = 1500) -> float:
    """The cosine-weighted solid angle above the horizon of a cone of directions (midpoint
    rule over its polar and azimuth angles, in its own frame)."""
    ct = np.cos(half_angle) + (1.0 - np.cos(half_angle)) * (np.arange(n) + 0.5) / n
    ph = 2.0 * np.pi * (np.arange(n) + 0.5) / n
    c, p = np.meshgrid(ct, ph, indexing="ij")
    z = -np.sin(tilt) * np.sqrt(1.0 - c * c) * np.cos(p) + np.cos(tilt) * c
    return float((1.0 - np.cos(half_angle)) * 2.0 * np.pi * np.mean(np.maximum(z, 0.0)))


@pytest.mark.parametrize("half_deg", [1.0, 20.0, 60.0, 89.5])
def test_cone_cut_at_the_horizon_is_its_integral(half_deg):
    a = np.radians(half_deg)
    tilts = np.radians([0.0, 30.0, 70.0, 85.0, 90.0, 95.0, 110.0, 150.0, 179.0])
    got = lights_mod.cone_projected_solid_angle(np.cos(tilts), np.sin(a) ** 2)
    want = np.array([_cone_integral(a, t) for t in tilts])
    scale = np.pi * np.sin(a) ** 2  # the cone facing the normal
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5 * scale)
    assert lights_mod.cone_projected_solid_angle(0.3, 1.0) == pytest.approx(np.pi)


def test_a_small_round_light_far_away_is_the_point():
    light = demo.cornell_box("POINT", (8, 8)).lights[0]
    cos_r = np.array([1.0, 0.5, 0.05])
    for soft in (True, False):
        small = dataclasses.replace(light, radius=0.01, soft_falloff=soft)
        got = lights_mod.round_geometry(small, cos_r, np.full(3, 100.0))
        np.testing.assert_allclose(got, cos_r / 100.0, rtol=2e-4)


def test_under_a_disk_light_the_distance_is_softened_by_its_radius():
    """Straight under a facing disk of radius r at height h: I / (h^2 + r^2); inside the
    sphere (Soft Falloff off) the hemisphere sees it: I / r^2 (pi L)."""
    light = dataclasses.replace(demo.cornell_box("POINT", (8, 8)).lights[0], radius=0.1)
    h2 = np.array([0.05**2, 0.2**2])
    np.testing.assert_allclose(lights_mod.round_geometry(light, np.ones(2), h2),
                               1.0 / (h2 + 0.01), rtol=1e-12)
    sphere = dataclasses.replace(light, soft_falloff=False)
    np.testing.assert_allclose(lights_mod.round_geometry(sphere, np.ones(2), h2),
                               [1.0 / 0.01, 1.0 / h2[1]], rtol=1e-12)


@pytest.mark.skipif(not jit.enabled(), reason="LPV_JIT=0: the kernels are off")
@pytest.mark.parametrize("kind", ["POINT", "SPOT"])
@pytest.mark.parametrize("soft", [True, False])
def test_compiled_round_lights_are_the_numpy_ones(kind, soft):
    """The direct light and the RSM's VPLs of a light whose sphere reaches the ceiling (some
    receivers inside it) are the numpy reference's."""
    scene = demo.cornell_box(kind, (16, 16), GISettings())
    light = dataclasses.replace(scene.lights[0], radius=0.6, soft_falloff=soft)
    pos, nrm = surface_points(np.random.default_rng(3), scene.positions, 20000)
    inside = np.linalg.norm(pos - light.position, axis=1) < light.radius
    assert inside.mean() > 0.01
    got = direct.irradiance(light, pos, nrm, None)
    with jit.disabled():
        want = direct.irradiance(light, pos, nrm, None)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12 * want.max())
    eng = engine.Engine()
    eng.upload(scene, engine.Stats())
    bounds = eng.lpv_bounds(scene)
    with jit.disabled():
        ref = rsm.render_rsm(eng.raster, light, bounds, 64)
    out = rsm.render_rsm(eng.raster, light, bounds, 64)
    assert ref.count > 100 and out.count == ref.count
    np.testing.assert_allclose(out.flux, ref.flux, rtol=1e-10, atol=1e-12 * ref.flux.max())
    point = dataclasses.replace(light, radius=0.0)
    with jit.disabled():
        bare = rsm.render_rsm(eng.raster, point, bounds, 64)
    assert not np.allclose(bare.flux, ref.flux, rtol=1e-3)  # the radius changes the flux


@pytest.mark.bpy
@pytest.mark.parametrize("soft", [True, False])
def test_a_point_light_whose_sphere_cuts_the_floor_lights_it_as_cycles(tmp_path, soft):
    """A 0.5 W point light of Blender's default radius 0.1 m, 5 cm over a white floor (the
    floor cuts its sphere): LPV's Diffuse Direct within 4 % of Cycles' over the floor, and
    under the light; as a point (1 / d^2) it was 1.8x Cycles'."""
    bpy = pytest.importorskip("bpy")
    import lpv_core as core
    from lpv_addon.render import cycles
    from lpv_addon.scene_io import demo as bdemo
    from lpv_addon.scene_io.extract import extract_scene
    from tools import report

    res = (48, 48)
    sc = bdemo.new_scene("round_light", res, True)
    bdemo.add_mesh_object(sc, "Floor", ([(-2, -2, 0), (2, -2, 0), (2, 2, 0), (-2, 2, 0)],
                                        [(0, 1, 2, 3)]),
                          bdemo.diffuse_material("Floor", (0.8, 0.8, 0.8), "DIFFUSE"))
    lamp = bpy.data.lights.new("Bulb", "POINT")
    lamp.energy, lamp.shadow_soft_size, lamp.use_soft_falloff = 0.5, 0.1, soft
    ob = bpy.data.objects.new("Bulb", lamp)
    ob.location = (0.0, 0.0, 0.05)
    sc.collection.objects.link(ob)
    cam = bpy.data.cameras.new("Cam")
    cam.type, cam.ortho_scale = "ORTHO", 1.2
    cam_ob = bpy.data.objects.new("Cam", cam)
    cam_ob.location = (0.0, 0.0, 3.0)
    sc.collection.objects.link(cam_ob)
    sc.camera = cam_ob
    exr = tmp_path / "cycles.exr"
    cycles.render_cycles_passes(str(exr), samples=128, resolution=res)
    cyc = np.asarray(report._read_exr(str(exr))["Diffuse Direct"])[..., :3].mean(-1)
    scene = extract_scene(bpy.context.evaluated_depsgraph_get(), sc, res)
    assert scene.lights[0].soft_falloff is soft and scene.lights[0].radius == pytest.approx(0.1)
    eng = report._make_engine(core.render.raster.Rasterizer())
    ours = np.asarray(report.run_lpv(scene, scene.settings, eng, 1)["passes"]
                      ["Diffuse Direct"])[..., :3].mean(-1)
    centre = np.zeros(res[::-1], bool)
    centre[20:28, 20:28] = True  # within 0.1 m of the point under the light
    ratio, under = ours.mean() / cyc.mean(), ours[centre].mean() / cyc[centre].mean()
    print(f"\nsoft falloff {soft}: LPV / Cycles Diffuse Direct {ratio:.3f}, under it {under:.3f}")
    assert abs(ratio - 1.0) < 0.04 and abs(under - 1.0) < 0.04
