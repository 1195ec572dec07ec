"""The team's test scenes, built with bpy data calls (no operators in loops), on the helpers
of the shipped demo (lpv_addon/scene_io/demo.py), with its conventions: a fresh file per build
unless ``new_file=False``, metres and Z up, purely diffuse materials, a black world, hard
lights invisible to the camera, wall quads facing into rooms (that module's docstring says
why each holds).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path

import bpy

from lpv_addon.scene_io.demo import (
    GREEN,
    RED,
    WHITE,
    add_camera,
    add_light,
    add_mesh_object,
    box_geometry,
    cornell_box,
    diffuse_material,
    new_scene,
    scene_facts,
)

__all__ = [
    "BUILDERS",
    "GREEN",
    "RED",
    "SCENES",
    "WHITE",
    "build",
    "checker_room",
    "city",
    "cornell_box",
    "emission_material",
    "library",
    "panel_room",
    "point_room",
    "save_scene",
    "sky_room",
    "sky_yard",
    "soft_room",
    "sun_yard",
    "sunlit_room",
    "window_room",
]


def _merge(*parts: tuple[list, list]) -> tuple[list, list]:
    verts: list = []
    faces: list = []
    for v, f in parts:
        base = len(verts)
        verts.extend(v)
        faces.extend(tuple(i + base for i in q) for q in f)
    return verts, faces


def _table() -> tuple[list, list]:
    """A 1.2 x 0.8 m table 0.77 m high: a 5 cm top on four 6 cm legs."""
    legs = [box_geometry((x - 0.03, y - 0.03, 0.0), (x + 0.03, y + 0.03, 0.72))
            for x in (-0.55, 0.55) for y in (-0.35, 0.35)]
    return _merge(box_geometry((-0.6, -0.4, 0.72), (0.6, 0.4, 0.77)), *legs)


def _ground_plane(half: float) -> tuple[list, list]:
    """One quad from -half to half in x and y at z = 0, facing up."""
    return ([(-half, -half, 0.0), (half, -half, 0.0), (half, half, 0.0), (-half, half, 0.0)],
            [(0, 1, 2, 3)])


def point_room(resolution: Sequence[int] = (128, 128), *, shader: str = "DIFFUSE",
               new_file: bool = True) -> dict:
    """A closed 4 x 5 x 3 m room (x in [-2, 2], y in [-2.5, 2.5]) with a blue accent wall,
    a table, sofa, bookshelf and cabinet, lit by one 400 W point light near the ceiling;
    camera inside a corner. Returns the scene's facts."""
    scene = new_scene("point_room", resolution, new_file)
    wall = diffuse_material("Wall", (0.75, 0.73, 0.70), shader)
    accent = diffuse_material("Accent", (0.20, 0.35, 0.60), shader)
    ceiling = diffuse_material("Ceiling", (0.80, 0.80, 0.80), shader)
    floor = diffuse_material("Floor", (0.45, 0.30, 0.20), shader)
    wood = diffuse_material("Wood", (0.55, 0.40, 0.25), shader)
    fabric = diffuse_material("Fabric", (0.60, 0.15, 0.12), shader)
    shelf_mat = diffuse_material("Shelf", (0.25, 0.50, 0.25), shader)
    lo, hi = (-2.0, -2.5, 0.0), (2.0, 2.5, 3.0)
    add_mesh_object(scene, "Floor", box_geometry(lo, hi, ["-z"], inward=True), floor)
    add_mesh_object(scene, "Ceiling", box_geometry(lo, hi, ["+z"], inward=True), ceiling)
    add_mesh_object(scene, "Walls", box_geometry(lo, hi, ["-x", "-y", "+x"], inward=True), wall)
    add_mesh_object(scene, "AccentWall", box_geometry(lo, hi, ["+y"], inward=True), accent)
    table = _table()
    add_mesh_object(scene, "Table", table, wood, location=(0.3, 0.4, 0.0), rotation_z_deg=10.0)
    sofa = _merge(box_geometry((-1.0, -0.45, 0.0), (1.0, 0.45, 0.45)),
                  box_geometry((-1.0, 0.25, 0.45), (1.0, 0.45, 0.95)))
    add_mesh_object(scene, "Sofa", sofa, fabric, location=(-0.2, 1.9, 0.0))
    add_mesh_object(scene, "Bookshelf", box_geometry((-0.45, -0.175, 0.0), (0.45, 0.175, 2.0)), shelf_mat,
                 location=(-1.8, -0.5, 0.0), rotation_z_deg=90.0)
    add_mesh_object(scene, "Cabinet", box_geometry((-0.4, -0.25, 0.0), (0.4, 0.25, 0.9)), wood,
                 location=(1.7, 1.2, 0.0), rotation_z_deg=-90.0)
    add_mesh_object(scene, "Box", box_geometry((-0.2, -0.2, 0.0), (0.2, 0.2, 0.4)), wall,
                 location=(1.0, -0.9, 0.0), rotation_z_deg=30.0)
    lamp = add_light(scene, "Point", "POINT", 400.0, (0.0, 0.3, 2.4))
    add_camera(scene, (1.7, -2.25, 1.6), (-0.6, 1.0, 0.7), lens_mm=20.0)
    return scene_facts(scene, [lamp])


