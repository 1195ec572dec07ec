"""Blender depsgraph -> lpv_core Scene: evaluated triangles, materials, lights, camera, settings.

Geometry is read with ``foreach_get`` into numpy and transformed to world space in numpy (no
per-triangle Python). Per-mesh arrays are cached within one call so instances cost a transform.
"""

from __future__ import annotations

import math
import sys
import time
from contextlib import contextmanager

import bpy
import numpy as np

from .._core import core
from .materials import (  # noqa: F401 - re-exported: the material half of the extraction
    DEFAULT_ALBEDO,
    material_albedo,
    material_emits,
    material_info,
)
from .world import world_from_blender

MESH_LIKE = frozenset({"MESH", "CURVE", "SURFACE", "FONT", "META"})
# Object types with geometry we cannot triangulate (hair curves, point clouds, volumes, ...).
UNSUPPORTED = frozenset({"CURVES", "POINTCLOUD", "VOLUME", "GPENCIL", "GREASEPENCIL"})
# Scene.lpv properties copied into GISettings (see properties.py).
SCENE_SETTINGS = (
    "grid_resolution", "cascades", "cascades_auto", "rsm_resolution",
    "occlusion", "bounces", "backend", "intensity", "antialias", "contact_light",
)


class _Timer:
    """Accumulates milliseconds per phase into a dict (or does nothing without one)."""

    def __init__(self, out: dict | None) -> None:
        self.out = out

    @contextmanager
    def phase(self, name: str):
        if self.out is None:
            yield
            return
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.out[name] = self.out.get(name, 0.0) + (time.perf_counter() - t0) * 1000.0


def extract_scene(
    depsgraph: bpy.types.Depsgraph,
    scene: bpy.types.Scene | None = None,
    resolution: tuple[int, int] | None = None,
    settings_overrides: dict | None = None,
    *,
    require_camera: bool = True,
    render_visibility: bool = True,
    timings: dict | None = None,
) -> core.scene.Scene:
    """The evaluated scene of ``depsgraph`` as a validated core Scene (bad triangles dropped).

    ``render_visibility`` skips objects hidden for render; ``timings`` gets ms per phase.
    """
    if depsgraph is None or not hasattr(depsgraph, "object_instances"):
        raise ValueError(f"extract_scene needs a bpy Depsgraph, got {type(depsgraph).__name__}")
    if scene is None:
        # The original scene: Python-set properties reach it at once (the evaluated copy lags
        # until the next update), and the active depsgraph writes animated values back to it.
        scene = depsgraph.scene
    timer = _Timer(timings)
    geo = _GeometryCollector(timer, depsgraph.view_layer)
    lights: list = []
    dropped = dict.fromkeys(
        ("objects_without_geometry", "objects_degenerate_transform", "unsupported_objects"), 0
    )

    def count(key: str) -> None:
        dropped[key] += 1

    areas: list = []
    light_notes: list[str] = []  # what the lights' extraction approximated
    pending: dict = {}  # session_uid -> (object, matrix) of curve-like objects (below)
    for inst in depsgraph.object_instances:
        ob = inst.object
        kind = ob.type
        if kind == "EMPTY":
            area = area_from_object(ob, inst) if _visible(inst, ob, render_visibility) else None
            if area is not None:
                areas.append(area)
            continue
        if kind not in MESH_LIKE and kind != "LIGHT":
            if kind in UNSUPPORTED:
                count("unsupported_objects")
            continue
        if not _visible(inst, ob, render_visibility):
            continue
        matrix = np.array(inst.matrix_world, np.float64)  # copy now: inst is reused
        if kind == "LIGHT":
            if not getattr(ob, "visible_diffuse", True):
                continue  # Cycles: a light diffuse rays do not see lights no diffuse surface
            cycles = getattr(ob.data, "cycles", None)
            if ob.data.type == "AREA" and getattr(cycles, "is_portal", False):
                note = (f"light '{ob.name}': a Cycles portal (it guides the World's light "
                        "through an opening and emits none): left out")
                if note not in light_notes:
                    light_notes.append(note)
                continue
            with timer.phase("lights"):
                light = light_from_object(ob, matrix, light_notes)
                if light.power < 0:
                    light_notes.append(f"light '{ob.name}': negative power ({light.power:g} W) "
                                       "is not supported: left out")
                lights.append(light)
        elif kind != "MESH" and not inst.is_instance:
            # a curve, text or surface: its evaluated geometry set may hand its mesh on as an
            # instance of itself (the depsgraph then yields both): added only if none comes
            pending[ob.original.session_uid] = (ob, matrix)
        else:
            parent = inst.parent if inst.is_instance else None
            if parent is not None and ob.original.session_uid == parent.original.session_uid:
                pending.pop(parent.original.session_uid, None)
            geo.add(ob, matrix, count)
    for ob, matrix in pending.values():
        geo.add(ob, matrix, count)

    with timer.phase("camera"):
        camera = None
        if scene.camera is not None:
            camera = camera_from_scene(depsgraph, scene, resolution)
        elif require_camera:
            raise ValueError(
                f"scene '{scene.name}' has no active camera: set one (Scene properties > Camera) "
                "or extract with require_camera=False"
            )
        settings = settings_from_scene(scene, settings_overrides)
    with timer.phase("world"):
        world, world_notes, world_lights = world_from_blender(scene.world, scene)
    if not getattr(depsgraph.view_layer, "use_sky", True):  # View Layer > Filter > Environment
        world, world_notes, world_lights = None, [], []  # off: Cycles draws and lights none
    lights += world_lights

    positions, normals, mat_index, obj_index = geo.arrays()
    with timer.phase("make_scene"):
        result = core.scene.make_scene(
            positions, normals, mat_index, geo.materials, lights, camera, settings,
            object_index=obj_index, object_names=geo.object_names, areas=areas,
            **geo.flags(obj_index, mat_index), **geo.corner_arrays(), world=world,
        )
    result.approximated.extend(geo.approximated + world_notes + light_notes
                               + camera_notes(scene))
    result.film_transparent = bool(scene.render.film_transparent)
    for key, n in geo.defaulted.items():
        if n:
            result.dropped[f"{key}_nonfinite_or_negative_defaulted"] = n
    for key, value in dropped.items():
        result.dropped[key] = result.dropped.get(key, 0) + value
    return result


