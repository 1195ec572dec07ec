"""Viewport overlay: the LPV drawn with Blender's ``gpu`` module in a SpaceView3D handler.

How it shades (our choice, per fragment rather than per vertex): each cascade's combined LPV
(9 SH coefficients per colour, bands 0-2) is uploaded as seven 3D textures (RGBA16F, scaled by
the grid's largest magnitude so half floats keep their relative precision): per colour channel
one with SH coefficients 0-3 (bands 0-1) and one with coefficients 4-7 (band 2), and one whose
RGB is coefficient 8 of the three colours, plus its propagation
visibility (two RGB 3D textures: transmittance towards +x+y+z and -x-y-z) and its occluders'
cell gaps (two RGB 3D textures, geometry_volume.cell_gaps: slab depths below the +x+y+z faces
and above the -x-y-z faces); 11 samplers per draw, one draw per cascade. A fragment shader
repeats ``lpv_core.lookup.irradiance`` for every pixel of the extracted scene geometry: sample
half a cell along the viewer-facing normal, moved out of the slabs an occluder's face plane cut
off (``lookup.sample_points`` / ``gap_corrected``; skipped for a cascade without gaps),
trilinear over the 8 nearest cells (zero outside the grid) leaving out corners behind the
receiver's own plane (``lookup.front_corners``) and behind occluders and renormalising
(``injection.visible_corners``), then the irradiance kernel of
``sh.irradiance_weights`` / s^2; clamp at zero; cascades add up. Indirect radiance = irradiance / pi x albedo, 0 where ``gi_receiver`` is off (the albedo: per corner x corner colour, x the material's texture per pixel as ``textures.sample`` reads it: one draw per texture, uploaded once per digest; x the material's Diffuse Color share at the fragment's view angle, ``textures.share_at`` of the stacked ``textures.view_shares`` tables, uploaded once per result as a float texture: the 13th sampler). Per-vertex
shading would blur the LPV over large polygons (a Cornell wall is one quad). Transition areas are multiplied into the
uploaded grids per cell (exact inside a box and far from it; the falloff is resolved at cell
size), clip areas act in propagation and in the visibility already.

Modes (``Scene.lpv.overlay_mode``): ADD (indirect added on top of the viewport shading, for
EEVEE material preview or solid mode), INDIRECT (indirect only), and debug views: CASCADES
(grid bounds), VPLS (a VPL sample, coloured by flux), PROBES (each cell's SH as a glyph whose
radius is the intensity towards that direction, from all 9 coefficients) and OCCLUSION (points on the cell faces where
propagation is blocked: the geometry volume's occlusion times clip areas, white to red).
The viewport's colours are linear; the view transform (AgX, Filmic) of the viewport shading is
not applied to the overlay, so ADD is exact with the Standard transform.
"""

from __future__ import annotations

import gpu
import numpy as np
from gpu_extras.batch import batch_for_shader
from mathutils import Matrix

from .._core import core
from . import live

_SHADERS: dict = {}
_RESOURCES: dict = {}  # key -> GPU objects (textures, batches), freed with free_resources()
_HANDLES: list = []  # draw handler of SpaceView3D (at most one)

# Fragment shader samplers, by slot (11 per draw of a cascade, then albedo_tex and share_tex:
# 13; OpenGL 4.3 guarantees 16).
SAMPLERS = ("lpv_r", "lpv_g", "lpv_b", "vis_plus", "vis_minus", "lpv_r2", "lpv_g2", "lpv_b2",
            "lpv_c8", "gaps_plus", "gaps_minus")
# The albedo texture of a textured batch (12th sampler) and its modes' codes in tex_mode.
INTERPOLATION_CODES = {"Linear": 0, "Closest": 1, "Cubic": 2, "Smart": 2}
EXTENSION_CODES = {"REPEAT": 0, "EXTEND": 1, "CLIP": 2, "MIRROR": 3}
_TEXTURES: dict = {}  # digest -> GPUTexture of an albedo texture (uploaded once per digest)
UPLOADS = [0]  # albedo textures uploaded so far

VERTEX_SOURCE = """
void main() {
    v_pos = pos;
    v_nrm = nor;
    v_col = col;
    v_uv = uv;
    v_share = share;
    gl_Position = ModelViewProjectionMatrix * vec4(pos, 1.0);
}
"""

