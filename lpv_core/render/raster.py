"""Triangle rasterisation with moderngl: world position, normal and colours per pixel.

One routine serves the reflective shadow maps (a light's view) and the camera G-buffer.
Normals are flipped to face the viewer (Blender's surfaces are two-sided for diffuse light).
The OpenGL context is a standalone one (EGL headless) owned by this process; inside
Blender's UI process use the worker (see worker.py) instead, never this module directly.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ..scene import textures
from ..scene.model import HIDDEN_FROM_CAMERA

_CTX = None

# Hashed alpha [Wyman & McGuire 2017, with the PCG3D integer hash of Jarzynski & Olano 2020]:
# a fragment of a triangle of coverage v_alpha < 1 is kept with that probability, from a hash
# of its pixel and its triangle; the antialias samples of a pixel (``seed`` of ``samples``)
# take turns over strata of that hash, so that their mean is the coverage within 1 / samples
# (and a shadow map's filter sees it).
HASHED_ALPHA = """
uniform uint seed;
uniform uint samples;
uniform sampler2DArray alpha_maps;
flat in float v_alpha;
flat in float v_layer;  // its alpha map's layer (-1: none)
in vec2 v_uv;
bool hashed_out() {
    float a = v_alpha;
    if (v_layer >= 0.0) a *= texture(alpha_maps, vec3(fract(v_uv), v_layer)).r;
    if (a >= 1.0) return false;
    uvec3 k = uvec3(uvec2(gl_FragCoord.xy), uint(gl_PrimitiveID));
    k = k * 1664525u + 1013904223u;
    k.x += k.y * k.z; k.y += k.z * k.x; k.z += k.x * k.y;
    k ^= k >> 16u;
    k.x += k.y * k.z; k.y += k.z * k.x; k.z += k.x * k.y;
    float h = float(k.x >> 8u) * (1.0 / 16777216.0);
    return fract(h + float(seed) / float(max(samples, 1u))) >= a;
}
"""

# A tangent-space normal map, as Cycles' Normal Map node: the texel t in 0-1 read as
# 2 t - 1 along (T, B, N), B = sign x cross(N, T) (T made perpendicular to the interpolated
# normal N), then moved from N by Strength; the side facing the viewer is taken after it, as
# Cycles flips the mapped normal of a back face.
NORMAL_MAP = """
uniform sampler2DArray normal_maps;
uniform int normal_mapped;  // 0: no normal maps uploaded (in_tan, in_nmap unbound)
in vec4 v_tan;
flat in vec2 v_nmap;  // layer (-1: none), Strength
vec3 mapped(vec3 n) {
    if (normal_mapped == 0 || v_nmap.x < 0.0) return n;
    vec3 t = v_tan.xyz - n * dot(n, v_tan.xyz);
    if (dot(t, t) < 1e-12) return n;
    t = normalize(t);
    vec3 c = 2.0 * texture(normal_maps, vec3(fract(v_uv), v_nmap.x)).rgb - 1.0;
    vec3 m = c.x * t + c.y * (v_tan.w < 0.0 ? -1.0 : 1.0) * cross(n, t) + c.z * n;
    if (dot(m, m) < 1e-12) return n;
    m = n + (normalize(m) - n) * v_nmap.y;
    return dot(m, m) < 1e-12 ? n : normalize(m);
}
"""

# A triangle's in_recv: bit 0 receives GI, bits 1-3 its ray visibility (scene.model:
# HIDDEN_FROM_CAMERA, CASTS_NO_SHADOW, HOLDOUT, shifted up by one). A pass leaves out the
# triangles whose bits meet its ``hide`` mask: all three corners outside the clip volume.
VERTEX_SHADER = """
#version 330
uniform mat4 view_proj;
uniform int hide;
in vec3 in_pos;
in vec3 in_nrm;
in vec3 in_alb;
in vec3 in_refl;
in float in_recv;
in float in_alpha;
in float in_trans;
in vec2 in_uv;
in float in_layer;
in vec4 in_tan;
in vec2 in_nmap;
out vec3 v_pos;
out vec3 v_nrm;
out vec3 v_alb;
out vec3 v_refl;
flat out int v_code;
flat out float v_alpha;
flat out float v_trans;
flat out float v_layer;
out vec2 v_uv;
out vec4 v_tan;
flat out vec2 v_nmap;
void main() {
    v_tan = in_tan;
    v_nmap = in_nmap;
    v_alpha = in_alpha;
    v_layer = in_layer;
    v_uv = in_uv;
    v_trans = in_trans;
    v_pos = in_pos;
    v_nrm = in_nrm;
    v_alb = in_alb;
    v_refl = in_refl;
    v_code = int(in_recv + 0.5);
    gl_Position = (v_code & hide) != 0 ? vec4(0.0, 0.0, 2.0, 1.0)
                                       : view_proj * vec4(in_pos, 1.0);
}
"""

FRAGMENT_SHADER = """
#version 330
""" + HASHED_ALPHA + """
uniform vec3 eye;        // viewer position (perspective)
uniform vec3 view_dir;   // viewing direction (orthographic)
uniform int ortho;
uniform vec3 origin;     // subtracted from positions to keep precision far from the origin
in vec3 v_pos;
in vec3 v_nrm;
in vec3 v_alb;
in vec3 v_refl;
flat in int v_code;
flat in float v_trans;
layout(location = 0) out vec4 o_pos;
layout(location = 1) out vec4 o_nrm;
layout(location = 2) out vec4 o_alb;
layout(location = 3) out vec4 o_refl;
""" + NORMAL_MAP + """
void main() {
    if (hashed_out()) discard;
    vec3 n = normalize(v_nrm);
    vec3 to_eye = ortho == 1 ? -view_dir : eye - v_pos;
    n = dot(n, to_eye) < 0.0 ? -mapped(n) : mapped(n);
    o_pos = vec4(v_pos - origin, 1.0);
    // w: the translucency (0-1), or 2 for a holdout (Object.is_holdout)
    o_nrm = vec4(n, ((v_code >> 3) & 1) != 0 ? 2.0 : v_trans);
    o_alb = vec4(v_alb, float(v_code & 1));  // alpha: receives GI (Object.lpv.gi_receiver)
    o_refl = vec4(v_refl, 1.0);
}
"""


# The reflective shadow map's own pass: position (the main pass's expression, the same bits),
# the geometric normal (its length the shading normal's gain on the reflected light, at most
# 20: the surfel area's 1 / 0.05 cap) and the triangle's index (gl_PrimitiveID, split into two
# exactly representable floats) instead of a reflectance target: two targets instead of four.
# The reflectance comes from the uploaded per-triangle table (the main pass's target
# interpolates it: 0.8 reads 0.79999995).
RSM_VERTEX_SHADER = """
#version 330
uniform mat4 view_proj;
uniform int hide;
in vec3 in_pos;
in vec3 in_nrm;
in float in_recv;
in float in_alpha;
in vec2 in_uv;
in float in_layer;
out vec3 v_pos;
out vec3 v_nrm;
flat out float v_alpha;
flat out float v_layer;
out vec2 v_uv;
void main() {
    v_alpha = in_alpha;
    v_layer = in_layer;
    v_uv = in_uv;
    v_pos = in_pos;
    v_nrm = in_nrm;
    gl_Position = (int(in_recv + 0.5) & hide) != 0 ? vec4(0.0, 0.0, 2.0, 1.0)
                                                   : view_proj * vec4(in_pos, 1.0);
}
"""

RSM_FRAGMENT_SHADER = """
#version 330
#define SHADING_GAIN_MAX 20.0
""" + HASHED_ALPHA + """
uniform vec3 eye;
uniform vec3 view_dir;
uniform int ortho;
in vec3 v_pos;
in vec3 v_nrm;
layout(location = 0) out vec4 o_pos;  // w: 1 + triangle index / 2^24 (coverage: w > 0.5)
layout(location = 1) out vec4 o_nrm;  // w: triangle index % 2^24
void main() {
    if (hashed_out()) discard;
    vec3 s = normalize(v_nrm);
    vec3 n = cross(dFdx(v_pos), dFdy(v_pos));
    n = dot(n, n) > 0.0 ? normalize(n) : s;
    vec3 to_eye = normalize(ortho == 1 ? -view_dir : eye - v_pos);
    if (dot(n, to_eye) < 0.0) n = -n;
    // the shading normal on the lit side: the geometric normal's, or where it lies in the
    // surface's plane (custom normals), the side the triangle's winding faces (Cycles flips it
    // with the face)
    float side = dot(s, n);
    if (abs(side) < 1e-3 ? !gl_FrontFacing : side < 0.0) s = -s;
    // the light a diffuse surface reflects goes by its shading normal's cosine and leaves
    // around its geometric normal (Cycles): the normal out is the geometric one, its length
    // the reflected share over the geometric cosine (1 where they are one)
    float f = max(dot(s, to_eye), 0.0) / max(dot(n, to_eye), 1e-9);
    o_pos = vec4(v_pos, float(1 + (gl_PrimitiveID >> 24)));
    o_nrm = vec4(n * min(f, SHADING_GAIN_MAX), float(gl_PrimitiveID & 0xFFFFFF));
}
"""
ALPHA_MAP_SIDE = 256  # texels a side of each alpha map in the coverage's texture array
ALPHA_MAP_UNIT = 1  # its texture unit
NORMAL_MAP_SIDE = 1024  # texels a side of each normal map, at most (its own size below)
NORMAL_MAP_UNIT = 2
# The vertex buffer: pos, nrm, alb, refl (3 each), recv, alpha, trans, uv (2), layer; each pass
# reads its part (moderngl layouts). Normal maps add a buffer of their own, tangent (4) and
# map (layer, Strength), bound by the G-buffer passes only: the other passes (shadow, sky and
# RSM maps) read no more vertex data than without them.
VERTEX_FLOATS = 18
MAIN_LAYOUT = ("3f 3f 3f 3f 1f 1f 1f 2f 1f", "in_pos", "in_nrm", "in_alb", "in_refl",
               "in_recv", "in_alpha", "in_trans", "in_uv", "in_layer")
MAP_LAYOUT = ("4f 2f", "in_tan", "in_nmap")
RSM_LAYOUT = ("3f 3f 24x 1f 1f 4x 2f 1f", "in_pos", "in_nrm", "in_recv", "in_alpha",
              "in_uv", "in_layer")


def _resampled(a: np.ndarray, side: int) -> np.ndarray:
    """(side, side) bilinear resampling of an (H, W) map, texel centres to texel centres,
    rows kept bottom-first (GL's first row is the bottom: UV (0, 0) at the map's corner)."""
    h, w = a.shape
    ys = np.clip((np.arange(side) + 0.5) * h / side - 0.5, 0, h - 1)
    xs = np.clip((np.arange(side) + 0.5) * w / side - 0.5, 0, w - 1)
    y0, x0 = np.floor(ys).astype(int), np.floor(xs).astype(int)
    y1, x1 = np.minimum(y0 + 1, h - 1), np.minimum(x0 + 1, w - 1)
    fy, fx = (ys - y0)[:, None], (xs - x0)[None, :]
    top = a[y0][:, x0] * (1 - fx) + a[y0][:, x1] * fx
    bot = a[y1][:, x0] * (1 - fx) + a[y1][:, x1] * fx
    return (top * (1 - fy) + bot * fy).astype(np.float32)


TRIANGLE_SPLIT = 1 << 24  # the RSM pass's triangle index = (pos.w - 1) x this + nrm.w


def _with_barycentrics(vertex: str, fragment: str, location: int, value: str) -> tuple[str, str]:
    """A pass's shaders with one more target at ``location``: ``value`` of the barycentric
    coordinates ``v_bary`` of corners 1 and 2 (from gl_VertexID: every triangle's three
    corners are its own vertices), for the per-point albedo (textures.Surface)."""
    vertex = vertex.replace("void main() {", "out vec2 v_bary;\nvoid main() {\n"
                            "    int k = gl_VertexID % 3;\n"
                            "    v_bary = vec2(k == 1 ? 1.0 : 0.0, k == 2 ? 1.0 : 0.0);")
    fragment = fragment.replace("void main() {", f"in vec2 v_bary;\nlayout(location = "
                                f"{location}) out vec4 o_bary;\nvoid main() {{")
    return vertex, fragment[:fragment.rindex("}")] + f"    o_bary = {value};\n}}\n"


# Textured scenes' passes: the G-buffer's fifth target holds the barycentrics and the triangle
# index (split as in the RSM pass), the RSM's third the barycentrics.
TEXTURED_SHADERS = _with_barycentrics(VERTEX_SHADER, FRAGMENT_SHADER, 4,
                             "vec4(v_bary, float(1 + (gl_PrimitiveID >> 24)), "
                             "float(gl_PrimitiveID & 0xFFFFFF))")
TEXTURED_RSM_SHADERS = _with_barycentrics(RSM_VERTEX_SHADER, RSM_FRAGMENT_SHADER, 2,
                                 "vec4(v_bary, 0.0, 0.0)")


def to_eye(view, projection, positions: np.ndarray) -> np.ndarray:
    """Unit directions (N, 3) from ``positions`` towards a camera's eye (orthographic: its
    view axis, the same for every point)."""
    inv = np.linalg.inv(np.asarray(view, np.float64))
    if abs(float(np.asarray(projection)[3, 3])) > 0.5:  # orthographic: w = 1
        toward = np.broadcast_to(inv[:3, 2], np.shape(positions))  # camera +Z points back at it
    else:
        toward = inv[:3, 3] - positions
    return toward / np.maximum(np.linalg.norm(toward, axis=-1, keepdims=True), 1e-30)


class PixelRays:
    """The camera rays through points of the ``covered`` pixels' cells: world origin and
    direction from unprojecting the near and far planes (perspective and orthographic alike)."""

    def __init__(self, view, projection, width: int, height: int, covered, footprint: float):
        self.inv = np.linalg.inv(np.asarray(projection, np.float64) @ np.asarray(view, np.float64))
        r, c = np.nonzero(covered)  # rows top-first
        self.x = (c + 0.5) * (2.0 / width) - 1.0
        self.y = 1.0 - (r + 0.5) * (2.0 / height)
        self.step = (footprint * 2.0 / width, footprint * 2.0 / height)

    def at(self, rows: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(origins, directions) (len(rows), K, 3) through the cells' points ``offsets``
        (K, 2) in cell units from the centres."""
        x = self.x[rows, None] + offsets[None, :, 0] * self.step[0]
        y = self.y[rows, None] + offsets[None, :, 1] * self.step[1]
        ends = []
        for z in (-1.0, 1.0):
            h = (self.inv[:, 0] * x[..., None] + self.inv[:, 1] * y[..., None]
                 + self.inv[:, 2] * z + self.inv[:, 3])
            ends.append(h[..., :3] / h[..., 3:])
        return ends[0], ends[1] - ends[0]