def _visible(inst, ob, render_visibility: bool) -> bool:
    """What Cycles shows (show_self), and with ``render_visibility`` also what renders."""
    if not inst.show_self:
        return False
    if not render_visibility:
        return True
    orig = ob.original
    if orig.hide_render:
        return False
    if inst.is_instance:
        parent = inst.parent
        return parent is None or not parent.original.hide_render
    # A vertex/face instancer itself is hidden in renders unless asked for.
    if getattr(orig, "is_instancer", False) and orig.instance_type in ("VERTS", "FACES"):
        return bool(getattr(orig, "show_instancer_for_render", True))
    return True


# --------------------------------------------------------------------------------- geometry


class _GeometryCollector:
    """Gathers world-space triangle chunks, caching per-mesh local arrays across instances."""

    def __init__(self, timer: _Timer, view_layer=None) -> None:
        self.timer = timer
        self.view_layer = view_layer  # its collections' Holdout and Indirect Only
        self.cache: dict[int, tuple] = {}
        self.chunks: list[tuple] = []
        self.materials: list = []
        self._material_ids: dict = {}
        self.infos: list = []  # materials.MaterialInfo per material
        self.approximated: list[str] = []
        self.defaulted = {"texels": 0, "corner_colors": 0}  # non-finite or negative, set to 0
        self.object_names: list[str] = []
        self._object_ids: dict[str, int] = {}
        self.object_flags: list[tuple[bool, bool, bool]] = []  # caster, occluder, receiver
        self.object_hidden: list[int] = []  # ray_hidden bits per object (object_ray_hidden)

    def add(self, ob, matrix: np.ndarray, count) -> None:
        """Add one evaluated mesh-like object instance with its world matrix."""
        with self.timer.phase("materials"):
            table = self._slot_table(ob)
            infos = [self.infos[i] for i in table]
            uv_maps = tuple(sorted({i.uv_map for i in infos if i.uv_map is not None}))
            colors = tuple(sorted({i.color_attribute for i in infos
                                   if i.color_attribute is not None}))
            tangent_maps = tuple(sorted({i.uv_map for i in infos if i.uv_map is not None
                                         and i.material.normal_texture is not None}))
        local = self._local_arrays(ob, uv_maps, colors, tangent_maps)
        if local is None or local[0].shape[0] == 0:
            count("objects_without_geometry")
            return
        pos, nrm, slot_index, layers = local
        with self.timer.phase("materials"):
            slot = np.minimum(slot_index, len(table) - 1)  # Blender clamps
            mat = np.take(table, slot)
            uvs, cols = self._corners(ob, infos, slot, layers, uv_maps, colors)
            tans = self._tangents(ob, infos, slot, layers) if tangent_maps else None
        if _degenerate(matrix):
            count("objects_degenerate_transform")
            return
        oid = self._object_ids.setdefault(ob.name, len(self.object_names))
        if oid == len(self.object_names):
            self.object_names.append(ob.name)
            self.object_flags.append(object_gi_flags(ob))
            self.object_hidden.append(object_ray_hidden(ob, self.view_layer))
        self.chunks.append((pos, nrm, matrix, mat, oid, uvs, cols, tans))

    def _corners(self, ob, infos, slot, layers, uv_maps, colors):
        """Per-corner UVs (T, 3, 2) (each slot's material's UV map and Mapping) and colours
        (T, 3, 3) of one object, None where no material of it reads them."""
        uvs = np.zeros(slot.shape + (3, 2), np.float32) if uv_maps else None
        cols = np.ones(slot.shape + (3, 3), np.float32) if colors else None
        for k, info in enumerate(infos):
            if info.uv_map is None and info.color_attribute is None:
                continue
            sel = slot == k
            if not sel.any():
                continue
            name = info.material.name
            if info.uv_map is not None:
                uv = layers.get(("uv", info.uv_map))
                if uv is None:
                    self._note(f"material '{name}' on object '{ob.name}': UV map "
                               f"'{info.uv_map or 'render'}' is missing: UV (0, 0)")
                else:
                    uv = uv[sel]
                    if info.uv_transform is not None:
                        a = info.uv_transform.astype(np.float32)
                        uv = uv @ a[:2, :2].T + a[:2, 2]
                    uvs[sel] = uv
            if info.color_attribute is not None:
                col = layers.get(("color", info.color_attribute))
                if col is None:
                    self._note(f"material '{name}' on object '{ob.name}': colour attribute "
                               f"'{info.color_attribute or 'render'}' is missing: black, as "
                               "Cycles reads it")
                    cols[sel] = 0.0
                else:
                    cols[sel] = col[sel]
        self.defaulted["corner_colors"] += layers.get("defaulted", 0) if colors else 0
        return uvs, cols

    def _tangents(self, ob, infos, slot, layers):
        """Per-corner tangents (T, 3, 4) (tangent, bitangent sign) of each normal-mapped
        slot's UV map, zeros elsewhere (the mesh's own normal there)."""
        tans = np.zeros(slot.shape + (3, 4), np.float32)
        for k, info in enumerate(infos):
            if info.material.normal_texture is None or info.uv_map is None:
                continue
            sel = slot == k
            if not sel.any():
                continue
            tan = layers.get(("tangent", info.uv_map))
            note = layers.get(("tangent_note", info.uv_map))
            if note is not None:
                self._note(f"material '{info.material.name}' on object '{ob.name}': normal "
                           f"map with {note}")
            if tan is None:
                why = layers.get(("tangent_error", info.uv_map), "its UV map is missing")
                self._note(f"material '{info.material.name}' on object '{ob.name}': normal "
                           f"map left out ({why})")
            else:
                tans[sel] = tan[sel]
        return tans

    def _note(self, line: str) -> None:
        if line not in self.approximated:
            self.approximated.append(line)

    def _local_arrays(self, ob, uv_maps=(), colors=(), tangent_maps=()):
        key = ob.data.as_pointer() if ob.type == "MESH" and ob.data is not None else None
        if key is not None:
            key = (key, uv_maps, colors, tangent_maps)
        if key is not None and key in self.cache:
            return self.cache[key]
        with self.timer.phase("mesh_eval"):
            try:
                mesh = ob.to_mesh()
            except RuntimeError as exc:
                raise ValueError(f"object '{ob.name}': cannot evaluate its mesh ({exc})") from exc
        try:
            layers: dict = {}
            arrays = None if mesh is None else mesh_arrays(
                mesh, self.timer, uv_maps=uv_maps, color_attributes=colors, corners=layers,
                tangent_maps=tangent_maps)
            if arrays is not None:
                arrays = (*arrays, layers)
        finally:
            with self.timer.phase("mesh_eval"):
                ob.to_mesh_clear()
        if key is not None:
            self.cache[key] = arrays
        return arrays

    def _slot_table(self, ob) -> np.ndarray:
        slots = [slot.material for slot in ob.material_slots] or [None]
        override = getattr(self.view_layer, "material_override", None)
        if override is not None:  # the view layer's Material Override, as Cycles renders it
            slots = [override] * len(slots)
        return np.array([self._material_id(m) for m in slots], np.int32)

    def _material_id(self, mat) -> int:
        key = None if mat is None else mat.original.session_uid
        mid = self._material_ids.get(key)
        if mid is None:
            info = material_info(mat)
            for line in info.notes:
                self._note(line)
            self.defaulted["texels"] += info.defaulted_texels
            mid = self._material_ids[key] = len(self.materials)
            self.materials.append(info.material)
            self.infos.append(info)
        return mid

    def flags(self, object_index: np.ndarray, material_index: np.ndarray) -> dict:
        """Per-triangle caster/occluder/receiver arrays from Object.lpv (None: all on) and
        ray_hidden bits from the objects' visibility and Holdout shaders (None: none)."""
        table = np.array(self.object_flags or [(True, True, True)], bool).reshape(-1, 3)
        out = {}
        for i, name in enumerate(("caster", "occluder", "receiver")):
            if not table[:, i].all():
                out[name] = table[object_index, i] if object_index.size else None
        # a surface of no coverage (a volume's, Alpha 0) neither bounces nor blocks light
        clear = np.array([i.material.alpha <= 0 for i in self.infos] or [False], bool)
        if clear.any() and object_index.size:
            gone = clear[np.clip(material_index, 0, clear.size - 1)]
            for name in ("caster", "occluder"):
                arr = out.get(name)
                arr = np.ones(object_index.size, bool) if arr is None else arr.copy()
                arr[gone] = False
                out[name] = arr
        hidden = np.array(self.object_hidden or [0], np.uint8)
        held = np.array([i.holdout for i in self.infos] or [False], bool)
        if (hidden.any() or held.any()) and object_index.size:
            bits = hidden[object_index]
            bits[held[np.clip(material_index, 0, held.size - 1)]] |= core.scene.model.HOLDOUT
            out["ray_hidden"] = bits
        return out

    def arrays(self):
        """World-space (positions float64, normals, material, object index): each instance
        is transformed straight into its slice of the output (no per-chunk copies). Positions
        stay float64 until the core subtracts its own origin: float32 spacing is 1 m at 1e7 m."""
        with self.timer.phase("transform"):
            sizes = [len(c[3]) for c in self.chunks]
            total = sum(sizes)
            pos = np.empty((total, 3, 3), np.float64)
            nrm = np.empty((total, 3, 3), np.float32)
            start = 0
            for (p, n, matrix, *_), size in zip(self.chunks, sizes):
                _to_world(p, n, matrix, pos[start:start + size], nrm[start:start + size])
                start += size
            mat = np.concatenate([c[3] for c in self.chunks] or [np.zeros(0, np.int32)])
            oids = np.array([c[4] for c in self.chunks], np.int32)
            return pos, nrm, mat, np.repeat(oids, sizes)

    def corner_arrays(self) -> dict:
        """{"uvs": (T, 3, 2), "corner_colors": (T, 3, 3)} for make_scene, each only where some
        material reads it (UV 0 and colour 1 elsewhere); corners swapped like the positions
        of mirrored instances."""
        out = {}
        for slot, name, fill, width in ((5, "uvs", 0.0, 2), (6, "corner_colors", 1.0, 3)):
            if all(c[slot] is None for c in self.chunks):
                continue
            parts = []
            for c in self.chunks:
                arr = c[slot]
                if arr is None:
                    arr = np.full((len(c[3]), 3, width), fill, np.float32)
                elif np.isfinite(c[2]).all() and np.linalg.det(c[2][:3, :3]) < 0:
                    arr = arr[:, [0, 2, 1]]
                parts.append(arr)
            out[name] = np.concatenate(parts)
        if any(c[7] is not None for c in self.chunks):
            parts = []
            for c in self.chunks:
                parts.append(np.zeros((len(c[3]), 3, 4), np.float32) if c[7] is None
                             else _tangents_to_world(c[7], c[2]))
            out["tangents"] = np.concatenate(parts)
        return out