def sun_yard(resolution: Sequence[int] = (128, 128), *, shader: str = "DIFFUSE",
             new_file: bool = True) -> dict:
    """A 40 m ground plane with five coloured boxes, a 4 W/m^2 sun at 40 deg elevation
    (azimuth 30 deg), camera outside looking down at the group. Returns the scene's facts."""
    scene = new_scene("sun_yard", resolution, new_file)
    ground = diffuse_material("Ground", (0.5, 0.5, 0.5), shader)
    red = diffuse_material("Red", (0.7, 0.08, 0.06), shader)
    white = diffuse_material("White", (0.8, 0.8, 0.8), shader)
    green = diffuse_material("Green", (0.12, 0.5, 0.1), shader)
    blue = diffuse_material("Blue", (0.1, 0.2, 0.65), shader)
    yellow = diffuse_material("Yellow", (0.75, 0.65, 0.1), shader)
    plane = _ground_plane(20.0)
    add_mesh_object(scene, "Ground", plane, ground)
    boxes = [
        ("RedBox", (2.0, 2.0, 2.0), (0.0, 0.0), 20.0, red),
        ("WhiteTower", (1.0, 1.0, 3.0), (2.6, 1.6), 0.0, white),
        ("GreenWall", (4.0, 0.3, 1.5), (-1.8, 2.6), -10.0, green),
        ("BlueBox", (1.2, 1.2, 0.8), (-2.4, -0.8), 35.0, blue),
        ("YellowSlab", (1.6, 0.9, 0.4), (1.6, -2.0), -25.0, yellow),
    ]
    for name, (sx, sy, sz), (x, y), rot, mat in boxes:
        add_mesh_object(scene, name, box_geometry((-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2, sz)), mat,
                     location=(x, y, 0.0), rotation_z_deg=rot)
    # Local -Z rotated 50 deg about X travels 40 deg below the horizon, then turned 30 deg.
    lamp = add_light(scene, "Sun", "SUN", 4.0, (0.0, 0.0, 10.0), rotation_deg=(50.0, 0.0, 30.0))
    add_camera(scene, (8.5, -9.0, 5.5), (0.0, 0.3, 0.8), lens_mm=35.0)
    return scene_facts(scene, [lamp])


def _instance(
    scene: bpy.types.Scene, name: str, mesh: bpy.types.Mesh, location: Sequence[float],
    scale: Sequence[float] = (1.0, 1.0, 1.0), rotation_z_deg: float = 0.0,
) -> bpy.types.Object:
    """An object sharing ``mesh`` (a linked duplicate), placed, scaled and turned about Z."""
    ob = bpy.data.objects.new(name, mesh)
    ob.location = location
    ob.scale = scale
    ob.rotation_euler = (0.0, 0.0, math.radians(rotation_z_deg))
    scene.collection.objects.link(ob)
    return ob


def _unit_box_mesh(name: str, material: bpy.types.Material) -> bpy.types.Mesh:
    """A 1 m box mesh from (-0.5, -0.5, 0) to (0.5, 0.5, 1), normals out (scale it per object)."""
    verts, faces = box_geometry((-0.5, -0.5, 0.0), (0.5, 0.5, 1.0))
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts, [], faces)
    mesh.validate()
    mesh.update()
    mesh.materials.append(material)
    return mesh


def city(resolution: Sequence[int] = (128, 128), *, shader: str = "DIFFUSE",
         new_file: bool = True, seed: int = 5) -> dict:
    """An outdoor city block: a 200 m ground (x, y in [-100, 100]) with 8 x 8 blocks of
    buildings 4 to 30 m tall (fixed pseudo-random layout from ``seed``) along 7 m streets,
    a low 5 W/m^2 sun (15 deg elevation, from the north-west), camera 45 m up beyond the
    south-west corner looking across the district. Returns the scene's facts."""
    import random

    rng = random.Random(seed)
    scene = new_scene("city", resolution, new_file)
    ground = diffuse_material("Asphalt", (0.30, 0.30, 0.30), shader)
    facades = [
        diffuse_material("Plaster", (0.75, 0.70, 0.60), shader),
        diffuse_material("Brick", (0.55, 0.30, 0.22), shader),
        diffuse_material("Concrete", (0.55, 0.55, 0.55), shader),
        diffuse_material("BlueGlass", (0.25, 0.35, 0.50), shader),
        diffuse_material("Sandstone", (0.80, 0.68, 0.45), shader),
    ]
    add_mesh_object(scene, "Ground", box_geometry((-100.0, -100.0, -0.5), (100.0, 100.0, 0.0), ["+z"]),
                 ground)
    meshes = [_unit_box_mesh(f"Building_{m.name}", m) for m in facades]
    block, street = 18.0, 7.0
    start = -4 * (block + street) + street / 2  # blocks span [-96.5, 96.5]
    count = 0
    for i in range(8):
        for j in range(8):
            x0, y0 = start + i * (block + street), start + j * (block + street)
            # Split each block into 1 x 1, 1 x 2 or 2 x 2 lots, one building per lot.
            nx, ny = rng.choice([(1, 1), (1, 2), (2, 1), (2, 2)])
            lx, ly = block / nx, block / ny
            for a in range(nx):
                for b in range(ny):
                    w = lx * rng.uniform(0.65, 0.9)
                    d = ly * rng.uniform(0.65, 0.9)
                    h = rng.choice([rng.uniform(4.0, 12.0), rng.uniform(8.0, 20.0),
                                    rng.uniform(15.0, 30.0)])
                    cx = x0 + (a + 0.5) * lx
                    cy = y0 + (b + 0.5) * ly
                    count += 1
                    _instance(scene, f"Building{count:03d}", rng.choice(meshes), (cx, cy, 0.0),
                              (w, d, h))
    # Local -Z rotated 75 deg about X points 15 deg below the horizon, then turned 35 deg.
    lamp = add_light(scene, "Sun", "SUN", 5.0, (0.0, 0.0, 50.0), rotation_deg=(75.0, 0.0, 215.0))
    cam = add_camera(scene, (-118.0, -112.0, 45.0), (-5.0, 5.0, 0.0), lens_mm=30.0)
    cam.data.clip_end = 500.0
    return scene_facts(scene, [lamp])


