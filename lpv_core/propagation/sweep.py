"""Transport sweep: the discrete-ordinates propagation (ordinates.py) solved in one ordered
pass over the grid instead of step by step.

A step moves each direction's flux forward only: from a cell to the 8 cells at offsets
{0, s}^3 (s the signs of its octant), scaled by trilinear weights and the source cell's
transmittance towards that offset. Writing T for one step, the light the steps accumulate,
A = sum_k T^k y, solves A = y + T A. Cell by cell that is
    A(c) = (y(c) + sum_{o != 0} f_o(c - o) A(c - o)) / (1 - w_0),
with w_0 = prod_a (1 - |w_a|) < 1 the share that stays in the cell. In the octant's signed
coordinates every source cell c - o lies on an earlier hyperplane u0 + u1 + u2 = t, so the
planes are solved in order, each one at once: the wavefront ordering of discrete-ordinates
transport sweeps (Lewis & Miller 1984, "Computational Methods of Neutron Transport", ch. 4;
Koch, Baker & Alcouffe 1992, the "KBA" sweep). The result is the limit of infinitely many
steps (no iteration cap, no early stop, nothing still in flight) for the work of about
three steps: each cell is visited once per direction.

Layout: the light lives on "positions", the cells of every hyperplane's bounding square in
(u1, u2) in plane order, (positions, 3, directions); a cell's position differs per octant
(its signs). Its input and output are ordinates' padded flat layout (q, 3, (R+2)^3), the
layout unfold, launch and advance produce: gathering it into positions and putting it back
are one np.take / np.put. All 64 directions are swept together on one thread: split over
the 2 cores of this machine the many small numpy operations of a plane contended for the GIL
(16^3: 30 ms on one thread, 49 ms on two, 82 ms on four).

With numba (jit.enabled()) ``solve`` runs a compiled kernel instead, on the padded flat layout
itself: per direction, cell by cell in upwind order (slabs along x, rows along y, the
recurrence along z), no positions and no hyperplanes; the numpy sweep stays the reference and
the fallback. The engine's propagation (launched from surfaces) runs octants.py instead: the
same recurrence for all directions of an octant at once, launched and folded to SH as it goes
(``launch_solve`` and ``fold_parts`` compiled remain for other quadratures and the tests).
"""

from __future__ import annotations

import numpy as np

from .. import sh
from ..runtime import jit
from . import ordinates

SIGNED_OFFSETS = [(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1) if a + b + c]
_PLANS: dict = {}
_FACTORS: list = []  # [(visibility list or None, (R, shell), factors)], most recent first
FACTOR_CACHE = 4  # visibility arrays whose sweep factors are kept (one per cascade)
_DIRECTION_TABLES: dict = {}  # q -> the compiled sweep's per-direction tables
_STACKED: list = []  # [(visibility list or None, R, (rows, (R+2)^3) float32)], most recent first


def positions(p: int) -> int:
    """Positions of a sweep over a p^3 grid: the hyperplanes' bounding squares (~1.67 p^3;
    cached: every propagation checks its memory)."""
    if ("positions", p) not in _PLANS:
        _PLANS["positions", p] = sum((min(p - 1, t) + 1 - max(0, t - 2 * (p - 1))) ** 2
                                     for t in range(3 * p - 2))
    return _PLANS["positions", p]


def memory_bytes(r: int, shell: bool = True) -> int:
    """Bytes a sweep of an R^3 grid holds at once: per position and direction the light
    (3 floats) and its gather index (3 int64), per position and octant the 7 offsets'
    transmittances; per cell and direction the source, the result and its copy for the fold
    (3 floats each)."""
    p = r + 2 if shell else r
    q = ordinates.DIRECTIONS
    return positions(p) * (q * (3 * 4 + 3 * 8) + 8 * 7 * 4) + p**3 * q * 3 * 4 * 3


def check_memory(r: int, shell: bool = True) -> None:
    """Raise ValueError (with the figure) when sweeping an R^3 grid would need more than
    ordinates.STATE_BYTES."""
    need = memory_bytes(r, shell)
    if need > ordinates.STATE_BYTES:
        raise ValueError(
            f"grid_resolution {r} needs about {need / 2**30:.1f} GB for the discrete-ordinates "
            f"sweep (limit {ordinates.STATE_BYTES / 2**30:.0f} GB): use a smaller grid, or "
            "more cascades for a large scene")