def mesh_arrays(mesh: bpy.types.Mesh, timer: _Timer | None = None, *, uv_maps=(),
                color_attributes=(), corners: dict | None = None, tangent_maps=()):
    """Local (positions (T,3,3), corner normals (T,3,3), slot index (T,)) of a mesh; tri/quad
    meshes are split in numpy (the RNA ``loop_triangles`` read is slow: n-gons only).
    ``corners`` gets {("uv", name): (T,3,2), ("color", name): (T,3,3)} for the UV maps and
    colour attributes named ("" the render one; missing ones left out), and
    {("tangent", name): (T,3,4)} for ``tangent_maps`` (tangent_layers)."""
    timer = timer or _Timer(None)
    with timer.phase("triangles"):
        mesh.calc_loop_triangles()
        t = len(mesh.loop_triangles)
        n_poly = len(mesh.polygons)
        n_loop = len(mesh.loops)
        if t == 0:
            z = np.zeros((0, 3, 3), np.float32)
            return z, z.copy(), np.zeros(0, np.int32)
        tri_poly = _read(mesh.loop_triangle_polygons, "value", t, np.int32)
        corner_vert = _corner_verts(mesh, n_loop)
    with timer.phase("positions"):
        co = _read(mesh.attributes["position"].data, "vector", 3 * len(mesh.vertices), np.float32)
        co = co.reshape(-1, 3)
    with timer.phase("triangles"):
        loops = _quad_split_corners(tri_poly, n_poly, n_loop, corner_vert, co)
        if loops is None:
            loops = _read(mesh.loop_triangles, "loops", 3 * t, np.int32).reshape(t, 3)
        tri_verts = np.take(corner_vert, loops)
    with timer.phase("positions"):
        pos = np.take(co, tri_verts, axis=0)
    with timer.phase("normals"):
        domain = getattr(mesh, "normals_domain", "CORNER")
        if domain == "POINT":
            vn = _read(mesh.vertex_normals, "vector", 3 * len(mesh.vertices), np.float32)
            nrm = np.take(vn.reshape(-1, 3), tri_verts, axis=0)
        elif domain == "FACE":
            fn = _read(mesh.polygon_normals, "vector", 3 * n_poly, np.float32).reshape(-1, 3)
            nrm = np.repeat(np.take(fn, tri_poly, axis=0)[:, None, :], 3, axis=1)
        else:
            cn = _read(mesh.corner_normals, "vector", 3 * n_loop, np.float32)
            nrm = np.take(cn.reshape(-1, 3), loops, axis=0)
    if corners is not None and (uv_maps or color_attributes):
        with timer.phase("corners"):
            corners.update(corner_layers(mesh, loops, tri_verts, uv_maps, color_attributes))
    if corners is not None and tangent_maps:
        with timer.phase("corners"):
            corners.update(tangent_layers(mesh, loops, tangent_maps, pos))
    with timer.phase("materials"):
        attr = mesh.attributes.get("material_index")
        if attr is not None and attr.domain == "FACE" and attr.data_type == "INT":
            face_mat = _read(attr.data, "value", n_poly, np.int32)
            slot = np.maximum(np.take(face_mat, tri_poly), 0)
        else:
            slot = np.zeros(t, np.int32)
    return pos, nrm, slot


