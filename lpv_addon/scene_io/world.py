"""Blender World -> core World: the radiance arriving from every direction as an equirect map.

A colour (no nodes, or a Background with an unlinked colour) is a 1x1 map; an Environment
Texture (equirectangular or mirror ball, behind an optional Mapping node) is read from its
image's pixels in Python; everything else (the Sky Texture of every type, other node graphs)
is rendered by Cycles itself through an equirectangular camera in a temporary scene, cached by
a digest of the node tree's values in memory and on disk; its Light Path nodes read as for a
diffuse ray (DIFFUSE_RAY), since the map lights surfaces. A Sky Texture's sun disc is far
smaller than a map texel: it is taken out of the map and returned as a SUN light whose
irradiance is measured on Cycles' own render of the disc; an image's (or other graph's) sun,
a compact very bright region of the map, is split off the map as a SUN light too
(lpv_core sky.split_sun).
"""

from __future__ import annotations

import hashlib
import math
import os
import tempfile
from contextlib import contextmanager

import bpy
import numpy as np

from .._core import core

# Map size of a Cycles bake (W, H) and its samples per pixel (camera rays see the world
# directly: the samples only average each texel's footprint); largest map read from an image.
BAKE_SIZE = (128, 64)
BAKE_SAMPLES = 16
MAP_BUDGET = (512, 256)
# Pixels per side and field of view (in sun diameters) of the render that measures a sun disc.
SUN_PIXELS = 32
SUN_FOV = 1.5
SUN_SKIES = ("NISHITA", "SINGLE_SCATTERING", "MULTIPLE_SCATTERING")  # types with a sun disc
MISSING = (1.0, 0.0, 1.0)  # Cycles' colour for a missing texture
# Camera orientation of an equirectangular panorama in Blender's convention (measured: the
# camera's map then matches lpv_core World's u/v, rows top-first in the file).
_PANO_EULER = (math.pi / 2, 0.0, -math.pi / 2)
# What a Light Path node reads in the bake of the lighting map: the World as a diffuse bounce
# off a surface seen by the camera meets it (the camera's own view of the background, Is
# Camera Ray 1, would light the scene with an artist's camera-only branch). Cycles lights a
# diffuse surface by two estimators, MIS-weighted: the BSDF-sampled diffuse ray that reaches
# the background (shade_background.h: the path's flag PATH_RAY_DIFFUSE | PATH_RAY_REFLECT |
# PATH_RAY_EMISSION, bounce 1, diffuse bounce 1) and the World's light sample (light/sample.h
# light_sample_shader_eval: PATH_RAY_EMISSION only, bounce 0). Both give Is Camera Ray 0 and
# Is Shadow Ray 0; where they differ the BSDF ray's value is taken, the strategy whose MIS
# weight dominates for a smooth World under a diffuse surface (cos/pi against the map's pdf):
#   Is Camera Ray 0, Is Shadow Ray 0 (neither estimator sets PATH_RAY_CAMERA / _SHADOW);
#   Is Diffuse Ray 1, Is Reflection Ray 1 (a diffuse reflection; the light sample reads 0);
#   Is Glossy / Singular / Transmission / Volume Scatter Ray 0 (not set by a diffuse bounce);
#   Ray Depth 2 (svm light_path.h: the path's bounce 1, + 1 for a background evaluation,
#   PATH_RAY_EMISSION; the camera's view reads 1, measured; the light sample reads 1);
#   Diffuse Depth 1 (the light sample reads 0); Glossy, Transparent, Transmission Depth 0.
# Ray Length (shader_setup_from_background sets 0) and Portal Depth are the same for every ray
# reaching the background: left as the bake computes them.
DIFFUSE_RAY = {"Is Camera Ray": 0.0, "Is Shadow Ray": 0.0, "Is Diffuse Ray": 1.0,
               "Is Glossy Ray": 0.0, "Is Singular Ray": 0.0, "Is Reflection Ray": 1.0,
               "Is Transmission Ray": 0.0, "Is Volume Scatter Ray": 0.0, "Ray Depth": 2.0,
               "Diffuse Depth": 1.0, "Glossy Depth": 0.0, "Transparent Depth": 0.0,
               "Transmission Depth": 0.0}