def gl_context():
    """The process's standalone moderngl context (EGL headless, else the platform default)."""
    global _CTX
    if _CTX is None:
        import moderngl

        if "MESA_SHADER_CACHE_DIR" not in os.environ:
            cache = os.path.join(_cache_root(), "mesa")
            os.makedirs(cache, exist_ok=True)
            os.environ["MESA_SHADER_CACHE_DIR"] = cache
        attempts = ({"backend": "egl", "require": 430}, {"backend": "egl"}, {})
        for i, kwargs in enumerate(attempts):  # GL 4.3 for compute shaders where the driver
            try:  # offers it (NVIDIA's EGL gives 3.3 unless asked), else what the platform has
                _CTX = moderngl.create_standalone_context(**kwargs)
                break
            except Exception:
                if i == len(attempts) - 1:
                    raise
    return _CTX


def _cache_root() -> str:
    import tempfile

    return os.path.join(tempfile.gettempdir(), "lpv_gi_cache")


@dataclass
class Frame:
    """Rasterised buffers, (H, W, ...) float32 arrays, first row = top of the view."""

    position: np.ndarray  # world position (origin restored), NaN where empty
    normal: np.ndarray  # unit normal facing the viewer
    albedo: np.ndarray  # diffuse colour
    reflectance: np.ndarray  # GI reflectance (bleed colour where set)
    covered: np.ndarray  # bool mask
    receiver: np.ndarray | None = None  # bool mask: covered and receives indirect light