def corner_layers(mesh, loops: np.ndarray, tri_verts: np.ndarray, uv_maps, colors) -> dict:
    """Per-triangle-corner UVs and scene-linear colours of the named UV maps and colour
    attributes ("" the active render one), read with foreach_get."""
    out = {}
    n_loop = len(mesh.loops)
    for name in uv_maps:
        layer = (next((u for u in mesh.uv_layers if u.active_render), None) if name == ""
                 else mesh.uv_layers.get(name))
        if layer is not None:
            uv = _read(layer.uv, "vector", 2 * n_loop, np.float32).reshape(-1, 2)
            out[("uv", name)] = np.take(uv, loops, axis=0)
    attrs = mesh.color_attributes
    for name in colors:
        attr = None
        if name == "":
            i = attrs.render_color_index
            attr = attrs[i] if 0 <= i < len(attrs) else None
        else:
            attr = attrs.get(name)
        if attr is None or attr.domain not in ("CORNER", "POINT"):
            continue
        n = len(attr.data)
        col = _read(attr.data, "color", 4 * n, np.float32).reshape(-1, 4)[:, :3]
        index = loops if attr.domain == "CORNER" else tri_verts
        with np.errstate(invalid="ignore"):
            bad = ~(np.isfinite(col) & (col >= 0))
        if bad.any():
            out["defaulted"] = out.get("defaulted", 0) + int(bad.any(axis=1).sum())
            col = np.where(bad, 0.0, col)
        out[("color", name)] = np.take(col, index, axis=0)
    return out


