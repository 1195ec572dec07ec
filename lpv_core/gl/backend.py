"""moderngl compute-shader (GLSL 430) backend for injection, propagation and lookup.

Mirrors ``injection.inject``, ``propagation.step`` / ``propagate`` (all three angular models:
"sh" with either re-projection, the flux-conserving scale, optional visibility, first step
unoccluded unless ``occlude_first_step``, the accumulation and the early stop; "m1" with the
closure's bundles and the advection matrix; "dom", discrete ordinates (ordinates.py), with its
unfold, per-octant advection, fold into bands 0-2 (9 coefficients per colour, plus the
injected grid extended to band 2 as ordinates.emission_band2) and ``capture_outflow`` (folded to
4 moments); "dom" has no single step on moments and ``step`` raises as numpy's does) and
``lookup.sample`` / ``irradiance`` (4 coefficients: "sh", and "m1" / "dom" read as the
maximum-entropy lobe, closure.LOBE_MODELS; 9 coefficients, whatever the model: the band 0-2
irradiance kernel, sh.irradiance_weights), with the same signatures and semantics. The
shaders are generated from the numpy modules' own tables and constants (propagation.tables,
propagation._m1_tables, ordinates.tables, closure, sh), so a change there carries over; a
change of the algorithm itself must be ported. Agreement: 1e-4 relative or better
(tests/test_gl_backend.py; about 2e-7 of the grid's largest value in practice, up to 5e-7
for a "dom" grid's bands 0-2). Options not ported yet (``capture_outflow`` with "sh" / "m1", unknown keywords)
run the numpy code and are counted in ``GLBackend.fallbacks`` (so is ``flux`` of a
9-coefficient grid, summed by numpy after a readback).

Module-level functions take and return numpy arrays exactly like the numpy ones. The methods
of ``GLBackend`` keep data on the GPU between stages: ``inject`` returns a ``GLGrid`` (a
storage buffer laid out exactly like the numpy array, (R, R, R, 3, K) float32 in C order, K = 4;
9 for a "dom" propagated grid, ``GLGrid.coefficients``), ``propagate`` takes a 4-coefficient one
and reads back only the accumulated grid the engine caches per light (or nothing,
``readback=False``; ``keep_gpu`` keeps it as a GLGrid of the same K), ``irradiance`` takes
either K and reads back only the (M, 3) irradiance.
Positions go up as float64 and become cell coordinates in double precision in the shaders.

Injection without float atomics (they are not core GLSL): every VPL adds its 8 x 12 trilinear
contributions to 64-bit fixed-point accumulators built from two 32-bit words, with integer
``atomicAdd`` on the low word and a carry into the high word when the low word wraps
(``atomicAdd`` returns the old value, so the carry is detected exactly). The sum is exact and
independent of the order, i.e. deterministic. The scale is a power of two S with
S x (largest single contribution) <= 2^24, so every contribution is rounded to an integer of at
most 24 bits (float32's own precision: the only rounding is the same 2^-24 relative step a
float32 product makes), and the totals stay far below 2^63 for any number of VPLs (2^24 x N).
Signed values are biased by +2^24 so that every added word is non-negative (a carry then needs
the second atomic only once per 2^7 adds); one counter per cell removes the bias exactly at
resolve. The quantum 1/S is at most 2^-24 of the brightest contribution, and the brightest cell
holds at least 1/8 of it (band 0 only adds), so the absolute error is below 1e-6 of the grid's
largest value even after 10^4 adds to one cell.

Memory: the "m1" step keeps 27 x 3 vec4 of arrivals per cell between its two passes
(42 MB at 32^3, 340 MB at 64^3, 2.7 GB at 128^3).

"dom" keeps the flux per direction for the whole propagation, q x 3 x R^3 x 4 bytes (q = 64:
768 B per cell; packed per octant into 52 vec4 = 832 B) in each of three rgba32f 3-D textures
(current, next, accumulated; a fourth for the outflow with ``capture_outflow``, on the grid
padded by one cell): 82 MB at 32^3, 650 MB at 64^3, 5.2 GB at 128^3 (plus a few % where a
side is rounded off a power of two, see _texture3d); the folded result, 3 x 9 floats per cell
(108 B), is a storage buffer. The flux is held in images rather than storage buffers because
llvmpipe loads an image texel 3-5x faster than a storage-buffer vec4 at a per-invocation index
(its buffer loads run lane by lane). A step is one dispatch per octant
(each cell gathers its octant's ~8 directions from 8 sources), the moved flux is summed in
double precision per work group and finished in float64, so the early stop decides as numpy's
float64 sum does. The 10 "dom" programs take ~10 s to compile on llvmpipe (once; Mesa's disk
cache keeps them).

Backend "auto" (``auto_backend``) times numpy against GL on a small grid (``measure``, 1-2 s, and
the compile time above the first time on a machine). The choice is kept on disk, in
``auto_backend.json`` under ``$LPV_GI_CACHE_DIR``, else ``$XDG_CACHE_HOME/lpv_gi``, else
``~/.cache/lpv_gi``, keyed by everything it depends on: GL vendor, renderer and version, the
angular model, numpy's version, ``os.cpu_count()``, AUTO_MARGIN and a hash of the timed code's
sources (``code_fingerprint``), so later processes on the same machine reuse it and a change of
any of these measures again. ``LPV_GI_NO_CACHE=1`` turns the file off; an unreadable or
unwritable cache is ignored (the choice is measured), and a failed GL context is not stored.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import propagation, sh
from ..grid import Grid
from ..lookup import REPROJECTION_GAIN
from ..propagation import closure
from ..runtime import jit

LOCAL = 64  # invocations per work group (1-D)
MAX_GROUPS = 65535  # GL's guaranteed GL_MAX_COMPUTE_WORK_GROUP_COUNT per dimension
FIXED_BITS = 24  # largest contribution -> 2^24 (see the module notes)
WORDS_PER_CELL = 25  # 12 x (low, high) + one bias counter
GRID_COEFFICIENTS = (4, sh.BANDS2)  # SH coefficients per colour a grid may hold

_HEADER = """
#version 430
layout(local_size_x = 64) in;
uniform uint base;  // first item of this dispatch (large inputs are dispatched in chunks)
const float PI = 3.14159265358979;
const float C0 = 0.886226925452758;
const float C1 = 1.0233267079464885;
const float SQRT_4PI = 3.5449077018110318;
"""

# World position -> cell coordinates, as grid.cell_coords(p + n x offset x cell_size), in double
# precision (core since GLSL 4.00): whole cells ic0, the fraction fr in [0, 1] (float32 is plenty
# once the whole cells are off) and which way the nearest cell lies. A grid 1e5 m from the
# origin loses nothing, and the nearest-cell test (frac > 0.5 + 1e-3) decides as numpy's does.
# corner_weights: injection.trilinear_corners' weights (zero outside the grid) and, when
# use_vis, injection.visible_corners: each corner x the transmittance of the faces the step
# from the nearest cell to it crosses, renormalised to the inside weight (the plain weights
# where every corner is hidden). Needs R, use_vis and
# a buffer vis[] (6, R, R, R) declared before it.
_CELL_FN = """
vec3 cell_coords(dvec3 p, dvec3 n, out ivec3 ic0, out ivec3 near) {
    dvec3 u = (p - origin) * inv_cell + n * double(offset_cells) - 0.5;
    dvec3 whole = floor(u);
    ic0 = ivec3(clamp(whole, dvec3(-1073741824.0), dvec3(1073741824.0)));
    dvec3 frac = u - whole;
    near = ivec3(greaterThan(frac, dvec3(0.5 + 1e-3)));  // injection.visible_corners' tie rule
    return vec3(frac);
}
void corner_weights(vec3 fr, ivec3 ic0, ivec3 near, out float w[8]) {
    float plain[8];
    float original = 0.0;
    float total = 0.0;
    ivec3 nc = clamp(ic0 + near, ivec3(0), ivec3(R - 1));
    uint cells = uint(R * R * R);
    uint fc = uint((nc.x * R + nc.y) * R + nc.z);
    for (int k = 0; k < 8; ++k) {
        ivec3 d = ivec3((k >> 2) & 1, (k >> 1) & 1, k & 1);
        ivec3 ic = ic0 + d;
        bool inside = all(greaterThanEqual(ic, ivec3(0))) && all(lessThan(ic, ivec3(R)));
        vec3 wv = mix(1.0 - fr, fr, vec3(d));
        float wk = inside ? wv.x * wv.y * wv.z : 0.0;
        original += wk;
        plain[k] = wk;
        if (use_vis != 0) {
            for (int a = 0; a < 3; ++a) {
                int st = d[a] - near[a];
                if (st > 0) wk *= vis[uint(2 * a) * cells + fc];
                else if (st < 0) wk *= vis[uint(2 * a + 1) * cells + fc];
            }
        }
        w[k] = wk;
        total += wk;
    }
    if (use_vis != 0) {  // every corner hidden: the plain weights rather than lose the point
        float scale = total > 0.0 ? original / total : 0.0;
        for (int k = 0; k < 8; ++k) w[k] = total > 0.0 ? w[k] * scale : plain[k];
    }
}
"""

CLEAR_SRC = _HEADER + """
layout(std430, binding = 0) writeonly buffer Dst { uint dst[]; };
uniform uint count;
void main() {
    uint i = base + gl_GlobalInvocationID.x;
    if (i < count) dst[i] = 0u;
}
"""

INJECT_SRC = _HEADER + """
layout(std430, binding = 0) readonly buffer Pos { double pos[]; };  // (N, 3) world
layout(std430, binding = 1) readonly buffer Nrm { double nrm[]; };  // (N, 3)
layout(std430, binding = 2) readonly buffer Flx { double flx[]; };  // (N, 3) W
layout(std430, binding = 3) buffer Acc { uint acc[]; };  // per cell: 12 x (lo, hi), count
layout(std430, binding = 4) readonly buffer Vis { float vis[]; };  // (6, R, R, R)
uniform uint count;
uniform int R;
uniform int use_vis;
uniform dvec3 origin;
uniform double inv_cell;
uniform float offset_cells;
uniform float S;
""" + _CELL_FN + """
void main() {
    uint i = base + gl_GlobalInvocationID.x;
    if (i >= count) return;
    uint o = 3u * i;
    dvec3 nd = dvec3(nrm[o], nrm[o + 1u], nrm[o + 2u]);
    vec3 n = vec3(nd);
    vec3 phi = vec3(flx[o], flx[o + 1u], flx[o + 2u]);
    ivec3 ic0, near;
    vec3 fr = cell_coords(dvec3(pos[o], pos[o + 1u], pos[o + 2u]), nd, ic0, near);
    float wts[8];
    corner_weights(fr, ic0, near, wts);
    vec4 lobe = vec4(C0, -C1 * n.y, C1 * n.z, -C1 * n.x);
    vec4 coef[3];
    for (int ch = 0; ch < 3; ++ch) coef[ch] = (phi[ch] / PI) * lobe;
    for (int k = 0; k < 8; ++k) {
        ivec3 ic = ic0 + ivec3((k >> 2) & 1, (k >> 1) & 1, k & 1);
        float w = wts[k];
        if (!(w > 0.0)) continue;  // also every corner outside the grid
        uint wb = uint((ic.x * R + ic.y) * R + ic.z) * 25u;
        for (int ch = 0; ch < 3; ++ch) {
            for (int j = 0; j < 4; ++j) {
                int q = int(round(coef[ch][j] * w * S));
                uint add = uint(q + 16777216);  // + 2^24: never negative
                uint slot = wb + 2u * uint(ch * 4 + j);
                uint old = atomicAdd(acc[slot], add);
                if (old + add < old) atomicAdd(acc[slot + 1u], 1u);
            }
        }
        atomicAdd(acc[wb + 24u], 1u);
    }
}
"""

RESOLVE_SRC = _HEADER + """
layout(std430, binding = 0) readonly buffer Acc { uint acc[]; };
layout(std430, binding = 1) writeonly buffer Dst { float dst[]; };
uniform uint count;  // cells
uniform float inv_S;
void main() {
    uint c = base + gl_GlobalInvocationID.x;
    if (c >= count) return;
    uint wb = c * 25u;
    uint n = acc[wb + 24u];
    uint blo = n << 24;  // bias n x 2^24 as (bhi, blo)
    uint bhi = n >> 8;
    for (uint j = 0u; j < 12u; ++j) {
        uint lo = acc[wb + 2u * j];
        uint hi = acc[wb + 2u * j + 1u];
        uint rlo = lo - blo;
        uint rhi = hi - bhi - (lo < blo ? 1u : 0u);
        float sgn = 1.0;
        if ((rhi & 0x80000000u) != 0u) {  // negative: two's complement magnitude
            rlo = ~rlo + 1u;
            rhi = ~rhi + (rlo == 0u ? 1u : 0u);
            sgn = -1.0;
        }
        dst[c * 12u + j] = sgn * (float(rhi) * 4294967296.0 + float(rlo)) * inv_S;
    }
}
"""

# Propagation. The face tables (propagation.tables, float32) are baked into the source as
# constants, one program per re-projection mode: their many exact zeros then cost nothing (about
# half the arithmetic of a table lookup, which matters on CPU rasterisers such as llvmpipe).
def _reduce_fn(name: str, gtype: str, out: str, components: int, group: str) -> str:
    """GLSL ``void name(gtype f)``: sums f over a 64-invocation work group (tree reduction in
    shared memory) and writes the group's ``components`` sums to ``out[components x g]``,
    g = ``group`` (an expression of the dispatch's base and the work group id)."""
    writes = "\n".join(f"        {out}[{components}u * g + {i}u] = red_{name}[0].{'xyzw'[i]};"
                        for i in range(components))
    return f"""
shared {gtype} red_{name}[64];
void {name}({gtype} f) {{
    uint l = gl_LocalInvocationID.x;
    red_{name}[l] = f;
    barrier();
    for (uint s = 32u; s > 0u; s >>= 1) {{
        if (l < s) red_{name}[l] += red_{name}[l + s];
        barrier();
    }}
    if (l == 0u) {{
        uint g = {group};
{writes}
    }}
}}
"""


# Per work group flux sums (vec3) -> partial[3 x group], for the early stop.
_REDUCE_FN = _reduce_fn("reduce_flux", "vec3", "partial", 3, "base / 64u + gl_WorkGroupID.x")


def _lit(x) -> str:
    """A GLSL literal that parses back to exactly this float32 value."""
    return repr(float(np.float32(x)))


def _dot(var: str, coeffs) -> str:
    """<var, coeffs> with the zero terms left out."""
    terms = [f"{var}.{'xyzw'[k]} * {_lit(c)}" for k, c in enumerate(coeffs) if c != 0]
    return " + ".join(terms) if terms else "0.0"


def _propagation_sources(reprojection: str) -> tuple[str, str]:
    """(prepare, step) compute shaders with this mode's face tables as constants."""
    ev, rp = propagation.tables(reprojection)  # the numpy backend's own float32 tables
    evals = np.asarray(ev, np.float32).T.reshape(6, 5, 4)  # [direction, face, coefficient]
    reproj = np.asarray(rp, np.float32).reshape(6, 5, 4)
    axes = propagation.AXES.astype(int)
    # Flux-conserving scale of a cell and colour (propagation.step): all 30 faces.
    lines = ["float cell_scale(vec4 v) {", "    float total = 0.0;"]
    for i in range(6):
        for f in range(5):
            lines.append(f"    total += max({_dot('v', evals[i, f])}, 0.0);")
    lines += ["    float held = max(v.x, 0.0) * SQRT_4PI;",
              "    return total > held ? held / total : 1.0;", "}"]
    scale_fn = "\n".join(lines) + "\n"
    prepare = _HEADER + """
layout(std430, binding = 0) readonly buffer Cur { vec4 cur[]; };
layout(std430, binding = 1) writeonly buffer Scale { float scale_out[]; };
layout(std430, binding = 2) writeonly buffer Partial { float partial[]; };
uniform uint count;  // cells
""" + scale_fn + _REDUCE_FN + """
void main() {
    uint c = base + gl_GlobalInvocationID.x;
    vec3 f = vec3(0.0);
    if (c < count) {
        for (uint ch = 0u; ch < 3u; ++ch) {
            vec4 v = cur[c * 3u + ch];
            scale_out[c * 3u + ch] = cell_scale(v);
            f[ch] = max(v.x, 0.0);
        }
    }
    reduce_flux(f);
}
"""
    body = []
    for i in range(6):
        ax = axes[i]
        body.append(f"        // from the neighbour at dst - ({ax[0]}, {ax[1]}, {ax[2]})")
        body.append(f"        s = dst - ivec3({ax[0]}, {ax[1]}, {ax[2]});")
        body.append("        if (all(greaterThanEqual(s, ivec3(0))) && all(lessThan(s, ivec3(R)))) {")
        body.append("            sc = uint((s.x * R + s.y) * R + s.z);")
        body.append(f"            v = use_vis != 0 ? vis[{i}u * count + sc] : 1.0;")
        for ch in range(3):
            body.append(f"            src = cur[sc * 3u + {ch}u];")
            body.append(f"            k = scale_in[sc * 3u + {ch}u];")
            for f in range(5):
                body.append(f"            ff[{f}] = max({_dot('src', evals[i, f])}, 0.0) * k;")
            comps = []
            for j in range(4):
                t = [f"ff[{f}] * {_lit(reproj[i, f, j])}" for f in range(5) if reproj[i, f, j] != 0]
                comps.append(" + ".join(t) if t else "0.0")
            body.append(f"            o{ch} += vec4({', '.join(comps)}) * v;")
        body.append("        }")
    step = _HEADER + """
layout(std430, binding = 0) readonly buffer Cur { vec4 cur[]; };  // (R, R, R, 3) x 4
layout(std430, binding = 1) readonly buffer ScaleIn { float scale_in[]; };
layout(std430, binding = 2) writeonly buffer Nxt { vec4 nxt[]; };
layout(std430, binding = 3) buffer Acc { vec4 acc[]; };
layout(std430, binding = 4) writeonly buffer ScaleOut { float scale_out[]; };
layout(std430, binding = 5) readonly buffer Vis { float vis[]; };  // (6, R, R, R)
layout(std430, binding = 6) writeonly buffer Partial { float partial[]; };
uniform uint count;  // cells
uniform int R;
uniform int use_vis;
uniform int accumulate;
""" + scale_fn + _REDUCE_FN + """
void put(uint c, uint ch, vec4 o) {
    uint q = c * 3u + ch;
    nxt[q] = o;
    if (accumulate != 0) acc[q] += o;
    scale_out[c * 3u + ch] = cell_scale(o);
}
void main() {
    uint c = base + gl_GlobalInvocationID.x;
    vec3 fl = vec3(0.0);
    if (c < count) {
        ivec3 dst = ivec3(int(c) / (R * R), (int(c) / R) % R, int(c) % R);
        vec4 o0 = vec4(0.0), o1 = vec4(0.0), o2 = vec4(0.0);
        ivec3 s;
        uint sc;
        float v, k;
        vec4 src;
        float ff[5];
""" + "\n".join(body) + """
        put(c, 0u, o0);
        put(c, 1u, o1);
        put(c, 2u, o2);
        fl = max(vec3(o0.x, o1.x, o2.x), 0.0);
    }
    reduce_flux(fl);
}
"""
    return prepare, step


# closure.moments: flux held, mean cosine r (clipped) and unit direction d of a cell's SH.
_MOMENTS_FN = """
void moments(vec4 c, out float held, out float r, out vec3 d) {
    held = max(c.x, 0.0) * SQRT_4PI;
    vec3 v = vec3(-c.w, -c.y, c.z) * FLUX_FROM_BAND1;
    float norm = sqrt(dot(v, v));
    r = held > 0.0 ? norm / held : 0.0;
    d = norm > 0.0 ? v / norm : vec3(0.0);
    r = clamp(r, 0.0, MAX_MEAN_COSINE);
}
"""


def _closure_consts() -> str:
    return (f"const float FLUX_FROM_BAND1 = {_lit(closure.FLUX_FROM_BAND1)};\n"
            f"const float MAX_MEAN_COSINE = {_lit(closure.MAX_MEAN_COSINE)};\n")


def _cosine_table() -> tuple[np.ndarray, float]:
    """closure.cosine_expectation's table (n_r, n_t) float32 and its largest mean cosine."""
    closure.cosine_expectation(np.zeros(1), np.zeros(1))  # builds the table on first use
    rs, _ts, table = closure._TABLE
    return np.ascontiguousarray(table, np.float32), float(rs[-1])


def _lookup_source() -> str:
    k1, k2 = sh.IRRADIANCE_KERNEL[1], sh.IRRADIANCE_KERNEL[2]
    return _HEADER + _closure_consts() + f"""
const float Y2A = {_lit(sh.Y2A)};
const float Y2B = {_lit(sh.Y2B)};
const float Y2C = {_lit(sh.Y2C)};
const float W0 = {_lit(sh.IRRADIANCE_KERNEL[0] * sh.Y0)};  // sh.irradiance_weights: A_l Y_lm
const float W1 = {_lit(k1 * sh.Y1)};
const float K_BAND2 = {_lit(k2)};
""" + """
layout(std430, binding = 0) readonly buffer Values { vec4 values[]; };  // (R, R, R, 3) x 4
layout(std430, binding = 6) readonly buffer Values9 { float values9[]; };  // (R, R, R, 3, 9)
layout(std430, binding = 1) readonly buffer Pos { double pos[]; };  // (M, 3) world
layout(std430, binding = 2) readonly buffer Nrm { double nrm[]; };  // (M, 3)
layout(std430, binding = 3) writeonly buffer Dst { float dst[]; };
uniform uint count;
uniform int R;
uniform dvec3 origin;
uniform double inv_cell;
uniform float offset_cells;
uniform float k_irr;  // REPROJECTION_GAIN / cell^2 (mode 1), 1 / cell^2 (modes 2, 3)
uniform int mode;     // 0: SH samples (M, 3 K), no normals; 1: irradiance "sh"; 2: "m1";
                      // 3: bands 0-2 (sh.irradiance_weights)
uniform int nine;     // 1: the grid holds 9 coefficients (values9), else 4 (values)
layout(std430, binding = 4) readonly buffer Table { float table[]; };  // (n_r, n_t)
layout(std430, binding = 5) readonly buffer Vis { float vis[]; };  // (6, R, R, R)
uniform int use_vis;
uniform int n_r;
uniform int n_t;
uniform float r_last;
""" + _CELL_FN + _MOMENTS_FN + """
float cosine_expectation(float r, float t) {  // closure.cosine_expectation, bilinear
    float fr = clamp(r, 0.0, r_last) / r_last * float(n_r - 1);
    float ft = (clamp(t, -1.0, 1.0) + 1.0) / 2.0 * float(n_t - 1);
    int i0 = min(int(floor(fr)), n_r - 2);
    int j0 = min(int(floor(ft)), n_t - 2);
    float a = fr - float(i0);
    float b = ft - float(j0);
    int q = i0 * n_t + j0;
    return (1.0 - a) * (1.0 - b) * table[q] + a * (1.0 - b) * table[q + n_t]
        + (1.0 - a) * b * table[q + 1] + a * b * table[q + n_t + 1];
}
void main() {
    uint i = base + gl_GlobalInvocationID.x;
    if (i >= count) return;
    uint o = 3u * i;
    dvec3 nd = mode == 0 ? dvec3(0.0) : dvec3(nrm[o], nrm[o + 1u], nrm[o + 2u]);
    vec3 n = vec3(nd);
    ivec3 ic0, near;
    vec3 fr = cell_coords(dvec3(pos[o], pos[o + 1u], pos[o + 2u]), nd, ic0, near);
    float wts[8];
    corner_weights(fr, ic0, near, wts);
    vec4 s[3] = vec4[3](vec4(0.0), vec4(0.0), vec4(0.0));
    vec4 s2[3] = vec4[3](vec4(0.0), vec4(0.0), vec4(0.0));  // band 2 (nine): Y2-2 .. Y21
    vec3 s22 = vec3(0.0);                                    // and Y22 per colour
    for (int k = 0; k < 8; ++k) {
        float w = wts[k];
        if (!(w != 0.0)) continue;  // also every corner outside the grid
        ivec3 ic = ic0 + ivec3((k >> 2) & 1, (k >> 1) & 1, k & 1);
        uint vo = uint((ic.x * R + ic.y) * R + ic.z) * 3u;
        if (nine != 0) {
            for (uint ch = 0u; ch < 3u; ++ch) {
                uint b = (vo + ch) * 9u;
                s[ch] += w * vec4(values9[b], values9[b + 1u], values9[b + 2u], values9[b + 3u]);
                s2[ch] += w * vec4(values9[b + 4u], values9[b + 5u], values9[b + 6u],
                                   values9[b + 7u]);
                s22[ch] += w * values9[b + 8u];
            }
        } else {
            s[0] += w * values[vo];
            s[1] += w * values[vo + 1u];
            s[2] += w * values[vo + 2u];
        }
    }
    if (mode == 0) {
        uint width = nine != 0 ? 27u : 12u;
        uint k_coeffs = nine != 0 ? 9u : 4u;
        for (uint ch = 0u; ch < 3u; ++ch) {
            uint o = width * i + ch * k_coeffs;
            for (int j = 0; j < 4; ++j) dst[o + uint(j)] = s[ch][j];
            if (nine != 0) {
                for (int j = 0; j < 4; ++j) dst[o + 4u + uint(j)] = s2[ch][j];
                dst[o + 8u] = s22[ch];
            }
        }
    } else if (mode == 3) {  // <coeffs, sh.irradiance_weights(n)>: Y(-n) x the kernel
        vec4 w1 = vec4(W0, W1 * n.y, -W1 * n.z, W1 * n.x);  // band 2 is even: Y2(-n) = Y2(n)
        vec4 w2 = K_BAND2 * vec4(Y2A * n.x * n.y, Y2A * n.y * n.z, Y2B * (3.0 * n.z * n.z - 1.0),
                                 Y2A * n.x * n.z);
        float w22 = K_BAND2 * Y2C * (n.x * n.x - n.y * n.y);
        for (int ch = 0; ch < 3; ++ch) {
            float e = dot(s[ch], w1) + dot(s2[ch], w2) + s22[ch] * w22;
            dst[3u * i + uint(ch)] = max(e * k_irr, 0.0);
        }
    } else if (mode == 1) {
        vec4 lobe = vec4(C0, C1 * n.y, -C1 * n.z, C1 * n.x);  // lobe(-n)
        for (int ch = 0; ch < 3; ++ch) dst[3u * i + uint(ch)] = max(dot(s[ch], lobe) * k_irr, 0.0);
    } else {
        for (int ch = 0; ch < 3; ++ch) {
            float held, r;
            vec3 d;
            moments(s[ch], held, r, d);
            float e = held * cosine_expectation(r, -dot(d, n)) * k_irr;
            dst[3u * i + uint(ch)] = max(e, 0.0);
        }
    }
}
"""


def _m1_sources() -> tuple[str, str]:
    """(arrivals, gather) shaders of propagation.step_m1, its tables baked in as constants.

    Arrivals, per source cell and colour: the lobe's bundles b_j = exp(kappa <d, w_j>) along
    the q fixed directions, scaled to the flux held, each spread over the 8 neighbours its
    direction points to (the advection matrix's non-zero entries, ~q x 8 of q x 27 x 4).
    Gather, per destination cell: the 27 neighbours' arrivals for it x the visibility of the
    faces crossed. Storage: 27 x 3 vec4 per cell between the two passes.
    """
    dirs, adv, r_max = propagation._m1_tables()
    dirs = np.asarray(dirs, np.float32)
    adv = np.asarray(adv, np.float32).reshape(dirs.shape[0], len(propagation.OFFSETS), 4)
    n_off = len(propagation.OFFSETS)
    lines = []
    for j, w in enumerate(dirs):
        lines.append(f"            cw = dot(d, vec3({_lit(w[0])}, {_lit(w[1])}, {_lit(w[2])}));")
        lines.append("            b = emission != 0u ? (re > 0.5 ? (cw > 0.0 ? "
                     "exp2(ne * log2(cw)) : 0.0) : (1.0 - 2.0 * re) + (cw > 0.0 ? 4.0 * re : "
                     "0.0)) : exp(k * cw);")
        lines.append("            total += b;")
        for k in range(n_off):
            if np.any(adv[j, k] != 0):
                vals = ", ".join(_lit(x) for x in adv[j, k])
                lines.append(f"            a[{k}] += b * vec4({vals});")
    arrivals = _HEADER + _closure_consts() + f"""
const float R_MAX = {_lit(r_max)};
const float EMISSION_R_MAX = {_lit(closure.LAMBERTIAN_MEAN_COSINE)};
layout(std430, binding = 0) readonly buffer Cur {{ vec4 cur[]; }};
layout(std430, binding = 1) writeonly buffer Arr {{ vec4 arr[]; }};  // [(off x cells + c) x 3 + ch]
uniform uint count;  // cells
uniform uint emission;  // 1: read as just-emitted light (closure.emission_density)
""" + _MOMENTS_FN + """
void main() {
    uint c = base + gl_GlobalInvocationID.x;
    if (c >= count) return;
    for (uint ch = 0u; ch < 3u; ++ch) {
        vec4 a[N_OFF];
        for (int k = 0; k < N_OFF; ++k) a[k] = vec4(0.0);
        float held, r;
        vec3 d;
        moments(cur[c * 3u + ch], held, r, d);
        float scale = 0.0;
        if (held > 0.0) {  // empty cells send nothing
            float rc = min(r, R_MAX);
            float k = rc * (3.0 - rc * rc) / (1.0 - rc * rc);  // closure.kappa
            float re = r;  // closure.emission_density: cos^ne above 1/2, else iso + hemisphere
            float rr = clamp(r, 0.5 + 1e-6, EMISSION_R_MAX);
            float ne = rr >= EMISSION_R_MAX ? 1.0 : (2.0 * rr - 1.0) / (1.0 - rr);
            float b, cw, total = 0.0;
BUNDLES
            scale = held / total;
        }
        for (int k = 0; k < N_OFF; ++k) arr[(uint(k) * count + c) * 3u + ch] = a[k] * scale;
    }
}
""".replace("N_OFF", str(n_off)).replace("BUNDLES", "\n".join(lines))
    body = []
    for k, off in enumerate(propagation.OFFSETS):
        vis = [f"vis[{2 * a + (0 if off[a] == 1 else 1)}u * count + sc]"
               for a in range(3) if off[a] != 0]
        body += [f"        s = dst - ivec3({off[0]}, {off[1]}, {off[2]});",
                 "        if (all(greaterThanEqual(s, ivec3(0))) && all(lessThan(s, ivec3(R)))) {",
                 "            sc = uint((s.x * R + s.y) * R + s.z);",
                 f"            v = use_vis != 0 ? {' * '.join(['1.0'] + vis)} : 1.0;",
                 f"            q = ({k}u * count + sc) * 3u;",
                 "            o0 += arr[q] * v;",
                 "            o1 += arr[q + 1u] * v;",
                 "            o2 += arr[q + 2u] * v;",
                 "        }"]
    gather = _HEADER + """
layout(std430, binding = 0) readonly buffer Arr { vec4 arr[]; };
layout(std430, binding = 1) readonly buffer Vis { float vis[]; };  // (6, R, R, R)
layout(std430, binding = 2) writeonly buffer Nxt { vec4 nxt[]; };
layout(std430, binding = 3) buffer Acc { vec4 acc[]; };
layout(std430, binding = 4) writeonly buffer Partial { float partial[]; };
uniform uint count;  // cells
uniform int R;
uniform int use_vis;
uniform int accumulate;
""" + _REDUCE_FN + """
void main() {
    uint c = base + gl_GlobalInvocationID.x;
    vec3 fl = vec3(0.0);
    if (c < count) {
        ivec3 dst = ivec3(int(c) / (R * R), (int(c) / R) % R, int(c) % R);
        vec4 o0 = vec4(0.0), o1 = vec4(0.0), o2 = vec4(0.0);
        ivec3 s;
        uint sc, q;
        float v;
""" + "\n".join(body) + """
        nxt[c * 3u] = o0;
        nxt[c * 3u + 1u] = o1;
        nxt[c * 3u + 2u] = o2;
        if (accumulate != 0) {
            acc[c * 3u] += o0;
            acc[c * 3u + 1u] += o1;
            acc[c * 3u + 2u] += o2;
        }
        fl = max(vec3(o0.x, o1.x, o2.x), 0.0);
    }
    reduce_flux(fl);
}
"""
    return arrivals, gather


# Discrete ordinates (angular="dom", ordinates.py). State: flux per direction, (q, 3, R, R, R)
# float32 (q = 64), ping-pong between two buffers plus the accumulated flux (and, with
# capture_outflow, the flux that reached the one-cell pad shell). Sums for the early stop are
# reduced in double precision per work group and finished in float64 on the CPU.
_DREDUCE_FN = _reduce_fn("reduce_sums", "dvec4", "dpartial", 4,
                         "part_base + base / 64u + gl_WorkGroupID.x")


def _dom_layout():
    """Packing of the flux per cell into vec4 slots: per octant (first direction, directions,
    first slot, slots); its 3 x n (direction, colour) values fill ceil(3 n / 4) vec4s, value
    k = 3 i + colour of direction j0 + i at component k % 4 of slot first + k // 4 (the rest
    of the last slot is zero). Returns (octants, total slots)."""
    from ..propagation import ordinates

    _, _, groups = ordinates.tables()
    out, slot = [], 0
    for sl, _pairs in groups:
        n = sl.stop - sl.start
        m = -(-3 * n // 4)
        out.append((sl.start, n, slot, m))
        slot += m
    return out, slot


def _dom_pack(flux: np.ndarray, tiling: tuple[int, int]) -> bytes:
    """(q, 3, RF, RF, RF) flux per direction -> the bytes of the used region of the flux
    texture (_dom_layout slots, _dom_tiling tiles: slot t's cell (x, y, z) at texel
    (z + RF (t % A), y, x + RF (t // A)))."""
    octants, _ = _dom_layout()
    rf = flux.shape[-1]
    a, b = tiling
    texels = np.zeros((rf * b, rf, rf * a, 4), np.float32)  # (depth, height, width, rgba)
    for j0, n, s0, m in octants:
        values = np.zeros((4 * m, rf, rf, rf), np.float32)
        values[:3 * n] = flux[j0:j0 + n].reshape(3 * n, rf, rf, rf)  # k = 3 i + colour
        values = values.reshape(m, 4, rf, rf, rf).transpose(0, 2, 3, 4, 1)
        for i in range(m):
            t = s0 + i
            texels[rf * (t // a):rf * (t // a + 1), :, rf * (t % a):rf * (t % a + 1)] = values[i]
    return texels.tobytes()


def _not_power_of_two(n: int) -> int:
    """The smallest m >= n that is not a power of two."""
    while n & (n - 1) == 0:
        n += 1
    return n


def _set_tiles(prog, tiles: np.ndarray) -> None:
    """The tiles uniform (only the slots a program reads are active)."""
    u = prog["tiles"]
    u.write(np.ascontiguousarray(tiles[:u.array_length]).tobytes())


def _dom_tiling(r: int, slots: int, max_size: int) -> tuple[int, int] | None:
    """(A, B): the flux of an R^3 grid is one rgba32f 3-D texture (R A, R, R B), slot t's
    cells at the tile (t % A, t // A) (cell (x, y, z) at texel (z + R (t % A), y, x + R (t // A)):
    consecutive invocations read consecutive texels). None if it exceeds max_size."""
    b = -(-slots // max(1, min(slots, max_size // r)))  # fewest rows of tiles
    a = -(-slots // b)  # then the fewest tiles per row: a x b - slots unused tiles < b
    return (a, b) if r * a <= max_size and r * b <= max_size else None


_TEXEL_FN = """
ivec3 cell_of(uint c, int n) { return ivec3(int(c) / (n * n), (int(c) / n) % n, int(c) % n); }
bool inside(ivec3 s, int n) {
    return all(greaterThanEqual(s, ivec3(0))) && all(lessThan(s, ivec3(n)));
}
uint index_of(ivec3 s, int n) { return uint((s.x * n + s.y) * n + s.z); }
ivec3 texel(ivec3 p, int t) { return ivec3(p.z + tiles[t].x, p.y, p.x + tiles[t].y); }
"""


def _dom_sources() -> dict:
    """{"unfold", "fold", ("step", octant)...} shaders of ordinates.unfold / fold / step, the
    tables (ordinates.tables: directions, SH basis, per octant its 8 offsets' trilinear
    weights) baked in as constants. The flux lives in rgba32f 3-D images (_dom_layout,
    _dom_tiling): on llvmpipe an image load costs a fraction of a storage-buffer load with a
    per-invocation index (measured 3-5x), and a GPU caches them as textures.

    unfold, per cell of the flux grid: the injected lobe read as just-emitted light
    (closure.emission_density) over the q directions, scaled to the flux held; band 0 and the
    flux written are summed (injected flux, the early stop's reference). step, one program per
    octant, per destination cell: its octant's directions gather from the 8 (fewer at the
    border) sources dst - offset, x trilinear weight x the source's transmittance towards that
    offset (propagation._offset_visibility); arrivals in the pad shell go to outflow instead.
    The first step writes acc and outflow instead of adding (no clearing pass). fold, per
    output cell: sum_j flux_j Y(w_j) over bands 0-2 (``band2``: the values, 9 coefficients,
    plus the injected grid with its band 2 from ordinates.emission_band2) or bands 0-1 (the
    outflow, 4).
    """
    from ..propagation import ordinates

    dirs, basis, groups = ordinates.tables()
    dirs = np.asarray(dirs, np.float32)
    basis = np.asarray(basis, np.float32)
    q = dirs.shape[0]
    layout, slots = _dom_layout()
    where = {}  # direction -> index of its first value in the packed cell (4 x slots floats)
    for j0, n, s0, _m in layout:
        for i in range(n):
            where[j0 + i] = 4 * s0 + 3 * i
    lines = []
    for j, w in enumerate(dirs):
        lines += [f"        cw = dot(d, vec3({_lit(w[0])}, {_lit(w[1])}, {_lit(w[2])}));",
                  (f"        b[{j}] = r > 0.5 ? (cw > 0.0 ? exp2(ne * log2(cw)) : 0.0) "
                   ": (1.0 - 2.0 * r) + (cw > 0.0 ? 4.0 * r : 0.0);"),
                  f"        total += b[{j}];"]
    writes = [f"        x = b[{j}] * scale; f[{where[j]}u + ch] = x; tot += double(x);"
              for j in range(q)]
    stores = [f"        imageStore(flux, texel(p, {t}), vec4(f[{4 * t}], f[{4 * t + 1}], "
              f"f[{4 * t + 2}], f[{4 * t + 3}]));" for t in range(slots)]
    unfold = _HEADER + _closure_consts() + f"""
const float EMISSION_R_MAX = {_lit(closure.LAMBERTIAN_MEAN_COSINE)};
layout(std430, binding = 0) readonly buffer Inj {{ vec4 inj[]; }};  // (RI, RI, RI, 3) x 4
layout(std430, binding = 1) writeonly buffer DPartial {{ double dpartial[]; }};
layout(rgba32f, binding = 0) writeonly uniform image3D flux;
uniform uint count;  // cells of the flux grid, R^3
uniform int R;       // flux grid (RI + 2 pad)
uniform int RI;      // injected grid
uniform int pad;     // 0, or 1 with capture_outflow
uniform ivec2 tiles[SLOTS];  // per slot its tile's first texel along x and z (_dom_tiling)
uniform uint part_base;
""" + _MOMENTS_FN + _DREDUCE_FN + _TEXEL_FN + """
void main() {
    uint c = base + gl_GlobalInvocationID.x;
    dvec4 sums = dvec4(0.0);
    if (c < count) {
        ivec3 p = cell_of(c, R);
        ivec3 pi = p - pad;
        bool in_grid = inside(pi, RI);
        uint ic = in_grid ? index_of(pi, RI) : 0u;
        double tot = 0.0;
        float f[NF];
        for (int k = 0; k < NF; ++k) f[k] = 0.0;
        for (uint ch = 0u; ch < 3u; ++ch) {
        vec4 v = in_grid ? inj[ic * 3u + ch] : vec4(0.0);
        sums[ch] = double(max(v.x, 0.0));
        float held, r;
        vec3 d;
        moments(v, held, r, d);
        float rr = clamp(r, 0.5 + 1e-6, EMISSION_R_MAX);  // closure.emission_density
        float ne = rr >= EMISSION_R_MAX ? 1.0 : (2.0 * rr - 1.0) / (1.0 - rr);
        float b[Q];
        float cw, x, total = 0.0;
BUNDLES
        if (!(total > 0.0)) {  // nothing points anywhere: uniform (numpy's where(sum > 0))
            for (int j = 0; j < Q; ++j) b[j] = 1.0;
            total = float(Q);
        }
        float scale = held / total;
WRITES
        }
STORES
        sums.w = tot;
    }
    reduce_sums(sums);
}
""".replace("BUNDLES", "\n".join(lines)).replace("WRITES", "\n".join(writes)).replace(
        "STORES", "\n".join(stores)).replace("NF", str(4 * slots)).replace(
        "Q]", f"{q}]").replace("< Q;", f"< {q};").replace("float(Q)", f"float({q})")
    basis2 = np.asarray(sh.evaluate_basis2(dirs), np.float32)  # ordinates.fold's, bands 0-2
    fold4, fold9 = [], []
    for j0, n, s0, m in layout:
        for t in range(m):
            for lines_k in (fold4, fold9):
                lines_k.append(f"            f = imageLoad(acc, texel(pf, {s0 + t}));")
            for comp in range(min(4, 3 * n - 4 * t)):
                k = 4 * t + comp
                y = basis2[j0 + k // 3]
                x = f"f.{'xyzw'[comp]}"

                def vec(v):
                    return f"vec4({', '.join(_lit(c) for c in v)})"

                fold4.append(f"            m{k % 3} += {vec(basis[j0 + k // 3])} * {x};")
                fold9 += [f"            m{k % 3} += {vec(y[:4])} * {x};",
                          f"            n{k % 3} += {vec(y[4:8])} * {x};",
                          f"            e{k % 3} += {_lit(y[8])} * {x};"]
    fold = _HEADER + _closure_consts() + f"""
const float EMISSION_R_MAX = {_lit(closure.LAMBERTIAN_MEAN_COSINE)};
const float Y2A = {_lit(sh.Y2A)};
const float Y2B = {_lit(sh.Y2B)};
const float Y2C = {_lit(sh.Y2C)};
""" + """
layout(rgba32f, binding = 0) readonly uniform image3D acc;        // the flux, RF^3 cells
layout(std430, binding = 0) readonly buffer Inj { vec4 inj[]; };  // (R, R, R, 3) x 4
layout(std430, binding = 1) writeonly buffer Dst { float dst[]; };  // (R, R, R, 3, 4 or 9)
uniform uint count;  // output cells, R^3
uniform int R;
uniform int pad;
uniform ivec2 tiles[SLOTS];
uniform int use_acc;  // 0: no step was run, acc holds nothing
uniform int add_injected;  // with band2: + ordinates.emission_band2 of the injected grid
uniform int band2;    // 1: bands 0-2, 9 coefficients (the lookup's grid); 0: 4 (the outflow)
""" + _MOMENTS_FN + _TEXEL_FN + """
void main() {
    uint c = base + gl_GlobalInvocationID.x;
    if (c >= count) return;
    ivec3 pf = cell_of(c, R) + pad;
    vec4 m0 = vec4(0.0), m1 = vec4(0.0), m2 = vec4(0.0), f;
    vec4 n0 = vec4(0.0), n1 = vec4(0.0), n2 = vec4(0.0);
    float e0 = 0.0, e1 = 0.0, e2 = 0.0;
    if (use_acc != 0) {
        if (band2 != 0) {
FOLD9
        } else {
FOLD4
        }
    }
    vec4 m[3] = vec4[3](m0, m1, m2);
    vec4 nn[3] = vec4[3](n0, n1, n2);
    float e[3] = float[3](e0, e1, e2);
    for (uint ch = 0u; ch < 3u; ++ch) {
        if (add_injected != 0) {
            vec4 v = inj[c * 3u + ch];
            m[ch] += v;
            if (band2 != 0 && v.x > 0.0) {
                // ordinates.emission_band2: c_2m = Phi E[P2(<d, w>)] Y_2m(d) of cos^n
                float held, r;
                vec3 d;
                moments(v, held, r, d);
                float rr = clamp(r, 0.5 + 1e-6, EMISSION_R_MAX);
                float ne = rr >= EMISSION_R_MAX ? 1.0 : (2.0 * rr - 1.0) / (1.0 - rr);
                float h = held * (r > 0.5 ? ne / (ne + 3.0) : 0.0);
                nn[ch] += h * vec4(Y2A * d.x * d.y, Y2A * d.y * d.z, Y2B * (3.0 * d.z * d.z - 1.0),
                                   Y2A * d.x * d.z);
                e[ch] += h * (Y2C * (d.x * d.x - d.y * d.y));
            }
        }
        if (band2 != 0) {
            uint o = (c * 3u + ch) * 9u;
            for (int j = 0; j < 4; ++j) {
                dst[o + uint(j)] = m[ch][j];
                dst[o + 4u + uint(j)] = nn[ch][j];
            }
            dst[o + 8u] = e[ch];
        } else {
            uint o = (c * 3u + ch) * 4u;
            for (int j = 0; j < 4; ++j) dst[o + uint(j)] = m[ch][j];
        }
    }
}
""".replace("FOLD9", "\n".join(fold9)).replace("FOLD4", "\n".join(fold4))
    vis = _HEADER + """
layout(std430, binding = 0) readonly buffer Vis { float vis[]; };  // (6, R, R, R)
layout(rgba32f, binding = 0) writeonly uniform image3D dst;
uniform uint count;  // R^3
uniform int R;
void main() {
    uint c = base + gl_GlobalInvocationID.x;
    if (c >= count) return;
    ivec3 p = ivec3(int(c) / (R * R), (int(c) / R) % R, int(c) % R);
    imageStore(dst, ivec3(p.z, p.y, p.x), vec4(vis[c], vis[count + c], vis[2u * count + c],
                                               vis[3u * count + c]));
    imageStore(dst, ivec3(p.z, p.y, p.x + R), vec4(vis[4u * count + c], vis[5u * count + c],
                                                   1.0, 1.0));
}
"""
    out = {"unfold": unfold, "fold": fold, "vis": vis}
    for o, (_sl, pairs) in enumerate(groups):
        _j0, n, s0, m = layout[o]
        body = [f"        vec4 a{t} = vec4(0.0);" for t in range(m)]
        for _k_off, off, w in pairs:
            w = np.asarray(w, np.float32).reshape(-1)
            faces = [2 * a + (0 if off[a] == 1 else 1) for a in range(3) if off[a] != 0]
            body += [f"        s = dst - ivec3({off[0]}, {off[1]}, {off[2]});",
                     "        if (inside(s, R)) {",
                     "            v = 1.0;"]
            if faces:  # propagation._offset_visibility: the faces it crosses, at the source
                body.append("            if (use_vis != 0 && vis_cell(s, vc)) {")
                if any(f < 4 for f in faces):
                    body.append("                vv = imageLoad(vis, ivec3(vc.z, vc.y, vc.x));")
                    body += [f"                v *= vv.{'xyzw'[f]};" for f in faces if f < 4]
                if any(f >= 4 for f in faces):
                    body.append("                vv = imageLoad(vis, ivec3(vc.z, vc.y, "
                                "vc.x + RV));")
                    body += [f"                v *= vv.{'xy'[f - 4]};" for f in faces if f >= 4]
                body.append("            }")
            for t in range(m):
                ws = [float(w[(4 * t + comp) // 3]) if 4 * t + comp < 3 * n else 0.0
                      for comp in range(4)]
                body.append(f"            a{t} += imageLoad(cur, texel(s, {s0 + t})) * "
                            f"(vec4({', '.join(_lit(x) for x in ws)}) * v);")
            body.append("        }")
        body.append("        if (is_shell) {")
        for t in range(m):
            body += [f"            p = texel(dst, {s0 + t});",
                     (f"            imageStore(outflow, p, first != 0 ? a{t} : "
                      f"imageLoad(outflow, p) + a{t});"),
                     "            imageStore(nxt, p, vec4(0.0));",
                     "            if (first != 0) imageStore(acc, p, vec4(0.0));"]
        body.append("        } else {")
        for t in range(m):
            body += [f"            p = texel(dst, {s0 + t});",
                     f"            imageStore(nxt, p, a{t});",
                     (f"            imageStore(acc, p, first != 0 ? a{t} : "
                      f"imageLoad(acc, p) + a{t});"),
                     "            if (first != 0 && pad != 0) imageStore(outflow, p, vec4(0.0));",
                     (f"            sent += double(a{t}.x) + double(a{t}.y) + double(a{t}.z) "
                      f"+ double(a{t}.w);")]
        body.append("        }")
        out[("step", o)] = _HEADER + """
layout(rgba32f, binding = 0) readonly uniform image3D cur;  // the flux (_dom_tiling)
layout(rgba32f, binding = 1) writeonly uniform image3D nxt;
layout(rgba32f, binding = 2) uniform image3D acc;
layout(rgba32f, binding = 3) uniform image3D outflow;
layout(rgba32f, binding = 4) readonly uniform image3D vis;  // (+x, -x, +y, -y), (+z, -z) per cell
layout(std430, binding = 0) writeonly buffer DPartial { double dpartial[]; };
uniform uint count;  // cells of the flux grid, R^3
uniform int R;       // flux grid (RV + 2 pad)
uniform int RV;      // visibility grid
uniform int pad;     // 1: the outer shell is the pad (capture_outflow)
uniform ivec2 tiles[SLOTS];
uniform int use_vis;
uniform int first;   // the first step: acc and outflow are written, not added to
uniform uint part_base;
""" + _DREDUCE_FN + _TEXEL_FN + """
bool vis_cell(ivec3 s, out ivec3 vc) {  // the pad's transmittance is 1
    vc = s - pad;
    return inside(vc, RV);
}
void main() {
    uint c = base + gl_GlobalInvocationID.x;
    double sent = 0.0;
    if (c < count) {
        ivec3 dst = cell_of(c, R);
        bool is_shell = pad != 0 && (any(equal(dst, ivec3(0))) || any(equal(dst, ivec3(R - 1))));
        ivec3 s, p, vc;
        vec4 vv;
        float v;
""" + "\n".join(body) + """
    }
    reduce_sums(dvec4(0.0, 0.0, 0.0, sent));
}
"""
    return {key: src.replace("SLOTS", str(slots)) for key, src in out.items()}

ADD_SCALED_SRC = _HEADER + """
layout(std430, binding = 0) readonly buffer Src { float src[]; };
layout(std430, binding = 1) buffer Dst { float dst[]; };
uniform uint count;
uniform float weight;
void main() {
    uint i = base + gl_GlobalInvocationID.x;
    if (i < count) dst[i] += weight * src[i];
}
"""


class GLGrid:
    """An (R, R, R, 3, K) float32 SH grid held in a shader storage buffer: K = 4 (injected,
    "sh" / "m1" propagated, the outflow) or 9 (bands 0-2, a "dom" propagated grid)."""

    def __init__(self, buffer, resolution: int, owned: bool = True, coefficients: int = 4):
        if coefficients not in GRID_COEFFICIENTS:
            raise ValueError(f"a grid holds {GRID_COEFFICIENTS} coefficients, not {coefficients}")
        self.buffer = buffer
        self.resolution = int(resolution)
        self.owned = owned  # False for a backend's scratch buffer: release() leaves it alone
        self.coefficients = int(coefficients)

    @property
    def shape(self) -> tuple[int, int, int, int, int]:
        r = self.resolution
        return (r, r, r, 3, self.coefficients)

    @property
    def cells(self) -> int:
        return self.resolution**3

    @property
    def nbytes(self) -> int:
        return self.cells * 12 * self.coefficients

    def read(self) -> np.ndarray:
        """Read back to a numpy array (R, R, R, 3, K) float32."""
        data = self.buffer.read(size=self.nbytes)
        return np.frombuffer(data, np.float32).reshape(self.shape).copy()

    def release(self) -> None:
        if self.buffer is not None and self.owned:
            self.buffer.release()
        self.buffer = None

    def __del__(self):
        with contextlib.suppress(Exception):  # the context may already be gone at exit
            self.release()


@dataclass
class GLPropagationResult(propagation.PropagationResult):
    """``propagation.PropagationResult`` plus the accumulated grid on the GPU (or None)."""

    gpu: GLGrid | None = None


class GLBackend:
    """Compute shaders on one moderngl context (the process's shared one by default)."""

    name = "gl"

    def __init__(self, ctx=None):
        if ctx is None:
            from ..render.raster import gl_context

            ctx = gl_context()
        self.ctx = ctx
        self._programs: dict = {}
        self._scratch: dict = {}
        self._textures: dict = {}  # scratch 3-D textures (the "dom" flux)
        self._dom_src: dict | None = None  # _dom_sources(), generated on first use
        self.fallbacks = 0  # calls answered by the numpy code (modes not ported yet)

    # -- plumbing -------------------------------------------------------------------------------
    def _program(self, name: str, reprojection: str | None = None):
        key = (name, reprojection)
        prog = self._programs.get(key)
        if prog is None:
            if name == "lookup":
                src = _lookup_source()
            elif name in ("m1_arrivals", "m1_gather"):
                src = _m1_sources()[name == "m1_gather"]
            elif name.startswith("dom_"):
                sources = self._dom_src = self._dom_src or _dom_sources()
                src = sources[name[4:] if reprojection is None else (name[4:], reprojection)]
            elif reprojection is None:
                src = _SOURCES[name]
            else:
                prepare, step = _propagation_sources(reprojection)
                src = prepare if name == "prepare" else step
            prog = self.ctx.compute_shader(src)
            self._programs[key] = prog
        return prog

    def _buffer(self, name: str, nbytes: int):
        """A scratch buffer of at least ``nbytes`` (kept and reused between calls)."""
        nbytes = max(int(nbytes), 4)
        buf = self._scratch.get(name)
        if buf is None or buf.size < nbytes:
            if buf is not None:
                buf.release()
            buf = self.ctx.buffer(reserve=nbytes)
            self._scratch[name] = buf
        return buf

    def _run(self, prog, count: int, buffers) -> None:
        """Bind ``buffers`` to storage bindings 0.. and run ``count`` invocations in chunks."""
        for i, buf in enumerate(buffers):
            buf.bind_to_storage_buffer(i)
        if prog.get("count", None) is not None:
            prog["count"].value = int(count)
        groups = -(-int(count) // LOCAL)
        done = 0
        while done < groups:
            g = min(groups - done, MAX_GROUPS)
            prog["base"].value = done * LOCAL
            prog.run(g, 1, 1)
            done += g
        self.ctx.memory_barrier()

    def _upload_f64(self, name: str, array) -> object:
        """(N, 3) array -> scratch buffer of float64 (no copy when it already is one)."""
        a = np.ascontiguousarray(array, np.float64)
        buf = self._buffer(name, a.nbytes)
        buf.write(a)
        return buf

    @staticmethod
    def _set_grid(prog, grid: Grid, offset_cells: float) -> None:
        prog["R"].value = int(grid.resolution)
        prog["origin"].value = tuple(float(v) for v in grid.origin)
        prog["inv_cell"].value = 1.0 / float(grid.cell_size)
        prog["offset_cells"].value = float(offset_cells)

    def upload(self, values: np.ndarray) -> GLGrid:
        """A GPU copy of an (R, R, R, 3, 4) grid (or (R, R, R, 3, 9): bands 0-2)."""
        values = np.ascontiguousarray(values, np.float32)
        r = values.shape[0] if values.ndim else 0
        k = values.shape[-1] if values.ndim else 0
        if values.shape != (r, r, r, 3, k) or k not in GRID_COEFFICIENTS:
            raise ValueError(f"grid values must be (R, R, R, 3, 4) or (R, R, R, 3, 9), "
                             f"not {values.shape}")
        return GLGrid(self.ctx.buffer(values.tobytes()), r, coefficients=k)

    def _as_gpu(self, values, allowed: tuple = (4,)) -> tuple[GLGrid, bool]:
        """(grid on the GPU, whether it was uploaded here and must be released); ValueError
        unless it holds one of ``allowed`` coefficient counts (injection, propagation and the
        outflow take 4; lookup also 9)."""
        if _coefficients(values) not in allowed:
            raise ValueError(f"this stage takes grids of {allowed} SH coefficients per colour, "
                             f"not {tuple(getattr(values, 'shape', np.shape(values)))}")
        if isinstance(values, GLGrid):
            return values, False
        return self.upload(values), True

    def zeros(self, resolution: int, coefficients: int = 4) -> GLGrid:
        out = GLGrid(None, resolution, coefficients=coefficients)
        out.buffer = self.ctx.buffer(reserve=out.nbytes)
        self._run(self._program("clear"), out.nbytes // 4, [out.buffer])
        return out

    def finish(self) -> None:
        self.ctx.finish()

    # -- injection ------------------------------------------------------------------------------
    def inject(self, grid: Grid, positions: np.ndarray, normals: np.ndarray,
               flux: np.ndarray, offset_cells: float = 0.5, visibility=None) -> GLGrid:
        """``injection.inject`` leaving the result on the GPU (``.read()`` gives the array).

        With ``visibility`` (6, R, R, R) the splat leaves out corners behind occluders
        (injection.visible_corners)."""
        r = grid.resolution
        cells = r**3
        out = GLGrid(self.ctx.buffer(reserve=cells * 48), r)
        n = int(np.asarray(positions).shape[0])
        if n == 0:
            self._run(self._program("clear"), cells * 12, [out.buffer])
            return out
        flux = np.ascontiguousarray(flux, np.float64)
        cmax = float(np.abs(flux).max()) / np.pi * sh.C1  # |lobe| <= C1 (> C0)
        scale = fixed_point_scale(cmax)
        inputs = [self._upload_f64(name, a) for name, a in
                  (("vpl_pos", positions), ("vpl_nrm", normals), ("vpl_flux", flux))]
        acc = self._buffer("inject_acc", cells * WORDS_PER_CELL * 4)
        self._run(self._program("clear"), cells * WORDS_PER_CELL, [acc])
        prog = self._program("inject")
        self._set_grid(prog, grid, offset_cells)
        prog["S"].value = scale
        vis = self._visibility(visibility, r)
        prog["use_vis"].value = int(vis is not None)
        vis = vis if vis is not None else self._buffer("no_vis", 4)
        self._run(prog, n, inputs + [acc, vis])
        prog = self._program("resolve")
        prog["inv_S"].value = 1.0 / scale
        self._run(prog, cells, [acc, out.buffer])
        self.ctx.finish()  # the grid is ready on return: per-stage timings stay honest
        return out

    # -- propagation ----------------------------------------------------------------------------

    def _read_flux(self, partial, groups: int) -> np.ndarray:
        p = np.frombuffer(partial.read(size=groups * 12), np.float32).reshape(groups, 3)
        return p.sum(axis=0, dtype=np.float64) * sh.SQRT_4PI

    def _step_into(self, cur: GLGrid, scale_in, nxt: GLGrid, scale_out, acc: GLGrid | None,
                   vis, reprojection: str) -> np.ndarray:
        cells = cur.cells
        groups = -(-cells // LOCAL)
        partial = self._buffer("partial_b", groups * 12)
        prog = self._program("step", reprojection)
        prog["R"].value = cur.resolution
        prog["use_vis"].value = int(vis is not None)
        prog["accumulate"].value = int(acc is not None)
        vis_buf = vis if vis is not None else self._buffer("no_vis", 4)
        acc_buf = acc.buffer if acc is not None else self._buffer("no_acc", 4)
        self._run(prog, cells, [cur.buffer, scale_in, nxt.buffer, acc_buf, scale_out, vis_buf,
                                partial])
        return self._read_flux(partial, groups)

    def _visibility(self, visibility, r: int):
        if visibility is None:
            return None
        if not isinstance(visibility, np.ndarray) and hasattr(visibility, "bind_to_storage_buffer"):
            return visibility  # already a GPU buffer (6, R, R, R) float32
        vis = np.ascontiguousarray(visibility, np.float32)
        if vis.shape != (6, r, r, r):
            raise ValueError(f"visibility must be (6, {r}, {r}, {r}), not {vis.shape}")
        buf = self._buffer("visibility", vis.nbytes)
        buf.write(vis.tobytes())
        return buf

    def _prepare_scale(self, cur: GLGrid, reprojection: str, name: str):
        """Per-cell scale into scratch ``name``; returns it and the flux per colour of ``cur``."""
        cells = cur.cells
        groups = -(-cells // LOCAL)
        scale = self._buffer(name, cells * 12)
        partial = self._buffer("partial_a", groups * 12)
        self._run(self._program("prepare", reprojection), cells, [cur.buffer, scale, partial])
        return scale, self._read_flux(partial, groups)

    def _m1_into(self, cur: GLGrid, nxt: GLGrid, acc: GLGrid | None, vis,
                 emission: bool = False) -> np.ndarray:
        """One propagation.step_m1 from ``cur`` into ``nxt`` (acc += nxt); moved flux."""
        cells = cur.cells
        groups = -(-cells // LOCAL)
        arr = self._buffer("m1_arrivals", cells * len(propagation.OFFSETS) * 48)
        arrivals = self._program("m1_arrivals")
        arrivals["emission"].value = int(bool(emission))
        self._run(arrivals, cells, [cur.buffer, arr])
        partial = self._buffer("partial_b", groups * 12)
        prog = self._program("m1_gather")
        prog["R"].value = cur.resolution
        prog["use_vis"].value = int(vis is not None)
        prog["accumulate"].value = int(acc is not None)
        vis_buf = vis if vis is not None else self._buffer("no_vis", 4)
        acc_buf = acc.buffer if acc is not None else self._buffer("no_acc", 4)
        self._run(prog, cells, [arr, vis_buf, nxt.buffer, acc_buf, partial])
        return self._read_flux(partial, groups)

    def step(self, values, visibility=None, reprojection: str = "kd10",
             angular: str = "sh", emission: bool = False) -> GLGrid:
        """``propagation.step`` on the GPU: the newly arrived intensity as a GLGrid."""
        propagation.refuse_single_step(angular)
        if angular not in ("sh", "m1"):
            return self.upload(self._numpy_step(values, visibility, reprojection, angular))
        if angular == "sh":
            _check_reprojection(reprojection)
        cur, owned = self._as_gpu(values)
        try:
            r = cur.resolution
            vis = self._visibility(visibility, r)
            out = GLGrid(self.ctx.buffer(reserve=cur.nbytes), r)
            if angular == "m1":
                self._m1_into(cur, out, None, vis, emission)
            else:
                scale_a, _ = self._prepare_scale(cur, reprojection, "scale_a")
                scale_b = self._buffer("scale_b", cur.cells * 12)
                self._step_into(cur, scale_a, out, scale_b, None, vis, reprojection)
            return out
        finally:
            if owned:
                cur.release()

    def _numpy_step(self, values, visibility, reprojection, angular, **extra):
        self.fallbacks += 1
        values = values.read() if isinstance(values, GLGrid) else values
        return propagation.step(values, visibility, reprojection, angular, **extra)

    def propagate(self, injected, iterations: int, min_fraction: float = 1e-3,
                  visibility=None, reprojection: str = "kd10", angular: str = "sh",
                  occlude_first_step: bool = False, capture_outflow: bool = False,
                  readback: bool = True, keep_gpu: bool = False,
                  **extra) -> propagation.PropagationResult:
        """``propagation.propagate`` on the GPU (same early stop, same accumulation).

        ``injected`` is a numpy grid or a GLGrid (left untouched). The first step ignores
        ``visibility`` unless ``occlude_first_step``. ``values`` is read back unless
        ``readback`` is False; ``gpu`` holds the accumulated grid when ``keep_gpu``.
        ``capture_outflow`` and any keyword this backend does not know yet run the numpy code
        (counted in ``fallbacks``), so that the engine keeps working while the numpy
        reference moves ahead.
        """
        # ``sweep`` (dom's exact solve, sweep.py) is sequential over the grid's hyperplanes:
        # here the dom steps run up to ``iterations`` with the early stop instead, which
        # converges to the same limit.
        extra.pop("sweep", False)
        passing = extra.pop("passing", None)
        launch = extra.pop("launch", False) and angular == "dom"
        start = None
        if launch and iterations > 0 and not extra:
            # ordinates.launch (and the handed-on light's plain first step) in numpy, the
            # steps after it here
            host = injected.read() if isinstance(injected, GLGrid) else injected
            start, injected = propagation.first_arrivals(host, visibility, occlude_first_step,
                                                         passing)
        elif passing is not None:  # without a launch, handed-on light is injected light
            injected = (injected.read() if isinstance(injected, GLGrid) else injected) + passing
        if angular == "dom" and not extra:
            res = self._propagate_dom(injected, iterations, min_fraction, visibility,
                                      occlude_first_step, capture_outflow, readback, keep_gpu,
                                      start)
            if res is not None:
                return res
        if angular not in ("sh", "m1") or capture_outflow or extra:
            self.fallbacks += 1
            values = injected.read() if isinstance(injected, GLGrid) else injected
            if capture_outflow:
                extra["capture_outflow"] = True
            return propagation.propagate(values, iterations, min_fraction, visibility,
                                         reprojection, angular=angular,
                                         occlude_first_step=occlude_first_step, **extra)
        if angular == "sh":
            _check_reprojection(reprojection)
        src, owned = self._as_gpu(injected)
        try:
            r = src.resolution
            nbytes = src.nbytes
            acc = GLGrid(self.ctx.buffer(reserve=nbytes), r)
            self.ctx.copy_buffer(acc.buffer, src.buffer, size=nbytes)
            vis = self._visibility(visibility, r)
            prep = "kd10" if angular == "m1" else reprojection  # m1: only the flux is used
            scale_cur, flux0 = self._prepare_scale(src, prep, "scale_a")
            scale_nxt = self._buffer("scale_b", src.cells * 12)
            ping = [GLGrid(self._buffer(name, nbytes), r, owned=False) for name in ("ping", "pong")]
            total0 = float(flux0.astype(np.float32).sum())
            fraction = 1.0 if total0 > 0 else 0.0
            done = 0
            early = False
            cur = src
            for k in range(max(int(iterations), 0)):
                if total0 <= 0:
                    early = True
                    break
                nxt = ping[k % 2]
                step_vis = vis if (done > 0 or occlude_first_step) else None
                if angular == "m1":
                    moved = self._m1_into(cur, nxt, acc, step_vis, emission=done == 0)
                else:
                    moved = self._step_into(cur, scale_cur, nxt, scale_nxt, acc, step_vis,
                                            reprojection)
                    scale_cur, scale_nxt = scale_nxt, scale_cur
                cur = nxt
                done += 1
                fraction = float(moved.sum()) / total0
                if fraction < min_fraction:
                    early = True
                    break
            values = acc.read() if readback else None
            if not keep_gpu:
                acc.release()
                acc = None
            return GLPropagationResult(values, done, flux0.astype(np.float32), fraction, early,
                                       gpu=acc)
        finally:
            if owned:
                src.release()

    def _dom_sums(self, partial, groups: int) -> np.ndarray:
        """The double-precision per-work-group sums of a dom pass, finished in float64 (4,)."""
        p = np.frombuffer(partial.read(size=groups * 32), np.float64).reshape(groups, 4)
        return p.sum(axis=0)

    def _texture3d(self, name: str, size: tuple):
        """A scratch rgba32f 3-D texture of at least ``size`` (kept and reused between calls).
        Every side is made not a power of two: llvmpipe compiles a shader variant per
        power-of-two-ness of the bound images (~10 s for the dom shaders), this keeps it one."""
        size = tuple(_not_power_of_two(int(d)) for d in size)
        tex = self._textures.get(name)
        if tex is None or tex.size != tuple(size):
            if tex is not None:
                tex.release()
            tex = self._textures[name] = self.ctx.texture3d(tuple(size), 4, dtype="f4")
        return tex

    def _propagate_dom(self, injected, iterations, min_fraction, visibility, occlude_first_step,
                       capture_outflow, readback, keep_gpu, start=None
                       ) -> propagation.PropagationResult:
        """propagation._propagate_ordinates on the GPU: unfold once, step (one dispatch per
        octant) until the moved flux falls below ``min_fraction`` of the unfolded flux, fold
        the accumulated flux into bands 0-2 (+ the injected grid, extended to band 2 as
        ordinates.emission_band2) once: values (R, R, R, 3, 9), the outflow 4 moments. None if
        the flux textures would exceed GL_MAX_3D_TEXTURE_SIZE (the caller runs the numpy
        code). ``start``: the first step's arrivals, computed on the host (padded flat layout
        (q, 3, (R+2)^3), propagation.first_arrivals): uploaded as step 1, the steps after it
        run here."""
        octants, slots = _dom_layout()
        r = injected.resolution if isinstance(injected, GLGrid) else injected.shape[0]
        pad = 1 if capture_outflow else 0
        rf = r + 2 * pad
        tiling = _dom_tiling(rf, slots, int(self.ctx.info.get("GL_MAX_3D_TEXTURE_SIZE", 2048)))
        if tiling is None:
            return None
        src, owned = self._as_gpu(injected)
        try:
            cells = rf**3
            size = (rf * tiling[0], rf, rf * tiling[1])
            tiles = np.array([(rf * (t % tiling[0]), rf * (t // tiling[0]))
                              for t in range(slots)], np.int32)
            cur, nxt = self._texture3d("dom_a", size), self._texture3d("dom_b", size)
            acc = self._texture3d("dom_acc", size)
            none = self._texture3d("dom_none", (1, 1, 1))
            outflow = self._texture3d("dom_outflow", size) if pad else none
            vis = self._visibility(visibility, r)
            vis_img = none
            if vis is not None:
                vis_img = self._texture3d("dom_vis", (r, r, 2 * r))
                vis_img.bind_to_image(0, read=False, write=True)
                prog = self._program("dom_vis")
                prog["R"].value = r
                self._run(prog, r**3, [vis])
            groups = -(-cells // LOCAL)
            partial = self._buffer("dom_partial", groups * len(octants) * 32)
            prog = self._program("dom_unfold")
            prog["R"].value, prog["RI"].value, prog["pad"].value = rf, r, pad
            _set_tiles(prog, tiles)
            prog["part_base"].value = 0
            cur.bind_to_image(0, read=False, write=True)
            self._run(prog, cells, [src.buffer, partial])
            sums = self._dom_sums(partial, groups)
            injected_flux = (sums[:3] * sh.SQRT_4PI).astype(np.float32)
            total0 = float(sums[3])
            fraction = 1.0 if total0 > 0 else 0.0
            done, early = 0, total0 <= 0
            if start is not None and not early and iterations > 0:
                grid = start.reshape(*start.shape[:2], r + 2, r + 2, r + 2).copy()
                shell = grid.copy()
                shell[..., 1:-1, 1:-1, 1:-1] = 0.0
                grid -= shell  # the interior: what goes on stepping (and is accumulated)
                if not pad:
                    grid = grid[..., 1:-1, 1:-1, 1:-1]
                packed = _dom_pack(grid, tiling)
                for tex in (cur, acc):
                    tex.write(packed, viewport=(0, 0, 0) + size)
                if pad:
                    outflow.write(_dom_pack(shell, tiling), viewport=(0, 0, 0) + size)
                done = 1
                fraction = float(grid.sum(dtype=np.float64)) / total0
                early = fraction < min_fraction
            for _ in range(0 if early else max(int(iterations) - done, 0)):
                use_vis = vis is not None and (done > 0 or occlude_first_step)
                cur.bind_to_image(0, read=True, write=False)
                nxt.bind_to_image(1, read=False, write=True)
                acc.bind_to_image(2, read=True, write=True)
                outflow.bind_to_image(3, read=True, write=True)
                vis_img.bind_to_image(4, read=True, write=False)
                for o in range(len(octants)):
                    prog = self._program("dom_step", o)
                    prog["R"].value, prog["RV"].value, prog["pad"].value = rf, r, pad
                    _set_tiles(prog, tiles)
                    prog["first"].value = int(done == 0)
                    prog["use_vis"].value = int(use_vis)
                    prog["part_base"].value = o * groups
                    self._run(prog, cells, [partial])
                moved = float(self._dom_sums(partial, groups * len(octants))[3])
                cur, nxt = nxt, cur
                done += 1
                fraction = moved / total0
                if fraction < min_fraction:
                    early = True
                    break
            out = GLGrid(None, r, coefficients=sh.BANDS2)  # bands 0-2, as numpy's
            out.buffer = self.ctx.buffer(reserve=out.nbytes)
            fold = self._program("dom_fold")
            _set_tiles(fold, tiles)
            fold["use_acc"].value = int(done > 0)
            fold["R"].value, fold["pad"].value = r, pad
            fold["add_injected"].value = 1
            fold["band2"].value = 1
            acc.bind_to_image(0, read=True, write=False)
            self._run(fold, r**3, [src.buffer, out.buffer])
            outflow_values = None
            if pad:
                outflow_values = np.zeros((rf, rf, rf, 3, 4), np.float32)
                if done > 0:
                    folded = self._buffer("dom_outflow_moments", cells * 48)
                    fold["R"].value, fold["pad"].value = rf, 0
                    fold["add_injected"].value = 0
                    fold["band2"].value = 0  # the outflow stays 4 moments (hand-on)
                    outflow.bind_to_image(0, read=True, write=False)
                    self._run(fold, cells, [src.buffer, folded])
                    outflow_values[:] = np.frombuffer(folded.read(size=cells * 48),
                                                      np.float32).reshape(outflow_values.shape)
            values = out.read() if readback else None
            if not keep_gpu:
                out.release()
                out = None
            return GLPropagationResult(values, done, injected_flux, fraction, early,
                                       outflow_values, gpu=out)
        finally:
            if owned:
                src.release()

    def flux(self, values) -> np.ndarray:
        """Mirror of ``propagation.flux``: flux per colour held by a grid (a 9-coefficient
        grid is read back and summed by numpy)."""
        if _coefficients(values) != 4:
            self.fallbacks += 1
            return propagation.flux(values.read() if isinstance(values, GLGrid) else values)
        cur, owned = self._as_gpu(values)
        try:
            _, f = self._prepare_scale(cur, "kd10", "scale_a")
            return f
        finally:
            if owned:
                cur.release()

    def add_scaled(self, dst: GLGrid, src: GLGrid, weight: float) -> None:
        """dst += weight x src on the GPU (the engine's per-light combine)."""
        prog = self._program("add_scaled")
        if src.shape != dst.shape:
            raise ValueError(f"add_scaled: {src.shape} onto {dst.shape}")
        prog["weight"].value = float(weight)
        self._run(prog, src.nbytes // 4, [src.buffer, dst.buffer])

    # -- lookup ---------------------------------------------------------------------------------
    def _lookup(self, grid: Grid, values, positions, normals, offset_cells: float, mode: int,
                visibility=None):
        positions = np.asarray(positions, np.float64)
        m = positions.shape[0]
        k = _coefficients(values)
        width = 3 * k if mode == 0 else 3
        if m == 0:
            return np.zeros((0, width), np.float64)
        g, owned = self._as_gpu(values, GRID_COEFFICIENTS)
        try:
            pbuf = self._upload_f64("recv_pos", positions)
            nbuf = self._upload_f64("recv_nrm", normals) if normals is not None else pbuf
            out = self._buffer("lookup_out", m * width * 4)
            prog = self._program("lookup")
            self._set_grid(prog, grid, offset_cells)
            gain = REPROJECTION_GAIN if mode == 1 else 1.0
            prog["k_irr"].value = float(gain / grid.cell_size**2)
            prog["mode"].value = mode
            prog["nine"].value = int(k == sh.BANDS2)
            table = self._cosine_table(prog)
            vis = self._visibility(visibility, grid.resolution)
            prog["use_vis"].value = int(vis is not None)
            vis = vis if vis is not None else self._buffer("no_vis", 4)
            g.buffer.bind_to_storage_buffer(6)  # the float view (values9) of the same grid
            self._run(prog, m, [g.buffer, pbuf, nbuf, out, table, vis])
            res = np.frombuffer(out.read(size=m * width * 4), np.float32).reshape(m, width)
            return res.astype(np.float64)
        finally:
            if owned:
                g.release()

    def _cosine_table(self, prog):
        buf = self._scratch.get("cosine_table")
        if buf is None:
            table, r_last = _cosine_table()
            buf = self._scratch["cosine_table"] = self.ctx.buffer(table)
            self._table_shape = (table.shape[0], table.shape[1], r_last)
        n_r, n_t, r_last = self._table_shape
        prog["n_r"].value = n_r
        prog["n_t"].value = n_t
        prog["r_last"].value = r_last
        return buf

    def sample(self, grid: Grid, values, positions: np.ndarray,
               visibility=None) -> np.ndarray:
        """Mirror of ``lookup.sample``: trilinear SH (M, 3, K), K = the grid's coefficients."""
        return self._lookup(grid, values, positions, None, 0.0, 0,
                            visibility).reshape(-1, 3, _coefficients(values))

    def irradiance(self, grid: Grid, values, positions: np.ndarray, normals: np.ndarray,
                   offset_cells: float = 0.5, angular: str = "sh", visibility=None,
                   **extra) -> np.ndarray:
        """Mirror of ``lookup.irradiance``: indirect irradiance (M, 3) in W/m^2 (unknown
        keywords: the numpy code). A 9-coefficient grid (a "dom" propagation's) is read with
        sh.irradiance_weights' kernel, whatever ``angular``, as numpy reads it."""
        if angular not in ("sh",) + closure.LOBE_MODELS or extra:
            from .. import lookup

            self.fallbacks += 1
            values = values.read() if isinstance(values, GLGrid) else values
            return lookup.irradiance(grid, values, positions, normals, offset_cells,
                                     angular=angular, visibility=visibility, **extra)
        if _coefficients(values) == sh.BANDS2:  # bands 0-2 whatever the model, as numpy
            mode = 3
        else:
            mode = 1 if angular == "sh" else 2
        return self._lookup(grid, values, positions, normals, offset_cells, mode, visibility)

    def discard(self, obj) -> None:
        """Free a GLGrid this backend returned (no-op for anything else)."""
        if isinstance(obj, GLGrid):
            obj.release()

    def release(self) -> None:
        """Free the backend's programs and scratch buffers."""
        for obj in (list(self._scratch.values()) + list(self._textures.values())
                    + list(self._programs.values())):
            obj.release()
        self._scratch.clear()
        self._textures.clear()
        self._programs.clear()


_SOURCES = {
    "clear": CLEAR_SRC,
    "inject": INJECT_SRC,
    "resolve": RESOLVE_SRC,
    "add_scaled": ADD_SCALED_SRC,
}


def fixed_point_scale(cmax: float) -> float:
    """Power of two S with S x cmax <= 2^FIXED_BITS (1 for an all-zero or non-finite input)."""
    if not (cmax > 0.0) or not math.isfinite(cmax):
        return 1.0
    e = FIXED_BITS - math.ceil(math.log2(cmax))
    while math.ldexp(cmax, e) > 2.0**FIXED_BITS:  # log2 rounding at exact powers of two
        e -= 1
    return math.ldexp(1.0, max(min(e, 126), -126))


# -- module-level mirrors of the numpy functions (shared backend on the process's context) --------
_BACKEND: GLBackend | None = None


def backend() -> GLBackend:
    """The process's GLBackend on ``raster.gl_context()``."""
    global _BACKEND
    if _BACKEND is None:
        _BACKEND = GLBackend()
    return _BACKEND


def _coefficients(values) -> int:
    """SH coefficients per colour of a numpy grid or GLGrid (its last axis)."""
    shape = values.shape if isinstance(values, GLGrid) else np.shape(values)
    return int(shape[-1]) if shape else 0


def _check_reprojection(reprojection: str) -> None:
    if reprojection not in propagation.REPROJECTIONS:
        raise ValueError(f"reprojection must be one of {propagation.REPROJECTIONS}, "
                         f"not {reprojection!r}")


def _read_release(g: GLGrid) -> np.ndarray:
    try:
        return g.read()
    finally:
        g.release()


def inject(grid: Grid, positions: np.ndarray, normals: np.ndarray, flux: np.ndarray,
           offset_cells: float = 0.5, visibility: np.ndarray | None = None) -> np.ndarray:
    """``injection.inject`` on the GPU: (R, R, R, 3, 4) float32."""
    return _read_release(backend().inject(grid, positions, normals, flux, offset_cells,
                                          visibility))


def step(values: np.ndarray, visibility: np.ndarray | None = None,
         reprojection: str = "kd10", angular: str = "sh", emission: bool = False) -> np.ndarray:
    """``propagation.step`` on the GPU."""
    return _read_release(backend().step(values, visibility, reprojection, angular, emission))


def propagate(injected: np.ndarray, iterations: int, min_fraction: float = 1e-3,
              visibility: np.ndarray | None = None, reprojection: str = "kd10",
              angular: str = "sh", occlude_first_step: bool = False,
              capture_outflow: bool = False, **extra) -> propagation.PropagationResult:
    """``propagation.propagate`` on the GPU."""
    return backend().propagate(injected, iterations, min_fraction, visibility, reprojection,
                               angular, occlude_first_step, capture_outflow, **extra)


def flux(values: np.ndarray) -> np.ndarray:
    """``propagation.flux`` on the GPU (float64 sum of the per-work-group float32 sums)."""
    return backend().flux(values)


def sample(grid: Grid, values: np.ndarray, positions: np.ndarray,
           visibility: np.ndarray | None = None) -> np.ndarray:
    """``lookup.sample`` on the GPU: (M, 3, K) float64."""
    return backend().sample(grid, values, positions, visibility)


def irradiance(grid: Grid, values: np.ndarray, positions: np.ndarray, normals: np.ndarray,
               offset_cells: float = 0.5, angular: str = "sh",
               visibility: np.ndarray | None = None, **extra) -> np.ndarray:
    """``lookup.irradiance`` on the GPU: (M, 3) float64."""
    return backend().irradiance(grid, values, positions, normals, offset_cells, angular,
                                visibility, **extra)


# -- backend choice ---------------------------------------------------------------------------------
_AUTO: dict = {}  # angular model -> auto_backend record


STAGES = ("inject", "propagate", "lookup")


def measure(resolution: int = 16, vpls: int = 16384, receivers: int = 65536,
            iterations: int = 4, repeat: int = 3, gl: GLBackend | None = None,
            angular: str = "sh") -> dict:
    """{stage: {backend: ms}}: the fastest of ``repeat`` interleaved runs of each stage on a
    small random grid (the minimum is the figure least disturbed by other load on the
    machine). GL figures include the transfers the engine makes."""
    from .. import injection, lookup

    if gl is None:
        gl = backend()
    rng = np.random.default_rng(0)
    g = Grid((0.0, 0.0, 0.0), 1.0, resolution)
    pos = rng.uniform(1.0, resolution - 1.0, (vpls, 3))
    nrm = rng.normal(size=(vpls, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    flux = rng.uniform(0.0, 1.0, (vpls, 3))
    rpos = rng.uniform(1.0, resolution - 1.0, (receivers, 3))
    rnrm = rng.normal(size=(receivers, 3))
    rnrm /= np.linalg.norm(rnrm, axis=1, keepdims=True)
    injected = injection.inject(g, pos, nrm, flux)
    kw = {"angular": angular}
    values = propagation.propagate(injected, iterations, **kw).values
    # What the engine asks for. dom: light launched from its surfaces, to convergence (numpy
    # sweeps; GL steps to the early stop, capped at engine.auto_iterations).
    its, stop, engine_kw = iterations, 0.0, kw
    if angular == "dom":
        from ..engine import auto_iterations

        its, stop = auto_iterations(resolution, angular), 1e-3
        engine_kw = dict(kw, launch=True, sweep=True)
    runs = {
        ("inject", "numpy"): lambda: injection.inject(g, pos, nrm, flux),
        ("inject", "gl"): lambda: gl.inject(g, pos, nrm, flux).release(),
        ("propagate", "numpy"): lambda: propagation.propagate(injected, its, stop, **engine_kw),
        ("propagate", "gl"): lambda: gl.propagate(injected, its, stop, **engine_kw),
        ("lookup", "numpy"): lambda: lookup.irradiance(g, values, rpos, rnrm, **kw),
        ("lookup", "gl"): lambda: gl.irradiance(g, values, rpos, rnrm, **kw),
    }
    times = {key: [] for key in runs}
    for fn in runs.values():
        fn()  # warm-up: shader compilation, scratch buffers
    for _ in range(repeat):
        for key, fn in runs.items():
            t0 = time.perf_counter()
            fn()
            times[key].append((time.perf_counter() - t0) * 1000.0)
    out: dict = {stage: {} for stage in STAGES}
    for (stage, name), t in times.items():
        out[stage][name] = round(float(min(t)), 3)
    return out


# GL must beat numpy by this factor to be picked: the measurement is a few runs on a small
# grid of a shared machine (near-ties flipped with load: 40 vs 50 ms), and numpy is the
# reference. A real GPU wins by 10x or more, so the margin costs nothing there.
AUTO_MARGIN = 1.5


def choose(ms: dict) -> dict:
    """{stage: backend} from measure()'s {stage: {backend: ms}}: gl only where it is
    AUTO_MARGIN times faster than numpy."""
    return {stage: "gl" if ms[stage].get("gl", np.inf) * AUTO_MARGIN < ms[stage]["numpy"]
            else "numpy" for stage in STAGES}


CACHE_FILE = "auto_backend.json"
# The modules whose code measure() times (a change to any of them measures again).
_TIMED_MODULES = ("gl_backend", "propagation", "ordinates", "sweep", "injection", "lookup",
                  "closure", "sh", "grid", "jit")
_FINGERPRINT: str | None = None


def code_fingerprint() -> str:
    """sha256 (16 hex digits) of the sources of the code measure() times."""
    global _FINGERPRINT
    if _FINGERPRINT is None:
        h = hashlib.sha256()
        here = Path(__file__).resolve().parent
        for name in _TIMED_MODULES:
            h.update(name.encode())
            try:
                h.update((here / f"{name}.py").read_bytes())
            except OSError:
                h.update(b"?")
        _FINGERPRINT = h.hexdigest()[:16]
    return _FINGERPRINT


def cache_dir() -> Path:
    """Where the auto choice is kept: $LPV_GI_CACHE_DIR, else $XDG_CACHE_HOME/lpv_gi, else
    ~/.cache/lpv_gi."""
    if os.environ.get("LPV_GI_CACHE_DIR"):
        return Path(os.environ["LPV_GI_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "lpv_gi"


def _cache_enabled() -> bool:
    return os.environ.get("LPV_GI_NO_CACHE", "").strip().lower() in ("", "0", "false", "no")


def cache_key(gl: GLBackend, angular: str) -> str:
    """Everything the auto choice depends on, as one string."""
    info = gl.ctx.info
    parts = {"vendor": info.get("GL_VENDOR", ""), "renderer": info.get("GL_RENDERER", ""),
             "version": info.get("GL_VERSION", ""), "angular": angular,
             "numpy": np.__version__, "cpus": os.cpu_count(), "margin": AUTO_MARGIN,
             "code": code_fingerprint(), "cpu_kernels": jit.name()}
    return json.dumps(parts, sort_keys=True)


def _cache_read() -> dict:
    """The cache file's {key: record}; {} when missing, unreadable or not a JSON object."""
    try:
        with open(cache_dir() / CACHE_FILE, encoding="utf-8") as f:
            data = json.load(f)
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _cache_write(key: str, record: dict) -> None:
    """Add ``record`` under ``key`` (atomically: temp file + os.replace); errors are ignored
    (a cache that cannot be written is no cache)."""
    tmp = None
    with contextlib.suppress(Exception):
        folder = cache_dir()
        folder.mkdir(parents=True, exist_ok=True)
        data = _cache_read()
        data[key] = record
        fd, tmp = tempfile.mkstemp(prefix=".auto_backend.", suffix=".tmp", dir=folder)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=1)
        os.replace(tmp, folder / CACHE_FILE)
        tmp = None
    if tmp is not None:  # written but not moved into place
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def _valid(record) -> bool:
    return (isinstance(record, dict) and isinstance(record.get("stages"), dict)
            and set(record["stages"]) == set(STAGES)
            and all(v in ("numpy", "gl") for v in record["stages"].values())
            and record.get("backend") in ("numpy", "gl", "mixed"))


def auto_backend(gl: GLBackend | None = None, angular: str = "sh") -> dict:
    """Where each stage runs fastest on this machine for this angular model (``choose``),
    measured once per machine, GL driver, code version and model (kept on disk, see the module
    notes; "cached": True when read from there) and remembered per process: {"backend":
    "numpy" | "gl" | "mixed", "stages": {stage: backend}, "ms": measure()}."""
    if angular not in _AUTO:
        try:
            if gl is None:
                gl = backend()
            key = None
            if _cache_enabled():
                try:
                    key = cache_key(gl, angular)
                    hit = _cache_read().get(key)
                except Exception:  # noqa: BLE001 - the cache never stops a render
                    key, hit = None, None
                if _valid(hit):
                    stages = {stage: hit["stages"][stage] for stage in STAGES}
                    _AUTO[angular] = dict(hit, stages=stages, cached=True)
                    return _AUTO[angular]
            ms = measure(gl=gl, angular=angular)
            stages = choose(ms)
            names = set(stages.values())
            record = {"backend": names.pop() if len(names) == 1 else "mixed",
                      "stages": stages, "ms": ms, "angular": angular}
            if key is not None:
                _cache_write(key, record)
            _AUTO[angular] = dict(record, cached=False)
        except Exception as exc:  # noqa: BLE001 - no usable GL context: numpy it is
            _AUTO[angular] = {"backend": "numpy", "stages": dict.fromkeys(STAGES, "numpy"),
                              "ms": {}, "angular": angular, "reason": f"gl unavailable: {exc}"}
    return _AUTO[angular]


class MixedBackend:
    """Each stage on the backend that measured fastest for it (``auto_backend``); a grid
    crosses from GL to numpy by one readback, from numpy to GL by one upload."""

    def __init__(self, stages: dict, backends: dict):
        self.stages = dict(stages)
        self._backends = backends
        self.name = "mixed(" + ", ".join(f"{k}={v}" for k, v in self.stages.items()) + ")"

    def inject(self, *args, **kwargs):
        return self._backends[self.stages["inject"]].inject(*args, **kwargs)

    def propagate(self, injected, *args, **kwargs):
        be = self._backends[self.stages["propagate"]]
        if isinstance(injected, GLGrid) and not isinstance(be, GLBackend):
            injected = injected.read()
        return be.propagate(injected, *args, **kwargs)

    def irradiance(self, *args, **kwargs):
        return self._backends[self.stages["lookup"]].irradiance(*args, **kwargs)

    @property
    def fresh_results(self) -> bool:
        """Whether propagate's results are new arrays nobody keeps (engine: no copy)."""
        return getattr(self._backends[self.stages["propagate"]], "fresh_results", False)

    @staticmethod
    def discard(obj) -> None:
        if isinstance(obj, GLGrid):
            obj.release()


def auto_select(gl: GLBackend | None, numpy_backend, angular: str = "sh"):
    """(backend object for settings.backend = "auto", the auto_backend record)."""
    choice = auto_backend(gl, angular) if gl is not None else {
        "backend": "numpy", "stages": dict.fromkeys(STAGES, "numpy"), "ms": {},
        "reason": "gl unavailable"}
    backends = {"numpy": numpy_backend, "gl": gl}
    if choice["backend"] == "mixed":
        return MixedBackend(choice["stages"], backends), choice
    return backends[choice["backend"]], choice