_MEMORY: dict[str, tuple] = {}  # digest -> (map, sun) of bakes and image maps
_NOT_DIGEST = frozenset({"location", "location_absolute", "width", "height", "select", "name",
                         "show_options", "show_preview", "hide", "show_texture", "label",
                         "use_custom_color", "color", "parent", "warning_propagation",
                         "rna_type", "dimensions", "type", "internal_links", "inputs",
                         "outputs", "is_active_output", "color_tag", "description"})


class BakeUnavailable(RuntimeError):
    """Blender cannot render the world now (a render is already running)."""


def world_from_blender(world, scene) -> tuple:
    """(core World or None, approximated lines, extra core Lights) for ``world`` as ``scene``
    lights it: the Scene panel's World GI switch and intensity (Scene.lpv) set ``enabled``
    and ``gi_intensity``; a black world (or none) gives None; a Sky Texture's sun disc comes
    back as a SUN light."""
    if world is None:
        return None, [], []
    props = getattr(scene, "lpv", None)
    enabled = bool(getattr(props, "world_gi", True))
    gi = float(getattr(props, "world_gi_intensity", 1.0))
    if not enabled:  # switched off: nothing is read or baked
        return core.scene.World(world.name, gi_intensity=gi, enabled=False), [], []
    notes: list[str] = []
    radiance, sun = _radiance(world, scene, notes)
    radiance = np.nan_to_num(np.asarray(radiance, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    radiance = np.maximum(radiance, 0.0)
    lights = []
    if sun is not None:
        lights.append(_sun_light(world.name, *sun, gi))
        e = float(np.dot(sun[0], core.sky.LUMA))
        notes.append(f"World '{world.name}': its sun ({math.degrees(sun[2]):.2f} deg across, "
                     f"{e / max(e + _light(radiance), 1e-30):.0%} of its light) is the SUN lamp "
                     f"'{lights[-1].name}', out of the World's map")
    if not radiance.max() > 0 and not lights:
        return None, notes, []
    digest = hashlib.sha256(radiance.tobytes() + str(radiance.shape).encode()).hexdigest()
    return (core.scene.World(world.name, radiance=radiance, gi_intensity=gi, enabled=True,
                             digest=digest), notes, lights)


def _radiance(world, scene, notes: list[str]):
    """(map (H, W, 3) rows bottom-first, sun or None) of the world's surface shader."""
    # Blender < 5 keeps a node tree that is off unless use_nodes (deprecated since 5.0).
    tree = world.node_tree if bpy.app.version >= (5, 0, 0) or world.use_nodes else None
    if tree is None:
        return np.array(world.color[:3], np.float32).reshape(1, 1, 3), None
    outputs = [n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputWorld" and not n.mute]
    output = next((n for n in outputs if n.is_active_output), outputs[0] if outputs else None)
    source = None if output is None else _source(output.inputs["Surface"])
    if source is None or source[0] is None:  # unlinked, or a muted shader: black
        return np.zeros((1, 1, 3), np.float32), None
    node = source[0]
    if node.bl_idname == "ShaderNodeBackground" and not node.inputs["Strength"].is_linked:
        strength = float(node.inputs["Strength"].default_value)
        colour = node.inputs["Color"]
        feed = _source(colour)
        if feed is None:
            return np.array(colour.default_value[:3], np.float32).reshape(1, 1, 3) * strength, None
        if feed[0] is not None and feed[0].bl_idname == "ShaderNodeRGB":
            return np.array(feed[1].default_value[:3], np.float32).reshape(1, 1, 3) * strength, None
        if feed[0] is not None and feed[0].bl_idname == "ShaderNodeTexEnvironment" \
                and feed[1].name == "Color":
            env = environment_map(world, feed[0], notes)
            if env is not None:
                sun = env[1] if strength > 0 else None
                return env[0] * np.float32(strength), None if sun is None else (
                    sun[0] * np.float32(strength), *sun[1:])
    return _baked(world, scene, notes)


def _light(radiance: np.ndarray) -> float:
    """The map's luminance integrated over the sphere (sum of radiance x texel solid angle)."""
    r = np.asarray(radiance, np.float64).reshape(np.shape(radiance)[0], -1, 3)
    return float(((r @ core.sky.LUMA) * core.sky.map_directions(*r.shape[:2])[1]).sum())


def _source(socket):
    """(node, output socket) feeding an input, through reroutes and muted nodes' pass-through
    is not followed (a muted node gives None); None if unlinked."""
    for _ in range(64):
        if not socket.is_linked or not socket.links:
            return None
        link = socket.links[0]
        if not link.is_valid or link.is_muted:
            return None
        node = link.from_node
        if node.bl_idname == "NodeReroute":
            socket = node.inputs[0]
            continue
        return (None if node.mute else node), link.from_socket
    return None


# ------------------------------------------------------------------------- environment image


def environment_map(world, node, notes: list[str]) -> tuple | None:
    """(radiance map (H, W, 3), bottom-first, at most MAP_BUDGET, in the World's equirect
    convention and directions, its sun split off; the sun or None) of an Environment Texture;
    None where only Cycles can evaluate its input (then the caller bakes)."""
    mapping = None
    vec = _source(node.inputs["Vector"])
    if vec is not None:
        if vec[0] is None or vec[0].bl_idname != "ShaderNodeMapping":
            if not (vec[0] is not None and vec[0].bl_idname == "ShaderNodeTexCoord"
                    and vec[1].name == "Generated"):
                return None
        else:
            mapping = vec[0]
            feed = _source(mapping.inputs["Vector"])
            if feed is None or feed[0] is None or feed[0].bl_idname != "ShaderNodeTexCoord" \
                    or feed[1].name != "Generated" \
                    or any(s.is_linked for s in mapping.inputs[1:] if s.enabled):
                return None
    image = node.image
    if image is None or not image.has_data and not _load(image):
        notes.append(f"World '{world.name}': Environment Texture '{node.name}' has no image "
                     f"({'none set' if image is None else image.filepath}); lit magenta, "
                     "as Cycles renders it")
        return np.array(MISSING, np.float32).reshape(1, 1, 3), None
    key = "|".join(map(str, (image.name, image.filepath, tuple(image.size), image.is_float,
                             image.colorspace_settings.name, node.projection,
                             _values(mapping) if mapping else "")))
    if key in _MEMORY:
        return _MEMORY[key]
    pixels = _image_pixels(image, world, notes)
    if mapping is None and node.projection == "EQUIRECTANGULAR":
        out = _area_resample(pixels, MAP_BUDGET)
    else:
        src = _area_resample(pixels, (2 * MAP_BUDGET[0], 2 * MAP_BUDGET[1]))
        w = min(MAP_BUDGET[0], max(8, pixels.shape[1]))
        out = _lookup(src, _mapped(_directions(w, max(4, w // 2)), mapping, world, notes),
                      node.projection)
    _MEMORY[key] = core.sky.split_sun(out)  # on the final, world-space map
    return _MEMORY[key]


def _load(image) -> bool:
    try:
        image.pixels[0]  # loads the file's pixels
    except (IndexError, RuntimeError):
        return False
    return bool(image.has_data) and image.size[0] > 0


def _image_pixels(image, world, notes: list[str]) -> np.ndarray:
    """Linear RGB (h, w, 3) float32, rows bottom-first as Blender stores them."""
    w, h = image.size[:]
    c = image.channels
    px = np.empty(w * h * c, np.float32)
    image.pixels.foreach_get(px)
    px = px.reshape(h, w, c)[..., :3] if c >= 3 else np.repeat(px.reshape(h, w, c)[..., :1], 3, 2)
    space = image.colorspace_settings.name
    if not image.is_float and space == "sRGB":
        px = np.where(px <= 0.04045, px / 12.92, ((np.maximum(px, 0) + 0.055) / 1.055) ** 2.4)
    elif not image.is_float and space not in ("Linear Rec.709", "Linear", "Non-Color", "Raw"):
        notes.append(f"World '{world.name}': image '{image.name}' in colour space '{space}' "
                     "read as sRGB")
        px = np.where(px <= 0.04045, px / 12.92, ((np.maximum(px, 0) + 0.055) / 1.055) ** 2.4)
    return np.nan_to_num(px.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)


def _area_resample(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Box-average ``img`` (h, w, 3) down to at most ``size`` (W, H): every source pixel lands
    in exactly one output texel, so the map's total light is kept."""
    h, w = img.shape[:2]
    ow, oh = min(w, size[0]), min(h, size[1])
    if (ow, oh) == (w, h):
        return img.astype(np.float32)
    xs = np.linspace(0, w, ow + 1).round().astype(int)[:-1]
    ys = np.linspace(0, h, oh + 1).round().astype(int)[:-1]
    sums = np.add.reduceat(np.add.reduceat(img.astype(np.float64), ys, axis=0), xs, axis=1)
    counts = np.outer(np.diff(np.append(ys, h)), np.diff(np.append(xs, w)))
    return (sums / counts[..., None]).astype(np.float32)


def _directions(w: int, h: int) -> np.ndarray:
    """Unit directions (h, w, 3) through the texel centres of an equirect map, bottom-first."""
    u = (np.arange(w) + 0.5) / w
    v = (np.arange(h) + 0.5) / h
    phi = (0.5 - u)[None, :] * 2.0 * np.pi
    el = (v - 0.5)[:, None] * np.pi
    return np.stack([np.cos(el) * np.cos(phi), np.cos(el) * np.sin(phi),
                     np.sin(el) * np.ones_like(phi)], -1)


def _euler(rot) -> np.ndarray:
    """Blender's XYZ Euler rotation matrix (Rz Ry Rx)."""
    (cx, cy, cz), (sx, sy, sz) = np.cos(rot), np.sin(rot)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _mapped(d: np.ndarray, mapping, world, notes: list[str]) -> np.ndarray:
    """Directions after the Mapping node, as Cycles' svm_mapping applies it per vector type."""
    if mapping is None:
        return d
    kind = mapping.vector_type
    rot = _euler(np.array(mapping.inputs["Rotation"].default_value[:3], np.float64))
    scale = np.array(mapping.inputs["Scale"].default_value[:3], np.float64)
    loc_socket = mapping.inputs.get("Location")
    loc = np.zeros(3) if loc_socket is None or not loc_socket.enabled else \
        np.array(loc_socket.default_value[:3], np.float64)
    safe = np.where(scale != 0, scale, 1.0)
    if kind == "POINT":
        out = (d * scale) @ rot.T + loc
    elif kind == "TEXTURE":
        out = ((d - loc) @ rot) / safe
    elif kind == "VECTOR":
        out = (d * scale) @ rot.T
    else:  # NORMAL
        out = (d / safe) @ rot.T
    if np.any(loc != 0) and kind in ("POINT", "TEXTURE"):
        notes.append(f"World '{world.name}': Mapping '{mapping.name}' location shifts "
                     "directions; applied before normalising, as Cycles looks them up")
    return out


def _lookup(src: np.ndarray, d: np.ndarray, projection: str) -> np.ndarray:
    """Bilinear lookup of map ``src`` (bottom-first) along directions ``d`` (..., 3)."""
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    d = d / np.where(n > 0, n, 1.0)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    if projection == "MIRROR_BALL":  # Cycles' direction_to_mirrorball
        y1 = y - 1.0
        div = 2.0 * np.sqrt(np.maximum(-0.5 * y1, 0.0))
        div = np.where(div > 0, div, 1.0)
        u, v = 0.5 * (x / div + 1.0), 0.5 * (z / div + 1.0)
    else:
        u = 0.5 - np.arctan2(y, x) / (2.0 * np.pi)
        v = 0.5 + np.arcsin(np.clip(z, -1.0, 1.0)) / np.pi
    h, w = src.shape[:2]
    fx, fy = u * w - 0.5, np.clip(v * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(fx).astype(int), np.floor(fy).astype(int)
    tx, ty = (fx - x0)[..., None], (fy - y0)[..., None]
    y1i = np.minimum(y0 + 1, h - 1)
    wrap = (lambda i: i % w) if projection != "MIRROR_BALL" else (lambda i: np.clip(i, 0, w - 1))
    a, b = src[y0, wrap(x0)], src[y0, wrap(x0 + 1)]
    c, e = src[y1i, wrap(x0)], src[y1i, wrap(x0 + 1)]
    return ((a * (1 - tx) + b * tx) * (1 - ty) + (c * (1 - tx) + e * tx) * ty).astype(np.float32)


# ------------------------------------------------------------------------------ Cycles bake


def _values(node, depth: int = 0) -> str:
    """The settings of a node that change what it computes (no layout), as text."""
    parts = [node.bl_idname, str(node.mute)]
    for p in node.bl_rna.properties:
        ident = p.identifier
        if ident in _NOT_DIGEST or ident.startswith("bl_") or p.is_readonly and \
                p.type != "POINTER":
            continue
        value = getattr(node, ident, None)
        if p.type == "POINTER":
            if isinstance(value, bpy.types.Image):
                value = (value.name, value.filepath, tuple(value.size), value.source)
            elif isinstance(value, bpy.types.NodeTree) and depth < 8:
                value = tree_digest(value, depth + 1)
            else:
                value = getattr(value, "name", None)
        elif p.type in ("FLOAT", "INT", "BOOLEAN") and getattr(p, "array_length", 0):
            value = tuple(value)
        parts.append(f"{ident}={value}")
    for s in node.inputs:
        dv = getattr(s, "default_value", None)
        dv = tuple(dv) if hasattr(dv, "__len__") and not isinstance(dv, str) else dv
        parts.append(f"{s.identifier}:{s.is_linked}:{s.enabled}:{dv}")
    return ";".join(parts)


def tree_digest(tree, depth: int = 0) -> str:
    """A digest of a node tree's values and links (what a Cycles render of it depends on)."""
    h = hashlib.sha256()
    for node in sorted(tree.nodes, key=lambda n: n.name):
        h.update(f"{node.name}|{_values(node, depth)}\n".encode())
    for link in tree.links:
        h.update(f"{link.from_node.name}.{link.from_socket.identifier}>{link.to_node.name}."
                 f"{link.to_socket.identifier}:{link.is_muted}\n".encode())
    return h.hexdigest()


def world_digest(world, scene) -> str:
    """Key of a world's bake: its node tree's digest, the frame (animated values), the bake
    size and Blender's version."""
    return hashlib.sha256("|".join(map(str, (
        tree_digest(world.node_tree), scene.frame_current, BAKE_SIZE, BAKE_SAMPLES,
        sorted(DIFFUSE_RAY.items()),
        SUN_PIXELS, SUN_FOV, core.sky.SUN_MAX_DIAMETER, core.sky.SUN_MIN_SHARE,
        bpy.app.version))).encode()).hexdigest()[:32]


def cache_dir() -> str:
    """Where bakes are kept: $LPV_GI_CACHE_DIR, else the extension's user folder, else (a
    source tree) the system's temporary folder."""
    root = os.environ.get("LPV_GI_CACHE_DIR")
    ext = (__package__ or "").rpartition(".lpv_addon")[0]
    if not root and ext.startswith("bl_ext."):
        try:
            root = bpy.utils.extension_path_user(ext, path="cache", create=True)
        except (OSError, ValueError):
            root = None
    path = os.path.join(root or os.path.join(tempfile.gettempdir(), "lpv_gi_cache"), "world")
    os.makedirs(path, exist_ok=True)
    return path


def _baked(world, scene, notes: list[str]):
    """(map, sun) of a world only Cycles evaluates: from memory, disk, or a new bake; else a
    uniform map of the world's viewport colour, reported."""
    world = world.original if getattr(world, "original", None) is not None else world
    if _reads_light_path(world.node_tree):
        notes.append(f"World '{world.name}': its Light Path node reads as for a diffuse ray "
                     "(Is Camera Ray 0) in the World's lighting map; the camera sees the "
                     "lighting map as the background, not the graph's camera branch")
    digest = world_digest(world, scene)
    if digest in _MEMORY:
        return _MEMORY[digest]
    path = os.path.join(cache_dir(), f"{digest}.npz")
    try:
        with np.load(path) as data:
            sun = None if data["sun"].size == 0 else (data["sun"][:3], data["sun"][3:6],
                                                      float(data["sun"][6]))
            _MEMORY[digest] = (data["map"], sun)
            return _MEMORY[digest]
    except (OSError, KeyError, ValueError):
        pass
    try:
        result = bake(world, scene)
    except BakeUnavailable as exc:
        notes.append(f"World '{world.name}': not baked ({exc}); lit as a uniform world of its "
                     f"viewport colour {tuple(round(c, 3) for c in world.color[:3])}")
        return np.array(world.color[:3], np.float32).reshape(1, 1, 3), None
    if result[1] is None:  # no Sky Texture disc: the graph's own sun, if any (an image's)
        result = core.sky.split_sun(result[0])
    _MEMORY[digest] = result
    sun = np.zeros(0) if result[1] is None else np.concatenate(
        [result[1][0], result[1][1], [result[1][2]]])
    tmp = f"{path}.{os.getpid()}.tmp.npz"
    np.savez(tmp, map=result[0], sun=sun)
    os.replace(tmp, path)
    return result


def bake(world, scene) -> tuple:
    """Render ``world`` with Cycles: (equirect map (H, W, 3) bottom-first without sun discs,
    sun (rgb irradiance W/m^2, unit direction to the sun, angular diameter) or None). Works
    on a temporary copy of the world in a temporary scene, all removed afterwards; raises
    BakeUnavailable where Blender refuses to render (inside another render)."""
    if bpy.app.is_job_running("RENDER"):
        raise BakeUnavailable("a render is running")
    copy = world.copy()
    if hasattr(copy, "cycles"):  # camera rays only: no light importance map (1-3 s per render)
        copy.cycles.sampling_method = "NONE"
    groups: list = []  # the copy's own copies of node groups holding a Light Path node
    skies = [n for n in _nodes(copy.node_tree) if n.bl_idname == "ShaderNodeTexSky"
             and n.sky_type in SUN_SKIES and n.sun_disc and not n.mute and n.sun_size > 0]
    try:
        _as_diffuse_ray(copy.node_tree, groups)
        with _temporary_scene(copy, scene.frame_current) as (sc, cam):
            for n in skies:
                n.sun_disc = False
            cam.data.type = "PANO"
            cam.data.panorama_type = "EQUIRECTANGULAR"
            cam.rotation_euler = _PANO_EULER
            radiance = _render(sc, BAKE_SIZE, BAKE_SAMPLES)[::-1]
            sun = None
            if skies:
                sun = _measure_sun(sc, cam, skies)
    finally:
        bpy.data.worlds.remove(copy)
        for g in groups:
            bpy.data.node_groups.remove(g)
    return np.ascontiguousarray(radiance), sun


def _nodes(tree, depth: int = 0):
    for n in tree.nodes:
        yield n
        if getattr(n, "node_tree", None) is not None and depth < 8:
            yield from _nodes(n.node_tree, depth + 1)


def _reads_light_path(tree) -> bool:
    """Whether a Light Path node (not muted) of ``tree`` or its groups feeds anything."""
    return tree is not None and any(
        n.bl_idname == "ShaderNodeLightPath" and not n.mute
        and any(o.is_linked for o in n.outputs) for n in _nodes(tree))


def _as_diffuse_ray(tree, groups: list, depth: int = 0) -> None:
    """Replace, in ``tree`` (a temporary copy's), every linked Light Path output of
    DIFFUSE_RAY by a Value node of that constant; a group holding one is copied first (into
    ``groups``, for the caller to remove) so the user's group is never touched."""
    for node in list(tree.nodes):
        sub = getattr(node, "node_tree", None)
        if sub is not None and depth < 8 and _reads_light_path(sub):
            node.node_tree = sub = sub.copy()
            groups.append(sub)
            _as_diffuse_ray(sub, groups, depth + 1)
        if node.bl_idname != "ShaderNodeLightPath" or node.mute:
            continue
        for out in node.outputs:
            if out.name not in DIFFUSE_RAY or not out.is_linked:
                continue
            value = tree.nodes.new("ShaderNodeValue")
            value.outputs[0].default_value = DIFFUSE_RAY[out.name]
            for link in list(out.links):
                muted = link.is_muted
                tree.links.new(value.outputs[0], link.to_socket).is_muted = muted


def sun_direction(elevation: float, rotation: float) -> np.ndarray:
    """Unit direction to a Sky Texture's sun: elevation above the horizon, rotation from +Y
    towards +X (measured on Cycles' render of the disc: the brightest texel of a 512x256 bake
    lies along this direction)."""
    ce = math.cos(elevation)
    return np.array([ce * math.sin(rotation), ce * math.cos(rotation), math.sin(elevation)])


def _measure_sun(sc, cam, skies) -> tuple | None:
    """The first sky's sun disc as (rgb irradiance normal to it, direction, diameter): a
    perspective render looking at the disc, the sky around it (beyond 0.6 diameters from its
    centre: the disc is 1e5 times brighter, so the sky under it hardly matters) taken off,
    the rest integrated over each pixel's solid angle."""
    from mathutils import Vector

    sky = skies[0]
    size = float(sky.sun_size)
    d = sun_direction(float(sky.sun_elevation), float(sky.sun_rotation))
    fov = SUN_FOV * size
    cam.data.type = "PERSP"
    cam.data.sensor_fit = "HORIZONTAL"
    cam.data.angle = fov
    cam.rotation_euler = Vector(d).to_track_quat("-Z", "Y").to_euler()
    for n in skies:
        n.sun_disc = True
    on = _render(sc, (SUN_PIXELS, SUN_PIXELS), BAKE_SAMPLES).astype(np.float64)
    half = math.tan(fov / 2)
    c = (np.arange(SUN_PIXELS) + 0.5) / SUN_PIXELS * 2 * half - half
    r2 = c[None, :] ** 2 + c[:, None] ** 2
    omega = (2 * half / SUN_PIXELS) ** 2 / (1 + r2) ** 1.5
    around = np.arctan(np.sqrt(r2)) > 0.6 * size
    disc = np.maximum(on - on[around].mean(axis=0), 0.0) * ~around[..., None]
    irradiance = (disc * omega[..., None]).sum(axis=(0, 1))
    if not irradiance.max() > 0:
        return None
    return irradiance.astype(np.float32), d, size


@contextmanager
def _temporary_scene(world, frame: int):
    """A scene of its own with ``world``, a camera and Cycles settings; removed afterwards."""
    sc = bpy.data.scenes.new("LPV GI world bake")
    cam = bpy.data.objects.new("LPV GI world bake", bpy.data.cameras.new("LPV GI world bake"))
    try:
        sc.world = world
        sc.frame_current = frame
        sc.collection.objects.link(cam)
        sc.camera = cam
        r, c = sc.render, sc.cycles
        r.engine = "CYCLES"
        for attr, value in (("device", "CPU"), ("use_denoising", False),
                            ("use_adaptive_sampling", False), ("pixel_filter_type", "BOX"),
                            ("max_bounces", 0), ("seed", 0)):
            setattr(c, attr, value)
        r.filter_size = 1.0
        r.resolution_percentage = 100
        r.film_transparent = False
        r.use_compositing = r.use_sequencer = False
        r.image_settings.file_format = "OPEN_EXR"
        r.image_settings.color_depth = "32"
        r.use_file_extension = False
        yield sc, cam
    finally:
        data = cam.data
        bpy.data.objects.remove(cam)
        bpy.data.cameras.remove(data)
        bpy.data.scenes.remove(sc)


def _render(sc, size: tuple[int, int], samples: int) -> np.ndarray:
    """Render ``sc`` at ``size`` into a temporary EXR: (H, W, 3) float32, rows top-first."""
    sc.render.resolution_x, sc.render.resolution_y = size
    sc.cycles.samples = samples
    fd, path = tempfile.mkstemp(prefix="lpv_world_", suffix=".exr")
    os.close(fd)
    try:
        sc.render.filepath = path
        try:
            bpy.ops.render.render(write_still=True, scene=sc.name)
        except RuntimeError as exc:
            raise BakeUnavailable(str(exc).strip().splitlines()[-1]) from exc
        img = core.render.exr.read_multilayer(path)["Combined"][..., :3]
    finally:
        os.unlink(path)
    if img.shape[:2] != (size[1], size[0]):
        raise BakeUnavailable(f"the render gave {img.shape[1]}x{img.shape[0]} pixels")
    return img.astype(np.float32)


def _sun_light(world_name: str, irradiance, direction, size: float, gi: float):
    """A SUN core Light shining along -direction with the disc's irradiance and diameter."""
    z = np.asarray(direction, np.float64)
    x = np.cross((0.0, 0.0, 1.0) if abs(z[2]) < 0.99 else (1.0, 0.0, 0.0), z)
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = x, np.cross(z, x), z
    e = np.asarray(irradiance, np.float64)
    power = float(e.max())
    return core.scene.Light(name=f"{world_name} sun", type="SUN", matrix=m,
                            color=(e / power).astype(np.float32), power=power,
                            angle=float(size), gi_intensity=gi)