def plan(r: int, shell: bool = True) -> dict:
    """Per R^3 grid (cached): the hyperplanes' squares (lo, hi, first position), per octant
    (its direction slice in ordinates.tables, the padded cell of each position), and the
    gather index from the padded flat layout with one zero dummy cell appended per row,
    (q, 3, (R+2)^3 + 1) flattened, into the positions (n, 3, q). ``shell``: the sweep covers
    the padded grid, whose one-cell shell collects what leaves it; without, only the R^3
    interior (light leaving it is dropped: a third less work at 16^3)."""
    if (r, shell) in _PLANS:
        return _PLANS[r, shell]
    dirs, _, groups = ordinates.tables()
    q = len(dirs)
    big = r + 2  # the padded grid the layout holds
    p = big if shell else r  # the grid swept
    o = 0 if shell else 1  # where it starts in the padded grid
    planes, first = [], 0
    for t in range(3 * p - 2):
        lo, hi = max(0, t - 2 * (p - 1)), min(p - 1, t) + 1
        planes.append((lo, hi, first))
        first += (hi - lo) ** 2
    t_of = np.concatenate([np.full((hi - lo) ** 2, t) for t, (lo, hi, _) in enumerate(planes)])
    u1 = np.concatenate([np.repeat(np.arange(lo, hi), hi - lo) for lo, hi, _ in planes])
    u2 = np.concatenate([np.tile(np.arange(lo, hi), hi - lo) for lo, hi, _ in planes])
    u0 = t_of - u1 - u2
    valid = (u0 >= 0) & (u0 < p)
    u0 = np.clip(u0, 0, p - 1)
    octants = []
    index = np.empty((first, 3, q), np.int64)
    row = big**3 + 1
    for sl, _ in groups:
        sign = np.where(dirs[sl.start] < 0, -1, 1)
        i, j, k = ((u if s > 0 else p - 1 - u) + o for u, s in zip((u0, u1, u2), sign))
        cell = np.where(valid, (i * big + j) * big + k, big**3)
        octants.append((sl, cell))
        index[:, :, sl] = (np.arange(sl.start, sl.stop) * 3 + np.arange(3)[:, None]) * row \
            + cell[:, None, None]
    inside = np.zeros((big, big, big), bool)
    inside[1:-1, 1:-1, 1:-1] = True
    _PLANS[r, shell] = {"p": p, "planes": planes, "positions": first, "octants": octants,
                        "index": index, "inside": inside.reshape(-1),
                        "shell": np.flatnonzero(~inside)}
    return _PLANS[r, shell]


def factors(r: int, offset_visibility: list | None, shell: bool = True) -> tuple:
    """(transmittance, weight, column, 1 / (1 - w_0)): the transmittance of each position's
    cell towards each SIGNED_OFFSETS entry, per octant ({offset: (positions, 8)}; 0 in the
    padded shell, which only receives: what lands there left the grid), each direction's
    trilinear weight towards it ({offset: (q,)}), each direction's octant (q,) and the
    self-share term (q,). The sweep multiplies transmittance and weight plane by plane: a
    fused (positions, q) table per offset took longer to write than it saved (16^3: 25 ms
    against 1.6 ms, for 7 ms more sweeping). Cached for the last FACTOR_CACHE visibility
    arrays (one per cascade)."""
    for vis, key, table in _FACTORS:
        if vis is offset_visibility and key == (r, shell):
            return table
    pl = plan(r, shell)
    pairs_of = {sl.start: pairs for sl, pairs in ordinates.tables()[2]}
    inside = pl["inside"].astype(np.float32)
    n, k, q = pl["positions"], len(pl["octants"]), ordinates.DIRECTIONS
    vis = {off: np.empty((n, k), np.float32) for off in SIGNED_OFFSETS}
    weight = {off: np.empty(q, np.float32) for off in SIGNED_OFFSETS}
    column = np.empty(q, np.intp)
    inv = np.empty(q, np.float32)
    padded = {}
    for o, (sl, cell) in enumerate(pl["octants"]):
        column[sl] = o
        for k_off, off, w in pairs_of[sl.start]:
            w = w[:, 0, 0, 0, 0]
            soff = tuple(abs(x) for x in off)
            if soff == (0, 0, 0):
                inv[sl] = 1.0 / (1.0 - w)
                continue
            if k_off not in padded:
                v = inside
                if offset_visibility is not None:
                    v = np.pad(offset_visibility[k_off].astype(np.float32), 1).reshape(-1)
                padded[k_off] = np.append(v, np.float32(0.0))
            vis[soff][:, o] = padded[k_off][cell]
            weight[soff][sl] = w
    table = (vis, weight, column, inv)
    _FACTORS.insert(0, (offset_visibility, (r, shell), table))
    del _FACTORS[FACTOR_CACHE:]
    return table


