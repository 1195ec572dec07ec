"""Normal maps as Cycles shades them: a tangent-space Normal Map node on the BSDF's Normal
input turns the G-buffer's normal per point (raster.NORMAL_MAP, Blender's own MikkTSpace
tangents), so the lamps', the World's and the GI's light on a normal-mapped surface follow
its relief. A rotated, scaled plane under a low sun, against Cycles."""

from __future__ import annotations

import math

import numpy as np
import pytest


def _tilted_floor(tilt_deg: float, digest: str):
    """A core 4 m floor whose constant normal map tilts the normal ``tilt_deg`` towards +X,
    under a sun 40 deg from the zenith on the +X side, seen from above."""
    from lpv_core.scene import Camera, GISettings, Light, Material, make_scene
    from lpv_core.scene.textures import Texture
    from tools.core_scenes import light_matrix, quad

    t = np.radians(tilt_deg)
    texel = np.array([0.5 + 0.5 * np.sin(t), 0.5, 0.5 + 0.5 * np.cos(t)], np.float32)
    tex = Texture("n", np.tile(texel, (4, 4, 1)), digest=digest)
    pos = quad((-2, -2, 0), (2, -2, 0), (2, 2, 0), (-2, 2, 0))
    tan = np.zeros((2, 3, 4), np.float32)
    tan[..., 0], tan[..., 3] = 1.0, 1.0
    sun = Light("Sun", "SUN", light_matrix((0, 0, 0), (-np.sin(np.radians(40)), 0,
                                                        -np.cos(np.radians(40)))), power=1.0)
    cam = Camera.look_at((0, 0, 5), (0, 0, 0), up=(0, 1, 0), fov_y=np.radians(30),
                         resolution=(8, 8))
    return make_scene(pos, materials=[Material("m", np.full(3, 0.8, np.float32),
                                               normal_texture=tex)],
                      lights=[sun], camera=cam, uvs=(pos[..., :2] + 2) / 4, tangents=tan,
                      settings=GISettings(grid_resolution=8, rsm_resolution=32,
                                          shadow_resolution=256, antialias=1))


def test_the_normal_maps_texture_is_kept_while_its_maps_are_the_same():
    """The rasteriser keeps its normal-map texture array while the maps' digests hold (each
    antialias sample uploads the scene again: 140 ms a 1024^2 map otherwise) and makes it
    again for another map: Diffuse Direct follows each map's tilt, cos(40 deg - tilt) / pi."""
    from lpv_core import engine
    from lpv_core.render import deferred

    eng = engine.Engine()
    for tilt, digest in ((30.0, "a"), (30.0, "a"), (20.0, "b")):
        scene = _tilted_floor(tilt, digest)
        before = eng.raster._normal_maps
        direct = deferred.render(eng, scene, eng.update(scene))["Diffuse Direct"][..., 0]
        assert direct.mean() == pytest.approx(np.cos(np.radians(40 - tilt)) / np.pi, rel=1e-4)
        if digest == "a" and before is not None:
            assert eng.raster._normal_maps is before  # the same maps: the same array


bpy = pytest.importorskip("bpy")

from conftest import factory_scene, lpv_and_cycles

RES = (64, 48)


