"""A closed emissive object (a glowing cube, a neon tube) lights its surroundings from its
outer side only: Cycles' emission is two-sided, but what the inner side sends meets the
object's own faces (emitters.outward_side), which the emitters' shadow maps leave out."""

from __future__ import annotations

import numpy as np
import pytest

from lpv_core import emitters
from lpv_core.scene import Material, make_scene
from tools.core_scenes import box_triangles


@pytest.mark.parametrize("flip, open_box, expected", [
    (False, False, 1), (True, False, -1), (False, True, 0)])
def test_a_closed_objects_outer_side_is_found_from_its_winding(flip, open_box, expected):
    """A box whose triangles close a volume is +1 with its normals out, -1 wound inwards; an
    open one (a face removed) 0: both sides."""
    tris = box_triangles((-1.0, -1.0, 0.0), (1.0, 1.0, 2.0))
    if flip:
        tris = tris[:, ::-1]
    if open_box:
        tris = tris[2:]
    scene = make_scene(tris, materials=[Material("glow", np.full(3, 0.5, np.float32))])
    assert emitters.outward_side(scene, np.ones(len(tris), bool)) == expected


bpy = pytest.importorskip("bpy")


@pytest.mark.bpy
def test_a_glowing_cube_lights_the_floor_as_cycles(tmp_path):
    """Blender's default cube with Principled Emission 5 (orange) over a 20 m floor, the lamp
    removed and the World black: the floor's Diffuse Direct mean against Cycles, measured
    0.995 (2.42 while the cube's far faces shone through it), its indirect 0.87 (5.7)."""
    from conftest import factory_scene, lpv_and_cycles

    sc = factory_scene((64, 48))
    sc.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    bpy.data.objects.remove(bpy.data.objects["Light"])
    bpy.ops.mesh.primitive_plane_add(size=20, location=(0, 0, -1))
    bsdf = bpy.data.objects["Cube"].active_material.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Emission Color"].default_value = (1.0, 0.5, 0.2, 1.0)
    bsdf.inputs["Emission Strength"].default_value = 5.0
    ours, ref, _ = lpv_and_cycles(tmp_path, sc, (64, 48), rgb=True)
    ratio = ours["Diffuse Direct"].mean() / ref["Diffuse Direct"].mean()
    assert abs(ratio - 1.0) <= 0.05, ratio
    indirect = ours["Diffuse Indirect"].mean() / ref["Diffuse Indirect"].mean()
    assert 0.7 <= indirect <= 1.3, indirect
