// The flux per direction of the dom propagation, in one rgba32f 3-D image per state (current,
// next, accumulated, outflow). A cell's 3 x q values (direction, colour) are packed per octant
// into vec4 slots (backend._dom_layout); slot t of the flux grid (RF^3 cells) is a tile of RF^3
// texels: tile (t % TILES_PER_ROW, t / TILES_PER_ROW), cell (x, y, z) at texel
// (z + RF (t % TILES_PER_ROW), y, x + RF (t / TILES_PER_ROW)), so consecutive invocations
// read consecutive texels.
uniform int RF;             // flux grid side
uniform int tiles_per_row;

ivec3 cell_of(uint c, int n) { return ivec3(int(c) / (n * n), (int(c) / n) % n, int(c) % n); }

bool inside(ivec3 s, int n) {
    return all(greaterThanEqual(s, ivec3(0))) && all(lessThan(s, ivec3(n)));
}

ivec3 texel(ivec3 p, int t) {
    return ivec3(p.z + RF * (t % tiles_per_row), p.y, p.x + RF * (t / tiles_per_row));
}