def tangent_layers(mesh, loops: np.ndarray, uv_maps, pos: np.ndarray) -> dict:
    """Per-triangle-corner (tangent, bitangent sign) (T, 3, 4) of the named UV maps ("" the
    active render one), Blender's own MikkTSpace tangents (Mesh.calc_tangents, on the
    evaluated copy), the ones Cycles' Normal Map node reads; a mesh with n-gons, which Blender
    computes none for, gets each triangle's own (triangle_tangents), noted as
    ("tangent_note", name); a missing UV map ("tangent_error", name)."""
    out = {}
    n_loop = len(mesh.loops)
    for name in uv_maps:
        layer = (next((u for u in mesh.uv_layers if u.active_render), None) if name == ""
                 else mesh.uv_layers.get(name))
        if layer is None:
            out[("tangent_error", name)] = f"UV map '{name or 'render'}' is missing"
            continue
        try:
            mesh.calc_tangents(uvmap=layer.name)
        except RuntimeError:  # n-gons: Blender's tangents are for triangles and quads
            uv = _read(layer.uv, "vector", 2 * n_loop, np.float32).reshape(-1, 2)
            out[("tangent", name)] = triangle_tangents(pos, np.take(uv, loops, axis=0))
            out[("tangent_note", name)] = ("faces of more than four corners: tangents from "
                                           "each triangle's UVs, not Blender's")
            continue
        tan = _read(mesh.loops, "tangent", 3 * n_loop, np.float32).reshape(-1, 3)
        sign = _read(mesh.loops, "bitangent_sign", n_loop, np.float32).reshape(-1, 1)
        out[("tangent", name)] = np.take(np.hstack([tan, sign]), loops, axis=0)
    return out


def triangle_tangents(pos: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(T, 3, 4) each triangle's own tangent dP/du (unit) and bitangent sign (+1 where dP/dv
    turns as N x T, N the face normal) at its three corners; zeros where its UVs are
    degenerate."""
    p, t = np.asarray(pos, np.float64), np.asarray(uv, np.float64)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    ok = np.abs(det) > 1e-20
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)[:, None]
    tan = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * inv
    bit = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * inv
    length = np.linalg.norm(tan, axis=1, keepdims=True)
    tan = np.where(length > 0, tan / np.where(length > 0, length, 1.0), 0.0)
    sign = np.where(np.einsum("ij,ij->i", np.cross(np.cross(e1, e2), tan), bit) < 0, -1.0, 1.0)
    out = np.zeros((p.shape[0], 3, 4), np.float32)
    out[..., :3] = tan[:, None, :]
    out[..., 3] = np.where(ok, sign, 0.0)[:, None]
    return out


def _tangents_to_world(tans: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Local (T, 3, 4) tangents in world space: the tangent by the matrix (a surface
    direction; make it unit), the sign flipped by a mirror, corners swapped as the positions'."""
    m3 = np.asarray(matrix, np.float64)[:3, :3]
    if not np.isfinite(m3).all():
        return np.zeros_like(tans)
    out = tans.astype(np.float32).copy()
    t = tans[..., :3].reshape(-1, 3).astype(np.float64) @ m3.T
    length = np.linalg.norm(t, axis=1, keepdims=True)
    out[..., :3] = (t / np.where(length > 0, length, 1.0)).reshape(tans.shape[:2] + (3,))
    if np.linalg.det(m3) < 0:
        out[..., 3] = -out[..., 3]
        out = out[:, [0, 2, 1]]
    return out


def _read(collection, prop: str, n: int, dtype) -> np.ndarray:
    out = np.empty(n, dtype)
    collection.foreach_get(prop, out)
    return out


