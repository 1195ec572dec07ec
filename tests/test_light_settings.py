"""Light and camera settings artists use, read as Cycles reads them: a light's node tree
(Emission colour x strength), a light diffuse rays do not see, a Cycles portal and a negative
power (named, left out), a panoramic camera (a clear error), depth of field and motion blur (named)."""

from __future__ import annotations

import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from conftest import factory_scene, lpv_and_cycles

from lpv_addon.scene_io import extract

pytestmark = pytest.mark.bpy

RES = (48, 36)


def _floor_and_light(**light_settings):
    """Blender's default file: a 10 m grey floor under the default point light (1000 W), the
    default camera, a black World; ``light_settings`` set on the light object."""
    sc = factory_scene(RES)
    bpy.data.objects.remove(bpy.data.objects["Cube"])
    bpy.ops.mesh.primitive_plane_add(size=10)
    sc.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    lamp = bpy.data.objects["Light"]
    lamp.data.energy = 1000.0
    for key, value in light_settings.items():
        setattr(lamp, key, value)
    return sc, lamp


def _direct_means(tmp_path, sc):
    """(LPV, Cycles) mean Diffuse Direct of the context scene."""
    ours, ref, scene = lpv_and_cycles(tmp_path, sc, RES, samples=16, rgb=True)
    return float(ours["Diffuse Direct"].mean()), float(ref["Diffuse Direct"].mean()), scene


def test_a_lights_node_tree_scales_its_emission_as_in_cycles(tmp_path):
    sc, lamp = _floor_and_light()
    lamp.data.use_nodes = True
    emission = next(n for n in lamp.data.node_tree.nodes if n.bl_idname == "ShaderNodeEmission")
    emission.inputs["Strength"].default_value = 0.3
    emission.inputs["Color"].default_value = (0.2, 0.5, 1.0, 1.0)
    ours, ref, scene = _direct_means(tmp_path, sc)
    assert np.allclose(scene.lights[0].color, [0.06, 0.15, 0.3], rtol=1e-6)
    assert abs(ours / ref - 1.0) < 0.03  # without the node tree: 2.6x
    tex = lamp.data.node_tree.nodes.new("ShaderNodeTexNoise")
    lamp.data.node_tree.links.new(tex.outputs["Fac"], emission.inputs["Strength"])
    scene = extract.extract_scene(bpy.context.evaluated_depsgraph_get(), sc, RES)
    assert any("light 'Light'" in line and "Strength" in line for line in scene.approximated)


def test_a_light_diffuse_rays_do_not_see_lights_nothing(tmp_path):
    sc, _ = _floor_and_light(visible_diffuse=False)
    ours, ref, scene = _direct_means(tmp_path, sc)
    assert ref < 1e-6 and ours == 0.0 and not scene.lights


def test_a_cycles_portal_emits_nothing_and_is_named(tmp_path):
    """An area light marked Portal (Cycles: it guides the World's light through a window and
    emits none) beside the default light: Diffuse Direct as Cycles' (measured 1.000; 4.2x
    while it was lit as a 500 W area light), the portal named."""
    sc, _ = _floor_and_light()
    data = bpy.data.lights.new("Portal", "AREA")
    data.size, data.energy = 2.0, 500.0
    data.cycles.is_portal = True
    portal = bpy.data.objects.new("Portal", data)
    sc.collection.objects.link(portal)
    portal.location = (0.0, 0.0, 3.0)
    ours, ref, scene = _direct_means(tmp_path, sc)
    assert [lt.name for lt in scene.lights] == ["Light"]
    assert abs(ours / ref - 1.0) < 0.03, ours / ref
    assert any("light 'Portal': a Cycles portal" in line for line in scene.approximated)


def test_a_negative_light_is_named_and_left_out():
    sc, lamp = _floor_and_light()
    lamp.data.energy = -300.0
    scene = extract.extract_scene(bpy.context.evaluated_depsgraph_get(), sc, RES)
    assert not scene.lights
    assert any("light 'Light': negative power" in line for line in scene.approximated)


def test_a_panoramic_camera_is_a_clear_error():
    sc, _ = _floor_and_light()
    sc.camera.data.type = "PANO"
    with pytest.raises(ValueError, match="camera 'Camera': panoramic cameras are not"):
        extract.extract_scene(bpy.context.evaluated_depsgraph_get(), sc, RES)


def test_depth_of_field_and_motion_blur_are_named():
    sc, _ = _floor_and_light()
    sc.camera.data.dof.use_dof = True
    sc.camera.data.dof.aperture_fstop = 0.5
    sc.render.use_motion_blur = True
    notes = extract.extract_scene(bpy.context.evaluated_depsgraph_get(), sc, RES).approximated
    assert any("camera 'Camera': depth of field" in line for line in notes)
    assert any("motion blur" in line for line in notes)
    assert math.isfinite(sc.camera.data.dof.aperture_fstop)  # the user's settings untouched