_PLANE = core.lookup.OFFSET_CELLS + core.lookup.PLANE_TOLERANCE  # front_corners', in cells
FRAGMENT_SOURCE = f"const float PLANE = {_PLANE!r};\n" + """
const float PI = 3.14159265358979;
/* sh.irradiance_weights: Y(-n) x (pi, 2 pi / 3, pi / 4) per band */
const float K0 = 0.886226925452758;       /* pi Y0 */
const float K1 = 1.0233267079464885;      /* 2 pi / 3 Y1 */
const float K2A = 0.8580855308097834;     /* pi / 4 Y2A */
const float K2B = 0.2477079561003757;     /* pi / 4 Y2B */
const float K2C = 0.4290427654048917;     /* pi / 4 Y2C */

/* textures.sample in GLSL (Cycles' CPU image kernel) with texelFetch: codes in tex_mode */
int wrap(int i, int n, int ext) {
    if (ext == 0) {
        i = i % n;
        return i < 0 ? i + n : i;
    }
    if (ext == 3) {
        int m = abs(i + (i < 0 ? 1 : 0)) % (2 * n);
        return m >= n ? 2 * n - m - 1 : m;
    }
    return clamp(i, 0, n - 1);
}

float tap_weight(float t, int d, int interp) {
    if (interp == 0) {
        return d == 0 ? 1.0 - t : t;
    }
    if (d == -1) {
        return ((-t / 6.0 + 0.5) * t - 0.5) * t + 1.0 / 6.0;
    }
    if (d == 0) {
        return (0.5 * t - 1.0) * t * t + 2.0 / 3.0;
    }
    if (d == 1) {
        return ((-0.5 * t + 0.5) * t + 0.5) * t + 1.0 / 6.0;
    }
    return t * t * t / 6.0;
}

vec3 albedo_texture(vec2 uv) {
    ivec2 size = textureSize(albedo_tex, 0);
    int interp = int(tex_mode.y);
    int ext = int(tex_mode.z);
    vec2 x = uv * vec2(size);
    vec2 c = interp == 1 ? x : x - 0.5;
    vec2 b = floor(c);
    vec2 t = c - b;
    ivec2 ib = ivec2(b);
    int lo = interp == 2 ? -1 : 0;
    int hi = interp == 0 ? 1 : (interp == 2 ? 2 : 0);
    vec3 sum = vec3(0.0);
    for (int dy = lo; dy <= hi; dy++) {
        for (int dx = lo; dx <= hi; dx++) {
            ivec2 i = ib + ivec2(dx, dy);
            if (ext == 2 && (any(lessThan(i, ivec2(0))) || any(greaterThanEqual(i, size)))) {
                continue;
            }
            float w = interp == 1 ? 1.0 : tap_weight(t.x, dx, interp) * tap_weight(t.y, dy, interp);
            sum += w * texelFetch(albedo_tex, ivec2(wrap(i.x, size.x, ext),
                                                    wrap(i.y, size.y, ext)), 0).rgb;
        }
    }
    return sum;
}

/* textures.footprint_factor over the pixel: the UV's screen derivatives span its cell; where
   the 4 corners' mean differs from the centre by more than FOOTPRINT_TOL, the mean of
   FOOTPRINT_SPLIT^2 sub-points (the render tests its neighbours' second difference instead) */
vec3 albedo_footprint(vec2 uv, vec2 du, vec2 dv) {
    vec3 c = albedo_texture(uv);
    vec3 m = 0.25 * (albedo_texture(uv + 0.5 * (du + dv)) + albedo_texture(uv + 0.5 * (du - dv))
                     + albedo_texture(uv - 0.5 * (du - dv)) + albedo_texture(uv - 0.5 * (du + dv)));
    vec3 d = abs(m - c);
    if (max(d.r, max(d.g, d.b)) <= FOOTPRINT_TOL) {
        return c;
    }
    vec3 sum = vec3(0.0);
    for (int i = 0; i < FOOTPRINT_SPLIT; i++) {
        for (int j = 0; j < FOOTPRINT_SPLIT; j++) {
            vec2 o = (vec2(i, j) + 0.5) / float(FOOTPRINT_SPLIT) - 0.5;
            sum += albedo_texture(uv + o.x * du + o.y * dv);
        }
    }
    return sum / float(FOOTPRINT_SPLIT * FOOTPRINT_SPLIT);
}

/* textures.share_at: row ``row`` of share_tex (one row per material, a column per SHARE_COS
   entry) at the view cosine c, linear between the (non-uniform) cosines, held at the ends */
vec3 view_share(int row, float c) {
    float x = clamp(isnan(c) ? 1.0 : abs(c), SHARE_COS[0], SHARE_COS[SHARE_K - 1]);
    int i = 0;
    while (i < SHARE_K - 2 && x > SHARE_COS[i + 1]) {
        i++;
    }
    float t = (x - SHARE_COS[i]) / (SHARE_COS[i + 1] - SHARE_COS[i]);
    return mix(texelFetch(share_tex, ivec2(i, row), 0).rgb,
               texelFetch(share_tex, ivec2(i + 1, row), 0).rgb, t);
}

void main() {
    vec2 du = dFdx(v_uv), dv = dFdy(v_uv);  /* in uniform control flow */
    int res = int(params.x);
    vec3 n = normalize(v_nrm);
    vec3 to_eye = eye.w > 0.5 ? -view_dir.xyz : eye.xyz - v_pos;
    if (dot(n, to_eye) < 0.0) {
        n = -n;
    }
    float cell = grid.w;
    /* deferred.toward_viewer: edge pixels read from the side the camera sees */
    vec3 p = v_pos + normalize(to_eye) * nudge;
    /* lookup.sample_points: half a cell along the normal, in face-plane units */
    vec3 rel = (p + n * (0.5 * cell) - grid.xyz) / cell;
    if (use_gaps > 0.5) {
        /* lookup.gap_corrected: a point in a slab behind a blocked face of its cell goes to
           the centre of the neighbour across that face (each axis on its own, tested on the
           uncorrected point) */
        vec3 fl = floor(rel);
        ivec3 gc = ivec3(fl);
        if (all(greaterThanEqual(gc, ivec3(0))) && all(lessThan(gc, ivec3(res)))) {
            vec3 g_up = texelFetch(gaps_plus, gc, 0).xyz;   /* slabs below the upper faces */
            vec3 g_lo = texelFetch(gaps_minus, gc, 0).xyz;  /* slabs above the lower faces */
            vec3 fr = rel - fl;
            for (int a = 0; a < 3; a++) {
                if (fr[a] < g_lo[a]) {
                    rel[a] = fl[a] - 0.5;
                }
                else if (1.0 - fr[a] < g_up[a]) {
                    rel[a] = fl[a] + 1.5;
                }
            }
        }
    }
    /* lookup.sample: continuous cell coordinates (integers on cell centres) */
    vec3 c = rel - 0.5;
    vec3 base = floor(c);
    vec3 f = c - base;
    ivec3 ib = ivec3(base);
    /* injection.visible_corners: transmittance from the nearest cell to each corner */
    ivec3 near = ivec3(greaterThanEqual(f, vec3(0.5)));
    vec3 plus = vec3(1.0);
    vec3 minus = vec3(1.0);
    if (params.w > 0.5) {
        ivec3 nc = clamp(ib + near, ivec3(0), ivec3(res - 1));
        plus = texelFetch(vis_plus, nc, 0).xyz;
        minus = texelFetch(vis_minus, nc, 0).xyz;
    }
    vec4 sr = vec4(0.0);
    vec4 sg = vec4(0.0);
    vec4 sb = vec4(0.0);
    vec4 sr2 = vec4(0.0);  /* band 2: coefficients 4-7 */
    vec4 sg2 = vec4(0.0);
    vec4 sb2 = vec4(0.0);
    vec3 s8 = vec3(0.0);   /* coefficient 8 of r, g, b */
    float w_all = 0.0;
    float w_seen = 0.0;
    /* lookup.front_corners: corners behind the receiver's plane out (unless all are) */
    float w_front = 0.0;
    for (int k = 0; k < 8; k++) {
        ivec3 d = ivec3(k >> 2, (k >> 1) & 1, k & 1);
        ivec3 i = ib + d;
        if (any(lessThan(i, ivec3(0))) || any(greaterThanEqual(i, ivec3(res)))) {
            continue;
        }
        vec3 wv = mix(1.0 - f, f, vec3(d));
        w_front += dot(vec3(d) - f, n) > -PLANE ? wv.x * wv.y * wv.z : 0.0;
    }
    for (int k = 0; k < 8; k++) {
        ivec3 d = ivec3(k >> 2, (k >> 1) & 1, k & 1);
        ivec3 i = ib + d;
        if (any(lessThan(i, ivec3(0))) || any(greaterThanEqual(i, ivec3(res)))) {
            continue;
        }
        vec3 wv = mix(1.0 - f, f, vec3(d));
        float w = wv.x * wv.y * wv.z;
        w_all += w;
        if (w_front > 0.0 && !(dot(vec3(d) - f, n) > -PLANE)) {
            w = 0.0;
        }
        ivec3 st = d - near;
        for (int a = 0; a < 3; a++) {
            w *= st[a] > 0 ? plus[a] : (st[a] < 0 ? minus[a] : 1.0);
        }
        w_seen += w;
        sr += w * texelFetch(lpv_r, i, 0);
        sg += w * texelFetch(lpv_g, i, 0);
        sb += w * texelFetch(lpv_b, i, 0);
        sr2 += w * texelFetch(lpv_r2, i, 0);
        sg2 += w * texelFetch(lpv_g2, i, 0);
        sb2 += w * texelFetch(lpv_b2, i, 0);
        s8 += w * texelFetch(lpv_c8, i, 0).xyz;
    }
    float renorm = w_seen > 0.0 ? params.z * w_all / w_seen : 0.0;
    sr *= renorm;
    sg *= renorm;
    sb *= renorm;
    sr2 *= renorm;
    sg2 *= renorm;
    sb2 *= renorm;
    s8 *= renorm;
    vec4 w01 = vec4(K0, K1 * n.y, -K1 * n.z, K1 * n.x);  /* band 1 is odd: Y(-n) */
    vec4 w2 = vec4(K2A * n.x * n.y, K2A * n.y * n.z, K2B * (3.0 * n.z * n.z - 1.0),
                   K2A * n.x * n.z);
    float w8 = K2C * (n.x * n.x - n.y * n.y);
    vec3 e = vec3(dot(sr, w01) + dot(sr2, w2), dot(sg, w01) + dot(sg2, w2),
                  dot(sb, w01) + dot(sb2, w2)) + s8 * w8;
    e = max(e, vec3(0.0)) / (cell * cell);
    vec3 albedo = tex_mode.x > 0.5 ? v_col.rgb * albedo_footprint(v_uv, du, dv) : v_col.rgb;
    if (v_share > -0.5) {  /* the Diffuse Color's share at the view angle */
        albedo *= view_share(int(v_share + 0.5), dot(n, normalize(to_eye)));
    }
    vec3 radiance = e / PI * albedo * v_col.a;
    /* cascades.Read.takes: the receivers inside keep and not inside skip read this grid */
    bool takes = all(greaterThanEqual(p, keep_lo.xyz)) && all(lessThan(p, keep_hi.xyz))
                 && !(all(greaterThanEqual(p, skip_lo.xyz)) && all(lessThan(p, skip_hi.xyz)));
    FragColor = vec4(takes ? radiance * params.y : vec3(0.0), 1.0);
}
"""