def _sweep(x: np.ndarray, planes: list, vis: dict, weight: dict, column: np.ndarray,
           inv: np.ndarray) -> None:
    """Solve in place: ``x`` (positions, 3, q) holds the source light on entry and the
    accumulated light A on return, plane after plane (``factors`` gives the rest)."""
    width, k = x.shape[2], next(iter(vis.values())).shape[1]
    most = max((hi - lo) ** 2 for lo, hi, _ in planes) * width
    buf, fbuf = np.empty(most * 3, np.float32), np.empty(most, np.float32)
    for t, (lo, hi, first) in enumerate(planes):
        h = hi - lo
        dst = x[first:first + h * h].reshape(h, h, 3, width)
        for off in SIGNED_OFFSETS:
            s = sum(off)
            if t < s:
                continue
            lo2, hi2, first2 = planes[t - s]
            h2 = hi2 - lo2
            _, b, c = off
            j0, j1 = max(lo, lo2 + b), min(hi, hi2 + b)
            k0, k1 = max(lo, lo2 + c), min(hi, hi2 + c)
            if j1 <= j0 or k1 <= k0:
                continue
            sj = slice(j0 - b - lo2, j1 - b - lo2)
            sk = slice(k0 - c - lo2, k1 - c - lo2)
            hj, hk = j1 - j0, k1 - k0
            src = x[first2:first2 + h2 * h2].reshape(h2, h2, 3, width)[sj, sk]
            fac = fbuf[:hj * hk * width].reshape(hj, hk, 1, width)
            np.take(vis[off][first2:first2 + h2 * h2].reshape(h2, h2, k)[sj, sk], column,
                    axis=2, out=fac[:, :, 0], mode="clip")
            fac *= weight[off]
            tmp = buf[:hj * hk * 3 * width].reshape(hj, hk, 3, width)
            np.multiply(fac, src, out=tmp)
            dst[j0 - lo:j1 - lo, k0 - lo:k1 - lo] += tmp
        dst *= inv


def direction_tables() -> dict:
    """Per direction, in ordinates.tables order (cached): its octant's signs (q, 3), per
    SIGNED_OFFSETS entry its trilinear weight (q, 7) and its index into propagation.OFFSETS
    (q, 7) (the row of ``stacked_visibility``; "none": all 0, its one row without
    visibility), 1 / (1 - w_0) (q,), the SIGNED_OFFSETS themselves (7, 3) and each octant's
    (first, stop) direction: what the compiled sweep reads instead of ``plan`` and
    ``factors``."""
    q = ordinates.DIRECTIONS
    if q in _DIRECTION_TABLES:
        return _DIRECTION_TABLES[q]
    dirs, _, groups = ordinates.tables()
    sign = np.where(dirs < 0, -1, 1).astype(np.int64)
    weight = np.zeros((q, len(SIGNED_OFFSETS)), np.float32)
    koff = np.zeros((q, len(SIGNED_OFFSETS)), np.int64)
    inv = np.empty(q, np.float32)
    for sl, pairs in groups:
        for k_off, off, w in pairs:
            w = w[:, 0, 0, 0, 0]
            soff = tuple(abs(x) for x in off)
            if soff == (0, 0, 0):
                inv[sl] = 1.0 / (1.0 - w)
                continue
            m = SIGNED_OFFSETS.index(soff)
            weight[sl, m] = w
            koff[sl, m] = k_off
    _DIRECTION_TABLES[q] = {"sign": sign, "weight": weight, "koff": koff,
                            "none": np.zeros_like(koff), "inv": inv,
                            "offsets": np.array(SIGNED_OFFSETS, np.int64),
                            "octants": [(sl.start, sl.stop) for sl, _ in groups]}
    return _DIRECTION_TABLES[q]


