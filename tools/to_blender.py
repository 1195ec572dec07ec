"""Builds a Blender scene from a core Scene, so core test scenes get real Cycles references."""

from __future__ import annotations

import bpy
import numpy as np
from mathutils import Matrix


def _material(m) -> bpy.types.Material:
    mat = bpy.data.materials.new(m.name)
    mat.use_nodes = True
    nodes = mat.node_tree.nodes
    nodes.clear()
    out = nodes.new("ShaderNodeOutputMaterial")
    bsdf = nodes.new("ShaderNodeBsdfDiffuse")
    bsdf.inputs["Color"].default_value = (*[float(c) for c in m.albedo], 1.0)
    bsdf.inputs["Roughness"].default_value = 0.0
    mat.node_tree.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    mat.diffuse_color = (*[float(c) for c in m.albedo], 1.0)
    return mat


def build(scene_core, name: str = "LPV Scene") -> bpy.types.Scene:
    """Create objects, materials, lights and camera for ``scene_core`` in the current file.

    Returns the bpy scene (made current), with a black world so only the lights illuminate.
    """
    scn = bpy.context.scene
    scn.name = name
    world = bpy.data.worlds.new("Black")
    world.use_nodes = True
    bg = world.node_tree.nodes.get("Background")
    if bg is not None:
        bg.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        bg.inputs["Strength"].default_value = 0.0
    scn.world = world
    t = scene_core.triangle_count
    if t:
        mesh = bpy.data.meshes.new("Geometry")
        verts = scene_core.positions.reshape(-1, 3).astype(np.float64)
        mesh.vertices.add(3 * t)
        mesh.vertices.foreach_set("co", verts.ravel())
        mesh.loops.add(3 * t)
        mesh.loops.foreach_set("vertex_index", np.arange(3 * t, dtype=np.int32))
        mesh.polygons.add(t)
        mesh.polygons.foreach_set("loop_start", np.arange(0, 3 * t, 3, dtype=np.int32))
        mesh.polygons.foreach_set("material_index", scene_core.material_index.astype(np.int32))
        mesh.update(calc_edges=True)
        mesh.validate()
        for m in scene_core.materials:
            mesh.materials.append(_material(m))
        ob = bpy.data.objects.new("Geometry", mesh)
        scn.collection.objects.link(ob)
    for light in scene_core.lights:
        data = bpy.data.lights.new(light.name, light.type)
        data.color = tuple(float(c) for c in light.color)
        data.energy = float(light.power)
        if hasattr(data, "shadow_soft_size"):
            data.shadow_soft_size = float(light.radius)
        if light.type == "SPOT":
            data.spot_size = float(light.spot_size)
            data.spot_blend = float(light.spot_blend)
        if light.type == "AREA":
            data.shape = "RECTANGLE"
            data.size, data.size_y = (float(v) for v in light.size)
        if light.type == "SUN":
            data.angle = 0.0
        ob = bpy.data.objects.new(light.name, data)
        ob.matrix_world = Matrix(np.asarray(light.matrix, np.float64).tolist())
        scn.collection.objects.link(ob)
    cam = scene_core.camera
    if cam is not None:
        cdata = bpy.data.cameras.new("Camera")
        p = np.asarray(cam.projection, np.float64)
        w, h = cam.resolution
        cdata.sensor_fit = "VERTICAL"
        cdata.sensor_height = 24.0
        cdata.lens = 0.5 * 24.0 * p[1, 1]
        near = p[2, 3] / (p[2, 2] - 1.0)
        far = p[2, 3] / (p[2, 2] + 1.0)
        cdata.clip_start, cdata.clip_end = float(near), float(far)
        ob = bpy.data.objects.new("Camera", cdata)
        ob.matrix_world = Matrix(np.linalg.inv(np.asarray(cam.view, np.float64)).tolist())
        scn.collection.objects.link(ob)
        scn.camera = ob
        scn.render.resolution_x, scn.render.resolution_y = int(w), int(h)
        scn.render.resolution_percentage = 100
        scn.render.pixel_aspect_x = scn.render.pixel_aspect_y = 1.0
    return scn


__all__ = ["build"]