def sunlit_room(resolution: Sequence[int] = (128, 128), *, shader: str = "DIFFUSE",
                new_file: bool = True) -> dict:
    """A closed 5 x 4 x 2.8 m room (inside x in [-2.5, 2.5], y in [-2, 2], z in [0, 2.8])
    built from solid 0.2 m walls, floor and roof slabs, with a 1.8 x 1.3 m window in the
    +y wall. A 6 W/m^2 sun 35 deg above the horizon shines in through the window onto a red
    rug; the outside of the walls is sunlit too (light that must not leak in). Camera
    inside the -x/-y corner. Returns the scene's facts."""
    scene = new_scene("sunlit_room", resolution, new_file)
    wall = diffuse_material("Wall", (0.78, 0.76, 0.72), shader)
    floor_mat = diffuse_material("Floor", (0.50, 0.36, 0.24), shader)
    rug = diffuse_material("Rug", (0.70, 0.12, 0.10), shader)
    wood = diffuse_material("Wood", (0.55, 0.40, 0.25), shader)
    fabric = diffuse_material("Fabric", (0.20, 0.35, 0.55), shader)
    t = 0.2
    x0, x1, y0, y1, z1 = -2.5, 2.5, -2.0, 2.0, 2.8
    wx0, wx1, wz0, wz1 = -0.9, 0.9, 0.9, 2.2  # window opening in the +y wall
    add_mesh_object(scene, "FloorSlab", box_geometry((x0 - t, y0 - t, -t), (x1 + t, y1 + t, 0.0)), floor_mat)
    add_mesh_object(scene, "Roof", box_geometry((x0 - t, y0 - t, z1), (x1 + t, y1 + t, z1 + t)), wall)
    walls = _merge(
        box_geometry((x0 - t, y0, 0.0), (x0, y1, z1)),  # -x
        box_geometry((x1, y0, 0.0), (x1 + t, y1, z1)),  # +x
        box_geometry((x0 - t, y0 - t, 0.0), (x1 + t, y0, z1)),  # -y
        # +y wall around the window: below, above, left, right of the opening
        box_geometry((x0 - t, y1, 0.0), (x1 + t, y1 + t, wz0)),
        box_geometry((x0 - t, y1, wz1), (x1 + t, y1 + t, z1)),
        box_geometry((x0 - t, y1, wz0), (wx0, y1 + t, wz1)),
        box_geometry((wx1, y1, wz0), (x1 + t, y1 + t, wz1)),
    )
    add_mesh_object(scene, "Walls", walls, wall)
    add_mesh_object(scene, "Rug", box_geometry((-1.2, -1.2, 0.0), (1.2, 0.8, 0.02)), rug)
    add_mesh_object(scene, "Table", _table(), wood, location=(1.6, -1.1, 0.0), rotation_z_deg=8.0)
    sofa = _merge(box_geometry((-1.0, -0.45, 0.0), (1.0, 0.45, 0.45)),
                  box_geometry((-1.0, -0.45, 0.45), (1.0, -0.25, 0.95)))
    add_mesh_object(scene, "Sofa", sofa, fabric, location=(-0.2, -1.5, 0.0))
    add_mesh_object(scene, "Cabinet", box_geometry((-0.25, -0.6, 0.0), (0.25, 0.6, 1.1)), wood,
                 location=(2.2, 0.6, 0.0))
    # Local -Z rotated -55 deg about X travels towards -y, 35 deg below the horizon.
    lamp = add_light(scene, "Sun", "SUN", 6.0, (0.0, 6.0, 6.0), rotation_deg=(-55.0, 0.0, 18.0))
    add_camera(scene, (-2.25, -1.75, 1.55), (0.6, 1.0, 0.7), lens_mm=16.0)
    return scene_facts(scene, [lamp])