def stacked_visibility(r: int, offset_visibility: list | None) -> np.ndarray:
    """The transmittances the compiled sweep reads, one padded flat row per
    propagation.OFFSETS entry ((27, (R+2)^3) float32, 0 in the shell: it only receives), or
    without visibility one row, 1 inside and 0 in the shell. Cached like ``factors``, by the
    identity of the list, for the last FACTOR_CACHE of them."""
    for vis, key, table in _STACKED:
        if vis is offset_visibility and key == r:
            return table
    p = r + 2
    if offset_visibility is None:
        table = np.zeros((1, p, p, p), np.float32)
        table[:, 1:-1, 1:-1, 1:-1] = 1.0
    else:
        table = np.zeros((len(offset_visibility), p, p, p), np.float32)
        for k, v in enumerate(offset_visibility):
            table[k, 1:-1, 1:-1, 1:-1] = v
    table = table.reshape(len(table), -1)
    _STACKED.insert(0, (offset_visibility, r, table))
    del _STACKED[FACTOR_CACHE:]
    return table


@jit.kernel
def _add_slab_behind(a0, a1, a2, v, w, shift, scale, c0, c1):  # pragma: no cover - compiled
    """Cells c0..c1-1 of one slab, all three colours: what arrives from the slab behind (the
    4 offsets with an x part, SIGNED_OFFSETS[3:]: ``shift`` their flat offsets, ``v`` and
    ``w`` their transmittance rows and weights, indexed like SIGNED_OFFSETS) added and the
    sum times ``scale`` ((c1 - c0,): 1 / (1 - w_0) inside the grid, 1 in the shell). One loop
    the compiler vectorizes: c0..c1 leaves out the slab's upwind edge (``_sweep_direction``),
    so no source range overlaps the cells written, else its runtime check falls back to
    scalar code."""
    d0, d1, d2 = a0[c0:c1], a1[c0:c1], a2[c0:c1]
    s, t = c0 - shift[3], c1 - shift[3]
    x0, x1, x2, v3 = a0[s:t], a1[s:t], a2[s:t], v[3][s:t]
    s, t = c0 - shift[4], c1 - shift[4]
    y0, y1, y2, v4 = a0[s:t], a1[s:t], a2[s:t], v[4][s:t]
    s, t = c0 - shift[5], c1 - shift[5]
    z0, z1, z2, v5 = a0[s:t], a1[s:t], a2[s:t], v[5][s:t]
    s, t = c0 - shift[6], c1 - shift[6]
    u0, u1, u2, v6 = a0[s:t], a1[s:t], a2[s:t], v[6][s:t]
    w3, w4, w5, w6 = w[3], w[4], w[5], w[6]
    for t in range(c1 - c0):
        f3, f4, f5, f6 = w3 * v3[t], w4 * v4[t], w5 * v5[t], w6 * v6[t]
        d0[t] = scale[t] * (d0[t] + f3 * x0[t] + f4 * y0[t] + f5 * z0[t] + f6 * u0[t])
        d1[t] = scale[t] * (d1[t] + f3 * x1[t] + f4 * y1[t] + f5 * z1[t] + f6 * u1[t])
        d2[t] = scale[t] * (d2[t] + f3 * x2[t] + f4 * y2[t] + f5 * z2[t] + f6 * u2[t])


@jit.kernel
def _scale_slab(a0, a1, a2, scale, base):  # pragma: no cover - compiled
    """The slab at ``base`` (all colours) times ``scale`` (plane,): a slab with nothing
    behind it."""
    for col in (a0, a1, a2):
        dst = col[base:base + scale.shape[0]]
        for t in range(scale.shape[0]):
            dst[t] *= scale[t]


@jit.kernel
def _row_factors(f, v, w, scale, c0):  # pragma: no cover - compiled
    """f[t] = scale[t] w v[c0 + t] for the cells t of one slab: a within-slab offset's factor
    (transmittance of the source, weight, the receiving cell's 1 / (1 - w_0)), vectorized
    once per slab and read by the recurrence (c0 = the slab's first cell less the offset)."""
    vv = v[c0:c0 + f.shape[0]]
    for t in range(f.shape[0]):
        f[t] = scale[t] * (w * vv[t])


