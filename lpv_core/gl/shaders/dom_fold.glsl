// The flux per direction folded into SH per cell (ordinates.fold): sum_j flux_j Y(w_j), bands
// 0-2 (the lookup's grid, 9 coefficients) or bands 0-1 (the outflow handed on, 4). Output
// cell (x, y, z) reads flux cell (x, y, z) + pad. Needs flux_layout.glsl.
layout(rgba32f, binding = 0) readonly uniform image3D flux;
// [value x 9 + l]: Y_l of the direction of each packed value (0 for the slots' unused ends);
// [SLOTS x 4 x 9 + value]: its colour (backend._dom_fold_table)
layout(std430, binding = 0) readonly buffer Basis { float basis[]; };
layout(std430, binding = 1) writeonly buffer Dst { float dst[]; };  // (R, R, R, 3, K)
uniform uint count;  // output cells, R^3
uniform int R;
uniform int pad;
uniform int K;       // coefficients: 9 or 4

void main() {
    uint c = base + gl_GlobalInvocationID.x;
    if (c >= count) return;
    ivec3 pf = cell_of(c, R) + pad;
    float m[27];
    for (int i = 0; i < 27; ++i) m[i] = 0.0;
    for (int t = 0; t < SLOTS; ++t) {
        vec4 f = imageLoad(flux, texel(pf, t));
        for (int comp = 0; comp < 4; ++comp) {
            int v = 4 * t + comp;
            int ch = int(basis[SLOTS * 36 + v]);
            for (int l = 0; l < K; ++l) m[9 * ch + l] += basis[9 * v + l] * f[comp];
        }
    }
    for (int ch = 0; ch < 3; ++ch) {
        for (int l = 0; l < K; ++l) dst[(c * 3u + uint(ch)) * uint(K) + uint(l)] = m[9 * ch + l];
    }
}
