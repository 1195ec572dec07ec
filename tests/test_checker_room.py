"""tools.scenes.checker_room: the materials acceptance scene carries what it claims (a packed
checker image on a UV-mapped Principled floor, a Metallic 1 block, a plain diffuse block)."""

import pytest

bpy = pytest.importorskip("bpy")
pytestmark = pytest.mark.bpy

from tools import scenes


def test_checker_room_materials(tmp_path):
    facts = scenes.save_scene("checker_room", tmp_path / "c.blend", resolution=(16, 16))
    bpy.ops.wm.open_mainfile(filepath=facts["path"], load_ui=False)
    floor = bpy.data.objects["Floor"]
    uvs = [tuple(d.uv) for d in floor.data.uv_layers["UVMap"].data]
    assert sorted({round(u, 6) for u, _ in uvs}) == [0.0, 1.0]
    tex = next(n for n in floor.active_material.node_tree.nodes if n.bl_idname == "ShaderNodeTexImage")
    img = tex.image
    assert img.packed_file is not None and tuple(img.size) == (8, 8)
    px = list(img.pixels)
    assert px[:3] == pytest.approx(scenes.CHECKER[0]) and px[4:7] == pytest.approx(scenes.CHECKER[1])
    metal = bpy.data.objects["Metal"].active_material.node_tree.nodes["Principled BSDF"]
    assert metal.inputs["Metallic"].default_value == 1.0
    plain = bpy.data.objects["Plain"].active_material.node_tree.nodes
    assert {n.bl_idname for n in plain} == {"ShaderNodeOutputMaterial", "ShaderNodeBsdfDiffuse"}
    assert facts["lights"] == ["Point"]
