"""Extraction from real (headless) Blender scenes into the core scene model."""

import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from bpy_extras.object_utils import world_to_camera_view
from mathutils import Vector

from lpv_addon.scene_io import extract

pytestmark = pytest.mark.bpy


@pytest.fixture(autouse=True)
def empty_file():
    bpy.ops.wm.read_homefile(use_empty=True)
    yield


def dg():
    return bpy.context.evaluated_depsgraph_get()


def run(**kw):
    kw.setdefault("require_camera", False)
    return extract.extract_scene(dg(), **kw)


def link(ob):
    bpy.context.scene.collection.objects.link(ob)
    return ob


def mesh_object(name, verts, faces, smooth=False):
    me = bpy.data.meshes.new(name)
    me.from_pydata([tuple(v) for v in verts], [], [tuple(f) for f in faces])
    if smooth:
        me.shade_smooth()
    return link(bpy.data.objects.new(name, me))


CUBE_V = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
# Outward (counter-clockwise seen from outside) quads of the cube above (index = 4x + 2y + z).
CUBE_F = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]


def cube(name="cube", smooth=False):
    return mesh_object(name, CUBE_V, CUBE_F, smooth)


def assert_outward(scene, center):
    """Every corner normal points away from ``center`` and agrees with the winding."""
    p = scene.positions.astype(np.float64)
    n = scene.normals.astype(np.float64)
    out = p - np.asarray(center, np.float64)
    assert (np.einsum("tci,tci->tc", n, out) > 0).all()
    geo = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert (np.einsum("ti,tci->tc", geo, n) > 0).all()


def material(name, kind="ShaderNodeBsdfPrincipled"):
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender < 5: node trees are opt-in
        mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    for node in list(nodes):
        if node.bl_idname != "ShaderNodeOutputMaterial":
            nodes.remove(node)
    out = next(n for n in nodes if n.bl_idname == "ShaderNodeOutputMaterial")
    bsdf = nodes.new(kind)
    links.new(bsdf.outputs[0], out.inputs["Surface"])
    return mat, bsdf


# ----------------------------------------------------------------------------- geometry


def test_transformed_cube_world_positions_and_normals():
    ob = cube()
    ob.location = (1, 2, 3)
    ob.rotation_euler = (0, 0, math.pi / 2)
    ob.scale = (2, 1, 1)
    s = run()
    assert s.triangle_count == 12
    # Local (x, y, z) -> scale (2x, y, z) -> Rz(90) (-y, 2x, z) -> + (1, 2, 3).
    expected = {(x, y, z) for x in (0, 2) for y in (0, 4) for z in (2, 4)}
    got = {tuple(np.round(v, 5)) for v in s.positions.reshape(-1, 3).tolist()}
    assert got == expected
    assert_outward(s, (1, 2, 3))
    # Flat cube: every corner normal is one of the six axes.
    assert np.allclose(np.abs(s.normals).max(axis=2), 1.0, atol=1e-6)
    assert s.object_names == ["cube"] and (s.object_index == 0).all()


@pytest.mark.parametrize("scale", [(-1, 1, 1), (-1, -1, -1), (1, -2, 0.5)])
def test_negative_scale_keeps_normals_outward(scale):
    flat = cube("flat")
    flat.scale = scale
    bpy.ops.mesh.primitive_uv_sphere_add(segments=16, ring_count=8, location=(6, 0, 0))
    sphere = bpy.context.object
    sphere.data.shade_smooth()
    sphere.scale = scale
    s = run()
    flat_tris = s.object_index == s.object_names.index("flat")
    for mask, center in ((flat_tris, (0, 0, 0)), (~flat_tris, (6, 0, 0))):
        part = extract.core.scene.make_scene(s.positions[mask], s.normals[mask])
        assert_outward(part, center)