@jit.kernel
def _sweep_rows(a0, a1, a2, fy0, fy1, fz, base, p, lo, hi, first, sy, sz):  # pragma: no cover
    """Rows first..n-1 (upwind order) of the slab at ``base``, cells lo..hi-1 of each, whose
    sums so far (source, slab behind, scale) are in a: per cell, in upwind order along z,
    what arrives from the row behind (offsets (0,1,0), (0,1,1): that row is final) and the
    recurrence along z (0,0,1), its factors fy0, fy1, fz (``_row_factors``, by cell in the
    slab). One pass per row, the cell behind and the row-behind cell behind it (the (0,1,1)
    source) kept in registers. A row's first cell has no source in the row: b and q start
    at 0, and its factors towards the wrapped flat neighbours (shell cells) are 0 anyway.
    Indices are cast to unsigned: numba then skips its negative-index wraparound."""
    n = hi - lo
    back = sy * p  # flat offset to the row behind
    zero = np.float32(0.0)
    for jj in range(first, n):
        j = lo + jj if sy > 0 else hi - 1 - jj
        t = j * p + (lo if sz > 0 else hi - 1)  # the row's first cell, in the slab
        c = base + t
        b0 = b1 = b2 = q0 = q1 = q2 = zero
        for _ in range(n):
            u, s, f = np.uintp(c), np.uintp(c - back), np.uintp(t)
            e0, e1, g = fy0[f], fy1[f], fz[f]
            p0, p1, p2 = a0[s], a1[s], a2[s]
            b0 = a0[u] + e0 * p0 + e1 * q0 + g * b0  # g * b last: the only serial step
            b1 = a1[u] + e0 * p1 + e1 * q1 + g * b1
            b2 = a2[u] + e0 * p2 + e1 * q2 + g * b2
            a0[u], a1[u], a2[u] = b0, b1, b2
            q0, q1, q2 = p0, p1, p2
            c += sz
            t += sz


@jit.kernel
def _sweep_kernel(y, a, vis, sign, weight, koff, inv, offsets, p, lo, hi, d0, d1):
    """Compiled sweep of directions d0..d1-1: ``y`` the source and ``a`` the light A, in the
    padded flat layout (q, 3, p^3). A direction's source is copied into ``a`` and swept there
    in place while it is in cache (470 kB at 32^3). Slabs along x are solved in upwind order,
    those before the first one holding light skipped (they stay dark). In a slab, first what
    arrives from the slab behind (the offsets with an x part) for all its cells in one
    vectorized loop, each sum then scaled by 1 / (1 - w_0) inside the grid; then row by row
    along y one pass per row in upwind order along z: what arrives from the row behind
    (final by then) and the recurrence along z, its cell behind kept in registers (the
    factors of both, transmittance x weight x scale, are computed per slab beforehand). A
    source past the slab's or the row's edge wraps onto a shell cell, whose transmittance is
    0; shell cells keep what they receive.
    Swept are slabs lo..hi-1 and in them rows and cells lo..hi-1; with lo = 1 the shell's
    rows still collect light from the slab behind, and the shell is emptied at the end.
    Single-threaded at 32^3, all 64 directions with transmittances: about 19 ms, 5.5 of them
    the copy (30 ms with a short loop per row and offset, measured alternately)."""
    for d in range(d0, d1):
        a[d, 0] = y[d, 0]
        a[d, 1] = y[d, 1]
        a[d, 2] = y[d, 2]
        _sweep_direction(a, vis, sign, weight, koff, inv, offsets, p, lo, hi, d)


@jit.kernel
def _launch_sweep_kernel(flux, m, start, dirs, lvis, pcol, pcell, pflux, a, vis, sign, weight,
                         koff, inv, offsets, p, lo, hi, d0, d1):  # pragma: no cover - compiled
    """``launch_solve`` of directions d0..d1-1 (compiled): per direction, a[d] is zeroed, the
    launch scattered into it (ordinates._launch_direction), the handed-on light pflux[d]
    added at (pcol, pcell), swept (``_sweep_direction``) and that light taken off again, all
    while a[d] is in cache: no source array of the whole grid is written or read."""
    zero = np.float32(0.0)
    for d in range(d0, d1):
        a[d] = zero
        ordinates._launch_direction(flux, m, start, dirs, lvis, p, a, d)
        for t in range(pcol.shape[0]):
            a[d, pcol[t], pcell[t]] += pflux[d, t]
        _sweep_direction(a, vis, sign, weight, koff, inv, offsets, p, lo, hi, d)
        for t in range(pcol.shape[0]):
            a[d, pcol[t], pcell[t]] -= pflux[d, t]


