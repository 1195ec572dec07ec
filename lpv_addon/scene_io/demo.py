"""The built-in demo: a Cornell box with a spot light and a camera, built with bpy data calls
(no operators in loops), for ``python -m lpv_addon.batch --demo`` (tools/scenes.py builds the
team's other test scenes on these helpers).

By default it starts a fresh file with ``bpy.ops.wm.read_homefile(use_empty=True)`` (add-ons
stay registered) and builds into its one scene, which is then the context scene; with
``new_file=False`` it adds a new scene to the current file instead (made the window's scene
when there is a window; headless, pass it to the renderer explicitly).

Conventions: metres, Z up; purely diffuse Lambertian materials (Diffuse BSDF with roughness 0
by default, or Principled BSDF with Specular IOR Level 0 / roughness 1: Cycles puts all the
light of either into the Diffuse passes, measured Combined == (DiffDir + DiffInd) x DiffCol);
a black world (light comes from the lamps only); lights with shadow_soft_size 0 and sun
angle 0 (hard shadows), invisible to camera rays; a camera with sensor_fit HORIZONTAL; render
engine Cycles at the given resolution, 100 %. Wall quads face into rooms, boxes face out.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import bpy
from mathutils import Vector

Color = tuple[float, float, float]
WHITE: Color = (0.73, 0.73, 0.73)
RED: Color = (0.63, 0.065, 0.05)
GREEN: Color = (0.14, 0.45, 0.091)

# Face winding of an axis-aligned box with corners 0..7 (bit 0: x, bit 1: y, bit 2: z) laid
# out as below; every quad is counter-clockwise seen from outside (normal points out).
# 0 (x0,y0,z0) 1 (x1,y0,z0) 2 (x1,y1,z0) 3 (x0,y1,z0), 4..7 the same at z1.
_BOX_FACES = {
    "-z": (0, 3, 2, 1),
    "+z": (4, 5, 6, 7),
    "-y": (0, 1, 5, 4),
    "+y": (2, 3, 7, 6),
    "-x": (3, 0, 4, 7),
    "+x": (1, 2, 6, 5),
}


def _box_verts(lo: Sequence[float], hi: Sequence[float]) -> list[tuple[float, float, float]]:
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    return [
        (x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0),
        (x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1),
    ]


def box_geometry(
    lo: Sequence[float], hi: Sequence[float], faces: Sequence[str] = tuple(_BOX_FACES),
    inward: bool = False,
) -> tuple[list, list]:
    """Vertices and quads of a box (a subset of its faces), normals out or in."""
    quads = [_BOX_FACES[f][::-1] if inward else _BOX_FACES[f] for f in faces]
    return _box_verts(lo, hi), quads


def diffuse_material(name: str, color: Color, shader: str) -> bpy.types.Material:
    """A purely diffuse material: Diffuse BSDF (roughness 0: Lambert) or zero-specular
    Principled BSDF."""
    mat = bpy.data.materials.new(name)
    mat.diffuse_color = (*color, 1.0)  # solid-mode viewport colour
    tree = mat.node_tree
    if tree is None:  # pragma: no cover - Blender < 5 needs nodes switched on
        mat.use_nodes = True
        tree = mat.node_tree
    tree.nodes.clear()
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    out.location = (300, 0)
    if shader == "DIFFUSE":
        bsdf = tree.nodes.new("ShaderNodeBsdfDiffuse")
        bsdf.inputs["Color"].default_value = (*color, 1.0)
        bsdf.inputs["Roughness"].default_value = 0.0
    elif shader == "PRINCIPLED":
        bsdf = tree.nodes.new("ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = (*color, 1.0)
        bsdf.inputs["Roughness"].default_value = 1.0
        bsdf.inputs["Metallic"].default_value = 0.0
        bsdf.inputs["Specular IOR Level"].default_value = 0.0
    else:
        raise ValueError(f"shader must be 'DIFFUSE' or 'PRINCIPLED', not {shader!r}")
    tree.links.new(bsdf.outputs[0], out.inputs["Surface"])
    return mat


def add_mesh_object(
    scene: bpy.types.Scene, name: str, geometry: tuple[list, list],
    material: bpy.types.Material, location: Sequence[float] = (0, 0, 0),
    rotation_z_deg: float = 0.0,
) -> bpy.types.Object:
    verts, faces = geometry
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts, [], faces)
    mesh.validate()
    mesh.update()
    mesh.materials.append(material)
    ob = bpy.data.objects.new(name, mesh)
    ob.location = location
    ob.rotation_euler = (0.0, 0.0, math.radians(rotation_z_deg))
    scene.collection.objects.link(ob)
    return ob


def _look_at(ob: bpy.types.Object, target: Sequence[float]) -> None:
    direction = Vector(target) - Vector(ob.location)
    ob.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()


def add_camera(
    scene: bpy.types.Scene, location: Sequence[float], target: Sequence[float],
    lens_mm: float, name: str = "Camera",
) -> bpy.types.Object:
    cam = bpy.data.cameras.new(name)
    cam.type = "PERSP"
    cam.sensor_fit = "HORIZONTAL"
    cam.sensor_width = 36.0
    cam.sensor_height = 24.0
    cam.lens = lens_mm
    cam.clip_start = 0.05
    cam.clip_end = 200.0
    ob = bpy.data.objects.new(name, cam)
    ob.location = location
    _look_at(ob, target)
    scene.collection.objects.link(ob)
    scene.camera = ob
    return ob


def add_light(
    scene: bpy.types.Scene, name: str, kind: str, energy: float,
    location: Sequence[float], rotation_deg: Sequence[float] = (0, 0, 0), **settings,
) -> bpy.types.Object:
    light = bpy.data.lights.new(name, kind)
    light.energy = energy
    light.color = (1.0, 1.0, 1.0)
    light.use_shadow = True
    if kind == "SUN":
        light.angle = 0.0
    else:
        light.shadow_soft_size = 0.0
    for key, value in settings.items():
        setattr(light, key, value)
    ob = bpy.data.objects.new(name, light)
    ob.location = location
    ob.rotation_euler = tuple(math.radians(a) for a in rotation_deg)
    ob.visible_camera = False  # no emitter in Combined: it holds diffuse light only
    scene.collection.objects.link(ob)
    return ob


def _black_world() -> bpy.types.World:
    world = bpy.data.worlds.new("LPV Black")
    world.color = (0.0, 0.0, 0.0)
    tree = world.node_tree
    if tree is None:  # pragma: no cover - Blender < 5
        world.use_nodes = True
        tree = world.node_tree
    bg = tree.nodes.get("Background")
    if bg is not None:
        bg.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        bg.inputs["Strength"].default_value = 0.0
    return world


def new_scene(name: str, resolution: Sequence[int], new_file: bool) -> bpy.types.Scene:
    if new_file:
        bpy.ops.wm.read_homefile(use_empty=True)
        scene = bpy.context.scene
        scene.name = name
    else:
        scene = bpy.data.scenes.new(name)
        window = getattr(bpy.context, "window", None)
        if window is not None:
            window.scene = scene
    scene.unit_settings.system = "METRIC"
    scene.unit_settings.scale_length = 1.0
    scene.world = _black_world()
    r = scene.render
    r.engine = "CYCLES"
    scene.cycles.device = "CPU"
    r.resolution_x, r.resolution_y = (int(v) for v in resolution)
    r.resolution_percentage = 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    scene.frame_set(1)
    return scene


def scene_facts(scene: bpy.types.Scene, lights: Sequence[bpy.types.Object]) -> dict:
    return {
        "scene": scene.name,
        "camera": scene.camera.name,
        "lights": [ob.name for ob in lights],
        "objects": sorted(ob.name for ob in scene.objects if ob.type == "MESH"),
        "resolution": (scene.render.resolution_x, scene.render.resolution_y),
    }


def cornell_box(
    light: str = "SPOT", resolution: Sequence[int] = (128, 128), *, shader: str = "DIFFUSE",
    new_file: bool = True,
) -> dict:
    """Cornell box 2 m wide/deep/high (x, y in [-1, 1], z in [0, 2]), open at the front (-y):
    red left wall, green right wall, white floor/ceiling/back, a short and a tall white block;
    camera at (0, -3.9, 1) looking in (+y).

    light: SPOT (300 W at z 1.95 pointing down, 100 deg cone, blend 0.15), POINT (150 W at
    z 1.6), AREA (0.5 m square, 100 W, z 1.98, facing down) or SUN (4 W/m^2 tilted 20 deg
    towards the camera through a 1 m hole in the ceiling). Returns the scene's facts.
    """
    light = light.upper()
    if light not in ("SPOT", "POINT", "SUN", "AREA"):
        raise ValueError(f"light must be SPOT, POINT, SUN or AREA, not {light!r}")
    scene = new_scene(f"cornell_{light.lower()}", resolution, new_file)
    white = diffuse_material("White", WHITE, shader)
    red = diffuse_material("Red", RED, shader)
    green = diffuse_material("Green", GREEN, shader)
    lo, hi = (-1.0, -1.0, 0.0), (1.0, 1.0, 2.0)
    add_mesh_object(scene, "Floor", box_geometry(lo, hi, ["-z"], inward=True), white)
    add_mesh_object(scene, "BackWall", box_geometry(lo, hi, ["+y"], inward=True), white)
    add_mesh_object(scene, "LeftWall", box_geometry(lo, hi, ["-x"], inward=True), red)
    add_mesh_object(scene, "RightWall", box_geometry(lo, hi, ["+x"], inward=True), green)
    if light == "SUN":
        # Ceiling with a 1 m hole (x in [-0.5, 0.5], y in [-0.2, 0.8]): four quads facing down.
        hx0, hx1, hy0, hy1 = -0.5, 0.5, -0.2, 0.8
        z = 2.0
        rects = [(-1, -1, 1, hy0), (-1, hy1, 1, 1), (-1, hy0, hx0, hy1), (hx1, hy0, 1, hy1)]
        verts, faces = [], []
        for x0, y0, x1, y1 in rects:
            b = len(verts)
            verts += [(x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)]
            faces.append((b, b + 3, b + 2, b + 1))  # normal -z (into the box)
        add_mesh_object(scene, "Ceiling", (verts, faces), white)
    else:
        add_mesh_object(scene, "Ceiling", box_geometry(lo, hi, ["+z"], inward=True), white)
    add_mesh_object(
        scene, "ShortBlock", box_geometry((-0.3, -0.3, 0.0), (0.3, 0.3, 0.6)), white,
        location=(0.33, -0.3, 0.0), rotation_z_deg=-17.0,
    )
    add_mesh_object(
        scene, "TallBlock", box_geometry((-0.3, -0.3, 0.0), (0.3, 0.3, 1.2)), white,
        location=(-0.35, 0.3, 0.0), rotation_z_deg=17.0,
    )
    if light == "SPOT":
        lamp = add_light(scene, "Spot", "SPOT", 300.0, (0.0, 0.0, 1.95),
                      spot_size=math.radians(100.0), spot_blend=0.15)
    elif light == "POINT":
        lamp = add_light(scene, "Point", "POINT", 150.0, (0.0, 0.0, 1.6))
    elif light == "AREA":
        lamp = add_light(scene, "Area", "AREA", 100.0, (0.0, 0.0, 1.98), shape="SQUARE", size=0.5)
    else:
        lamp = add_light(scene, "Sun", "SUN", 4.0, (0.0, 0.3, 4.0), rotation_deg=(-20.0, 0.0, 12.0))
    add_camera(scene, (0.0, -3.9, 1.0), (0.0, 0.0, 1.0), lens_mm=50.0)
    return scene_facts(scene, [lamp])