def _lpv_shader():
    shader = _SHADERS.get("lpv")
    if shader is None:
        iface = gpu.types.GPUStageInterfaceInfo("lpv_gi_iface")
        iface.smooth("VEC3", "v_pos")
        iface.smooth("VEC3", "v_nrm")
        iface.smooth("VEC4", "v_col")
        iface.smooth("VEC2", "v_uv")
        iface.flat("FLOAT", "v_share")
        info = gpu.types.GPUShaderCreateInfo()
        info.vertex_in(0, "VEC3", "pos")
        info.vertex_in(1, "VEC3", "nor")
        info.vertex_in(2, "VEC4", "col")
        info.vertex_in(3, "VEC2", "uv")
        info.vertex_in(4, "FLOAT", "share")  # row of share_tex, -1 none
        info.vertex_out(iface)
        info.push_constant("MAT4", "ModelViewProjectionMatrix")
        info.push_constant("VEC4", "grid")  # origin xyz, cell size
        info.push_constant("VEC4", "params")  # resolution, weight, value scale, use visibility
        info.push_constant("VEC4", "eye")  # eye position, 1 if orthographic
        info.push_constant("VEC4", "view_dir")  # view direction (orthographic views)
        info.push_constant("FLOAT", "nudge")  # deferred.toward_viewer's distance
        for name in ("keep_lo", "keep_hi", "skip_lo", "skip_hi"):  # cascades.Read's boxes
            info.push_constant("VEC4", name)
        info.push_constant("FLOAT", "use_gaps")  # 1: move sample points (gap_corrected)
        info.push_constant("VEC4", "tex_mode")  # textured, interpolation, extension codes
        for slot, name in enumerate(SAMPLERS):
            info.sampler(slot, "FLOAT_3D", name)
        info.sampler(len(SAMPLERS), "FLOAT_2D", "albedo_tex")
        info.sampler(len(SAMPLERS) + 1, "FLOAT_2D", "share_tex")
        info.fragment_out(0, "VEC4", "FragColor")
        info.vertex_source(VERTEX_SOURCE)
        tx = core.scene.textures  # the render's footprint rule (albedo_footprint)
        info.define("FOOTPRINT_SPLIT", str(int(tx.FOOTPRINT_SPLIT)))
        info.define("FOOTPRINT_TOL", f"{float(tx.FOOTPRINT_TOL):.9g}")
        info.define("SHARE_K", str(len(tx.SHARE_COS)))
        cosines = ", ".join(f"{float(c):.9g}" for c in tx.SHARE_COS)
        info.fragment_source(f"const float SHARE_COS[SHARE_K] = float[SHARE_K]({cosines});\n"
                             + FRAGMENT_SOURCE)
        shader = _SHADERS["lpv"] = gpu.shader.create_from_info(info)
    return shader


