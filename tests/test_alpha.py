"""Partly transparent surfaces (Principled Alpha, a Transparent BSDF mixed in) as Cycles shows
them: the camera sees through them by their coverage and they cast a shadow of that density
(hashed alpha in every pass, raster.HASHED_ALPHA). A card of Alpha 0.3 over a floor under the
default point light, against Cycles."""

from __future__ import annotations

import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from conftest import factory_scene, lpv_and_cycles

pytestmark = pytest.mark.bpy

RES = (64, 48)


def _card_over_floor(transparent_mix: bool):
    """A 10 m diffuse floor, a 3 m red card 1 m over it (Alpha 0.3, or a Diffuse mixed with a
    Transparent BSDF at 0.7), the default light 4 m up, seen from the default camera."""
    sc = factory_scene(RES)
    bpy.data.objects.remove(bpy.data.objects["Cube"])
    sc.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    bpy.ops.mesh.primitive_plane_add(size=10)
    floor = bpy.data.materials.new("Floor")  # a Diffuse BSDF: Combined without a glossy part
    if floor.node_tree is None:  # pragma: no cover - Blender < 5 needs nodes switched on
        floor.use_nodes = True
    diffuse = floor.node_tree.nodes.new("ShaderNodeBsdfDiffuse")
    floor.node_tree.links.new(diffuse.outputs[0],
                              floor.node_tree.nodes["Material Output"].inputs["Surface"])
    bpy.context.object.data.materials.append(floor)
    bpy.ops.mesh.primitive_plane_add(size=3, location=(0.0, 0.0, 1.0))
    card = bpy.context.object
    mat = bpy.data.materials.new("Card")
    if mat.node_tree is None:  # pragma: no cover - Blender < 5 needs nodes switched on
        mat.use_nodes = True
    tree = mat.node_tree
    bsdf = tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (0.8, 0.1, 0.05, 1.0)
    if transparent_mix:
        mix = tree.nodes.new("ShaderNodeMixShader")
        mix.inputs["Fac"].default_value = 0.7
        tree.links.new(bsdf.outputs[0], mix.inputs[1])
        tree.links.new(tree.nodes.new("ShaderNodeBsdfTransparent").outputs[0], mix.inputs[2])
        tree.links.new(mix.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    else:
        bsdf.inputs["Alpha"].default_value = 0.3
    card.data.materials.append(mat)
    light = bpy.data.objects["Light"]
    light.location = (0.5, -0.5, 4.0)
    light.data.energy = 1000.0
    return sc


@pytest.mark.parametrize("transparent_mix", [False, True])
def test_a_partly_transparent_card_is_seen_through_and_shadows_by_its_coverage(
        tmp_path, transparent_mix):
    from lpv_core.render.error import relative_rmse

    ours, ref, scene = lpv_and_cycles(tmp_path, _card_over_floor(transparent_mix), RES,
                                      rgb=True)
    assert math.isclose(scene.materials[-1].alpha, 0.3, abs_tol=1e-6) or math.isclose(
        min(m.alpha for m in scene.materials), 0.3, abs_tol=1e-6)
    # through the card the floor shows: Diffuse Color 0.3 x card + 0.7 x floor
    # (drawn opaque at 0.3 x its colour: Diffuse Color relative RMSE 0.33, Combined 0.88x)
    assert relative_rmse(ours["Diffuse Color"], ref["Diffuse Color"]) < 0.12
    for name in ("Diffuse Color", "Diffuse Direct", "Combined"):
        ratio = ours[name].mean() / ref[name].mean()
        assert abs(ratio - 1.0) < 0.05, (name, ratio)


def test_an_image_alpha_cuts_the_card_per_texel(tmp_path):
    """A leaf card's Alpha from its image (a 4 x 4 checker of alpha 0 and 1 through the
    card's UV map): the floor shows through and is lit through the holes texel by texel
    (measured 0.077 and 0.35; its mean alpha, 0.5, as a uniform coverage: Diffuse Color
    relative RMSE 0.12, Diffuse Direct 0.50)."""
    from lpv_core.render.error import relative_rmse

    sc = _card_over_floor(False)
    tree = bpy.data.materials["Card"].node_tree
    image = bpy.data.images.new("checker", 4, 4, alpha=True)
    px = np.ones((4, 4, 4), np.float32)
    px[..., 3] = (np.add.outer(np.arange(4), np.arange(4)) % 2).astype(np.float32)
    image.pixels.foreach_set(px.ravel())
    image.pack()
    node = tree.nodes.new("ShaderNodeTexImage")
    node.image, node.interpolation = image, "Closest"
    tree.links.new(node.outputs["Alpha"], tree.nodes["Principled BSDF"].inputs["Alpha"])
    ours, ref, scene = lpv_and_cycles(tmp_path, sc, RES, rgb=True)
    card = next(m for m in scene.materials if m.name == "Card")
    assert card.alpha_texture is not None and card.alpha == 1.0
    assert relative_rmse(ours["Diffuse Color"], ref["Diffuse Color"]) < 0.1
    assert relative_rmse(ours["Diffuse Direct"], ref["Diffuse Direct"]) < 0.42


def test_a_volume_only_material_is_a_transparent_surface(tmp_path):
    """A fog box: the default cube with a Principled Volume (density 0) on its Volume output
    and nothing on Surface; Cycles' rays pass its surface. LPV draws no surface there, it
    neither shadows nor bounces (caster and occluder off), and the volume is named (measured
    relative RMSE while it was drawn as a black box: Diffuse Color 0.40, Diffuse Direct 0.47;
    now 0.12, most of it the floor's far edge, and 0.026)."""
    from lpv_core.render.error import relative_rmse

    sc = factory_scene(RES)
    bpy.ops.mesh.primitive_plane_add(size=20, location=(0, 0, -1))
    mat = bpy.data.materials.new("Fog")
    if mat.node_tree is None:  # pragma: no cover - Blender < 5 needs nodes switched on
        mat.use_nodes = True
    tree = mat.node_tree
    out = tree.nodes["Material Output"]
    for link in list(out.inputs["Surface"].links):
        tree.links.remove(link)
    volume = tree.nodes.new("ShaderNodeVolumePrincipled")
    volume.inputs["Density"].default_value = 0.0
    tree.links.new(volume.outputs[0], out.inputs["Volume"])
    cube = bpy.data.objects["Cube"]
    cube.data.materials.clear()
    cube.data.materials.append(mat)
    ours, ref, scene = lpv_and_cycles(tmp_path, sc, RES, rgb=True)
    fog = [i for i, m in enumerate(scene.materials) if m.name == "Fog"]
    assert fog and scene.materials[fog[0]].alpha == 0.0
    boxed = scene.material_index == fog[0]
    assert not scene.flag("occluder")[boxed].any() and not scene.flag("caster")[boxed].any()
    assert any("volume only" in line for line in scene.approximated)
    assert relative_rmse(ours["Diffuse Color"], ref["Diffuse Color"]) < 0.15
    assert relative_rmse(ours["Diffuse Direct"], ref["Diffuse Direct"]) < 0.05