def library(resolution: Sequence[int] = (128, 128), *, shader: str = "DIFFUSE",
            new_file: bool = True, seed: int = 11) -> dict:
    """A real-world-style interior with thousands of objects: a 16 x 10 x 4 m reading room
    (x in [-8, 8], y in [-5, 5]) with 10 bookcases of 5 shelves holding about 2900 books
    (separate objects sharing six book meshes), reading tables and chairs, lit by four
    250 W point lights under the ceiling; camera at eye height at the -x end. Returns the
    scene's facts (``objects`` lists every mesh object)."""
    import random

    rng = random.Random(seed)
    scene = new_scene("library", resolution, new_file)
    wall = diffuse_material("Wall", (0.80, 0.77, 0.70), shader)
    floor_mat = diffuse_material("Parquet", (0.45, 0.30, 0.18), shader)
    ceiling = diffuse_material("Ceiling", (0.85, 0.85, 0.85), shader)
    wood = diffuse_material("DarkWood", (0.30, 0.18, 0.10), shader)
    green = diffuse_material("TableTop", (0.15, 0.40, 0.20), shader)
    book_colors = [(0.60, 0.10, 0.08), (0.10, 0.20, 0.50), (0.15, 0.40, 0.15),
                   (0.70, 0.60, 0.35), (0.35, 0.20, 0.40), (0.80, 0.78, 0.70)]
    books = [_unit_box_mesh(f"Book{i}", diffuse_material(f"Binding{i}", c, shader))
             for i, c in enumerate(book_colors)]
    lo, hi = (-8.0, -5.0, 0.0), (8.0, 5.0, 4.0)
    add_mesh_object(scene, "Floor", box_geometry(lo, hi, ["-z"], inward=True), floor_mat)
    add_mesh_object(scene, "Ceiling", box_geometry(lo, hi, ["+z"], inward=True), ceiling)
    add_mesh_object(scene, "Walls", box_geometry(lo, hi, ["-x", "+x", "-y", "+y"], inward=True), wall)
    # Bookcases: 2 m wide, 0.4 m deep, 2.4 m high, 5 shelves, facing +-y in two rows.
    case_w, case_d, case_h, shelves = 2.0, 0.4, 2.4, 5
    case_parts = [box_geometry((-case_w / 2, -case_d / 2, 0.0), (case_w / 2, -case_d / 2 + 0.03, case_h))]
    case_parts += [box_geometry((sx - 0.02, -case_d / 2, 0.0), (sx + 0.02, case_d / 2, case_h))
                   for sx in (-case_w / 2, case_w / 2)]
    case_parts += [box_geometry((-case_w / 2, -case_d / 2, z), (case_w / 2, case_d / 2, z + 0.03))
                   for z in [k * case_h / shelves for k in range(shelves)] + [case_h - 0.03]]
    case_geo = _merge(*case_parts)
    n_books = 0
    placements = [(x, y, 0.0) for x in (-5.0, -2.5, 0.0, 2.5, 5.0) for y in (-4.75,)]
    placements += [(x, y, 180.0) for x in (-5.0, -2.5, 0.0, 2.5, 5.0) for y in (4.75,)]
    for c, (cx, cy, rot) in enumerate(placements):
        add_mesh_object(scene, f"Bookcase{c:02d}", case_geo, wood, location=(cx, cy, 0.0),
                     rotation_z_deg=rot)
        sign = 1.0 if rot == 0.0 else -1.0
        for k in range(shelves):
            z = k * case_h / shelves + 0.03
            x = -case_w / 2 + 0.03
            while True:
                w = rng.uniform(0.02, 0.05)
                if x + w > case_w / 2 - 0.03:
                    break
                h = rng.uniform(0.18, min(0.34, case_h / shelves - 0.06))
                d = rng.uniform(0.16, 0.3)
                n_books += 1
                bx = cx + sign * (x + w / 2)
                by = cy + sign * (-case_d / 2 + 0.03 + d / 2)
                _instance(scene, f"Book{n_books:04d}", rng.choice(books), (bx, by, z),
                          (w * 0.95, d, h), rotation_z_deg=rot)
                x += w
    for t, tx in enumerate((-4.0, 0.0, 4.0)):
        legs = [box_geometry((x - 0.04, y - 0.04, 0.0), (x + 0.04, y + 0.04, 0.74))
                for x in (-0.9, 0.9) for y in (-0.45, 0.45)]
        add_mesh_object(scene, f"Table{t}", _merge(box_geometry((-1.0, -0.5, 0.74), (1.0, 0.5, 0.78)),
                                                *legs), green, location=(tx, 0.0, 0.0))
        for ci, (dx, dy, rot) in enumerate(((-0.5, -0.85, 0.0), (0.5, -0.85, 0.0),
                                            (-0.5, 0.85, 180.0), (0.5, 0.85, 180.0))):
            chair = _merge(box_geometry((-0.22, -0.22, 0.42), (0.22, 0.22, 0.46)),
                           box_geometry((-0.22, -0.26, 0.0), (0.22, -0.22, 0.9)))
            add_mesh_object(scene, f"Chair{t}{ci}", chair, wood, location=(tx + dx, dy, 0.0),
                         rotation_z_deg=rot)
    lamps = [add_light(scene, f"Lamp{i}", "POINT", 250.0, (x, 0.0, 3.6))
             for i, x in enumerate((-6.0, -2.0, 2.0, 6.0))]
    add_camera(scene, (-7.6, -1.2, 1.7), (0.0, 0.6, 1.1), lens_mm=20.0)
    return scene_facts(scene, lamps)


def _world(scene: bpy.types.Scene, name: str) -> tuple[bpy.types.World, bpy.types.Node]:
    """A new World on ``scene`` with its Background node (Blender's default tree)."""
    world = bpy.data.worlds.new(name)
    if world.node_tree is None:  # pragma: no cover - Blender < 5 needs nodes switched on
        world.use_nodes = True
    scene.world = world
    bg = next(n for n in world.node_tree.nodes if n.bl_idname == "ShaderNodeBackground")
    return world, bg


def _sky_texture(scene: bpy.types.Scene, elevation_deg: float, rotation_deg: float) -> None:
    """A new World on ``scene``: Blender's default Sky Texture (its default sky type and
    settings) with its sun at that elevation and rotation, at Background strength 0.05."""
    world, bg = _world(scene, "SkyTexture")
    sky = world.node_tree.nodes.new("ShaderNodeTexSky")
    sky.sun_elevation = math.radians(elevation_deg)
    sky.sun_rotation = math.radians(rotation_deg)
    world.node_tree.links.new(sky.outputs["Color"], bg.inputs["Color"])
    bg.inputs["Strength"].default_value = 0.05