@jit.kernel
def _sweep_direction(a, vis, sign, weight, koff, inv, offsets, p, lo, hi, d):  # pragma: no cover
    """The compiled sweep of direction d in place in a[d] (``_sweep_kernel``). Per slab: what
    arrives from the slab behind and the scale (``_add_slab_behind``), the within-slab
    factors (``_row_factors``), then the rows (``_sweep_rows``). Interior cells' sums are
    scaled before the rows add theirs, so the row factors carry 1 / (1 - w_0) instead.
    SIGNED_OFFSETS order: 0 (0,0,1), 1 (0,1,0), 2 (0,1,1), then the four with an x part."""
    plane = p * p
    n = hi - lo
    sx, sy, sz = sign[d, 0], sign[d, 1], sign[d, 2]
    a0, a1, a2 = a[d, 0], a[d, 1], a[d, 2]
    start = n
    for ii in range(n):
        base = (lo + ii if sx > 0 else hi - 1 - ii) * plane
        for c in range(base, base + plane):
            if a0[c] != 0.0 or a1[c] != 0.0 or a2[c] != 0.0:
                start = ii
                break
        if start < n:
            break
    shell = lo == 0
    tables = np.empty((5, plane), np.float32)
    scale, ones, fy0, fy1, fz = tables[0], tables[1], tables[2], tables[3], tables[4]
    ones[:] = 1.0
    scale[:] = 1.0  # per cell of a slab: 1 / (1 - w_0) inside, 1 in the shell
    for j in range(1, p - 1):
        scale[j * p + 1:j * p + p - 1] = inv[d]
    v = (vis[koff[d, 0]], vis[koff[d, 1]], vis[koff[d, 2]], vis[koff[d, 3]],
         vis[koff[d, 4]], vis[koff[d, 5]], vis[koff[d, 6]])
    w = weight[d]
    shift = np.empty(offsets.shape[0], np.int64)  # flat offset from each source to its cell
    for m in range(offsets.shape[0]):
        shift[m] = ((sx * offsets[m, 0]) * p + offsets[m, 1] * sy) * p + offsets[m, 2] * sz
    back = sy * p
    # a slab's cells that can receive from the slab behind: all but its upwind edge (the
    # row upwind in y and one cell upwind in z), whose sources lie past the slab behind
    t0 = max(0, back) + max(0, sz)
    t1 = plane + min(0, back) + min(0, sz)
    for ii in range(start, n):
        i = lo + ii if sx > 0 else hi - 1 - ii
        base = i * plane
        if shell and (ii == 0 or ii == n - 1):  # shell slabs only receive from the slab behind
            if ii == n - 1:
                _add_slab_behind(a0, a1, a2, v, w, shift, ones[t0:t1], base + t0, base + t1)
            continue
        # an interior slab from here: the flat neighbours the factors and rows read (up to
        # p + 1 cells past the slab) lie inside the array
        if ii == start or (shell and ii == 1):  # dark or shell (transmittance 0) behind
            _scale_slab(a0, a1, a2, scale, base)
        else:
            _add_slab_behind(a0, a1, a2, v, w, shift, scale[t0:t1], base + t0, base + t1)
        _row_factors(fy0, v[1], w[1], scale, base - back)
        _row_factors(fy1, v[2], w[2], scale, base - back - sz)
        _row_factors(fz, v[0], w[0], scale, base - sz)
        # with the shell, the slab's first row (in the shell) only receives from behind
        _sweep_rows(a0, a1, a2, fy0, fy1, fz, base, p, lo, hi, 1 if shell else 0, sy, sz)
    if lo > 0:  # without the shell, what left the grid (and the source's shell) is dropped
        for col in range(3):
            for i in range(p):
                for j in range(p):
                    row = (i * p + j) * p
                    if i == 0 or i == p - 1 or j == 0 or j == p - 1:
                        a[d, col, row:row + p] = 0.0
                    else:
                        a[d, col, row] = 0.0
                        a[d, col, row + p - 1] = 0.0


