"""Cached Cycles references: a scene content hash and where its reference lives.

:func:`scene_hash` digests what the picture depends on (geometry, materials, lights, camera,
world, resolution) straight from bpy data, so cached references (:func:`reference_path`)
follow content, never file names or mtimes. The render itself is the add-on's
(lpv_addon/render/cycles.py: render_cycles_passes).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path
from typing import Any

import bpy
import numpy as np

from lpv_addon.render.cycles import default_view_layer

__all__ = ["HASH_VERSION", "reference_path", "scene_hash"]

# Bump when the hashed content or the render recipe changes meaning (invalidates caches).
HASH_VERSION = 1


def reference_path(
    cache_dir: str | os.PathLike, blend_or_scene_hash: str, samples: int, bounces: int
) -> Path:
    """Where the cached reference for a scene content hash (:func:`scene_hash`) lives.

    The name carries the hash, samples and bounces; the resolution is part of the hash.
    """
    h = str(blend_or_scene_hash)
    if not re.fullmatch(r"[0-9a-f]{16,128}", h):
        raise ValueError(f"expected a hex scene hash from scene_hash(), got {h!r}")
    return Path(cache_dir) / f"ref_{h[:20]}_s{int(samples)}_b{int(bounces)}.exr"


# ---------------------------------------------------------------------------------------------
# Scene content hash
# ---------------------------------------------------------------------------------------------

# Never part of the content: identity, bookkeeping, deprecated accessors.
_SKIP_PROPS = frozenset({
    "rna_type", "name", "name_full", "tag", "is_runtime_data", "use_fake_user",
    "use_extra_user", "asset_data", "use_nodes", "is_evaluated", "original", "users",
    "session_uid", "is_editmode", "is_override_data", "library", "library_weak_reference",
    "override_library", "preview", "id_type", "is_embedded_data", "is_missing",
    "is_library_indirect", "animation_data",
})
# Display-only settings (viewport overlays, camera guides).
_SKIP_PREFIXES = ("bl_", "show_", "display_", "composition_", "passepartout")
# Node editor state that does not change the picture.
_SKIP_NODE_PROPS = _SKIP_PROPS | {
    "location", "location_absolute", "width", "height", "dimensions", "hide", "select",
    "show_options", "show_preview", "show_texture", "use_custom_color", "color", "color_tag",
    "label", "parent", "warning_propagation", "mute", "is_active_output", "internal_links",
    "inputs", "outputs",
}
_OBJECT_PROPS = (
    "type", "hide_render", "visible_camera", "visible_diffuse", "visible_glossy",
    "visible_transmission", "visible_volume_scatter", "visible_shadow", "is_holdout",
    "is_shadow_catcher", "instance_type",
)


def _plain(value: Any) -> Any:
    """JSON-able, deterministic form of an RNA value (floats exact via repr in json)."""
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    if isinstance(value, float):
        return float(value)
    if isinstance(value, (set, frozenset)):
        return sorted(value)
    if isinstance(value, bpy.types.ID):
        return ["ID", type(value).__name__, value.name]
    try:
        return [_plain(v) for v in value]
    except TypeError:
        return repr(value)


def _rna(struct: Any, depth: int = 1, skip: frozenset[str] = _SKIP_PROPS) -> dict:
    """Every editable plain property of an RNA struct (nested non-ID structs to ``depth``)."""
    out: dict[str, Any] = {}
    if struct is None:
        return out
    for prop in struct.bl_rna.properties:
        ident = prop.identifier
        if ident in skip or ident.startswith(_SKIP_PREFIXES):
            continue
        try:
            if prop.type == "POINTER":
                sub = getattr(struct, ident)
                if sub is None or isinstance(sub, bpy.types.ID):
                    out[ident] = _plain(sub)
                elif depth > 0:
                    out[ident] = _rna(sub, depth - 1, skip)
                continue
            if prop.type == "COLLECTION" or prop.is_readonly:
                continue
            out[ident] = _plain(getattr(struct, ident))
        except (AttributeError, RuntimeError, TypeError, ValueError):
            out[ident] = "<unreadable>"  # context-dependent property: same in every run
    return out


def _node_tree(tree: bpy.types.NodeTree | None, seen: set[str] | None = None) -> Any:
    """Nodes (type, settings, unlinked input values) and links of a node tree, sorted."""
    if tree is None:
        return None
    seen = set() if seen is None else seen
    if tree.name in seen:
        return ["cycle", tree.name]
    seen = seen | {tree.name}
    nodes = []
    for node in sorted(tree.nodes, key=lambda n: n.name):
        inputs = []
        for sock in node.inputs:
            val = getattr(sock, "default_value", None) if not sock.is_linked else "linked"
            inputs.append([sock.identifier, _plain(val)])
        entry: dict[str, Any] = {
            "name": node.name,
            "type": node.bl_idname,
            "props": _rna(node, depth=0, skip=_SKIP_NODE_PROPS),
            "inputs": inputs,
        }
        sub = getattr(node, "node_tree", None)
        if sub is not None:
            entry["group"] = _node_tree(sub, seen)
        image = getattr(node, "image", None)
        if image is not None:
            entry["image"] = [image.filepath, list(image.size), image.source]
        nodes.append(entry)
    links = sorted(
        [lk.from_node.name, lk.from_socket.identifier, lk.to_node.name, lk.to_socket.identifier]
        for lk in tree.links
        if not lk.is_muted
    )
    return {"nodes": nodes, "links": links}


def _material(mat: bpy.types.Material | None) -> Any:
    if mat is None:
        return None
    return {
        "diffuse_color": _plain(mat.diffuse_color),
        "tree": _node_tree(getattr(mat, "node_tree", None)),
    }


def _mesh_digest(mesh: bpy.types.Mesh) -> str:
    """sha256 of positions, face corners, face sizes and per-face attributes that shade."""
    h = hashlib.sha256()
    nv, nl, npoly = len(mesh.vertices), len(mesh.loops), len(mesh.polygons)
    h.update(np.array([nv, nl, npoly], np.int64).tobytes())
    co = np.empty(nv * 3, np.float32)
    mesh.vertices.foreach_get("co", co)
    h.update(co.tobytes())
    corner = np.empty(nl, np.int32)
    mesh.loops.foreach_get("vertex_index", corner)
    h.update(corner.tobytes())
    sizes = np.empty(npoly, np.int32)
    mesh.polygons.foreach_get("loop_total", sizes)
    h.update(sizes.tobytes())
    for name in ("material_index", "sharp_face"):
        attr = mesh.attributes.get(name)
        if attr is not None and attr.domain == "FACE":
            vals = np.empty(npoly, np.int32 if name == "material_index" else bool)
            attr.data.foreach_get("value", vals)
            h.update(name.encode() + vals.tobytes())
    return h.hexdigest()


def scene_hash(scene: bpy.types.Scene | None = None) -> str:
    """Deterministic sha256 of what a reference render of ``scene`` depends on.

    Covers render-visible objects (world matrix, ray visibility, mesh geometry, modifiers,
    materials and their node trees), lights and cameras (every editable setting), the world,
    the active camera, resolution/pixel aspect/border, the frame, Blender's version and
    HASH_VERSION. Names of objects and data are left out; order of objects does not matter.
    """
    scene = scene or bpy.context.scene
    # World matrices are only current after an evaluation (a moved object keeps its old
    # matrix_world until then).
    default_view_layer(scene).update()
    objects = []
    for ob in scene.objects:
        if ob.hide_render:
            continue
        entry: dict[str, Any] = {k: _plain(getattr(ob, k, None)) for k in _OBJECT_PROPS}
        entry["matrix"] = [list(map(float, row)) for row in ob.matrix_world]
        entry["modifiers"] = [
            [m.type, _rna(m, depth=0)] for m in ob.modifiers if m.show_render
        ]
        data = ob.data
        if ob.type == "MESH":
            entry["mesh"] = _mesh_digest(data)
            entry["materials"] = [
                _material(slot.material) for slot in ob.material_slots
            ]
        elif ob.type == "LIGHT":
            entry["light"] = _rna(data, depth=1)
            entry["light_tree"] = _node_tree(getattr(data, "node_tree", None))
        elif ob.type == "CAMERA":
            entry["camera"] = _rna(data, depth=1)
            entry["active"] = ob == scene.camera
        elif data is not None:
            entry["data"] = _rna(data, depth=0)
        objects.append(json.dumps(entry, sort_keys=True))
    r = scene.render
    world = scene.world
    content = {
        "version": HASH_VERSION,
        "blender": bpy.app.version_string,
        "objects": sorted(objects),
        "world": None if world is None else {
            "color": _plain(world.color), "tree": _node_tree(getattr(world, "node_tree", None))
        },
        "render": {
            k: _plain(getattr(r, k))
            for k in (
                "resolution_x", "resolution_y", "resolution_percentage", "pixel_aspect_x",
                "pixel_aspect_y", "use_border", "border_min_x", "border_min_y",
                "border_max_x", "border_max_y", "film_transparent",
            )
        },
        "frame": scene.frame_current,
        "camera": None if scene.camera is None else _plain(
            [list(map(float, row)) for row in scene.camera.matrix_world]
        ),
    }
    blob = json.dumps(content, sort_keys=True, default=repr).encode()
    return hashlib.sha256(blob).hexdigest()