def _roof_with_hole(lo: Sequence[float], hi: Sequence[float],
                    hole: tuple[float, float, float, float]) -> tuple[list, list]:
    """A roof slab from ``lo`` to ``hi`` with an open rectangle (x0, x1, y0, y1) in it."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    hx0, hx1, hy0, hy1 = hole
    return _merge(
        box_geometry((x0, y0, z0), (x1, hy0, z1)), box_geometry((x0, hy1, z0), (x1, y1, z1)),
        box_geometry((x0, hy0, z0), (hx0, hy1, z1)), box_geometry((hx1, hy0, z0), (x1, hy1, z1)),
    )


def _roof_quads(x0: float, x1: float, y0: float, y1: float, z: float,
                hole: tuple[float, float, float, float]) -> tuple[list, list]:
    """Single quads of a roof in the plane z over [x0, x1] x [y0, y1] (normals -z) around an
    open rectangle (hx0, hx1, hy0, hy1)."""
    hx0, hx1, hy0, hy1 = hole
    rects = [(x0, x1, y0, hy0), (x0, x1, hy1, y1), (x0, hx0, hy0, hy1), (hx1, x1, hy0, hy1)]
    verts, faces = [], []
    for a, b, c, d in rects:
        n = len(verts)
        verts += [(a, c, z), (a, d, z), (b, d, z), (b, c, z)]
        faces.append((n, n + 1, n + 2, n + 3))
    return verts, faces


def sky_room(resolution: Sequence[int] = (128, 128), *, shader: str = "DIFFUSE",
             new_file: bool = True, single_faces: bool = False, ground: float = 0.0) -> dict:
    """A closed 5 x 4 x 2.8 m room (inside x in [-2.5, 2.5], y in [-2, 2], z in [0, 2.8]) of
    solid 0.2 m slabs with a 2.0 x 1.2 m skylight in the roof, lit only by a uniform pale
    blue World (radiance (0.6, 0.7, 0.9) x 2) through it; a table, sofa and cabinet; no lamp.
    Camera inside the -x/-y corner. ``single_faces``: the floor, walls and roof are single
    quads (normals in), the quick way of modelling a room; ``ground`` > 0 with them: the floor
    is a ground plane reaching that far from the centre. Returns the scene's facts."""
    scene = new_scene("sky_room", resolution, new_file)
    _, bg = _world(scene, "Sky")
    bg.inputs["Color"].default_value = (0.6, 0.7, 0.9, 1.0)
    bg.inputs["Strength"].default_value = 2.0
    wall = diffuse_material("Wall", (0.78, 0.76, 0.72), shader)
    floor_mat = diffuse_material("Floor", (0.50, 0.36, 0.24), shader)
    rug = diffuse_material("Rug", (0.15, 0.45, 0.25), shader)
    wood = diffuse_material("Wood", (0.55, 0.40, 0.25), shader)
    fabric = diffuse_material("Fabric", (0.65, 0.18, 0.12), shader)
    t = 0.2
    x0, x1, y0, y1, z1 = -2.5, 2.5, -2.0, 2.0, 2.8
    if single_faces:
        lo, hi = (x0, y0, 0.0), (x1, y1, z1)
        add_mesh_object(scene, "FloorSlab", _ground_plane(ground) if ground > 0 else
                        box_geometry(lo, hi, ["-z"], inward=True), floor_mat)
        add_mesh_object(scene, "Walls", box_geometry(lo, hi, ["-x", "+x", "-y", "+y"],
                                                     inward=True), wall)
        add_mesh_object(scene, "Roof", _roof_quads(x0, x1, y0, y1, z1, (-0.6, 1.4, -0.5, 0.7)),
                        wall)
    else:
        add_mesh_object(scene, "FloorSlab",
                        box_geometry((x0 - t, y0 - t, -t), (x1 + t, y1 + t, 0.0)), floor_mat)
        add_mesh_object(scene, "Roof", _roof_with_hole(
            (x0 - t, y0 - t, z1), (x1 + t, y1 + t, z1 + t), (-0.6, 1.4, -0.5, 0.7)), wall)
        walls = _merge(
            box_geometry((x0 - t, y0, 0.0), (x0, y1, z1)),
            box_geometry((x1, y0, 0.0), (x1 + t, y1, z1)),
            box_geometry((x0 - t, y0 - t, 0.0), (x1 + t, y0, z1)),
            box_geometry((x0 - t, y1, 0.0), (x1 + t, y1 + t, z1)),
        )
        add_mesh_object(scene, "Walls", walls, wall)
    add_mesh_object(scene, "Rug", box_geometry((-0.8, -0.9, 0.0), (1.6, 1.1, 0.02)), rug)
    add_mesh_object(scene, "Table", _table(), wood, location=(0.6, 0.1, 0.0), rotation_z_deg=12.0)
    sofa = _merge(box_geometry((-1.0, -0.45, 0.0), (1.0, 0.45, 0.45)),
                  box_geometry((-1.0, 0.25, 0.45), (1.0, 0.45, 0.95)))
    add_mesh_object(scene, "Sofa", sofa, fabric, location=(0.0, 1.5, 0.0))
    add_mesh_object(scene, "Cabinet", box_geometry((-0.25, -0.6, 0.0), (0.25, 0.6, 1.1)), wood,
                    location=(2.2, -0.6, 0.0))
    add_camera(scene, (-2.25, -1.75, 1.5), (0.6, 0.6, 0.9), lens_mm=16.0)
    return scene_facts(scene, [])