def _solve_compiled(source: np.ndarray, r: int, offset_visibility: list | None,
                    shell: bool) -> np.ndarray:
    """``solve`` by the compiled kernel: no positions, only the source, the result and the
    stacked transmittances (memory: 2 x q 3 (R+2)^3 floats). Octant by octant on ordinates'
    thread pool (the kernel releases the GIL; 8 parts balance octants that stay dark). On
    this 2-core machine at 32^3 with visibility: about 25 ms on one thread, 14 ms on the pool,
    the numpy sweep 380 ms."""
    tab = direction_tables()
    vis = stacked_visibility(r, offset_visibility)
    koff = tab["none"] if offset_visibility is None else tab["koff"]
    y = np.ascontiguousarray(source, np.float32)
    out = np.empty_like(y)
    p = r + 2
    lo, hi = (0, p) if shell else (1, p - 1)

    def run(span):
        with jit.flush_subnormals():  # light fading behind walls (jit.py)
            _sweep_kernel(y, out, vis, tab["sign"], tab["weight"], koff, tab["inv"],
                          tab["offsets"], p, lo, hi, span[0], span[1])

    for _ in ordinates._pool().map(run, tab["octants"]):
        pass  # iterating re-raises an octant's exception here
    return out


def launch_solve(injected: np.ndarray, launch_visibility: list | None, passing: np.ndarray | None,
                 offset_visibility: list | None, shell: bool = True) -> np.ndarray:
    """``solve`` of ordinates.launch(injected, launch_visibility) plus the handed-on light
    ``passing`` unfolded in place (ordinates.unfold_sparse, (R, R, R, 3, 4) or None), less the
    latter (it is not an arrival): A in the padded flat layout. Compiled (``jit.enabled()``):
    one kernel per octant launches, adds, sweeps and subtracts direction by direction in
    cache (32^3 Cornell box, two cascades: about 10 ms less than the steps apart, which
    write and read a 25 MB source)."""
    r = injected.shape[0]
    index, flux = ordinates.unfold_sparse(passing) if passing is not None else (None, None)
    if not jit.enabled():
        source = ordinates.launch(injected, launch_visibility)
        if index is not None:
            source.reshape(source.shape[0], -1)[:, index] += flux
        acc = np.ascontiguousarray(solve(source, r, offset_visibility, shell))  # reshape: a view
        if index is not None:
            acc.reshape(acc.shape[0], -1)[:, index] -= flux
        return acc
    tab = direction_tables()
    vis = stacked_visibility(r, offset_visibility)
    koff = tab["none"] if offset_visibility is None else tab["koff"]
    p = r + 2
    lo, hi = (0, p) if shell else (1, p - 1)
    launch = ordinates.launch_inputs(injected, launch_visibility,
                                     vis if launch_visibility is offset_visibility else None)
    if index is None:
        index, flux = np.zeros(0, np.int64), np.zeros((ordinates.DIRECTIONS, 0), np.float32)
    pcol, pcell = np.divmod(index, p**3)
    out = np.empty((ordinates.DIRECTIONS, 3, p**3), np.float32)

    def run(span):
        with jit.flush_subnormals():  # light fading behind walls (jit.py)
            _launch_sweep_kernel(*launch, pcol, pcell, flux, out, vis, tab["sign"],
                                 tab["weight"], koff, tab["inv"], tab["offsets"], p, lo, hi,
                                 span[0], span[1])

    for _ in ordinates._pool().map(run, tab["octants"]):
        pass  # iterating re-raises an octant's exception here
    return out


def solve(source: np.ndarray, r: int, offset_visibility: list | None,
          shell: bool = True) -> np.ndarray:
    """A = source + T A for the light ``source`` in the padded flat layout (q, 3, (R+2)^3),
    interior cells only: returns A in the same layout. With ``shell`` the shell of A holds
    what left the grid, summed over all steps; without, it stays empty (the light is
    dropped). ``offset_visibility``: per propagation.OFFSETS entry the (R, R, R)
    transmittance of each cell towards it, or None. Runs the compiled kernel when
    ``jit.enabled()``, else the numpy sweep over hyperplanes below (the reference)."""
    if jit.enabled():
        return _solve_compiled(source, r, offset_visibility, shell)
    pl = plan(r, shell)
    table = factors(r, offset_visibility, shell)
    q = source.shape[0]
    flat = np.zeros((q, 3, source.shape[-1] + 1), np.float32)  # + the zero dummy cell
    flat[..., :-1] = source
    x = np.take(flat, pl["index"])
    _sweep(x, pl["planes"], *table)
    out = np.zeros_like(flat)
    np.put(out, pl["index"], x)  # every cell once per direction; the dummy gets zeros
    out = out[..., :-1]
    if shell:  # the shell only receives: undo the 1 / (1 - w_0) the sweep applied to it
        out[..., pl["shell"]] /= table[3][:, None, None]
    return out