def _quad_split_corners(tri_poly, n_poly, n_loop, corner_vert, co) -> np.ndarray | None:
    """(T, 3) corners for tri/quad meshes (else None), quads split as Blender does: on 0-2, or
    on 1-3 where 1 and 3 lie on one side of 0-2 (BLI is_quad_flip_v3_first_third_fast)."""
    t = tri_poly.shape[0]
    if t == n_poly and n_loop == 3 * t:  # all triangles
        return np.arange(n_loop, dtype=np.int32).reshape(t, 3)
    counts = np.bincount(tri_poly, minlength=n_poly)
    if counts.shape[0] != n_poly or counts.max() > 2 or counts.min() < 1:
        return None
    if int(counts.sum()) + 2 * n_poly != n_loop:
        return None
    if t == 2 * n_poly:  # all quads: no index arithmetic per triangle needed
        starts = np.arange(0, n_loop, 4, dtype=np.int32)
        first = np.arange(0, t, 2, dtype=np.int32)
        loops = np.empty((n_poly, 2, 3), np.int32)
        loops[:, :, 0] = starts[:, None]
        loops[:, 0, 1] = starts + 1
        loops[:, :, 2] = starts[:, None] + np.array([2, 3], np.int32)
        loops[:, 1, 1] = loops[:, 0, 2]
        loops = loops.reshape(t, 3)
        quad_verts = corner_vert.reshape(n_poly, 4).T
    else:
        sizes = counts + 2
        starts = (np.cumsum(sizes) - sizes).astype(np.int32)
        first_tri = (np.cumsum(counts) - counts).astype(np.int32)
        ls = np.take(starts, tri_poly)
        k = np.arange(t, dtype=np.int32) - np.take(first_tri, tri_poly)
        loops = np.stack([ls, ls + k + 1, ls + k + 2], axis=1)
        is_quad = counts == 2
        starts, first = starts[is_quad], first_tri[is_quad]
        quad_verts = np.stack([np.take(corner_vert, starts + j) for j in range(4)])
    if starts.size:
        # Components as contiguous rows (3, 4, Q): strided column maths is several times slower.
        (v0x, v1x, v2x, v3x), (v0y, v1y, v2y, v3y), (v0z, v1z, v2z, v3z) = np.take(
            np.ascontiguousarray(co.T), quad_verts, axis=1
        )
        ax, ay, az = v1x - v0x, v1y - v0y, v1z - v0z
        bx, by, bz = v3x - v0x, v3y - v0y, v3z - v0z
        cx, cy, cz = v2x - v0x, v2y - v0y, v2z - v0z
        # (a x c) . (b x c) > 0 in float32, component-wise as Blender computes it.
        flip = (
            (ay * cz - az * cy) * (by * cz - bz * cy)
            + (az * cx - ax * cz) * (bz * cx - bx * cz)
            + (ax * cy - ay * cx) * (bx * cy - by * cx)
        ) > 0
        if flip.any():
            s = starts[flip][:, None]
            tri = first[flip]
            loops[tri] = s + np.array([0, 1, 3], np.int32)
            loops[tri + 1] = s + np.array([1, 2, 3], np.int32)
    return loops


def _corner_verts(mesh, n_loop: int) -> np.ndarray:
    attr = mesh.attributes.get(".corner_vert")
    if attr is not None:
        return _read(attr.data, "value", n_loop, np.int32)
    return _read(mesh.loops, "vertex_index", n_loop, np.int32)


def _degenerate(matrix: np.ndarray) -> bool:
    """A finite transform that flattens the object (zero scale on some axis)."""
    m3 = matrix[:3, :3]
    return bool(np.isfinite(m3).all()) and abs(float(np.linalg.det(m3))) < 1e-30


def _to_world(pos, nrm, matrix: np.ndarray, out_pos: np.ndarray, out_nrm: np.ndarray) -> None:
    """Write world-space triangles into ``out_*``: positions in float64 (the matrix Blender
    holds, applied without rounding), normals by the inverse transpose, winding kept consistent
    with them for mirrored objects (NaN transforms give NaN: dropped later)."""
    m3 = matrix[:3, :3]
    if not np.isfinite(matrix).all():
        out_pos.fill(np.nan)
        out_nrm[:] = nrm
        return
    if np.array_equal(matrix, np.eye(4)):
        out_pos[:] = pos
        out_nrm[:] = nrm
        return
    # One (3T, 3) x (3, 3) product: several times faster than a batched (T, 3, 3) matmul.
    np.matmul(pos.reshape(-1, 3).astype(np.float64), m3.T, out=out_pos.reshape(-1, 3))
    out_pos += matrix[:3, 3]
    # n' = inv(M)^T n; as row vectors: n @ inv(M). make_scene renormalises.
    np.matmul(nrm.reshape(-1, 3), np.linalg.inv(m3).astype(np.float32),
              out=out_nrm.reshape(-1, 3))
    if np.linalg.det(m3) < 0:  # a mirror flips winding: swap two corners to match the normals
        for arr in (out_pos, out_nrm):
            corner = arr[:, 1].copy()
            arr[:, 1] = arr[:, 2]
            arr[:, 2] = corner


# ------------------------------------------------------------------------------- GI flags


def object_gi_flags(ob) -> tuple[bool, bool, bool]:
    """(caster, occluder, receiver) from Object.lpv (all on without the add-on's properties),
    casting and occluding only if diffuse rays see the object (Object.visible_diffuse, as in
    Cycles: its light bounces nowhere and nothing's bounce is blocked by it). Instances take
    the flags of the instanced object."""
    diffuse = bool(getattr(ob, "visible_diffuse", True))
    props = getattr(ob, "lpv", None)
    if props is None or not hasattr(props, "gi_caster"):
        return diffuse, diffuse, True
    return (bool(props.gi_caster) and diffuse, bool(props.gi_occluder) and diffuse,
            bool(props.gi_receiver))