def _texture(shape, fmt: str, data: np.ndarray):
    data = np.ascontiguousarray(data, np.float32)
    buf = gpu.types.Buffer("FLOAT", data.size, data.ravel())
    return gpu.types.GPUTexture(shape, format=fmt, data=buf)


LPV_SAMPLERS = ("lpv_r", "lpv_g", "lpv_b", "lpv_r2", "lpv_g2", "lpv_b2", "lpv_c8")


def lpv_textures(grid, values: np.ndarray):
    """RGBA16F 3D textures of an (R, R, R, 3, 9) grid and the scale the values were divided by
    (the largest magnitude), in ``LPV_SAMPLERS`` order: SH coefficients 0-3 of the R, G, B
    channel, coefficients 4-7 of the R, G, B channel, and one whose RGB is coefficient 8 of
    R, G, B. Texture data is C-order (z, y, x, c); our grid is [x, y, z]."""
    r = grid.resolution
    k = values.shape[-1]
    if k != core.sh.BANDS2:
        raise ValueError(f"LPV grid with {k} SH coefficients ({core.sh.BANDS2} expected)")
    scale = float(np.abs(values).max()) if values.size else 0.0
    scale = scale if scale > 0 and np.isfinite(scale) else 1.0
    zyx = np.asarray(values, np.float32).transpose(2, 1, 0, 3, 4) / scale  # (z, y, x, 3, 9)
    texs = [_texture((r, r, r), "RGBA16F", zyx[:, :, :, ch, 0:4]) for ch in range(3)]
    texs += [_texture((r, r, r), "RGBA16F", zyx[:, :, :, ch, 4:8]) for ch in range(3)]
    last = np.zeros((r, r, r, 4), np.float32)
    last[..., :3] = zyx[..., 8]
    texs.append(_texture((r, r, r), "RGBA16F", last))
    return texs, scale


def _axis_textures(grid, per_face: np.ndarray, fmt: str):
    """Two 3D textures of a (6, R, R, R) per-face array in propagation.AXES order (+x, -x,
    +y, -y, +z, -z): RGB = its +x, +y, +z entries, and its -x, -y, -z entries."""
    arr6 = np.asarray(per_face, np.float32)
    r = grid.resolution
    out = []
    for sign in (0, 1):
        arr = np.ones((r, r, r, 4), np.float32)
        for axis in range(3):
            arr[..., axis] = arr6[2 * axis + sign]
        out.append(_texture((r, r, r), fmt, arr.transpose(2, 1, 0, 3)))
    return out


