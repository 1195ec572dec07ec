// One dom propagation step of one octant (ordinates.advance): every destination cell gathers
// its octant's directions from the 8 sources dst - offset, offset = (bits of k) x the octant's
// sign, x the trilinear weight of each direction towards that offset x the source's
// transmittance through the faces the offset crosses (propagation._offset_visibility).
// Arrivals in the pad shell (capture_outflow) go to the outflow; the others are the next
// state and are added to the accumulated flux. The interior arrivals are summed in double
// precision per work group (the early stop's moved flux). Needs flux_layout.glsl.
layout(rgba32f, binding = 0) readonly uniform image3D cur;
layout(rgba32f, binding = 1) writeonly uniform image3D nxt;
layout(rgba32f, binding = 2) uniform image3D acc;
layout(rgba32f, binding = 3) uniform image3D outflow;
layout(rgba32f, binding = 4) readonly uniform image3D vis;  // faces (+x, -x, +y, -y), (+z, -z)
// [slot x 8 + k]: per packed value of the slot, its direction's trilinear weight towards
// offset k (backend._dom_weights, from ordinates.tables)
layout(std430, binding = 0) readonly buffer Weights { vec4 weights[]; };
layout(std430, binding = 1) writeonly buffer Partial { double partial[]; };
uniform uint count;      // cells of the flux grid, RF^3
uniform int RV;          // visibility grid side (RF - 2 pad)
uniform int pad;         // 1: the outer shell of the flux grid is the pad (capture_outflow)
uniform int use_vis;
uniform ivec3 sign;      // the octant's direction signs
uniform int first_slot;  // the octant's slots
uniform int slots;
uniform uint part_base;  // this octant's first work-group sum in partial

shared double red[LOCAL];

void main() {
    uint c = base + gl_GlobalInvocationID.x;
    double sent = 0.0;
    if (c < count) {
        ivec3 dst = cell_of(c, RF);
        bool shell = pad != 0 && (any(equal(dst, ivec3(0))) || any(equal(dst, ivec3(RF - 1))));
        ivec3 src[8];
        float trans[8];
        for (int k = 0; k < 8; ++k) {
            ivec3 off = ivec3((k >> 2) & 1, (k >> 1) & 1, k & 1) * sign;
            src[k] = dst - off;
            trans[k] = inside(src[k], RF) ? 1.0 : 0.0;  // nothing comes from outside
            ivec3 vc = src[k] - pad;  // the pad's transmittance is 1
            if (use_vis != 0 && trans[k] > 0.0 && inside(vc, RV)) {
                vec4 v0 = imageLoad(vis, ivec3(vc.z, vc.y, vc.x));
                vec4 v1 = imageLoad(vis, ivec3(vc.z, vc.y, vc.x + RV));
                float face[6] = float[6](v0.x, v0.y, v0.z, v0.w, v1.x, v1.y);
                for (int a = 0; a < 3; ++a) {
                    if (off[a] != 0) trans[k] *= face[2 * a + (off[a] > 0 ? 0 : 1)];
                }
            }
        }
        for (int t = first_slot; t < first_slot + slots; ++t) {
            vec4 arrived = vec4(0.0);
            for (int k = 0; k < 8; ++k) {
                if (trans[k] > 0.0) {
                    arrived += imageLoad(cur, texel(src[k], t)) * (weights[8 * t + k] * trans[k]);
                }
            }
            ivec3 p = texel(dst, t);
            if (shell) {
                imageStore(outflow, p, imageLoad(outflow, p) + arrived);
                imageStore(nxt, p, vec4(0.0));
            } else {
                imageStore(nxt, p, arrived);
                imageStore(acc, p, imageLoad(acc, p) + arrived);
                sent += double(arrived.x) + double(arrived.y) + double(arrived.z)
                    + double(arrived.w);
            }
        }
    }
    uint l = gl_LocalInvocationID.x;  // tree sum over the work group
    red[l] = sent;
    barrier();
    for (uint s = LOCAL / 2u; s > 0u; s >>= 1) {
        if (l < s) red[l] += red[l + s];
        barrier();
    }
    if (l == 0u) partial[part_base + base / LOCAL + gl_WorkGroupID.x] = red[0];
}