def _relief(side: int = 128) -> np.ndarray:
    """(side, side, 4) RGBA of a tangent-space normal map: ridges along u and along v of
    different period, tilting the normal up to 35 deg towards +-T and +-B (rows bottom-first,
    as Image.pixels)."""
    u = (np.arange(side) + 0.5) / side
    tx = 0.57 * np.cos(2 * np.pi * 3 * u)[None, :] * np.ones((side, 1))
    ty = 0.57 * np.sin(2 * np.pi * 2 * u)[:, None] * np.ones((1, side))
    n = np.stack([tx, ty, np.ones_like(tx)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.concatenate([0.5 * n + 0.5, np.ones((side, side, 1))], axis=-1).astype(np.float32)


def _normal_mapped_plane(strength: float = 1.0, mirrored: bool = False,
                         textured: bool = False):
    """Blender's factory scene without the cube: a 6 m plane turned 30 deg about Z (x -1 in
    X when ``mirrored``), its Principled BSDF's Normal from a Normal Map of _relief (Non-Color,
    the plane's UV map; ``textured``: its Base Color a 4 x 4 grey checker image too), lit by
    a sun 35 deg up; the World black."""
    sc = factory_scene(RES)
    bpy.data.objects.remove(bpy.data.objects["Cube"])
    bpy.data.objects.remove(bpy.data.objects["Light"])
    sc.world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    bpy.ops.mesh.primitive_plane_add(size=6, rotation=(0.0, 0.0, math.radians(30)))
    plane = bpy.context.object
    if mirrored:
        plane.scale = (-1.0, 1.0, 1.0)
    image = bpy.data.images.new("relief", 128, 128, alpha=True, float_buffer=True)
    image.colorspace_settings.name = "Non-Color"
    image.pixels.foreach_set(_relief().ravel())
    image.pack()
    mat = bpy.data.materials.new("Relief")
    if mat.node_tree is None:  # pragma: no cover - Blender < 5 needs nodes switched on
        mat.use_nodes = True
    tree = mat.node_tree
    tex = tree.nodes.new("ShaderNodeTexImage")
    tex.image = image
    nmap = tree.nodes.new("ShaderNodeNormalMap")
    nmap.inputs["Strength"].default_value = strength
    tree.links.new(tex.outputs["Color"], nmap.inputs["Color"])
    tree.links.new(nmap.outputs["Normal"], tree.nodes["Principled BSDF"].inputs["Normal"])
    if textured:
        checker = bpy.data.images.new("checker", 4, 4)
        grey = 0.3 + 0.5 * (np.add.outer(np.arange(4), np.arange(4)) % 2)
        checker.pixels.foreach_set(np.dstack([grey] * 3 + [np.ones((4, 4))]).ravel()
                                   .astype(np.float32))
        checker.pack()
        base = tree.nodes.new("ShaderNodeTexImage")
        base.image, base.interpolation = checker, "Closest"
        tree.links.new(base.outputs["Color"], tree.nodes["Principled BSDF"].inputs["Base Color"])
    plane.data.materials.append(mat)
    sun_data = bpy.data.lights.new("Sun", "SUN")
    sun_data.energy, sun_data.angle = 3.0, 0.0
    sun = bpy.data.objects.new("Sun", sun_data)
    sc.collection.objects.link(sun)
    sun.rotation_euler = (math.radians(55), 0.0, math.radians(20))
    cam = bpy.data.objects["Camera"]
    cam.location, cam.rotation_euler = (0.0, -4.5, 6.0), (math.radians(35), 0.0, 0.0)
    return sc


def _inside(ref: dict) -> np.ndarray:
    """Pixels whose 3 x 3 neighbourhood Cycles covers with the plane: the silhouette's
    pixels left out (their Diffuse Direct, light over colour of a partial cover, differs
    from LPV's antialias samples whatever the normal: 90 % of the squared error there)."""
    covered = ref["Diffuse Color"].mean(axis=-1) > 0
    inside = covered.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            inside &= np.roll(np.roll(covered, dy, 0), dx, 1)
    inside[0, :] = inside[-1, :] = inside[:, 0] = inside[:, -1] = False
    return inside


@pytest.mark.bpy
@pytest.mark.parametrize("strength, mirrored, textured",
                         [(1.0, False, False), (0.5, False, False), (1.0, True, False),
                          (1.0, False, True)])
def test_a_normal_map_shades_diffuse_direct_as_cycles(tmp_path, strength, mirrored, textured):
    """Diffuse Direct inside the plane per pixel against Cycles: with the normal map read,
    relative RMSE measured 0.026 at Strength 1 (mean 1.02x Cycles'); with the mesh's own
    normals (the map left out) about 20 times that. The mirrored plane checks the tangents'
    transform and the bitangent's sign, the textured one the G-buffer's textured pass."""
    import dataclasses

    import lpv_core as core
    from lpv_core.render.error import relative_rmse
    from tools import report

    sc = _normal_mapped_plane(strength, mirrored, textured)
    ours, ref, scene = lpv_and_cycles(tmp_path, sc, RES, rgb=True)
    relief = next(m for m in scene.materials if m.name == "Relief")
    assert relief.normal_texture is not None and relief.normal_strength == strength
    assert scene.tangents is not None and not scene.approximated, scene.approximated
    inside = _inside(ref)
    target = ref["Diffuse Direct"][inside]
    mapped = relative_rmse(ours["Diffuse Direct"][inside], target)
    flat_scene = dataclasses.replace(scene, materials=[
        dataclasses.replace(m, normal_texture=None) for m in scene.materials])
    eng = report._make_engine(core.render.raster.Rasterizer())
    flat = report.run_lpv(flat_scene, flat_scene.settings, eng, 1)["passes"]
    flat_err = relative_rmse(np.asarray(flat["Diffuse Direct"], np.float64)[..., :3][inside],
                             target)
    assert inside.sum() > 0.5 * inside.size
    assert mapped < 0.05 and flat_err > 4 * mapped, (mapped, flat_err)


@pytest.mark.bpy
def test_a_bump_or_an_object_space_normal_map_is_named_and_left_out():
    """What is not read is said: a Bump node, a Normal Map in Object space, a Displacement."""
    from lpv_addon.scene_io.extract import extract_scene

    sc = _normal_mapped_plane()
    tree = bpy.data.materials["Relief"].node_tree
    tree.nodes["Normal Map"].space = "OBJECT"
    scene = extract_scene(bpy.context.evaluated_depsgraph_get(), sc, RES)
    assert scene.materials[0].normal_texture is None
    assert any("Normal Map" in line and "Object space" in line for line in scene.approximated)
    bump = tree.nodes.new("ShaderNodeBump")
    tree.links.new(bump.outputs["Normal"], tree.nodes["Principled BSDF"].inputs["Normal"])
    scene = extract_scene(bpy.context.evaluated_depsgraph_get(), sc, RES)
    assert any("Bump" in line and "left out" in line for line in scene.approximated)
    displace = tree.nodes.new("ShaderNodeDisplacement")
    tree.links.new(displace.outputs[0], tree.nodes["Material Output"].inputs["Displacement"])
    scene = extract_scene(bpy.context.evaluated_depsgraph_get(), sc, RES)
    assert any("Displacement" in line and "left out" in line for line in scene.approximated)


def test_the_worker_carries_the_normal_map_and_the_tangents(tmp_path):
    """The render worker's scene file holds a material's normal map (once per digest) and
    the per-corner tangents, and the scene read back holds them as they were."""
    from lpv_core import worker
    from lpv_core.scene import Material, make_scene
    from lpv_core.scene.textures import Texture

    tris = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], np.float64)
    tan = np.zeros((1, 3, 4), np.float32)
    tan[..., 0], tan[..., 3] = 1.0, -1.0
    tex = Texture("relief", _relief(8)[..., :3].copy(), digest="relief8")
    scene = make_scene(tris, materials=[Material("m", np.full(3, 0.5, np.float32),
                                                 normal_texture=tex, normal_strength=0.7)],
                       uvs=tris[..., :2].astype(np.float32), tangents=tan)
    path = str(tmp_path / "scene.npz")
    worker.save_scene(path, scene)
    back = worker.load_scene(path)
    m = back.materials[0]
    assert m.normal_strength == 0.7 and m.normal_texture.digest == "relief8"
    assert np.array_equal(np.asarray(m.normal_texture.pixels), tex.pixels)
    assert np.array_equal(back.tangents, tan)


@pytest.mark.bpy
@pytest.mark.parametrize("mirrored", [False, True])
def test_each_triangles_own_tangents_are_blenders_on_a_flat_plane(mirrored):
    """The n-gon fallback (extract.triangle_tangents, a triangle's dP/du and bitangent sign)
    gives Blender's MikkTSpace tangents where those are exact (a flat quad with a linear UV
    map), and the world-space tangents the extraction hands on are those of the positions it
    hands on (the object's rotation, scale and mirror applied)."""
    from lpv_addon.scene_io.extract import extract_scene, triangle_tangents

    sc = _normal_mapped_plane(mirrored=mirrored)
    scene = extract_scene(bpy.context.evaluated_depsgraph_get(), sc, RES)
    own = triangle_tangents(scene.positions, scene.uvs)
    assert np.allclose(scene.tangents, own, atol=1e-5), np.abs(scene.tangents - own).max()
    assert np.allclose(np.abs(scene.tangents[..., 3]), 1.0)