class Rasterizer:
    """Uploads a scene's triangles once and renders them from any view."""

    def __init__(self, ctx=None):
        self.ctx = ctx or gl_context()
        self.program = self.ctx.program(
            vertex_shader=VERTEX_SHADER, fragment_shader=FRAGMENT_SHADER
        )
        self.rsm_program = self.ctx.program(
            vertex_shader=RSM_VERTEX_SHADER, fragment_shader=RSM_FRAGMENT_SHADER
        )
        self._vao = None
        self._rsm_vao = None
        self._alpha_maps = None  # the coverage's texture array (_upload_alpha_maps)
        self.hashed = False  # a triangle's coverage is below 1 or has an alpha map (upload)
        self._normal_maps = None  # the normal maps' texture array (_upload_normal_maps)
        self._array_keys: dict = {}  # what each texture array was made of (_texture_array)
        self._vbo = None
        self._map_vbo = None  # the normal maps' vertex data (_upload_normal_maps)
        self._key = None
        self._fbos: dict = {}
        self.origin = np.zeros(3)
        # (T, 3) float32 GI reflectance per uploaded triangle: what read_rsm's indices select
        self.reflectance = np.zeros((0, 3), np.float32)
        # (T, 3) glossy reflectance per uploaded triangle or None, and the RSM's 6-column table
        self.specular = self._rsm_table = None
        # Per-point albedo of a textured upload (textures.Surface; None: per triangle), the
        # textures kept per digest, and the textured passes' programs (made on first use)
        self.surface = None
        self.texture_store = textures.Store()
        self.albedo = np.zeros((0, 3), np.float32)
        self._textured: dict = {}
        # textures.view_shares of the upload (None: none) and, with it or a surface, the
        # triangles' world corners (T, 3, 3) float64 the footprint rays meet
        self.shares = self.corners = None

    def upload(self, positions, normals, albedo, reflectance, key=None, receiver=None,
               origin=None, surface: textures.Layout | None = None, specular=None,
               shares: tuple | None = None, hidden=None, alpha=None,
               translucency=None, alpha_maps=None, normal_maps=None) -> None:
        """Upload (T,3,3) corners and normals with (T,3) per-triangle colours and an optional
        (T,) receiver flag (default: every triangle receives GI). Positions are kept relative
        to ``origin`` (default: the centre of the vertices' bounds) for float32 precision.
        ``surface`` (textures.layout): the textures and corner colours the albedo and the
        GI reflectance take per point; its textures are fitted and kept per digest.
        ``specular`` (T, 3) glossy reflectance (Scene.specular_per_triangle; None: none).
        ``shares`` (textures.view_shares): the Diffuse Color's view-angle share per triangle.
        ``hidden`` (T,) ray-visibility bits (Scene.ray_hidden; None: seen by every ray);
        ``alpha`` (T,) coverage (Scene.alpha_per_triangle; None: opaque), hashed per pass;
        ``translucency`` (T,) (Scene.translucency_per_triangle; None: none);
        ``alpha_maps`` ((T,) layer, (T, 3, 2) UVs, maps) the coverage per point
        (Scene.alpha_maps and Scene.uvs; None: none); ``normal_maps`` ((T,) layer, (T,)
        Strength, (T, 3, 2) UVs, (T, 3, 4) tangents, maps) the G-buffer's normal per point
        (Scene.normal_maps, Scene.uvs and Scene.tangents; None: none)."""
        if key is not None and key == self._key:
            return
        self.surface = None if surface is None else textures.Surface(surface,
                                                                     self.texture_store)
        pos = np.asarray(positions, np.float64).reshape(-1, 3, 3)
        t = pos.shape[0]
        # Keep vertex positions relative to a scene origin: float32 precision far from 0.
        if origin is not None:
            self.origin = np.asarray(origin, np.float64).reshape(3)
        else:
            self.origin = (
                0.5 * (pos.reshape(-1, 3).min(0) + pos.reshape(-1, 3).max(0)) if t
                else np.zeros(3)
            )
        rel = (pos - self.origin).astype(np.float32)
        data = np.empty((t, 3, VERTEX_FLOATS), np.float32)
        data[..., 0:3] = rel
        data[..., 3:6] = np.asarray(normals, np.float32).reshape(-1, 3, 3)
        data[..., 6:9] = np.asarray(albedo, np.float32).reshape(-1, 1, 3)
        data[..., 9:12] = np.asarray(reflectance, np.float32).reshape(-1, 1, 3)
        data[..., 12] = 1.0 if receiver is None else np.asarray(receiver, np.float32).reshape(-1, 1)
        if hidden is not None:
            data[..., 12] += 2.0 * np.asarray(hidden, np.float32).reshape(-1, 1)
        data[..., 13] = 1.0 if alpha is None else np.asarray(alpha, np.float32).reshape(-1, 1)
        # whether any fragment may be hashed out (render/atlas.py draws opaque scenes without)
        self.hashed = bool(alpha_maps is not None or (alpha is not None and
                                                      (np.asarray(alpha) < 1.0).any()))
        data[..., 14] = 0.0 if translucency is None else np.asarray(
            translucency, np.float32).reshape(-1, 1)
        data[..., 15:17] = 0.0
        data[..., 17] = -1.0
        self._upload_alpha_maps(alpha_maps, data)
        extra = self._upload_normal_maps(normal_maps, data)
        self.release_geometry()
        if t:
            self._vbo = self.ctx.buffer(data.tobytes())
            if extra is not None:
                self._map_vbo = self.ctx.buffer(extra.tobytes())
            self._vao = self.ctx.vertex_array(self.program, self._gbuffer_buffers(MAIN_LAYOUT))
            self._rsm_vao = self.ctx.vertex_array(self.rsm_program,
                                                  [(self._vbo, *RSM_LAYOUT)])
        self.reflectance = np.ascontiguousarray(data[:, 0, 9:12])
        if specular is not None:
            self.specular = np.asarray(specular, np.float32).reshape(t, 3)
            self._rsm_table = np.ascontiguousarray(np.hstack([self.reflectance, self.specular]))
        self.shares = shares
        self.corners = pos if self.surface is not None or shares is not None else None
        if self.corners is not None:
            self.albedo = np.ascontiguousarray(data[:, 0, 6:9])
            for name, (program, layout) in self._programs().items():
                buffers = (self._gbuffer_buffers(layout) if name == "gbuffer"
                           else [(self._vbo, *layout)])
                self._textured[name + "_vao"] = None if not t else self.ctx.vertex_array(
                    program, buffers)
        self._key = key

    def _texture_array(self, name: str, maps: list | None, keys: list | None, side: int,
                       channels: int):
        """The ``name`` texture array ("_alpha_maps", "_normal_maps"): bilinear layers of
        ``maps`` resampled to side^2 x ``channels``, kept while the maps' ``keys`` (digests)
        and size are the ones it was made of (a render uploads the scene once per antialias
        sample); None, released, without maps."""
        made = (None if maps is None else tuple(keys), side, channels)
        current = getattr(self, name)
        if current is not None and self._array_keys.get(name) == made:
            return current
        if current is not None:
            current.release()
        setattr(self, name, None)
        self._array_keys.pop(name, None)
        if maps is None:
            return None
        stack = np.stack([np.stack([_resampled(np.asarray(m, np.float32)[..., c], side)
                                    for c in range(channels)], axis=-1) for m in maps])
        array = self.ctx.texture_array((side, side, len(maps)), channels,
                                       np.ascontiguousarray(stack).tobytes(), dtype="f4")
        import moderngl

        array.filter = (moderngl.LINEAR, moderngl.LINEAR)
        setattr(self, name, array)
        self._array_keys[name] = made
        return array

    def _upload_alpha_maps(self, alpha_maps, data: np.ndarray) -> None:
        """The alpha maps as one texture array (ALPHA_MAP_SIDE^2 layers), their layer and
        UVs into the vertex ``data``; none: the array released."""
        layer, uvs, maps, keys = alpha_maps or (None,) * 4
        self._texture_array("_alpha_maps", maps, keys, ALPHA_MAP_SIDE, 1)
        if alpha_maps is not None:
            data[..., 15:17] = np.asarray(uvs, np.float32).reshape(-1, 3, 2)
            data[..., 17] = np.asarray(layer, np.float32).reshape(-1, 1)

    def _gbuffer_buffers(self, layout: tuple) -> list:
        """A G-buffer pass's vertex buffers: the main one, and the normal maps' when there."""
        return [(self._vbo, *layout)] + ([(self._map_vbo, *MAP_LAYOUT)]
                                         if self._map_vbo is not None else [])

    def _upload_normal_maps(self, normal_maps, data: np.ndarray) -> np.ndarray | None:
        """The normal maps as one texture array (layers of their largest side, at most
        NORMAL_MAP_SIDE), their UVs into the vertex ``data``; returns their own vertex data
        (T, 3, 6): tangent, layer and Strength (None, the array released, without any)."""
        if normal_maps is None:
            self._texture_array("_normal_maps", None, None, 0, 3)
            return None
        layer, strength, uvs, tangents, maps, keys = normal_maps
        side = min(NORMAL_MAP_SIDE, max(max(m.shape[:2]) for m in maps))
        self._texture_array("_normal_maps", maps, keys, side, 3)
        data[..., 15:17] = np.asarray(uvs, np.float32).reshape(-1, 3, 2)
        extra = np.empty(data.shape[:2] + (6,), np.float32)
        extra[..., 0:4] = np.asarray(tangents, np.float32).reshape(-1, 3, 4)
        extra[..., 4] = np.asarray(layer, np.float32).reshape(-1, 1)
        extra[..., 5] = np.asarray(strength, np.float32).reshape(-1, 1)
        return extra

    def _programs(self) -> dict:
        """The textured passes' programs and vertex layouts, compiled on first use."""
        if "gbuffer" not in self._textured:
            for name, (vs, fs) in (("gbuffer", TEXTURED_SHADERS),
                                   ("rsm", TEXTURED_RSM_SHADERS)):
                self._textured[name] = self.ctx.program(vertex_shader=vs, fragment_shader=fs)
        return {"gbuffer": (self._textured["gbuffer"], MAIN_LAYOUT),
                "rsm": (self._textured["rsm"], RSM_LAYOUT)}

    def release_geometry(self) -> None:
        vaos = [self._textured.pop(k) for k in ("gbuffer_vao", "rsm_vao") if k in self._textured]
        for obj in (self._vao, self._rsm_vao, self._vbo, self._map_vbo, *vaos):
            if obj is not None:
                obj.release()
        self._vao = self._rsm_vao = self._vbo = self._map_vbo = None
        self.reflectance = np.zeros((0, 3), np.float32)
        self.specular = self._rsm_table = None
        self._key = None

    def _fbo(self, width: int, height: int, targets: int = 4):
        """The framebuffer of ``targets`` RGBA float32 colour targets and a depth buffer."""
        fbo = self._fbos.get((width, height, targets))
        if fbo is None:
            colors = [self.ctx.texture((width, height), 4, dtype="f4") for _ in range(targets)]
            depth = self.ctx.depth_renderbuffer((width, height))
            fbo = self.ctx.framebuffer(color_attachments=colors, depth_attachment=depth)
            self._fbos[(width, height, targets)] = fbo
        return fbo

    def _draw(self, program, vao, fbo, view, projection, ortho: bool, hide: int = 0,
              seed: tuple[int, int] = (0, 1)) -> None:
        """Clear ``fbo`` and draw the uploaded triangles into it with ``program`` (its
        view_proj, eye, view_dir and ortho uniforms set from the view; vertices are relative to
        ``self.origin``), leaving out the triangles whose ray-visibility bits meet ``hide``;
        ``seed``: (sample, samples) of the hashed alpha (the same seed keeps the same
        fragments)."""
        view = np.asarray(view, np.float64)
        inv_view = np.linalg.inv(view)
        eye = inv_view[:3, 3]
        view_dir = -inv_view[:3, 2]
        # Translate the view so that it works on origin-relative vertices.
        shift = np.eye(4)
        shift[:3, 3] = self.origin
        view_proj = np.asarray(projection, np.float64) @ view @ shift
        fbo.use()
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        if vao is None:
            return
        import moderngl

        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        program["view_proj"].write(view_proj.T.astype(np.float32).tobytes())
        program["eye"].value = tuple((eye - self.origin).astype(np.float32))
        program["view_dir"].value = tuple(view_dir.astype(np.float32))
        program["ortho"].value = int(ortho)
        program["hide"].value = 2 * int(hide)
        if self._alpha_maps is not None:
            self._alpha_maps.use(location=ALPHA_MAP_UNIT)
            if "alpha_maps" in program:
                program["alpha_maps"].value = ALPHA_MAP_UNIT
        if "normal_mapped" in program:
            program["normal_mapped"].value = int(self._normal_maps is not None)
        if self._normal_maps is not None:
            self._normal_maps.use(location=NORMAL_MAP_UNIT)
            if "normal_maps" in program:
                program["normal_maps"].value = NORMAL_MAP_UNIT
        program["seed"].value, program["samples"].value = (int(v) for v in seed)
        vao.render()

    @staticmethod
    def _targets(fbo, targets, width: int, height: int) -> list[np.ndarray]:
        """Colour targets ``targets`` of ``fbo`` read back as float32 (H, W, 4), rows
        top-first (views of the readback: GL's first row is the bottom)."""
        return [np.frombuffer(fbo.color_attachments[t].read(), np.float32)
                .reshape(height, width, 4)[::-1] for t in targets]

    def read(
        self,
        view: np.ndarray,
        projection: np.ndarray,
        width: int,
        height: int,
        ortho: bool = False,
        targets: tuple[int, ...] = (0, 1, 2, 3),
        hide: int = 0,
        seed: tuple[int, int] = (0, 1),
    ) -> list[np.ndarray]:
        """Rasterise and read back the render targets ``targets`` (0 position, 1 normal +
        holdout flag, 2 albedo + receiver flag, 3 reflectance) as float32 (H, W, 4), rows
        top-first (views of the readback), positions relative to ``self.origin``; coverage is
        position's w. ``hide``: ray-visibility bits whose triangles are left out (shadow maps:
        CASTS_NO_SHADOW); ``seed``: the hashed alpha's."""
        if self._vao is not None:
            # Positions were uploaded relative to origin; the shader's origin uniform is 0.
            self.program["origin"].value = (0.0, 0.0, 0.0)
        fbo = self._fbo(width, height)
        self._draw(self.program, self._vao, fbo, view, projection, ortho, hide, seed)
        return self._targets(fbo, targets, width, height)

    def read_rsm(self, view: np.ndarray, projection: np.ndarray, size: int,
                 ortho: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """A reflective shadow map's two targets as float32 (size, size, 4), rows top-first:
        position relative to ``self.origin`` and the normal facing the viewer, as ``read``
        gives them, their w the triangle index (``triangles``); coverage is position's w > 0.5.
        A pass of its own with two targets instead of four (RSM_FRAGMENT_SHADER)."""
        fbo = self._fbo(size, size, 2)
        self._draw(self.rsm_program, self._rsm_vao, fbo, view, projection, ortho)
        pos, nrm = self._targets(fbo, (0, 1), size, size)
        return pos, nrm

    def rsm_texels(self, view: np.ndarray, projection: np.ndarray, size: int,
                   ortho: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """read_rsm's targets and the reflectance table their w indices select: the
        per-triangle table, or on a textured upload each covered texel's own reflectance
        (the triangle's x corner colour x texture at the texel's point, textures.Surface)
        with the w channels holding the texel's row in it. With glossy reflectance uploaded
        the table has 6 columns: the reflectance, then the glossy reflectance."""
        if self.surface is None or self._vao is None:
            pos, nrm = self.read_rsm(view, projection, size, ortho)
            if self.specular is None:
                return pos, nrm, self.reflectance
            return pos, nrm, self._rsm_table
        fbo = self._fbo(size, size, 3)
        self._draw(self._textured["rsm"], self._textured["rsm_vao"], fbo, view, projection,
                   ortho)
        pos, nrm, bary = self._targets(fbo, (0, 1, 2), size, size)
        covered = pos[..., 3] > 0.5
        tri = self.triangles(pos[covered], nrm[covered])
        table = self.reflectance[tri] * self.surface.factor(tri, bary[covered][:, :2], gi=True)
        if self.specular is not None:
            table = np.hstack([table, self.specular[tri]])
        # copies laid out like the read-back (rows reversed, read-only): the compiled texel
        # pass sees the same array types as untextured maps
        pos, nrm = pos[::-1].copy()[::-1], nrm[::-1].copy()[::-1]
        row = np.arange(tri.shape[0])
        pos[..., 3][covered] = 1 + row // TRIANGLE_SPLIT
        nrm[..., 3][covered] = row % TRIANGLE_SPLIT
        pos.setflags(write=False)
        nrm.setflags(write=False)
        return pos, nrm, np.ascontiguousarray(table, np.float32)

    @staticmethod
    def triangles(pos: np.ndarray, nrm: np.ndarray) -> np.ndarray:
        """Triangle index (int64, same shape) of covered texels of read_rsm's ``pos``, ``nrm``
        (or rows of them, (..., 4)); meaningless where not covered."""
        high = pos[..., 3].astype(np.int64) - 1
        return high * TRIANGLE_SPLIT + nrm[..., 3].astype(np.int64)

    def render(
        self,
        view: np.ndarray,
        projection: np.ndarray,
        width: int,
        height: int,
        ortho: bool = False,
    ) -> Frame:
        """Rasterise from a world-to-view and projection matrix (OpenGL conventions).
        (Shadow maps read the position target alone: direct.render_shadow_map.)"""
        out = self.read(view, projection, width, height, ortho, (0, 1, 2, 3), HIDDEN_FROM_CAMERA)
        covered = out[0][..., 3] > 0.5
        pos = out[0][..., :3].astype(np.float64) + self.origin
        pos[~covered] = np.nan
        return Frame(
            position=pos,
            normal=np.ascontiguousarray(out[1][..., :3]),
            albedo=np.ascontiguousarray(out[2][..., :3]),
            reflectance=np.ascontiguousarray(out[3][..., :3]),
            covered=covered,
            receiver=covered & (out[2][..., 3] > 0.5),
        )

    def gbuffer(self, view: np.ndarray, projection: np.ndarray, width: int,
                height: int, footprint: float = 0.0, holdout: bool = False,
                seed: tuple[int, int] = (0, 1), only: np.ndarray | None = None,
                reflectance: bool = False) -> tuple:
        """The covered pixels of a camera view, as ``render`` gives them at frame.covered
        (the same numbers, pixels in row-major order, rows top-first): (covered (H, W) bool,
        world positions (M, 3) float64, normals (M, 3) float64, albedo (M, 3) float32,
        receiver flags (M,) bool), and with ``holdout`` the holdout flags (M,) bool and the
        translucency (M,) float32 after them. Triangles hidden from the camera are left out. Converts only what is covered,
        not whole frames. ``footprint``: the side of each pixel's cell in pixels over which
        a textured albedo is integrated (textures.footprint_factor; 0: read at the pixel's
        centre); ``seed``: the hashed alpha's (antialias sample, samples); ``only`` (H, W)
        bool: these pixels alone are taken (covered is False elsewhere); ``reflectance``: the
        GI reflectance (M, 3) float32 last (the RSM's: 0 for non-casters, textured as
        rsm_texels)."""
        if self.corners is None or self._vao is None:
            targets = (0, 1, 2, 3) if reflectance else (0, 1, 2)
            pos4, nrm4, alb4, *refl4 = self.read(view, projection, width, height, False,
                                                 targets, HIDDEN_FROM_CAMERA, seed)
        else:  # textured: the fifth target's barycentrics and triangle give the albedo
            program = self._textured["gbuffer"]
            program["origin"].value = (0.0, 0.0, 0.0)
            fbo = self._fbo(width, height, 5)
            self._draw(program, self._textured["gbuffer_vao"], fbo, view, projection, False,
                       HIDDEN_FROM_CAMERA, seed)
            pos4, nrm4, alb4, bary4 = self._targets(fbo, (0, 1, 2, 4), width, height)
        covered = pos4[..., 3] > 0.5
        if only is not None:
            covered &= only
        pos = pos4[covered][:, :3].astype(np.float64) + self.origin
        nrm = nrm4[covered][:, :3].astype(np.float64)
        alb = alb4[covered]
        w4 = nrm4[covered][:, 3]
        # holdout flags, then the translucency (0-1) of the covered pixels
        held = (w4 > 1.5, np.where(w4 > 1.5, 0.0, w4).astype(np.float32)) if holdout else ()
        if self.corners is None or self._vao is None:
            refl = (np.ascontiguousarray(refl4[0][covered][:, :3]),) if reflectance else ()
            return (covered, pos, nrm, np.ascontiguousarray(alb[:, :3]), alb[:, 3] > 0.5,
                    *held, *refl)
        b = bary4[covered]
        tri = (b[:, 2].astype(np.int64) - 1) * TRIANGLE_SPLIT + b[:, 3].astype(np.int64)
        albedo = self.albedo[tri]
        if self.surface is not None:
            factor = self.surface.factor(tri, b[:, :2])
            self.surface.info["footprint_refined"] = 0
            # a pixel of an untextured triangle reads its exact factor at the centre (corner
            # colours are linear over it): without a textured pixel there is nothing to refine
            if footprint > 0 and (self.surface.layout.albedo_texture[tri] >= 0).any():
                corners = self.corners
                ray = PixelRays(view, projection, width, height, covered, footprint)

                def bary_at(rows, offsets):
                    return textures.plane_barycentric(corners[tri[rows]], *ray.at(rows, offsets),
                                                      b[rows, :2])

                factor, refined = textures.footprint_factor(self.surface, tri, factor,
                                                            covered, bary_at)
                self.surface.info["footprint_refined"] = refined
            albedo = albedo * factor
        if self.shares is not None:  # the Diffuse Color's share at the view angle
            rows, table = self.shares
            r = rows[tri]
            has = np.flatnonzero(r >= 0)
            cos = (nrm[has] * to_eye(view, projection, pos[has])).sum(-1)
            albedo[has] *= textures.share_at(table, r[has], cos)
        refl = ()
        if reflectance:
            refl = self.reflectance[tri]
            if self.surface is not None:
                refl = refl * self.surface.factor(tri, b[:, :2], gi=True)
            refl = (np.ascontiguousarray(refl, np.float32),)
        return (covered, pos, nrm, albedo, alb[:, 3] > 0.5, *held, *refl)

    def surroundings(self, point, near: float, far: float, size: int = 32):
        """What ``point`` sees in every direction: the six faces of a cube map of ``size``^2
        texels (near/far clip distances): world positions of the hits (N, 3) float64, the
        solid angle of each hit's texel (N,), the solid angle that sees nothing (sr) and the
        hits' position error (float32 targets relative to ``self.origin``)."""
        from ..scene.lights import CUBE_DIRECTIONS, CUBE_UPS
        from ..scene.model import look_at_matrix, perspective_matrix

        point = np.asarray(point, np.float64)
        u = (np.arange(size) + 0.5) / size * 2.0 - 1.0
        r2 = 1.0 + u[None, :] ** 2 + u[:, None] ** 2
        solid = (2.0 / size) ** 2 / (r2 * np.sqrt(r2))  # texel solid angle on a cube face
        proj = perspective_matrix(np.pi / 2, 1.0, near, far)
        hits, weights, missed, reach = [], [], 0.0, 0.0
        for d, up in zip(CUBE_DIRECTIONS, CUBE_UPS):
            (pos,) = self.read(look_at_matrix(point, point + d, up), proj, size, size,
                               targets=(0,))
            covered = pos[..., 3] > 0.5
            rel = pos[covered][:, :3]
            reach = max(reach, float(np.abs(rel).max(initial=0.0)))
            hits.append(rel.astype(np.float64) + self.origin)
            weights.append(solid[covered])
            missed += float(solid[~covered].sum())
        # float32 targets after interpolation: a few ulps measured (6 on llvmpipe); 2^-16 of
        # the largest relative coordinate (256 ulps) bounds them with room
        return np.concatenate(hits), np.concatenate(weights), missed, 2.0 ** -16 * reach

    def release(self) -> None:
        self.release_geometry()
        for maps in (self._alpha_maps, self._normal_maps):
            if maps is not None:
                maps.release()
        self._alpha_maps = self._normal_maps = None
        self._array_keys.clear()
        for fbo in self._fbos.values():
            for att in fbo.color_attachments:
                att.release()
            if fbo.depth_attachment is not None:
                fbo.depth_attachment.release()
            fbo.release()
        self._fbos.clear()
        self.program.release()
        self.rsm_program.release()
        for program in [self._textured.pop(k) for k in ("gbuffer", "rsm")
                        if k in self._textured]:
            program.release()