def object_ray_hidden(ob, view_layer=None) -> int:
    """Scene.ray_hidden bits of an object from Cycles' visibility: Camera off or in an
    Indirect Only collection (hidden from the camera), Shadow off, Holdout (the object's or
    its collection's in ``view_layer``)."""
    model = core.scene.model
    holdout, indirect = bool(getattr(ob, "is_holdout", False)), False
    if view_layer is not None and hasattr(ob, "holdout_get"):
        orig = ob.original
        holdout = holdout or bool(orig.holdout_get(view_layer=view_layer))
        indirect = bool(orig.indirect_only_get(view_layer=view_layer))
    camera = bool(getattr(ob, "visible_camera", True)) and not indirect
    return ((0 if camera else model.HIDDEN_FROM_CAMERA)
            | (0 if getattr(ob, "visible_shadow", True) else model.CASTS_NO_SHADOW)
            | (model.HOLDOUT if holdout else 0))


def area_from_object(ob, inst) -> core.scene.Area | None:
    """A GI area from an Empty whose ``lpv.area_type`` is CLIP or TRANSITION: its box is the
    Empty's cube display, [-size, size]^3 in local space, under the instance's world matrix."""
    props = getattr(ob, "lpv", None)
    kind = getattr(props, "area_type", "NONE") if props is not None else "NONE"
    if kind not in core.scene.AREA_TYPES:
        return None
    size = float(getattr(ob, "empty_display_size", 1.0))
    matrix = np.array(inst.matrix_world, np.float64) @ np.diag([size, size, size, 1.0])
    if not np.isfinite(matrix).all() or abs(np.linalg.det(matrix[:3, :3])) < 1e-30:
        return None
    return core.scene.Area(
        name=ob.name, type=kind, matrix=matrix, falloff=float(props.area_falloff),
        intensity=float(props.area_intensity),
        tint=np.array(props.area_tint[:3], np.float32),
    )


# ----------------------------------------------------------------------------------- lights


def light_from_object(ob: bpy.types.Object, matrix: np.ndarray,
                      notes: list | None = None) -> core.scene.Light:
    """A core Light in Cycles' units: power = energy x 2^exposure (x world area for area lights
    without ``normalize``); colour x blackbody tint when ``use_temperature``, x its node
    tree's Emission colour and strength (light_nodes; what it cannot read goes to ``notes``)."""
    light = ob.data
    kind = light.type
    if kind not in core.scene.LIGHT_TYPES:
        raise ValueError(f"light '{ob.name}': unsupported light type {kind}")
    color = np.array(light.color[:3], np.float64)
    if getattr(light, "use_temperature", False) and hasattr(light, "temperature_color"):
        color = color * np.array(light.temperature_color[:3], np.float64)
    color = color * light_nodes(ob, notes if notes is not None else [])
    power = float(light.energy)
    if hasattr(light, "exposure"):
        power *= 2.0 ** float(light.exposure)
    size = (1.0, 1.0)
    if kind == "AREA":
        sx = float(light.size)
        sy = sx if light.shape in ("SQUARE", "DISK") else float(light.size_y)
        size = (sx, sy)
        if not getattr(light, "normalize", True):
            # Cycles: the emitter's world size includes the object's scale.
            wx = sx * float(np.linalg.norm(matrix[:3, 0]))
            wy = sy * float(np.linalg.norm(matrix[:3, 1]))
            area = wx * wy * (math.pi / 4.0 if light.shape in ("DISK", "ELLIPSE") else 1.0)
            power *= area
    gi = 1.0
    gi_color = np.ones(3, np.float32)
    props = getattr(light, "lpv", None)
    if props is not None and hasattr(props, "gi_intensity"):
        gi = float(props.gi_intensity)
        gi_color = np.array(props.gi_color[:3], np.float32)
    values = np.concatenate([color, [power, gi], matrix.ravel()])
    if not np.isfinite(values).all():  # make_scene drops or defaults it and counts it
        print(f"LPV GI: light '{ob.name}': non-finite colour, power, GI intensity or "
              f"transform (colour {tuple(color)}, power {power}); left out or defaulted",
              file=sys.stderr)
    return core.scene.Light(
        name=ob.name,
        type=kind,
        matrix=matrix.copy(),
        color=color.astype(np.float32),
        power=power,
        spot_size=float(getattr(light, "spot_size", math.pi / 4.0)),
        spot_blend=float(getattr(light, "spot_blend", 0.15)),
        radius=float(getattr(light, "shadow_soft_size", 0.0)),
        soft_falloff=bool(getattr(light, "use_soft_falloff", True)),
        size=size,
        gi_intensity=gi,
        gi_color=gi_color,
        cast_shadow=bool(getattr(light, "use_shadow", True)),
        shape=str(getattr(light, "shape", "SQUARE")) if kind == "AREA" else "SQUARE",
        spread=float(getattr(light, "spread", math.pi)) if kind == "AREA" else math.pi,
        angle=float(getattr(light, "angle", 0.0)) if kind == "SUN" else 0.0,
    )