def sky_yard(resolution: Sequence[int] = (128, 128), *, shader: str = "DIFFUSE",
             new_file: bool = True) -> dict:
    """sun_yard's ground and five boxes under a Sky Texture of Blender's default sky type
    (its sun disc on, 35 deg up, rotated 150 deg) at Background strength 0.05, no lamp;
    camera outside looking down at the group. Returns the scene's facts."""
    scene = new_scene("sky_yard", resolution, new_file)
    _sky_texture(scene, 35.0, 150.0)
    ground = diffuse_material("Ground", (0.5, 0.5, 0.5), shader)
    plane = _ground_plane(20.0)
    add_mesh_object(scene, "Ground", plane, ground)
    boxes = [
        ("RedBox", (2.0, 2.0, 2.0), (0.0, 0.0), 20.0, (0.7, 0.08, 0.06)),
        ("WhiteTower", (1.0, 1.0, 3.0), (2.6, 1.6), 0.0, (0.8, 0.8, 0.8)),
        ("GreenWall", (4.0, 0.3, 1.5), (-1.8, 2.6), -10.0, (0.12, 0.5, 0.1)),
        ("BlueBox", (1.2, 1.2, 0.8), (-2.4, -0.8), 35.0, (0.1, 0.2, 0.65)),
        ("YellowSlab", (1.6, 0.9, 0.4), (1.6, -2.0), -25.0, (0.75, 0.65, 0.1)),
    ]
    for name, (sx, sy, sz), (x, y), rot, colour in boxes:
        add_mesh_object(scene, name, box_geometry((-sx / 2, -sy / 2, 0.0), (sx / 2, sy / 2, sz)),
                        diffuse_material(name, colour, shader), location=(x, y, 0.0),
                        rotation_z_deg=rot)
    add_camera(scene, (8.5, -9.0, 5.5), (0.0, 0.3, 0.8), lens_mm=35.0)
    return scene_facts(scene, [])