def test_instances_are_counted():
    src = bpy.data.collections.new("src")
    ico = bpy.data.objects.new("ico", cube("tmp").data)
    bpy.data.objects.remove(bpy.data.objects["tmp"])
    src.objects.link(ico)
    for i in range(3):  # collection instances
        e = link(bpy.data.objects.new(f"inst{i}", None))
        e.instance_type = "COLLECTION"
        e.instance_collection = src
        e.location = (3 * i, 0, 0)
    base = cube("base")
    for i in range(2):  # linked duplicates
        d = link(bpy.data.objects.new(f"dup{i}", base.data))
        d.location = (0, 3 * (i + 1), 0)
    s = run()
    assert s.triangle_count == 12 * (3 + 1 + 2)
    names = [s.object_names[i] for i in s.object_index]
    assert names.count("ico") == 36 and names.count("base") == 12
    # Each collection instance sits at its empty's location.
    ico_pos = s.positions[np.array(names) == "ico"].reshape(3, -1, 3)
    assert np.allclose(ico_pos.mean(axis=1), [[0, 0, 0], [3, 0, 0], [6, 0, 0]], atol=1e-6)


def test_geometry_nodes_instances_and_hidden_objects():
    small = cube("small")
    small.scale = (0.1, 0.1, 0.1)
    small.hide_render = True  # hidden itself, still instanced (as in Blender's renders)
    host = mesh_object("host", [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)])
    ng = bpy.data.node_groups.new("scatter", "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gin, gout = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    grid = ng.nodes.new("GeometryNodeMeshGrid")
    grid.inputs["Vertices X"].default_value = 3
    grid.inputs["Vertices Y"].default_value = 2
    info = ng.nodes.new("GeometryNodeObjectInfo")
    info.inputs["Object"].default_value = small
    iop = ng.nodes.new("GeometryNodeInstanceOnPoints")
    join = ng.nodes.new("GeometryNodeJoinGeometry")
    ng.links.new(grid.outputs["Mesh"], iop.inputs["Points"])
    ng.links.new(info.outputs["Geometry"], iop.inputs["Instance"])
    ng.links.new(gin.outputs[0], join.inputs[0])
    ng.links.new(iop.outputs[0], join.inputs[0])
    ng.links.new(join.outputs[0], gout.inputs[0])
    host.modifiers.new("gn", "NODES").node_group = ng
    s = run()
    assert s.triangle_count == 1 + 6 * 12
    s_all = run(render_visibility=False)
    assert s_all.triangle_count == 1 + 7 * 12


@pytest.mark.parametrize("shading", ["flat", "smooth", "sharp_edges"])
def test_fast_triangulation_and_normals_match_blender(shading):
    bpy.ops.mesh.primitive_monkey_add()  # triangles, quads (some split on 1-3)
    ob = bpy.context.object
    if shading != "flat":
        ob.data.shade_smooth()
    if shading == "sharp_edges":
        ob.data.set_sharp_from_angle(angle=0.6)
    me = ob.evaluated_get(dg()).to_mesh()
    try:
        assert me.normals_domain == {"flat": "FACE", "smooth": "POINT"}.get(shading, "CORNER")
        pos, nrm, _ = extract.mesh_arrays(me)
        t = len(me.loop_triangles)
        loops = np.empty(3 * t, np.int32)
        me.loop_triangles.foreach_get("loops", loops)
        verts = np.empty(3 * t, np.int32)
        me.loop_triangles.foreach_get("vertices", verts)
        co = np.array([v.co[:] for v in me.vertices], np.float32)
        assert np.array_equal(pos, co[verts].reshape(t, 3, 3))
        cn = np.array([c.vector[:] for c in me.corner_normals], np.float32)
        assert np.allclose(nrm, cn[loops].reshape(t, 3, 3), atol=1e-6)
    finally:
        ob.to_mesh_clear()


def test_ngons_and_smooth_normals():
    # A concave hexagon n-gon (slow path) and a smooth-shaded cube (vertex normals).
    hexagon = [(0, 0, 0), (2, 0, 0), (2, 2, 0), (1, 0.5, 0), (0, 2, 0), (-0.5, 1, 0)]
    mesh_object("ngon", hexagon, [range(6)])
    s = run()
    assert s.triangle_count == 4
    area = 0.5 * np.linalg.norm(
        np.cross(s.positions[:, 1] - s.positions[:, 0], s.positions[:, 2] - s.positions[:, 0]),
        axis=1,
    ).sum()
    assert area == pytest.approx(3.0)  # shoelace area of the concave hexagon
    bpy.data.objects.remove(bpy.data.objects["ngon"])
    cube("smooth", smooth=True)
    s = run()
    corner = s.positions.reshape(-1, 3)
    assert np.allclose(s.normals.reshape(-1, 3), corner / np.linalg.norm(corner, axis=1)[:, None])


def test_nan_vertices_and_degenerate_objects_dropped_and_counted():
    ob = mesh_object("grid", [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (2, 0, 0)],
                     [(0, 1, 2), (0, 2, 3), (1, 4, 2)])
    ob.data.vertices[4].co = (float("nan"), 0, 0)
    cube("flattened").scale = (1, 0, 1)
    cube("lost").location = (float("nan"), 0, 0)
    s = run()
    assert s.triangle_count == 2 and {s.object_names[i] for i in s.object_index} == {"grid"}
    assert s.dropped["nonfinite_vertices"] == 1 + 12
    assert s.dropped["objects_degenerate_transform"] == 1


def test_curve_text_and_empty_mesh():
    txt = bpy.data.curves.new("t", "FONT")
    txt.body = "L"
    link(bpy.data.objects.new("text", txt))
    link(bpy.data.objects.new("empty_mesh", bpy.data.meshes.new("nothing")))
    s = run()
    assert s.triangle_count > 0 and s.object_names == ["text"]
    assert s.dropped["objects_without_geometry"] == 1


def test_empty_scene_and_no_lights():
    s = run()
    assert s.triangle_count == 0 and s.lights == [] and s.camera is None
    cube()
    s = run()
    assert s.triangle_count == 12 and s.lights == []


def test_missing_camera_is_a_clear_error():
    bpy.context.scene.name = "Shot 010"
    with pytest.raises(ValueError, match="scene 'Shot 010' has no active camera"):
        extract.extract_scene(dg())


# ---------------------------------------------------------------------------- materials


# A default Principled's diffuse under its dielectric layer (roughness 0.5, IOR 1.5): Cycles'
# Diffuse Color of a white one, measured (tests/test_materials.py checks the rule on Cycles).
PRINCIPLED = 0.96261


def test_material_albedo_sources_and_per_triangle_assignment():
    principled, p = material("principled")
    p.inputs["Base Color"].default_value = (0.2, 0.4, 0.6, 1)
    diffuse, d = material("diffuse", "ShaderNodeBsdfDiffuse")
    d.inputs["Color"].default_value = (0.9, 0.1, 0.3, 1)
    ob = cube()
    ob.data.materials.append(principled)
    ob.data.materials.append(diffuse)
    ob.data.materials.append(None)  # empty slot: Cycles' default surface
    ob.data.polygons[1].material_index = 1
    ob.data.polygons[2].material_index = 2
    ob.data.polygons[3].material_index = 7  # out of range: Blender clamps to the last slot
    cube("bare").location = (5, 0, 0)  # no material at all
    # A linked duplicate whose object-linked slot overrides the shared mesh's material.
    override, _ = material("override", "ShaderNodeBsdfDiffuse")
    twin = link(bpy.data.objects.new("twin", ob.data))
    twin.location = (-5, 0, 0)
    twin.material_slots[0].link = "OBJECT"
    twin.material_slots[0].material = override
    s = run()
    twin_albedo = s.albedo_per_triangle()[s.object_index == s.object_names.index("twin")]
    assert np.allclose(twin_albedo.reshape(6, 2, 3)[[0, 4, 5], 0], 0.8)  # Diffuse default
    assert np.allclose(twin_albedo.reshape(6, 2, 3)[1, 0], [0.9, 0.1, 0.3])
    albedo = s.albedo_per_triangle()
    on_cube = s.object_index == s.object_names.index("cube")
    per_face = albedo[on_cube].reshape(6, 2, 3)[:, 0]
    grey = [0.8 * PRINCIPLED] * 3  # Cycles' default surface: a default Principled of 0.8
    base = np.array([0.2, 0.4, 0.6]) * PRINCIPLED
    assert np.allclose(per_face, [base, [0.9, 0.1, 0.3], grey, grey, base, base], atol=1e-6)
    assert np.allclose(albedo[s.object_index == s.object_names.index("bare")], grey)


def test_textured_base_color_is_the_image_mean():
    img = bpy.data.images.new("checker", 4, 2, float_buffer=True)
    px = np.zeros((2, 4, 4), np.float32)
    px[..., 3] = 1
    px[0, :, 0] = 1.0  # first row red, second row blue (linear float image)
    px[1, :, 2] = 0.5
    img.pixels.foreach_set(px.ravel())
    mat, p = material("textured")
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = img
    mat.node_tree.links.new(tex.outputs["Color"], p.inputs["Base Color"])
    assert np.allclose(extract.material_albedo(mat), np.array([0.5, 0.0, 0.25]) * PRINCIPLED,
                       atol=1e-6)
    # Byte images hold sRGB-encoded values: the mean is taken after linearising.
    byte = bpy.data.images.new("grey", 2, 2)
    byte.pixels.foreach_set(np.tile(np.float32([0.5, 0.5, 0.5, 1.0]), 4))  # opaque
    tex.image = byte
    stored = np.array(byte.pixels[:3])
    linear = np.where(stored <= 0.04045, stored / 12.92, ((stored + 0.055) / 1.055) ** 2.4)
    assert np.allclose(extract.material_albedo(mat), linear * PRINCIPLED, atol=1e-5)
    # A linked non-image node: the socket's own default value.
    p.inputs["Base Color"].default_value = (0.3, 0.3, 0.1, 1)
    noise = mat.node_tree.nodes.new("ShaderNodeTexNoise")
    mat.node_tree.links.new(noise.outputs["Color"], p.inputs["Base Color"])
    assert np.allclose(extract.material_albedo(mat), np.array([0.3, 0.3, 0.1]) * PRINCIPLED,
                       atol=1e-6)


def test_mix_shader_and_fallbacks():
    mat, p = material("mix", "ShaderNodeMixShader")
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    a, b = nodes.new("ShaderNodeBsdfDiffuse"), nodes.new("ShaderNodeBsdfPrincipled")
    a.inputs["Color"].default_value = (1, 0, 0, 1)
    b.inputs["Base Color"].default_value = (0, 0, 1, 1)
    links.new(a.outputs[0], p.inputs[1])
    links.new(b.outputs[0], p.inputs[2])
    p.inputs["Fac"].default_value = 0.25
    assert np.allclose(extract.material_albedo(mat), [0.75, 0, 0.25 * PRINCIPLED], atol=1e-6)
    emit, _ = material("emit", "ShaderNodeEmission")
    emit.diffuse_color = (0.1, 0.2, 0.3, 1)  # not the viewport colour: no diffuse, as Cycles
    assert np.allclose(extract.material_albedo(emit), 0.0, atol=1e-6)
    assert np.allclose(extract.material_albedo(None), [0.8 * PRINCIPLED] * 3, atol=1e-5)


# ------------------------------------------------------------------------------- lights


def light(kind, name=None, **props):
    data = bpy.data.lights.new(name or kind.lower(), kind)
    for key, value in props.items():
        setattr(data, key, value)
    return link(bpy.data.objects.new(name or kind.lower(), data))


def lights_by_name(scene):
    return {lt.name: lt for lt in scene.lights}


def test_light_units():
    light("POINT", "point", energy=100.0, exposure=1.0, shadow_soft_size=0.3)
    light("SUN", "sun", energy=3.0)
    sq = light("AREA", "square", energy=10.0, size=2.0, normalize=False)
    sq.scale = (2, 1, 1)
    light("AREA", "rect", energy=10.0, shape="RECTANGLE", size=2.0, size_y=3.0)
    light("AREA", "disk", energy=10.0, shape="DISK", size=2.0, normalize=False)
    light("AREA", "ellipse", energy=10.0, shape="ELLIPSE", size=2.0, size_y=4.0, normalize=False)
    warm = light("SPOT", "spot", energy=50.0, color=(1, 0.5, 1), spot_size=0.8,
                 spot_blend=0.3, use_temperature=True, temperature=3000)
    hidden = light("POINT", "hidden")
    hidden.hide_render = True
    ls = lights_by_name(run())
    assert set(ls) == {"point", "sun", "square", "rect", "disk", "ellipse", "spot"}
    assert ls["point"].power == pytest.approx(200.0)
    assert ls["point"].radius == pytest.approx(0.3)
    assert ls["sun"].power == pytest.approx(3.0) and ls["sun"].type == "SUN"
    assert ls["square"].power == pytest.approx(10.0 * (2 * 2) * (2 * 1))  # world size 4 x 2
    assert ls["square"].size == (2.0, 2.0)
    assert ls["rect"].power == pytest.approx(10.0) and ls["rect"].size == (2.0, 3.0)
    assert ls["disk"].power == pytest.approx(10.0 * math.pi)  # diameter 2: area pi
    assert ls["ellipse"].power == pytest.approx(10.0 * math.pi / 4 * 2 * 4)
    spot = ls["spot"]
    tint = np.array(warm.data.temperature_color[:3])
    assert np.allclose(spot.color, np.array([1, 0.5, 1]) * tint, atol=1e-6)
    assert not np.allclose(tint, 1.0)
    assert spot.spot_size == pytest.approx(0.8) and spot.spot_blend == pytest.approx(0.3)
    assert spot.gi_intensity == 1.0
    assert np.allclose(spot.matrix, np.array(warm.matrix_world))


def test_nonfinite_light_is_left_out_counted_and_named(capfd):
    light("POINT", "broken", energy=float("nan"))
    light("POINT", "tinted", energy=10.0, color=(float("nan"), 1.0, 1.0))
    light("POINT", "fine", energy=10.0)
    scene = run()
    ls = lights_by_name(scene)
    assert set(ls) == {"tinted", "fine"}  # the NaN power is dropped, the NaN colour defaulted
    assert np.isfinite(ls["tinted"].color).all()
    assert scene.dropped["lights_with_nonfinite_transform_or_power"] == 1
    err = capfd.readouterr().err
    assert "light 'broken'" in err and "light 'tinted'" in err and "'fine'" not in err


# ------------------------------------------------------------------------------- camera


def test_camera_projection_matches_blender():
    sc = bpy.context.scene
    sc.render.resolution_x, sc.render.resolution_y = 640, 360
    sc.render.resolution_percentage = 50
    cam = link(bpy.data.objects.new("cam", bpy.data.cameras.new("cam")))
    cam.data.lens = 35
    cam.data.shift_x = 0.1
    cam.location = (7, -6, 4)
    cam.rotation_euler = (1.1, 0.0, 0.85)
    cam.scale = (2, 2, 2)  # scale must not leak into the view matrix
    sc.camera = cam
    s = extract.extract_scene(dg())
    c = s.camera
    assert c.resolution == (320, 180)
    assert np.allclose(c.position, (7, -6, 4), atol=1e-5)
    assert np.allclose(np.linalg.det(c.view[:3, :3]), 1.0, atol=1e-6)
    for point in [(0, 0, 0), (1, 2, 0.5), (-1, 0.5, 1)]:
        clip = c.projection @ c.view @ np.array([*point, 1.0])
        ndc = clip[:2] / clip[3]
        expected = world_to_camera_view(sc, cam, Vector(point))
        assert np.allclose((ndc + 1) / 2, expected[:2], atol=1e-5)
    assert extract.extract_scene(dg(), resolution=(64, 48)).camera.resolution == (64, 48)
    with pytest.raises(ValueError, match="resolution"):
        extract.extract_scene(dg(), resolution=(0, 10))


# ----------------------------------------------------------------------------- settings


@pytest.fixture
def lpv_props():
    from lpv_addon import properties

    registered = not hasattr(bpy.types.Scene, "lpv")
    if registered:
        properties.register()
    yield
    if registered:
        properties.unregister()


def test_settings_from_scene_and_overrides(lpv_props):
    props = bpy.context.scene.lpv
    props.grid_resolution = 48
    props.occlusion = True
    props.intensity = 2.5
    s = run(settings_overrides={"cascades": 3, "iterations": "12"})
    assert s.settings.grid_resolution == 48 and s.settings.occlusion is True
    assert s.settings.intensity == pytest.approx(2.5)
    assert s.settings.cascades == 3 and s.settings.iterations == 12
    with pytest.raises(ValueError, match="unknown GI setting 'nope'"):
        run(settings_overrides={"nope": 1})


def test_world_light_and_emissive_materials_are_reported_as_not_modelled():
    """A lighting world reaches Scene.world (a black one is nothing to do); emissive
    materials are counted in Scene.dropped (stats.json) rather than silently missing."""
    ob = cube()
    bpy.context.scene.world = None
    assert run().world is None
    world = bpy.data.worlds.new("W")
    if world.node_tree is None:  # Blender < 5: node trees are opt-in
        world.use_nodes = True
    bpy.context.scene.world = world
    bg = next(n for n in world.node_tree.nodes if n.bl_idname == "ShaderNodeBackground")
    bg.inputs["Strength"].default_value = 0.0
    assert run().world is None
    bg.inputs["Strength"].default_value = 1.0
    bg.inputs["Color"].default_value = (0.2, 0.3, 0.4, 1.0)
    assert run().world.radiance.reshape(-1, 3)[0] == pytest.approx((0.2, 0.3, 0.4))
    glow, p = material("Glow")
    ob.data.materials.append(glow)
    emission = {m.name: m.emission for m in run().materials}
    assert emission["Glow"] == pytest.approx((0.0, 0.0, 0.0))
    p.inputs["Emission Strength"].default_value = 5.0
    p.inputs["Emission Color"].default_value = (1.0, 0.5, 0.2, 1.0)
    emission = {m.name: m.emission for m in run().materials}
    assert emission["Glow"] == pytest.approx((5.0, 2.5, 1.0))


@pytest.mark.parametrize("kind", ["FONT", "CURVE"])
def test_a_text_or_curve_is_extracted_once(kind):
    """A text (extruded) or a bevelled curve: the depsgraph yields the object and its
    geometry set's mesh as an instance of it; Cycles renders one surface, and the extraction
    takes one: the triangles' area is the evaluated mesh's (twice it while both were taken:
    a glowing text lit the floor 6.7x as Cycles does)."""
    if kind == "FONT":
        data = bpy.data.curves.new("t", "FONT")
        data.body, data.extrude = "LPV", 0.1
    else:
        data = bpy.data.curves.new("c", "CURVE")
        data.dimensions, data.bevel_depth = "3D", 0.1
        spline = data.splines.new("POLY")
        spline.points.add(2)
        for p, co in zip(spline.points, [(0, 0, 0, 1), (1, 0, 0, 1), (1, 1, 0.5, 1)]):
            p.co = co
    ob = link(bpy.data.objects.new("shape", data))
    depsgraph = dg()
    evaluated = ob.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    area = sum(p.area for p in mesh.polygons)
    evaluated.to_mesh_clear()
    scene = run()
    p = scene.positions
    got = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
    # (a twisted quad's two triangles are not its polygon area: 0.2 % on the curve)
    assert area > 0.1 and got == pytest.approx(area, rel=5e-3)