# ----------------------------------------------------------------------------------- camera


def render_resolution(scene: bpy.types.Scene) -> tuple[int, int]:
    """Output size in pixels: resolution x percentage / 100 (Blender rounds down, at least 1)."""
    r = scene.render
    pct = r.resolution_percentage / 100.0
    return max(1, int(r.resolution_x * pct)), max(1, int(r.resolution_y * pct))


def light_nodes(ob: bpy.types.Object, notes: list) -> np.ndarray:
    """The (3,) factor a light's node tree (Cycles only, Use Nodes) puts on its emission: the
    Emission shader's colour x strength at the Light Output; inputs that are linked (a
    texture, IES) keep their defaults and are named in ``notes``."""
    light = ob.data
    tree = getattr(light, "node_tree", None)
    if not getattr(light, "use_nodes", False) or tree is None:
        return np.ones(3)
    outs = [n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputLight"]
    out = next((n for n in outs if n.is_active_output), outs[0] if outs else None)
    surface = None if out is None else out.inputs.get("Surface")
    if surface is None or not surface.is_linked:
        return np.zeros(3) if out is not None else np.ones(3)  # Cycles: nothing emitted
    node = surface.links[0].from_node
    while node.bl_idname == "NodeReroute" and node.inputs[0].is_linked:
        node = node.inputs[0].links[0].from_node
    if node.bl_idname != "ShaderNodeEmission":
        notes.append(f"light '{ob.name}': its node tree's '{node.name}' ({node.bl_idname}) is "
                     "not evaluated: the light as if without nodes")
        return np.ones(3)
    linked = [i.name for i in node.inputs if i.name in ("Color", "Strength") and i.is_linked]
    if linked:
        notes.append(f"light '{ob.name}': the Emission node's {' and '.join(linked)} is "
                     "linked, not evaluated: its default value used")
    return (np.array(node.inputs["Color"].default_value[:3], np.float64)
            * float(node.inputs["Strength"].default_value))


def camera_notes(scene: bpy.types.Scene) -> list[str]:
    """What the camera does that LPV GI does not render: depth of field, motion blur."""
    notes = []
    cam = scene.camera
    if cam is not None and getattr(cam.data, "dof", None) is not None and cam.data.dof.use_dof:
        notes.append(f"camera '{cam.name}': depth of field is not rendered (all in focus)")
    if getattr(scene.render, "use_motion_blur", False):
        notes.append("motion blur is not rendered (Render Properties > Motion Blur)")
    return notes


def camera_from_scene(
    depsgraph: bpy.types.Depsgraph,
    scene: bpy.types.Scene,
    resolution: tuple[int, int] | None = None,
) -> core.scene.Camera:
    """The scene camera: view = inverse of its scale-free world matrix, Blender's projection."""
    ob = scene.camera
    if ob is None:
        raise ValueError(f"scene '{scene.name}' has no active camera")
    if not ob.is_evaluated:
        ob = ob.evaluated_get(depsgraph)
    if resolution is None:
        width, height = render_resolution(scene)
    else:
        try:
            width, height = (int(v) for v in resolution)
        except (TypeError, ValueError):
            raise ValueError(f"resolution must be (width, height), got {resolution!r}") from None
    if width < 1 or height < 1:
        raise ValueError(f"resolution must be positive, got {width}x{height}")
    if getattr(ob.data, "type", "PERSP") == "PANO":
        raise ValueError(f"camera '{ob.name}': panoramic cameras are not supported by LPV GI; "
                         "set its Type to Perspective or Orthographic")
    mw = ob.matrix_world
    if not np.isfinite(np.array(mw)).all():
        raise ValueError(f"camera '{ob.name}': non-finite world matrix")
    loc, rot, scale = mw.decompose()
    if min(abs(s) for s in scale) < 1e-12:
        raise ValueError(f"camera '{ob.name}': zero scale, its orientation is undefined")
    rigid = np.eye(4)
    rigid[:3, :3] = np.array(rot.to_matrix())
    rigid[:3, 3] = loc[:]
    view = np.linalg.inv(rigid)
    r = scene.render
    proj = np.array(
        ob.calc_matrix_camera(
            depsgraph, x=width, y=height, scale_x=r.pixel_aspect_x, scale_y=r.pixel_aspect_y
        ),
        np.float64,
    )
    if not np.isfinite(proj).all():
        raise ValueError(f"camera '{ob.name}': non-finite projection (check lens and clipping)")
    return core.scene.Camera(view=view, projection=proj, resolution=(width, height))


# --------------------------------------------------------------------------------- settings


def settings_from_scene(
    scene: bpy.types.Scene, overrides: dict | None = None
) -> core.scene.GISettings:
    """GISettings from ``scene.lpv`` (when registered), then ``overrides`` on top."""
    settings = core.scene.GISettings()
    props = getattr(scene, "lpv", None)
    if props is not None:
        values = {k: getattr(props, k) for k in SCENE_SETTINGS if hasattr(props, k)}
        settings = settings.updated(**values)
    if overrides:
        settings = settings.updated(**overrides)
    return settings