def emission_material(name: str, color: Sequence[float], strength: float,
                      principled: bool = False) -> bpy.types.Material:
    """An Emission shader (colour x strength), or a black Principled BSDF with that emission."""
    mat = bpy.data.materials.new(name)
    mat.diffuse_color = (*color, 1.0)
    tree = mat.node_tree
    if tree is None:  # pragma: no cover - Blender < 5 needs nodes switched on
        mat.use_nodes = True
        tree = mat.node_tree
    tree.nodes.clear()
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    if principled:
        node = tree.nodes.new("ShaderNodeBsdfPrincipled")
        node.inputs["Base Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        node.inputs["Specular IOR Level"].default_value = 0.0
        node.inputs["Roughness"].default_value = 1.0
        node.inputs["Emission Color"].default_value = (*color, 1.0)
        node.inputs["Emission Strength"].default_value = strength
    else:
        node = tree.nodes.new("ShaderNodeEmission")
        node.inputs["Color"].default_value = (*color, 1.0)
        node.inputs["Strength"].default_value = strength
    tree.links.new(node.outputs[0], out.inputs["Surface"])
    return mat


def _luminaire(scene, name: str, lo: Sequence[float], hi: Sequence[float], face: str,
               light: bpy.types.Material, frame: bpy.types.Material) -> bpy.types.Object:
    """A thin box from ``lo`` to ``hi`` (normals out) whose ``face`` emits (``light``), the
    other faces a diffuse ``frame``: a mounted panel, no light behind it."""
    ob = add_mesh_object(scene, name, box_geometry(lo, hi), frame)
    ob.data.materials.append(light)
    axis, sign = "xyz".index(face[1]), (1.0 if face[0] == "+" else -1.0)
    for poly in ob.data.polygons:
        poly.material_index = 1 if poly.normal[axis] * sign > 0.5 else 0
    return ob


def panel_room(resolution: Sequence[int] = (128, 128), *, shader: str = "DIFFUSE",
               new_file: bool = True) -> dict:
    """point_room's closed 4 x 5 x 3 m room and furniture, lit only by emissive panels, each
    the front face of a 3 cm box on the surface (its other faces dark grey): a 1.2 x 0.6 m
    ceiling panel (Emission shader, warm white, strength 12) and a 1.0 x 0.5 m wall panel
    on the -x wall (Principled BSDF, black, emission pale blue x 8); black world, no lamp.
    Returns the scene's facts."""
    name = point_room(resolution, shader=shader, new_file=new_file)["scene"]
    scene = bpy.data.scenes[name]
    scene.name = "panel_room"
    for ob in [o for o in scene.objects if o.type == "LIGHT"]:
        light = ob.data
        bpy.data.objects.remove(ob)
        bpy.data.lights.remove(light)
    frame = diffuse_material("PanelFrame", (0.1, 0.1, 0.1), shader)
    _luminaire(scene, "CeilingPanel", (-0.6, 0.0, 2.97), (0.6, 0.6, 2.999), "-z",
               emission_material("PanelWarm", (1.0, 0.85, 0.7), 12.0), frame)
    _luminaire(scene, "WallPanel", (-1.999, 0.5, 1.2), (-1.97, 1.5, 1.7), "+x",
               emission_material("PanelBlue", (0.6, 0.75, 1.0), 8.0, principled=True), frame)
    return scene_facts(scene, [])


def soft_room(resolution: Sequence[int] = (128, 128), *, shader: str = "DIFFUSE",
              new_file: bool = True) -> dict:
    """A closed 4 x 4 x 2.8 m room (x, y in [-2, 2]) with a table, a box and a stool, lit by
    a 1 x 1 m square area light under the ceiling (300 W) and a point light of radius 0.25 m
    (150 W): both cast soft shadows. Camera inside a corner, looking at the table. Returns
    the scene's facts."""
    scene = new_scene("soft_room", resolution, new_file)
    wall = diffuse_material("Wall", (0.75, 0.73, 0.70), shader)
    floor = diffuse_material("Floor", (0.55, 0.45, 0.35), shader)
    wood = diffuse_material("Wood", (0.55, 0.40, 0.25), shader)
    blue = diffuse_material("Blue", (0.20, 0.35, 0.60), shader)
    lo, hi = (-2.0, -2.0, 0.0), (2.0, 2.0, 2.8)
    add_mesh_object(scene, "Floor", box_geometry(lo, hi, ["-z"], inward=True), floor)
    add_mesh_object(scene, "Room", box_geometry(lo, hi, ["+z", "-x", "+x", "-y", "+y"],
                                                inward=True), wall)
    table = _table()
    add_mesh_object(scene, "Table", table, wood, location=(-0.3, 0.3, 0.0), rotation_z_deg=15.0)
    add_mesh_object(scene, "Box", box_geometry((-0.25, -0.25, 0.0), (0.25, 0.25, 0.5)), blue,
                    location=(0.9, -0.5, 0.0), rotation_z_deg=30.0)
    add_mesh_object(scene, "Stool", box_geometry((-0.2, -0.2, 0.0), (0.2, 0.2, 0.45)), wood,
                    location=(-1.2, -0.9, 0.0))
    area = add_light(scene, "Panel", "AREA", 300.0, (-0.2, 0.2, 2.7), shape="SQUARE", size=1.0)
    bulb = add_light(scene, "Bulb", "POINT", 150.0, (1.1, -0.9, 1.9), shadow_soft_size=0.25)
    add_camera(scene, (1.8, -1.8, 1.7), (-0.4, 0.4, 0.4), lens_mm=18.0)
    return scene_facts(scene, [area, bulb])


def _wall_with_window(y: float, x0: float, x1: float, z1: float,
                      window: tuple[float, float, float, float]) -> tuple[list, list]:
    """Single quads of a wall in the plane y from x0 to x1 and 0 to z1 (normals +y), around
    an open window (wx0, wx1, wz0, wz1)."""
    wx0, wx1, wz0, wz1 = window
    rects = [(x0, wx0, 0.0, z1), (wx1, x1, 0.0, z1), (wx0, wx1, 0.0, wz0), (wx0, wx1, wz1, z1)]
    verts, faces = [], []
    for a, b, c, d in rects:
        n = len(verts)
        verts += [(a, y, c), (a, y, d), (b, y, d), (b, y, c)]
        faces.append((n, n + 1, n + 2, n + 3))
    return verts, faces


def window_room(resolution: Sequence[int] = (128, 128), *, shader: str = "DIFFUSE",
                new_file: bool = True, wall_thickness: float = 0.0) -> dict:
    """A room modelled the quick way: walls and a roof of single faces (x in [-2.5, 2.5],
    y in [-2, 2], z in [0, 2.7]) standing on a 30 x 30 m ground plane that is also its
    floor, a 1.6 x 1.2 m window in the -y wall; lit only by Blender's default Sky Texture
    (sun 30 deg up, its disc shining in through the window) at Background strength 0.05;
    a table and a cabinet. Camera inside by the +y wall, looking at the window wall.
    ``wall_thickness``: the walls and roof given that thickness outward by a Solidify
    modifier, as an artist would."""
    scene = new_scene("window_room", resolution, new_file)
    _sky_texture(scene, 30.0, 200.0)
    ground = diffuse_material("Ground", (0.45, 0.42, 0.38), shader)
    wall = diffuse_material("Wall", (0.78, 0.76, 0.72), shader)
    wood = diffuse_material("Wood", (0.55, 0.40, 0.25), shader)
    plane = _ground_plane(15.0)
    add_mesh_object(scene, "Ground", plane, ground)
    lo, hi = (-2.5, -2.0, 0.0), (2.5, 2.0, 2.7)
    add_mesh_object(scene, "Walls", box_geometry(lo, hi, ["+z", "-x", "+x", "+y"],
                                                 inward=True), wall)
    window_wall = add_mesh_object(scene, "WindowWall", _wall_with_window(
        -2.0, -2.5, 2.5, 2.7, (-0.8, 0.8, 0.8, 2.0)), wall)
    if wall_thickness > 0:  # a Solidify modifier outward (the faces' normals point in)
        for obj in (bpy.data.objects["Walls"], window_wall):
            mod = obj.modifiers.new("Solidify", "SOLIDIFY")
            mod.thickness, mod.offset = wall_thickness, -1.0
    table = _table()
    add_mesh_object(scene, "Table", table, wood, location=(0.3, -0.4, 0.0), rotation_z_deg=10.0)
    add_mesh_object(scene, "Cabinet", box_geometry((-0.25, -0.6, 0.0), (0.25, 0.6, 1.1)), wood,
                    location=(-2.2, 0.5, 0.0))
    add_camera(scene, (1.6, 1.8, 1.6), (-0.3, -1.5, 0.8), lens_mm=16.0)
    return scene_facts(scene, [])


CHECKER = ((0.8, 0.1, 0.1), (0.1, 0.7, 0.1))


def checker_image(name: str, cells: int = 8) -> bpy.types.Image:
    """A generated, packed ``cells`` x ``cells`` red/green checker (linear, Non-Color), so a
    saved .blend carries it."""
    img = bpy.data.images.new(name, cells, cells, alpha=True, float_buffer=True)
    img.colorspace_settings.name = "Non-Color"
    px = [c for j in range(cells) for i in range(cells) for c in (*CHECKER[(i + j) % 2], 1.0)]
    img.pixels.foreach_set(px)
    img.pack()
    return img


def principled_material(name: str, color: Sequence[float], metallic: float = 0.0,
                        roughness: float = 0.5, image: bpy.types.Image | None = None,
                        ) -> bpy.types.Material:
    """A Principled BSDF material; with ``image``, a closest-filtered Image Texture on the
    object's UV map drives Base Color."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    bsdf = nt.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Metallic"].default_value = metallic
    bsdf.inputs["Roughness"].default_value = roughness
    if image is not None:
        tex = nt.nodes.new("ShaderNodeTexImage")
        tex.image = image
        tex.interpolation = "Closest"
        nt.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def checker_room(resolution: Sequence[int] = (128, 128), *, shader: str = "DIFFUSE",
                 new_file: bool = True) -> dict:
    """A 4 x 4 m floor with a UV-mapped packed checker image (Principled), two 1.5 m diffuse
    walls behind, a plain white block and a metallic block (Metallic 1, roughness 0.3) under
    one 300 W point light; ``shader`` sets the walls' and plain block's BSDF."""
    scene = new_scene("checker_room", resolution, new_file)
    floor_mat = principled_material("CheckerFloor", (0.8, 0.8, 0.8),
                                    image=checker_image("Checker"))
    wall = diffuse_material("Wall", (0.75, 0.73, 0.70), shader)
    plain = diffuse_material("Plain", (0.8, 0.8, 0.8), shader)
    metal = principled_material("Metal", (0.8, 0.8, 0.8), metallic=1.0, roughness=0.3)
    lo, hi = (-2.0, -2.0, 0.0), (2.0, 2.0, 1.5)
    floor = add_mesh_object(scene, "Floor", box_geometry(lo, hi, ["-z"], inward=True), floor_mat)
    mesh = floor.data
    uv = mesh.uv_layers.new(name="UVMap")
    for loop in mesh.loops:
        co = mesh.vertices[loop.vertex_index].co
        uv.data[loop.index].uv = ((co.x - lo[0]) / (hi[0] - lo[0]),
                                  (co.y - lo[1]) / (hi[1] - lo[1]))
    add_mesh_object(scene, "Walls", box_geometry(lo, hi, ["+y", "+x"], inward=True), wall)
    add_mesh_object(scene, "Plain", box_geometry((-1.2, 0.2, 0.0), (-0.4, 1.0, 1.0)), plain)
    add_mesh_object(scene, "Metal", box_geometry((0.4, -0.2, 0.0), (1.2, 0.6, 0.8)), metal)
    lamp = add_light(scene, "Point", "POINT", 300.0, (0.3, -0.6, 2.2))
    add_camera(scene, (0.0, -4.2, 3.0), (0.0, 0.2, 0.3), lens_mm=50.0)
    return scene_facts(scene, [lamp])


BUILDERS: dict[str, Callable[..., dict]] = {
    "cornell_box": cornell_box,
    "point_room": point_room,
    "sun_yard": sun_yard,
    "city": city,
    "sunlit_room": sunlit_room,
    "library": library,
    "sky_room": sky_room,
    "sky_yard": sky_yard,
    "panel_room": panel_room,
    "soft_room": soft_room,
    "checker_room": checker_room,
    "window_room": window_room,
}

# Named scenes of the team (tools/make_references.py): name -> (builder, keyword arguments).
SCENES: dict[str, tuple[str, dict]] = {
    "cornell_spot": ("cornell_box", {"light": "SPOT"}),
    "cornell_point": ("cornell_box", {"light": "POINT"}),
    "cornell_sun": ("cornell_box", {"light": "SUN"}),
    "cornell_area": ("cornell_box", {"light": "AREA"}),
    "point_room": ("point_room", {}),
    "sun_yard": ("sun_yard", {}),
    "city": ("city", {}),
    "sunlit_room": ("sunlit_room", {}),
    "library": ("library", {}),
    "sky_room": ("sky_room", {}),
    "sky_room_thin": ("sky_room", {"single_faces": True}),
    "sky_room_thin_ground": ("sky_room", {"single_faces": True, "ground": 15.0}),
    "sky_yard": ("sky_yard", {}),
    "panel_room": ("panel_room", {}),
    "soft_room": ("soft_room", {}),
    "window_room": ("window_room", {}),
    "window_room_thick": ("window_room", {"wall_thickness": 0.2}),
}
# The scenes lit by the World, emitting materials or soft lamps (issue 17's acceptance
# scenes, tools/sources_check.py); the others are lamp-lit, hard-shadowed, diffuse-only and
# black-world, as the radiometric calibration and the report need.
LIGHT_SOURCE_SCENES = ("sky_room", "sky_room_thin", "sky_room_thin_ground", "sky_yard",
                       "panel_room", "soft_room", "window_room", "window_room_thick")


def build(name: str, **kw) -> dict:
    """Build a named scene (a key of SCENES) or call a builder (a key of BUILDERS)."""
    if name in SCENES:
        builder, defaults = SCENES[name]
        return BUILDERS[builder](**{**defaults, **kw})
    if name in BUILDERS:
        return BUILDERS[name](**kw)
    raise KeyError(f"unknown scene {name!r}; known: {sorted(set(SCENES) | set(BUILDERS))}")


def save_scene(builder_name: str, path: str | Path, **kw) -> dict:
    """Build a scene (see :func:`build`) and save it as a .blend copy (the session's own file
    path is left alone). Returns the builder's facts plus "path"."""
    facts = build(builder_name, **kw)
    path = Path(path).resolve()
    path.parent.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(path), copy=True, check_existing=False)
    return {**facts, "path": str(path)}
