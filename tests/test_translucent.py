"""A Translucent BSDF is lit through the surface, from its far side, as in Cycles: a leaf lit
from behind shows the light that falls on its other side (direct and bounced), a closed
translucent box lit from the front shows none on that front."""

from __future__ import annotations

import math

import pytest

bpy = pytest.importorskip("bpy")

from conftest import factory_scene, lpv_and_cycles

pytestmark = pytest.mark.bpy

RES = (64, 48)


def _leaf(closed_box: bool):
    """A 10 m grey floor and a 2 m translucent green square (or, ``closed_box``, the default
    cube, translucent), lit by a 1000 W point light; the default camera sees the leaf's side
    away from the light (the box's lit faces)."""
    sc = factory_scene(RES)
    sc.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    cube = bpy.data.objects["Cube"]
    mat = bpy.data.materials.new("Leaf")
    if mat.node_tree is None:  # pragma: no cover - Blender < 5 needs nodes switched on
        mat.use_nodes = True
    tree = mat.node_tree
    translucent = tree.nodes.new("ShaderNodeBsdfTranslucent")
    translucent.inputs["Color"].default_value = (0.3, 0.7, 0.2, 1.0)
    tree.links.new(translucent.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    if closed_box:
        cube.location = (0.0, 0.0, 1.0)
        cube.data.materials[0] = mat
        light_at = (4.0, -4.0, 4.0)  # lighting the faces the camera sees
    else:
        bpy.data.objects.remove(cube)
        bpy.ops.mesh.primitive_plane_add(size=2, location=(0.0, 0.0, 1.5),
                                         rotation=(math.radians(70), 0.0, math.radians(40)))
        bpy.context.object.data.materials.append(mat)
        light_at = (-4.0, 4.0, 4.0)  # behind the leaf
    bpy.ops.mesh.primitive_plane_add(size=10)
    light = bpy.data.objects["Light"]
    light.location = light_at
    light.data.energy = 1000.0
    return sc


@pytest.mark.parametrize("closed_box", [False, True])
def test_translucent_surfaces_are_lit_from_their_far_side(tmp_path, closed_box):
    # the light through the leaf bounces as Cycles' transmission: one such bounce allowed
    ours, ref, scene = lpv_and_cycles(tmp_path, _leaf(closed_box), RES, rgb=True,
                                      transmission_bounces=1)
    assert any(math.isclose(m.translucency, 1.0) for m in scene.materials)
    dc = ref["Diffuse Color"]
    leaf = dc[..., 1] - dc[..., 0] > 0.3  # the green surface's pixels (not the grey floor)
    assert leaf.mean() > 0.03
    if closed_box:  # no light inside: its lit faces show none (lit as their near side before)
        floor = dc.max(-1) - dc.min(-1) < 0.02
        floor &= dc.max(-1) > 0.3
        for passes in (ours, ref):
            assert passes["Diffuse Direct"][leaf].mean() < 0.01 * passes["Diffuse Direct"][
                floor].mean()
        return
    direct = ours["Diffuse Direct"][leaf].mean() / ref["Diffuse Direct"][leaf].mean()
    assert abs(direct - 1.0) < 0.05, direct  # lit from the near side: 0.54x Cycles'
    # the lit floor's bounce comes through too
    indirect = ours["Diffuse Indirect"][leaf].mean() / ref["Diffuse Indirect"][leaf].mean()
    assert 0.6 < indirect < 1.4, indirect
