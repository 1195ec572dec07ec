"""A World that shows the camera one background and lights the scene with another (Light Path
"Is Camera Ray" mixing two Backgrounds, or two colours inside a node group) lights LPV's
surfaces as Cycles' diffuse rays see it, not as the camera does; the user's World is kept."""

from __future__ import annotations

import pytest

bpy = pytest.importorskip("bpy")

from conftest import factory_scene, lpv_and_cycles

pytestmark = pytest.mark.bpy

RES = (48, 36)
CAMERA = (1.0, 1.0, 1.0)  # what the camera sees, strength 1
LIGHTING = (0.3, 0.5, 1.0)  # what every other ray sees, x STRENGTH
STRENGTH = 0.1


def _camray_world(kind: str):
    """The factory scene without its lamp (the default cube on a 10 m floor, lit by the World
    only); the World is white for camera rays and a dim blue for all others: a Mix Shader of
    two Backgrounds (``kind`` "shader") or, "group", a Mix Color inside a node group feeding
    the Background's colour."""
    sc = factory_scene(RES)
    bpy.data.objects.remove(bpy.data.objects["Light"])
    bpy.ops.mesh.primitive_plane_add(size=10)
    tree = sc.world.node_tree
    out = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputWorld")
    path = tree.nodes.new("ShaderNodeLightPath")
    if kind == "shader":
        dim, bright = tree.nodes.new("ShaderNodeBackground"), tree.nodes.new("ShaderNodeBackground")
        dim.inputs["Color"].default_value = (*LIGHTING, 1.0)
        dim.inputs["Strength"].default_value = STRENGTH
        bright.inputs["Color"].default_value = (*CAMERA, 1.0)
        bright.inputs["Strength"].default_value = 1.0
        mix = tree.nodes.new("ShaderNodeMixShader")
        tree.links.new(path.outputs["Is Camera Ray"], mix.inputs[0])
        tree.links.new(dim.outputs[0], mix.inputs[1])
        tree.links.new(bright.outputs[0], mix.inputs[2])
        tree.links.new(mix.outputs[0], out.inputs["Surface"])
        return sc, path
    group = bpy.data.node_groups.new("Camera trick", "ShaderNodeTree")
    group.interface.new_socket("Color", in_out="OUTPUT", socket_type="NodeSocketColor")
    g_out = group.nodes.new("NodeGroupOutput")
    g_path = group.nodes.new("ShaderNodeLightPath")
    mix = group.nodes.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    sock = {s.identifier: s for s in mix.inputs}
    sock["A_Color"].default_value = tuple(c * STRENGTH for c in LIGHTING) + (1.0,)
    sock["B_Color"].default_value = (*CAMERA, 1.0)
    group.links.new(g_path.outputs["Is Camera Ray"], sock["Factor_Float"])
    group.links.new(next(s for s in mix.outputs if s.identifier == "Result_Color"),
                    g_out.inputs[0])
    node = tree.nodes.new("ShaderNodeGroup")
    node.node_tree = group
    bg = tree.nodes["Background"]
    bg.inputs["Strength"].default_value = 1.0
    tree.links.new(node.outputs[0], bg.inputs["Color"])
    tree.links.new(bg.outputs[0], out.inputs["Surface"])
    tree.nodes.remove(path)
    return sc, g_path


@pytest.mark.parametrize("kind", ["shader", "group"])
def test_camera_ray_trick_world_lights_as_cycles_diffuse_rays_see_it(tmp_path, kind):
    """LPV's Diffuse Direct mean within 5 % of Cycles' (the camera's white branch would make
    it ~8x); the camera-only branch is reported; the user's graph and groups are unchanged."""
    sc, path = _camray_world(kind)
    worlds, groups = len(bpy.data.worlds), len(bpy.data.node_groups)
    ours, ref, scene = lpv_and_cycles(tmp_path, sc, RES, rgb=True)
    ours, ref = ours["Diffuse Direct"], ref["Diffuse Direct"]
    assert any("Is Camera Ray 0" in line for line in scene.approximated)
    print(f"\n{kind}: LPV Diffuse Direct {ours.mean():.4f}, Cycles {ref.mean():.4f}")
    assert ref.mean() > 0.01
    assert ours.mean() == pytest.approx(ref.mean(), rel=0.05)
    # the user's data: the Light Path still feeds its mix, no copies left behind
    assert path.outputs["Is Camera Ray"].is_linked
    assert all(n.bl_idname != "ShaderNodeValue" for n in sc.world.node_tree.nodes)
    assert len(bpy.data.worlds) == worlds and len(bpy.data.node_groups) == groups