def visibility_textures(grid, visibility):
    """(+x, +y, +z) and (-x, -y, -z) transmittances of each cell as the lookup reads them
    (lookup.lookup_visibility) as two RGBA16F 3D textures (propagation.AXES order: +x, -x, +y,
    -y, +z, -z); None when nothing blocks."""
    if visibility is None:
        return None
    return _axis_textures(grid, core.lookup.lookup_visibility(visibility), "RGBA16F")


def gap_textures(grid, gaps):
    """geometry_volume.cell_gaps (6, R, R, R) as two RGBA32F 3D textures: RGB = the depths of
    the slabs below each cell's +x, +y, +z faces, and above its -x, -y, -z faces (32-bit: the
    shader compares sample points with them as lookup.gap_corrected does); None without."""
    if gaps is None:
        return None
    return _axis_textures(grid, gaps, "RGBA32F")


def _c(array, n: int) -> np.ndarray:
    """(M, n) C-contiguous float32: vertex buffers read the raw memory (a transposed view
    would be read in the wrong order)."""
    return np.ascontiguousarray(np.asarray(array, np.float32).reshape(-1, n))


def _resource(key, make):
    res = _RESOURCES.get(key)
    if res is None:
        res = _RESOURCES[key] = make()
    return res


def _geometry_batches(result) -> list:
    """(batch, texture or None) per albedo texture of the result's geometry (live._geometry:
    "texture" per triangle, -1 none, into "textures"; "uvs" per corner; "share" per triangle,
    -1 none, into "shares"), untextured first."""
    geo = result.geometry
    t = geo["positions"].shape[0]
    col = np.empty((t, 3, 4), np.float32)
    col[..., :3] = np.asarray(geo["albedo"], np.float32).reshape(t, -1, 3)  # (T,3) or (T,3,3)
    col[..., 3] = np.asarray(geo["receiver"], np.float32)[:, None]
    ids = np.asarray(geo.get("texture", np.full(t, -1)), np.int64)
    uvs = geo.get("uvs")
    uvs = np.zeros((t, 3, 2), np.float32) if uvs is None else np.asarray(uvs, np.float32)
    share = np.repeat(np.asarray(geo.get("share", np.full(t, -1)), np.float32)[:, None], 3, 1)
    out = []
    for k in np.unique(ids):
        sel = ids == k
        attrs = {"pos": _c(geo["positions"][sel], 3), "nor": _c(geo["normals"][sel], 3),
                 "col": _c(col[sel], 4), "uv": _c(uvs[sel], 2),
                 "share": np.ascontiguousarray(share[sel].ravel())}
        out.append((batch_for_shader(_lpv_shader(), "TRIS", attrs),
                    None if k < 0 else geo["textures"][k]))
    return out


def _albedo_texture(texture):
    """The GPU copy (RGBA16F, rows bottom-first like Image.pixels) of a textures.Texture."""
    gtex = _TEXTURES.get(texture.digest)
    if gtex is None:
        h, w = texture.pixels.shape[:2]
        rgba = np.ones((h, w, 4), np.float32)
        rgba[..., :3] = texture.pixels
        gtex = _TEXTURES[texture.digest] = gpu.types.GPUTexture(
            (w, h), format="RGBA16F", data=gpu.types.Buffer("FLOAT", h * w * 4, rgba.ravel()))
        UPLOADS[0] += 1
    return gtex


def share_texture(shares):
    """The stacked view-angle shares (S, K, 3) of textures.view_shares as an RGBA32F 2D
    texture, a row per material, a column per SHARE_COS entry; None without."""
    if shares is None:
        return None
    table = np.asarray(shares, np.float32)
    s, k = table.shape[:2]
    rgba = np.ones((s, k, 4), np.float32)
    rgba[..., :3] = table
    return _texture((k, s), "RGBA32F", rgba)


def reads(result) -> list:
    """The lookups of a result (core.cascades.reads: each cascade's grid and the receivers
    that read it), coarsest first."""
    if result is None:
        return []
    return core.cascades.reads(result)[::-1]


FAR = 1e30  # a box around everything


def _box(grid, inside: bool) -> tuple:
    """(lo, hi) vec4s of a read's box: ``grid``'s, or everything (``inside``) or nothing."""
    if grid is not None:
        lo, hi = grid.bounds()
        return (*lo, 0.0), (*hi, 0.0)
    return ((-FAR,) * 3 + (0.0,), (FAR,) * 3 + (0.0,)) if inside else \
        ((FAR,) * 3 + (0.0,), (-FAR,) * 3 + (0.0,))