def fold(light: np.ndarray, r: int, coefficients: int, part: str = "interior") -> np.ndarray:
    """ordinates.fold of light in the padded flat layout (q, 3, (R+2)^3): ``part``
    "interior" (R, R, R, 3, c), or "shell" (R+2, R+2, R+2, 3, c) with the interior zeroed
    (the outflow handed on to the next cascade)."""
    if part not in ("interior", "shell"):
        raise ValueError(f"part must be 'interior' or 'shell', not {part!r}")
    p = r + 2
    out = ordinates.fold(light.reshape(light.shape[0], 3, p, p, p), coefficients)
    if part == "interior":
        return np.ascontiguousarray(out[1:-1, 1:-1, 1:-1])
    out[1:-1, 1:-1, 1:-1] = 0.0
    return out


@jit.kernel
def _split_fold_kernel(m, r, values, shell, i0, i1):  # pragma: no cover - compiled
    """Padded slabs i0..i1-1 of the folded light m (9, 3, cells of those slabs) (bands 0-2 per
    colour and padded cell) into ``values`` (R, R, R, 3, 9) for interior cells and, when
    ``shell`` has cells, bands 0-1 of shell cells into ``shell`` (R+2, R+2, R+2, 3, 4) (its
    interior left as it is). Pure copies: the layout change ``fold``'s transposes make, in one
    pass."""
    p = r + 2
    has_shell = shell.shape[0] > 0
    first = i0 * p * p
    for i in range(i0, i1):
        for j in range(p):
            for k in range(p):
                c = (i * p + j) * p + k - first
                if 0 < i < p - 1 and 0 < j < p - 1 and 0 < k < p - 1:
                    for col in range(3):
                        for t in range(9):
                            values[i - 1, j - 1, k - 1, col, t] = m[t, col, c]
                elif has_shell:
                    for col in range(3):
                        for t in range(4):
                            shell[i, j, k, col, t] = m[t, col, c]


def _basis2() -> np.ndarray:
    """The band 0-2 basis of the directions, transposed (9, q) float32 (cached)."""
    dirs = ordinates.tables()[0]
    key = ("basis2", len(dirs))
    if key not in _DIRECTION_TABLES:
        _DIRECTION_TABLES[key] = np.ascontiguousarray(
            sh.evaluate_basis2(dirs).astype(np.float32).T)
    return _DIRECTION_TABLES[key]


def fold_parts(light: np.ndarray, r: int, shell: bool) -> tuple:
    """(``fold(light, r, 9)``, ``fold(light, r, 4, "shell")`` or None): the lookup's grid and
    the outflow from one product with the band 0-2 basis (its first 4 columns are the
    4-moment basis), split by a compiled copy when ``jit.enabled()`` (32^3 Cornell box:
    16.5 ms for the two folds, about 7 ms this way). The slabs go in two halves on the pool,
    each its own products (BLAS runs single-threaded in the engine's process: blas.py)."""
    if not jit.enabled():
        return fold(light, r, sh.BANDS2), (fold(light, r, 4, "shell") if shell else None)
    basis = _basis2()
    p = r + 2
    values = np.empty((r, r, r, 3, sh.BANDS2), np.float32)
    outflow = np.zeros((p, p, p, 3, 4) if shell else (0, 0, 0, 3, 4), np.float32)

    def part(slabs):
        lo, hi = slabs[0] * p * p, slabs[1] * p * p
        m = np.empty((sh.BANDS2, 3, hi - lo), np.float32)
        for col in range(3):
            np.matmul(basis, light[:, col, lo:hi], out=m[:, col])
        _split_fold_kernel(m, r, values, outflow, *slabs)

    half = p // 2
    for _ in ordinates._pool().map(part, ((0, half), (half, p))):
        pass
    return values, (outflow if shell else None)
