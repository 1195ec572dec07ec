"""Smooth and custom shading normals in the bounce, as Cycles: a diffuse surface reflects the
light its shading normal's cosine takes and sends it out around its geometric normal (its
BSDF's outgoing side is the face's), so the RSM's VPLs leave along the face normal with the
shading normal's share of the light (raster.RSM_FRAGMENT_SHADER, rsm.view_vpls)."""

from __future__ import annotations

import numpy as np
import pytest

from lpv_core import engine, rsm
from lpv_core.runtime import jit
from lpv_core.scene import Light, Material, make_scene
from tools.core_scenes import light_matrix, quad


@pytest.mark.parametrize("compiled", [False, True])
def test_a_tilted_shading_normal_reflects_its_cosine_around_the_face_normal(compiled):
    """A 4 m floor under a sun straight down, its corner normals tilted 30 deg: every VPL's
    normal is the floor's (0, 0, 1) and the VPLs carry albedo x E x area x cos 30 deg (the
    mesh's own normals: the full albedo x E x area), in the numpy reference and compiled."""
    tilt = np.radians(30.0)
    tris = quad((-2, -2, 0), (2, -2, 0), (2, 2, 0), (-2, 2, 0))
    sun = Light("Sun", "SUN", light_matrix((0, 0, 0), (0, 0, -1)), power=2.0)
    albedo = 0.5
    totals = {}
    for name, n in (("flat", (0.0, 0.0, 1.0)), ("tilted", (np.sin(tilt), 0.0, np.cos(tilt)))):
        scene = make_scene(tris, normals=np.tile(n, (2, 3, 1)),
                           materials=[Material("m", np.full(3, albedo, np.float32))],
                           lights=[sun])
        eng = engine.Engine()
        eng.upload(scene, engine.Stats())
        bounds = eng.lpv_bounds(scene)
        if compiled:
            assert jit.enabled()
            got = rsm.render_rsm(eng.raster, sun, bounds, 64)
        else:
            with jit.disabled():
                got = rsm.render_rsm(eng.raster, sun, bounds, 64)
        assert got.count > 1000
        np.testing.assert_allclose(got.normal, np.tile([0.0, 0.0, 1.0], (got.count, 1)),
                                   atol=1e-6)
        totals[name] = got.flux[:, 0].sum()
    # (the flat floor's 2 % over is the window's texels at the floor's edge: whole texels)
    assert totals["flat"] == pytest.approx(albedo * 2.0 * 16.0, rel=0.03)
    assert totals["tilted"] / totals["flat"] == pytest.approx(np.cos(tilt), rel=1e-6)


bpy = pytest.importorskip("bpy")


@pytest.mark.bpy
def test_custom_normals_keep_the_bounce(tmp_path):
    """Blender's factory cube over a 20 m floor, both with custom normals all pointing up
    (what an import can carry): the Diffuse Indirect mean against Cycles within a factor of two,
    as test_radiometry's indirect energy (0.029 while the VPLs left along the shading normal:
    the cube's sides sent their light up). Measured 0.72 at 16^3, 1.62 at 32^3: a side's
    receivers, read along the up normal over the whole sphere, count their own face's light in
    the cells beside it, which Cycles' rays below the side's surface never meet."""
    from conftest import factory_scene, lpv_and_cycles

    sc = factory_scene((64, 48))
    sc.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    bpy.ops.mesh.primitive_plane_add(size=20, location=(0, 0, -1))
    for ob in (bpy.data.objects["Cube"], bpy.context.object):
        ob.data.normals_split_custom_set([(0.0, 0.0, 1.0)] * len(ob.data.loops))
    ours, ref, _ = lpv_and_cycles(tmp_path, sc, (64, 48), rgb=True)
    ratio = ours["Diffuse Indirect"].mean() / ref["Diffuse Indirect"].mean()
    assert 0.5 <= ratio <= 2.0, ratio