def _result_resources(result):
    def make():
        out = []
        gaps = getattr(result, "gaps", None) or {}
        for read in reads(result):
            grid, visibility = read.grid, read.visibility
            values = core.areas.apply_transition_to_grid(grid, read.values, result.areas)
            texs, scale = lpv_textures(grid, values)
            out.append({"grid": grid, "textures": texs, "scale": scale,
                        "keep": _box(read.inside, True), "skip": _box(read.outside, False),
                        "visibility": visibility_textures(grid, visibility),
                        "gaps": gap_textures(grid, gaps.get(grid))})
        ones = _texture((1, 1, 1), "RGBA16F", np.ones(4, np.float32))
        zeros = _texture((1, 1, 1), "RGBA32F", np.zeros(4, np.float32))  # no slabs
        white = gpu.types.GPUTexture((1, 1), format="RGBA16F",
                                     data=gpu.types.Buffer("FLOAT", 4, [1.0] * 4))
        return {"levels": out, "ones": ones, "zeros": zeros, "white": white,
                "shares": share_texture(result.geometry.get("shares")),
                "batches": _geometry_batches(result)}

    return _resource(("result", result.serial), make)


def _prune(keep: set) -> None:
    for key in list(_RESOURCES):
        if key[1] not in keep:
            del _RESOURCES[key]


def _prune_textures(results) -> None:
    """Drop the albedo textures no drawn result uses."""
    used = {t.digest for r in results if r is not None
            for t in (r.geometry.get("textures") or [])}
    for digest in [d for d in _TEXTURES if d not in used]:
        del _TEXTURES[digest]


def free_resources() -> None:
    """Drop every GPU object we made (textures, batches, shaders)."""
    _RESOURCES.clear()
    _TEXTURES.clear()
    _SHADERS.clear()


def resource_count() -> int:
    return len(_RESOURCES) + len(_SHADERS) + len(_TEXTURES)


# -------------------------------------------------------------------------------- drawing


def _matrix(m) -> Matrix:
    return m if isinstance(m, Matrix) else Matrix(np.asarray(m, np.float64).tolist())


def _draw_indirect(result, mvp: Matrix, eye4, view_dir4, weight: float,
                   first_blend: str) -> None:
    """Every cascade of ``result`` (the first pass with ``first_blend``, the rest added)."""
    if not reads(result) or weight <= 0:
        return
    res = _result_resources(result)
    shader = _lpv_shader()
    nudge = core.render.deferred.VIEWER_NUDGE_CELLS * min(lv["grid"].cell_size
                                                      for lv in res["levels"])
    for i, level in enumerate(res["levels"]):
        gpu.state.blend_set(first_blend if i == 0 else "ADDITIVE")
        shader.bind()
        shader.uniform_float("ModelViewProjectionMatrix", mvp)
        g = level["grid"]
        vis = level["visibility"]
        shader.uniform_float("grid", (*g.origin, g.cell_size))
        shader.uniform_float("params", (float(g.resolution), float(weight), level["scale"],
                                        0.0 if vis is None else 1.0))
        shader.uniform_float("eye", eye4)
        shader.uniform_float("view_dir", view_dir4)
        shader.uniform_float("nudge", nudge)
        for name, corner in zip(("keep_lo", "keep_hi"), level["keep"]):
            shader.uniform_float(name, corner)
        for name, corner in zip(("skip_lo", "skip_hi"), level["skip"]):
            shader.uniform_float(name, corner)
        gaps = level["gaps"]
        shader.uniform_float("use_gaps", 0.0 if gaps is None else 1.0)
        for name, tex in zip(LPV_SAMPLERS, level["textures"]):
            shader.uniform_sampler(name, tex)
        plus, minus = vis if vis is not None else (res["ones"], res["ones"])
        shader.uniform_sampler("vis_plus", plus)
        shader.uniform_sampler("vis_minus", minus)
        g_plus, g_minus = gaps if gaps is not None else (res["zeros"], res["zeros"])
        shader.uniform_sampler("gaps_plus", g_plus)
        shader.uniform_sampler("gaps_minus", g_minus)
        shares = res["shares"]  # unread where no triangle has a row
        shader.uniform_sampler("share_tex", res["white"] if shares is None else shares)
        for batch, texture in res["batches"]:
            if texture is None:
                shader.uniform_float("tex_mode", (0.0, 0.0, 0.0, 0.0))
                shader.uniform_sampler("albedo_tex", res["white"])
            else:
                shader.uniform_float("tex_mode", (
                    1.0, INTERPOLATION_CODES[texture.interpolation],
                    EXTENSION_CODES[texture.extension], 0.0))
                shader.uniform_sampler("albedo_tex", _albedo_texture(texture))
            batch.draw(shader)


def _depth_prepass(result, mvp: Matrix) -> None:
    if result is None or result.geometry["positions"].shape[0] == 0:
        return
    shader = gpu.shader.from_builtin("UNIFORM_COLOR")
    batch = _resource(("depth", result.serial), lambda: batch_for_shader(
        shader, "TRIS", {"pos": _c(result.geometry["positions"], 3)}))
    gpu.state.color_mask_set(False, False, False, False)
    gpu.state.depth_mask_set(True)
    gpu.state.depth_test_set("LESS_EQUAL")
    with gpu.matrix.push_pop(), gpu.matrix.push_pop_projection():
        gpu.matrix.load_identity()
        gpu.matrix.load_projection_matrix(mvp)
        shader.uniform_float("color", (0.0, 0.0, 0.0, 1.0))
        batch.draw(shader)
    gpu.state.color_mask_set(True, True, True, True)
    gpu.state.depth_mask_set(False)


