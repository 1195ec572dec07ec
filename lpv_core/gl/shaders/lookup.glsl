// Indirect irradiance of a 9-coefficient (bands 0-2) grid at receivers (lookup.irradiance):
// the trilinear sample half a cell along the normal (lookup.front_corners, and
// injection.visible_corners' weights where there is a visibility), read with the band 0-2
// irradiance kernel (sh.irradiance_weights).
// Positions are float64 and become cell coordinates in double precision: a grid 1e5 m from the
// origin loses nothing.
layout(std430, binding = 0) readonly buffer Values { float values[]; };  // (R, R, R, 3, 9)
layout(std430, binding = 1) readonly buffer Pos { double pos[]; };  // (M, 3) world
layout(std430, binding = 2) readonly buffer Nrm { double nrm[]; };  // (M, 3)
layout(std430, binding = 3) writeonly buffer Dst { float dst[]; };  // (M, 3) W/m^2
layout(std430, binding = 4) readonly buffer Vis { float vis[]; };   // (6, R, R, R)
uniform uint count;
uniform int R;
uniform dvec3 origin;
uniform double inv_cell;
uniform float offset_cells;
uniform float k_irr;  // 1 / cell^2
uniform int use_vis;

// grid.cell_coords(p + n x offset x cell): whole cells ic0, the fraction fr in [0, 1], and
// which way the nearest cell lies (injection.visible_corners' tie rule: frac > 0.5 + 1e-3)
vec3 cell_coords(dvec3 p, dvec3 n, out ivec3 ic0, out ivec3 near) {
    dvec3 u = (p - origin) * inv_cell + n * double(offset_cells) - 0.5;
    dvec3 whole = floor(u);
    ic0 = ivec3(clamp(whole, dvec3(-1073741824.0), dvec3(1073741824.0)));
    dvec3 frac = u - whole;
    near = ivec3(greaterThan(frac, dvec3(0.5 + 1e-3)));
    return vec3(frac);
}

// injection.trilinear_corners' weights (zero outside the grid) less the corners behind the
// receiver's plane (lookup.front_corners: ahead of -LOOKUP_PLANE cells along n),
// renormalised, and, with use_vis, injection.visible_corners: each corner x the
// transmittance of the faces the step from the nearest cell to it crosses
// (lookup.lookup_visibility: below LOOKUP_OPEN, 0), renormalised to the inside weight (the
// weights before it where every corner is hidden)
void corner_weights(vec3 fr, ivec3 ic0, ivec3 near, vec3 n, out float w[8]) {
    float tri[8];
    float plain[8];
    float original = 0.0;
    float front = 0.0;
    for (int k = 0; k < 8; ++k) {
        ivec3 d = ivec3((k >> 2) & 1, (k >> 1) & 1, k & 1);
        ivec3 ic = ic0 + d;
        bool inside = all(greaterThanEqual(ic, ivec3(0))) && all(lessThan(ic, ivec3(R)));
        vec3 wv = mix(1.0 - fr, fr, vec3(d));
        tri[k] = inside ? wv.x * wv.y * wv.z : 0.0;
        original += tri[k];
        plain[k] = dot(vec3(d) - fr, n) > -LOOKUP_PLANE ? tri[k] : 0.0;
        front += plain[k];
    }
    float fs = front > 0.0 ? original / front : 0.0;
    for (int k = 0; k < 8; ++k) plain[k] = front > 0.0 ? plain[k] * fs : tri[k];
    float total = 0.0;
    ivec3 nc = clamp(ic0 + near, ivec3(0), ivec3(R - 1));
    uint cells = uint(R * R * R);
    uint fc = uint((nc.x * R + nc.y) * R + nc.z);
    for (int k = 0; k < 8; ++k) {
        ivec3 d = ivec3((k >> 2) & 1, (k >> 1) & 1, k & 1);
        float wk = plain[k];
        if (use_vis != 0) {
            for (int a = 0; a < 3; ++a) {
                int st = d[a] - near[a];
                float t = 1.0;
                if (st > 0) t = vis[uint(2 * a) * cells + fc];
                else if (st < 0) t = vis[uint(2 * a + 1) * cells + fc];
                wk *= t < LOOKUP_OPEN ? 0.0 : t;  // lookup.lookup_visibility
            }
        }
        w[k] = wk;
        total += wk;
    }
    if (use_vis != 0) {
        float scale = total > 0.0 ? original / total : 0.0;
        for (int k = 0; k < 8; ++k) w[k] = total > 0.0 ? w[k] * scale : plain[k];
    }
}

void main() {
    uint i = base + gl_GlobalInvocationID.x;
    if (i >= count) return;
    uint o = 3u * i;
    dvec3 nd = dvec3(nrm[o], nrm[o + 1u], nrm[o + 2u]);
    vec3 n = vec3(nd);
    ivec3 ic0, near;
    vec3 fr = cell_coords(dvec3(pos[o], pos[o + 1u], pos[o + 2u]), nd, ic0, near);
    float w[8];
    corner_weights(fr, ic0, near, n, w);
    float s[27];
    for (int j = 0; j < 27; ++j) s[j] = 0.0;
    for (int k = 0; k < 8; ++k) {
        if (!(w[k] != 0.0)) continue;  // also every corner outside the grid
        ivec3 ic = ic0 + ivec3((k >> 2) & 1, (k >> 1) & 1, k & 1);
        uint b = uint((ic.x * R + ic.y) * R + ic.z) * 27u;
        for (int j = 0; j < 27; ++j) s[j] += w[k] * values[b + uint(j)];
    }
    // sh.irradiance_weights(n) = A_l Y_lm(-n): band 1 is odd (sign flips), band 2 even
    float y[9] = float[9](
        W0, W1 * n.y, -W1 * n.z, W1 * n.x,
        W2 * Y2A * n.x * n.y, W2 * Y2A * n.y * n.z, W2 * Y2B * (3.0 * n.z * n.z - 1.0),
        W2 * Y2A * n.x * n.z, W2 * Y2C * (n.x * n.x - n.y * n.y));
    for (int ch = 0; ch < 3; ++ch) {
        float e = 0.0;
        for (int j = 0; j < 9; ++j) e += s[9 * ch + j] * y[j];
        dst[o + uint(ch)] = max(e * k_irr, 0.0);
    }
}