def _lines(mvp: Matrix, segments: np.ndarray, color) -> None:
    if segments.size == 0:
        return
    shader = gpu.shader.from_builtin("UNIFORM_COLOR")
    batch = batch_for_shader(shader, "LINES", {"pos": _c(segments, 3)})
    with gpu.matrix.push_pop(), gpu.matrix.push_pop_projection():
        gpu.matrix.load_identity()
        gpu.matrix.load_projection_matrix(mvp)
        shader.uniform_float("color", color)
        batch.draw(shader)


def _colored(mvp: Matrix, kind: str, builtin: str, pos: np.ndarray, col: np.ndarray) -> None:
    if pos.size == 0:
        return
    shader = gpu.shader.from_builtin(builtin)
    batch = batch_for_shader(shader, kind, {"pos": _c(pos, 3), "color": _c(col, 4)})
    with gpu.matrix.push_pop(), gpu.matrix.push_pop_projection():
        gpu.matrix.load_identity()
        gpu.matrix.load_projection_matrix(mvp)
        batch.draw(shader)


def box_segments(lo, hi) -> np.ndarray:
    """(12, 2, 3) edges of the box [lo, hi]."""
    lo, hi = np.asarray(lo, np.float32), np.asarray(hi, np.float32)
    c = np.array([[(hi if (i >> k) & 1 else lo)[k] for k in range(3)] for i in range(8)])
    edges = [(a, a | (1 << k)) for a in range(8) for k in range(3) if not (a >> k) & 1]
    return np.array([[c[a], c[b]] for a, b in edges], np.float32)


def _sphere(subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions and triangles of a subdivided octahedron."""
    verts = [np.array(v, float) for v in
             [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]]
    faces = [(0, 2, 4), (2, 1, 4), (1, 3, 4), (3, 0, 4), (2, 0, 5), (1, 2, 5), (3, 1, 5),
             (0, 3, 5)]

    def mid(a, b, cache):
        key = (min(a, b), max(a, b))
        if key not in cache:
            m = verts[a] + verts[b]
            verts.append(m / np.linalg.norm(m))
            cache[key] = len(verts) - 1
        return cache[key]

    for _ in range(subdivisions):
        cache: dict = {}
        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b, cache), mid(b, c, cache), mid(c, a, cache)
            new += [(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)]
        faces = new
    return np.array(verts), np.array(faces)


def probe_glyphs(grid, values: np.ndarray, max_probes: int = 1500):
    """Triangles (N, 3) and colours (N, 4) of SH glyphs on an even lattice of cells: the
    radius towards w is the intensity max(0, <I, Y(w)>) (its shape per probe) with all 9 of
    the grid's coefficients (band 2 sharpens the lobes), the glyph size grows with the cube root of the probe's flux, coloured by the intensity's
    colour."""
    dirs, faces = _sphere(2)
    k = values.shape[-1]
    if k != core.sh.BANDS2:
        raise ValueError(f"LPV grid with {k} SH coefficients ({core.sh.BANDS2} expected)")
    basis = core.sh.evaluate_basis2(dirs)  # (D, 9)
    r = grid.resolution
    flat = values.reshape(-1, 3, k)
    energy = np.maximum(flat[:, :, 0].mean(axis=1), 0.0)
    peak_energy = float(energy.max(initial=0.0))
    if peak_energy <= 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 4), np.float32)
    stride = max(1, int(np.ceil(r / round(max_probes ** (1.0 / 3.0)))))
    lattice = np.zeros((r, r, r), bool)
    lattice[stride // 2::stride, stride // 2::stride, stride // 2::stride] = True
    idx = np.flatnonzero(lattice.ravel() & (energy > 1e-3 * peak_energy))
    ijk = np.stack(np.unravel_index(idx, (r, r, r)), axis=1)
    centres = grid.origin_array + (ijk + 0.5) * grid.cell_size
    rgb = np.maximum(np.einsum("pcs,ds->pdc", flat[idx], basis), 0.0)  # (P, D, 3)
    radius = rgb.mean(axis=2)
    shape = radius / np.maximum(radius.max(axis=1, keepdims=True), 1e-30)
    size = 0.45 * stride * grid.cell_size * np.cbrt(energy[idx] / peak_energy)
    pos = centres[:, None, :] + dirs[None] * (shape * size[:, None])[..., None]
    col = np.ones(rgb.shape[:2] + (4,))
    col[..., :3] = rgb / np.maximum(rgb.max(axis=(1, 2), keepdims=True), 1e-30)
    return (pos[:, faces].reshape(-1, 3).astype(np.float32),
            col[:, faces].reshape(-1, 4).astype(np.float32))


def _draw_debug(result, mode: str, mvp: Matrix) -> None:
    if result is None or result.grid is None:
        return
    if mode == "CASCADES":
        grids = [result.grid] + [level[0] for level in result.fine or []]
        for i, grid in enumerate(grids):
            lo, hi = grid.bounds()
            _lines(mvp, box_segments(lo, hi), (1.0, 0.8 - 0.25 * i, 0.1 + 0.3 * i, 1.0))
    elif mode == "VPLS" and result.vpl_position is not None:
        flux = result.vpl_flux
        col = np.ones((flux.shape[0], 4), np.float32)
        col[:, :3] = flux / max(float(flux.max()), 1e-30)
        col[:, :3] = np.sqrt(np.clip(col[:, :3], 0, 1))
        gpu.state.point_size_set(4.0)
        _colored(mvp, "POINTS", "POINT_FLAT_COLOR", result.vpl_position, col)
        gpu.state.point_size_set(1.0)
    elif mode == "PROBES" and result.values is not None:
        pos, col = _resource(("probes", result.serial),
                             lambda: probe_glyphs(result.grid, result.values))
        _colored(mvp, "TRIS", "SMOOTH_COLOR", pos, col)
    elif mode == "OCCLUSION" and result.visibility is not None:
        pos, col = _resource(("occlusion", result.serial),
                             lambda: blocked_faces(result.grid, result.visibility))
        gpu.state.point_size_set(3.0)
        _colored(mvp, "POINTS", "POINT_FLAT_COLOR", pos, col)
        gpu.state.point_size_set(1.0)


def blocked_faces(grid, visibility: np.ndarray, threshold: float = 0.02):
    """Points at the cell faces where propagation is blocked (occlusion, clip areas), white
    to red with the blocked fraction 1 - V: (N, 3) positions, (N, 4) colours."""
    vis = np.asarray(visibility, np.float32)
    blocked = 1.0 - vis
    pos, col = [], []
    for i, d in enumerate(core.propagation.AXES):
        idx = np.argwhere(blocked[i] > threshold)
        if idx.size == 0:
            continue
        b = blocked[i][tuple(idx.T)]
        pos.append(grid.origin_array + (idx + 0.5 + 0.5 * d) * grid.cell_size)
        c = np.ones((b.size, 4), np.float32)
        c[:, 1] = c[:, 2] = 1.0 - b
        col.append(c)
    if not pos:
        return np.zeros((0, 3), np.float32), np.zeros((0, 4), np.float32)
    return np.concatenate(pos).astype(np.float32), np.concatenate(col)


def draw(view, projection, mode: str = "ADD", fade: float = 1.0, exposure: float = 0.0,
         depth_prepass: bool = False, current=None, previous=None) -> None:
    """Draw the overlay with the given world-to-view and projection matrices into the bound
    framebuffer. ``fade`` blends ``previous`` (1 - fade) into ``current`` (fade).
    ``depth_prepass`` writes the extracted geometry's depth first (offscreen pictures; the
    viewport already holds the scene's depth)."""
    current = live.STATE.current if current is None else current
    previous = live.STATE.previous if previous is None else previous
    view, projection = _matrix(view), _matrix(projection)
    mvp = projection @ view
    inv = view.inverted_safe()
    ortho = abs(projection[3][3] - 1.0) < 1e-6
    eye4 = (*inv.translation, 1.0 if ortho else 0.0)
    view_dir = -inv.col[2].xyz
    view_dir4 = (*view_dir.normalized(), 0.0)
    _prune({r.serial for r in (current, previous) if r is not None})
    _prune_textures((current, previous))
    try:
        gpu.state.depth_test_set("LESS_EQUAL")
        gpu.state.depth_mask_set(False)
        if mode in ("ADD", "INDIRECT"):
            if depth_prepass:
                _depth_prepass(current, mvp)
            gain = 2.0 ** float(exposure)
            f = fade if previous is not None and previous.values is not None else 1.0
            _draw_indirect(current, mvp, eye4, view_dir4, gain * f,
                           "ADDITIVE" if mode == "ADD" else "NONE")
            if f < 1.0:
                _draw_indirect(previous, mvp, eye4, view_dir4, gain * (1.0 - f), "ADDITIVE")
        else:
            gpu.state.blend_set("ALPHA")
            _draw_debug(current, mode, mvp)
    finally:
        gpu.state.blend_set("NONE")
        gpu.state.depth_mask_set(False)
        gpu.state.depth_test_set("NONE")
        gpu.state.color_mask_set(True, True, True, True)


def _draw_callback() -> None:
    """SpaceView3D POST_VIEW handler."""
    import bpy

    context = bpy.context
    scene = getattr(context, "scene", None)
    props = getattr(scene, "lpv", None) if scene is not None else None
    rv3d = getattr(context, "region_data", None)
    if props is None or rv3d is None or not props.enabled or not props.show_overlay:
        return
    shading = getattr(getattr(context, "space_data", None), "shading", None)
    if scene.render.engine == "LPV_GI" and getattr(shading, "type", "") == "RENDERED":
        return  # the engine's Rendered view holds the indirect light already
    if live.STATE.current is None:
        return
    try:
        draw(rv3d.view_matrix, rv3d.window_matrix, props.overlay_mode, live.fade(props),
             props.overlay_exposure)
    except Exception as exc:  # noqa: BLE001 - never break the viewport; say why once
        if live.STATE.error != f"overlay: {exc}":
            live.STATE.error = f"overlay: {exc}"
            print(f"LPV GI overlay: {exc}")


def add_handler() -> None:
    import bpy

    if not _HANDLES:
        _HANDLES.append(bpy.types.SpaceView3D.draw_handler_add(
            _draw_callback, (), "WINDOW", "POST_VIEW"))


def remove_handler() -> None:
    import bpy

    while _HANDLES:
        bpy.types.SpaceView3D.draw_handler_remove(_HANDLES.pop(), "WINDOW")


def handler_count() -> int:
    return len(_HANDLES)
