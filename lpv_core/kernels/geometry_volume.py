"""geometry_volume's compiled twins (numba, through runtime.jit): _subdivide, face_coverage,
face_offsets and occluder_volume under the stage's names and signatures. They repeat the numpy
reference's arithmetic operation for operation, so the results are the same bits, and skip what
provably changes no bit (each shortcut with a bound on the rounding it must not cross, 1e4-fold
or more apart).

Coverage in two passes. The first (_project_run) projects every sub-triangle onto its nearest
plane across each axis and keeps those that cover something as records (plane, corners' u, v in
sample units, twice the signed area), finding the largest sample window on the way. Then the
planes, split into parts of about equal work (_parts_kernel), are scanned from the records
(_cover_part_kernel: each part writes only its own planes' bits) and counted
(_finish_coverage_kernel, or _finish_volume_kernel straight into the visibility and gaps).
occluder_volume runs the first pass on the triangles themselves (_project_lattices): each one's
sub-triangle corners computed once per lattice point, as _subdivide_kernel computes them,
face_offsets' sums added on the way. Per triangle and axis (_classify_kernel, _edge_on):

- all its sub-triangles surely on one plane inside the grid (a wall, any size): the samples
  inside it are set row by row (_fill_part_kernel), and only the sub-triangles along its edges
  where samples lie within reach of an edge are scanned (_mark_band: none along an aligned
  wall's edges on half-samples); the rest add only their offset terms (an aligned wall's in a
  loop of its own);
- all surely edge-on (an aligned wall across the other two axes): no records; no planes in the
  grid: nothing (an aligned wall outside the grid is not even cut).

Records are scanned over their own sample window where no sample past it can count
(_own_window). Both passes are shared by this thread and the pool's (_front_back: however busy
the other core, this thread never waits for it); the visibility and gaps are written only on
planes with something on them; the working arrays are kept between calls (_Scratch).

Hot loops call no compiled function with array arguments (each such call counts references to
its arrays: atomic operations that cost more than the work per sub-triangle).

The stage's parameters COVERAGE_SAMPLES, SURFEL_SPACING and GAP_COVERAGE are defined here, for
both (the stage imports them; geometry_volume says why these values).
"""

from __future__ import annotations

import itertools
import math
import threading

import numpy as np

from ..grid import Grid
from ..runtime import jit
from ..runtime.pool import executor, workers

COVERAGE_SAMPLES = 8  # sample points per face edge (geometry_volume.face_coverage)
SURFEL_SPACING = 0.5  # sub-triangle length, in cells (geometry_volume._subdivide)
# A face stands for its surface in the gaps (geometry_volume.cell_gaps) when its surface covers
# over half of it. Its coverage is sampled: each edge of the surface's footprint on the face
# is placed to half a sample spacing, 1 / (2 M) of the face, so a footprint bounded by two
# edges across the face (a wall's part of a cell at a room's corner, the side wall and the
# roof each cutting it) reads up to 1 / M below what it covers: over half, read to within that
GAP_COVERAGE = 0.5 - 1.0 / COVERAGE_SAMPLES


def _subdivide(p: np.ndarray, spacing: float):
    """geometry_volume._subdivide of its float64 triangles p (T > 0, 3, 3): the same
    sub-triangles in the same order (grouped by k, ascending, then by triangle), written by
    _subdivide_kernel straight into the output arrays (no per-k einsum and repeats)."""
    normal, area2, k = _splits(p, spacing)
    k = np.where(k >= 1, k, 0)  # (a non-finite triangle: none, where numpy's path would fail)
    order = np.argsort(k, kind="stable")  # np.unique's groups, each in triangle order
    count = k[order] ** 2
    start = np.cumsum(count) - count
    n = int(count.sum())
    sub = np.empty((n, 3, 3))
    index = np.empty(n, np.int64)
    nrm = np.empty((n, 3))
    area = np.empty(n)
    _subdivide_kernel(p, order, k, start, np.ascontiguousarray(normal), area2, sub, index, nrm,
                      area)
    return sub, index, nrm, area


def _splits(p: np.ndarray, spacing: float):
    """geometry_volume._splits by _splits_kernel: the same normals, areas and k (0 where
    numpy's is no count: a non-finite triangle), without numpy's dozen small calls."""
    t = p.shape[0]
    normal = np.empty((t, 3))
    area2 = np.empty(t)
    k = np.empty(t, np.int64)
    _splits_kernel(np.ascontiguousarray(p), max(spacing, 1e-30), normal, area2, k)
    return normal, area2, k


def face_coverage(grid: Grid, tri: np.ndarray, m: int, out: np.ndarray) -> np.ndarray:
    """geometry_volume.face_coverage of its float64 sub-triangles tri (N > 0, 3, 3), m x m
    samples per face, into its zeroed ``out``: _project_subs_kernel's records and window,
    then the planes' coverage in parts on the pool."""
    r = grid.resolution
    rec = np.empty((3, tri.shape[0], _RECORD))
    nrec = np.zeros((1, 3), np.int64)
    windows = np.zeros((1, 3, 2))
    work = np.zeros((1, 3 * (r + 1)))
    _project_subs_kernel(np.ascontiguousarray(tri), grid.origin_array, float(grid.cell_size), r,
                         m, rec, nrec[0], windows[0], work[0])
    hit = np.zeros((3, r + 1, r, r, (m * m + 63) // 64), np.int64)
    first = np.zeros(1, np.int64)

    def part(b, window):
        _cover_part_kernel(rec, first, nrec, r, m, window, b[0], b[1], hit)
        _finish_coverage_kernel(hit, m, r, b[0], b[1], out)

    _run_parts(executor(), part, work, windows, r)
    return out


def face_offsets(grid: Grid, tri: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                 out: np.ndarray) -> np.ndarray:
    """geometry_volume.face_offsets of its float64 sub-triangles tri (N > 0, 3, 3), into its
    zeroed ``out``: the sums by _offsets_kernel, divided as numpy divides."""
    r = grid.resolution
    total = np.zeros((3, r + 1, r, r))
    moment = np.zeros((3, r + 1, r, r))
    _offsets_kernel(np.ascontiguousarray(tri), np.ascontiguousarray(normals, np.float64),
                    np.ascontiguousarray(areas, np.float64), grid.origin_array,
                    float(grid.cell_size), r, total, moment)
    return np.divide(moment, total, out=out, where=total > 0)


def occluder_volume(grid: Grid, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """geometry_volume.occluder_volume: _classify_kernel, _occluder_kernel on chunks of the
    triangles (in _subdivide's order), then the planes' coverage, visibility and gaps in
    parts, both shared by this thread and the pool's (_front_back).

    face_offsets' sums add the sub-triangles' terms in their order: the chunks taken from
    the front, in order, add their own; those taken from the back log them (face, weight,
    weighted distance), added after, chunk by chunk, in order."""
    p = np.ascontiguousarray(np.asarray(triangles, np.float64).reshape(-1, 3, 3))
    r = grid.resolution
    m = COVERAGE_SAMPLES
    if p.shape[0] == 0:
        return np.ones((6, r, r, r), np.float32), np.zeros((6, r, r, r), np.float32)
    normal, area2, k = _splits(p, SURFEL_SPACING * grid.cell_size)
    pool = executor()
    chunks = max(1, min(_CHUNKS * workers(), p.shape[0]))
    origin = grid.origin_array
    cell = float(grid.cell_size)
    far = float(np.max(np.abs(origin))) / cell  # (the origin's share of the rounding)
    mode = np.empty((p.shape[0], 3), np.int64)
    cost = np.empty(p.shape[0])
    fills = np.empty((3 * p.shape[0], _FILL))
    work = np.zeros((chunks, 3 * (r + 1)))
    nfill = _classify_kernel(p, k, normal, origin, cell, far, r, m, mode, fills, work[0], cost)
    order, o, first, n = _runs_kernel(k, cost, chunks)
    nrec = np.zeros((chunks, 3), np.int64)
    windows = np.zeros((chunks, 3, 2))
    touched = np.zeros((chunks, 3 * (r + 1)), np.bool_)  # planes with offset terms
    nlog = np.zeros(chunks, np.int64)
    scratch = _Scratch.get(r, m)
    total, moment, hit = scratch.sums
    rec = scratch.take("rec", 3 * n * _RECORD).reshape(3, n, _RECORD)
    # up to 3 terms per sub-triangle, chunk i's from 3 first[i]
    logged = scratch.take("logged", 9 * n).reshape(3, 3 * n)

    def run(i, log):
        _occluder_kernel(p, order, k, o[i], o[i + 1], mode, normal, area2, origin, cell, far,
                         r, m, rec, first[i], nrec[i], windows[i], work[i], touched[i], total,
                         moment, log, logged[:, 3 * first[i]:], nlog[i:i + 1])

    for i in _front_back(pool, lambda i: run(i, False), lambda i: run(i, True), chunks):
        _add_logged_kernel(logged[:, 3 * first[i]:], nlog[i], total, moment)
    vis = np.ones((6, r, r, r), np.float32)  # (_finish_volume_kernel writes the busy planes)
    gaps = np.zeros((6, r, r, r), np.float32)
    busy = _busy_kernel(work, touched)

    def part(b, window):
        _fill_part_kernel(fills, nfill, r, m, b[0], b[1], hit)
        _cover_part_kernel(rec, first, nrec, r, m, window, b[0], b[1], hit)
        _finish_volume_kernel(hit, m, r, total, moment, busy, b[0], b[1], vis, gaps)
        _clear_kernel(hit, total, moment, busy, b[0], b[1])

    _run_parts(pool, part, work, windows, r)
    scratch.clean = True
    return vis, gaps


_RECORD = 8  # (plane, u0, u1, u2, v0, v1, v2, area2) per kept sub-triangle and axis


class _Scratch:
    """occluder_volume's working arrays, kept between calls, one set per calling thread: the
    sums and hit bits for R and M (zero between calls: each call clears the planes it used),
    and buffers for records and logged terms (fresh arrays this size would cost their page
    faults every call), kept only up to _SCRATCH_MB."""

    _local = threading.local()

    def __init__(self, r: int, m: int) -> None:
        self.key = (r, m)
        shape = (3, r + 1, r, r)
        self.sums = (np.zeros(shape), np.zeros(shape),
                     np.zeros(shape + ((m * m + 63) // 64,), np.int64))
        self.buffers: dict[str, np.ndarray] = {}
        self.clean = True

    @classmethod
    def get(cls, r: int, m: int) -> _Scratch:
        """This thread's scratch for R and M, zeroed sums (fresh where the last call broke
        off, or R or M changed), marked in use (clean False) until the call ends."""
        kept = getattr(cls._local, "scratch", None)
        scratch = kept if kept is not None and kept.key == (r, m) and kept.clean else cls(r, m)
        if sum(a.nbytes for a in scratch.sums) <= _SCRATCH_MB << 20:
            cls._local.scratch = scratch
        scratch.clean = False
        return scratch

    def take(self, name: str, size: int) -> np.ndarray:
        """A float64 buffer of ``size`` (contents undefined), grown as needed."""
        buffer = self.buffers.get(name)
        if buffer is None or buffer.size < size:
            buffer = np.empty(size)
            if size <= _SCRATCH_MB << 17:  # (8-byte items)
                self.buffers[name] = buffer
        return buffer[:size]


_SCRATCH_MB = 32  # the most a thread's kept _Scratch arrays may take, each


@jit.kernel
def _clear_kernel(hit, total, moment, busy, b0, b1):
    """hit, total and moment zeroed on the busy planes b0 <= b < b1 (all others are)."""
    hit_flat = hit.reshape(-1)
    total_flat = total.reshape(-1)
    moment_flat = moment.reshape(-1)
    per = hit_flat.size // busy.size
    faces = total_flat.size // busy.size
    for b in range(b0, b1):
        if busy[b]:
            hit_flat[b * per:(b + 1) * per] = 0
            total_flat[b * faces:(b + 1) * faces] = 0.0
            moment_flat[b * faces:(b + 1) * faces] = 0.0


def _run_parts(pool, part, work: np.ndarray, windows: np.ndarray, r: int) -> None:
    """part((b0, b1), window) for the planes' parts (_parts_kernel), shared by this thread and the
    pool's (_front_back); window: the largest of the runs' windows (3, 2)."""

    bounds = np.empty(_CHUNKS * workers() + 1, np.int64)
    window = np.zeros((3, 2))
    _parts_kernel(work, windows, r, bounds, window)
    parts = [b for b in itertools.pairwise(bounds) if b[0] < b[1]]
    _front_back(pool, lambda i: part(parts[i], window), lambda i: part(parts[i], window),
                len(parts))


_CHUNKS = 4  # chunks of work per pool thread (_front_back)


def _front_back(pool, front, back, count: int) -> list[int]:
    """Chunks 0 .. count - 1, each done once: front(i) in ascending order on this thread,
    back(j) in descending order on the pool's other threads, until they meet; returns the
    chunks back did, ascending. This thread never waits for a pool thread that has not
    started (a busy machine's other core): it does the rest itself."""

    lock = threading.Lock()
    ends = [0, count]  # the next chunk from the front, one past the next from the back
    backs = []

    def take(from_front: bool) -> int:
        with lock:
            if ends[0] >= ends[1]:
                return -1
            if from_front:
                ends[0] += 1
                return ends[0] - 1
            ends[1] -= 1
            return ends[1]

    def helper() -> None:
        while (j := take(False)) >= 0:
            back(j)
            backs.append(j)

    futures = [pool.submit(helper) for _ in range(min(workers() - 1, count - 1))]
    try:
        while (i := take(True)) >= 0:
            front(i)
    finally:
        for future in futures:  # (all done before their arrays are let go)
            if not future.cancel():
                future.result()
    return sorted(backs)


@jit.kernel
def _runs_kernel(k, cost, runs):
    """_subdivide's order of the triangles (by k, stable) cut into ``runs`` runs of about
    equal cost (_classify_kernel): (order, the runs' first triangles in it (runs + 1), their first
    sub-triangles (runs), the number of sub-triangles)."""
    order = np.argsort(k, kind="mergesort")
    end = np.cumsum(k[order] ** 2)  # sub-triangles up to each triangle's
    spent = np.cumsum(cost[order])
    n = end[-1]
    o = np.empty(runs + 1, np.int64)
    first = np.zeros(runs, np.int64)
    o[0] = 0
    o[runs] = order.size
    for i in range(1, runs):
        o[i] = np.searchsorted(spent, i * (spent[-1] / runs), side="right")
        first[i] = end[o[i] - 1] if o[i] > 0 else 0
    return order, o, first, n


@jit.kernel
def _busy_kernel(work, touched):
    """Planes (3 (R + 1)) with records or fills (work) or offset terms (touched) in any run:
    where _finish_volume_kernel has something to read."""
    busy = np.zeros(work.shape[1], np.bool_)
    for i in range(work.shape[0]):
        for b in range(work.shape[1]):
            busy[b] = busy[b] or work[i, b] > 0.0 or touched[i, b]
    return busy


@jit.kernel
def _parts_kernel(work, windows, r, bounds, window):
    """Split the planes (3 (R + 1), axis-major: b = axis (R + 1) + plane) into len(bounds) - 1
    parts of about equal work, bounds[i] .. bounds[i + 1]: each plane's records (work, per
    run, plus its fills' work in records) times its axis's window, plus its faces' count.
    window: the largest of the runs' windows."""
    for i in range(windows.shape[0]):
        for axis in range(3):
            for d in range(2):
                window[axis, d] = max(window[axis, d], windows[i, axis, d])
    nb = work.shape[1]
    cost = np.empty(nb)
    for b in range(nb):
        axis = b // (r + 1)
        count = 0.0
        for i in range(work.shape[0]):
            count += work[i, b]
        cost[b] = count * (window[axis, 0] + 1.0) * (window[axis, 1] + 1.0) + 0.25 * r * r
    whole = cost.sum()
    parts = bounds.shape[0] - 1
    bounds[0] = 0
    b = 0
    acc = 0.0
    for i in range(1, parts):
        while b < nb and acc + 0.5 * cost[b] < whole * i / parts:
            acc += cost[b]
            b += 1
        bounds[i] = b
    bounds[parts] = nb


@jit.kernel
def _project_subs_kernel(tri, origin, cell, r, m, rec, nrec, window, work):
    """_project_run over the sub-triangles tri (N, 3, 3), their corners in cell units as
    face_coverage computes them: (tri - origin) / cell."""
    n = tri.shape[0]
    rel = np.empty((3 * n, 3))
    smp = np.empty((3 * n, 3))
    corners = np.empty((n, 3), np.int64)
    for s in range(n):
        for c in range(3):
            corners[s, c] = 3 * s + c
            for x in range(3):
                rel[3 * s + c, x] = (tri[s, c, x] - origin[x]) / cell
                smp[3 * s + c, x] = rel[3 * s + c, x] * m - 0.5
    none = np.zeros(0)
    _project_run(rel, smp, corners, n, r, rec, 0, nrec, window, work, none, none, none, False,
                 False, np.zeros((3, 0)), np.zeros(1, np.int64))


@jit.kernel
def _occluder_kernel(p, order, k, o0, o1, mode, normal, area2, origin, cell, far, r, m, rec,
                     first, nrec_out, window_out, work_out, touched, total, moment, log, logged,
                     nlog_out):
    """occluder_volume's first pass over the triangles p[order[o0:o1]] (_subdivide's order,
    records from row first): _project_lattices. Counts, window and work are kept here and
    written out at the end (runs on pool threads write next to each other). far: the largest
    |origin| coordinate, in cells."""
    nrec = np.zeros(3, np.int64)
    window = np.zeros((3, 2))
    work = work_out.copy()
    nlog = np.zeros(1, np.int64)
    _project_lattices(p, order, k, o0, o1, mode, normal, area2, origin, cell, far, r, m, rec,
                      first, nrec, window, work, touched, total.reshape(-1), moment.reshape(-1),
                      log, logged, nlog)
    nrec_out[:] = nrec
    window_out[:] = window
    work_out[:] = work
    nlog_out[0] = nlog[0]


@jit.kernel
def _lattice_point(w, u, v, p0, p1, p2, origin, cell):
    """A lattice point's coordinate in cells, as face_coverage computes a sub-triangle corner
    of _subdivide_kernel's: barycentric (w, u, v) of corners' p0, p1, p2."""
    return (w * p0 + u * p1 + v * p2 - origin) / cell


@jit.kernel
def _classify_kernel(p, k, normal, origin, cell, far, r, m, mode, fills, work, cost):
    """Each triangle p[t]'s mode[t] across each axis (_fill_plane from its corners' lattice
    points; below _FILL_MIN_K simply _GENERAL; _SKIP where k = 0), its fills with their work
    (_parts_kernel) and the cost of its sub-triangles (_runs_kernel: the lattice, a filled
    plane's offset terms, a scanned record, little where its normal says edge-on). Returns the
    number of fills."""
    rel = np.empty((3, 3))
    smp = np.empty((3, 3))
    nfill = 0
    rm = r * m
    for t in range(p.shape[0]):
        kk = k[t]
        cost[t] = 6.5 * kk * kk  # (about 1 per offset term, 2 per record)
        if kk < _FILL_MIN_K:
            for axis in range(3):
                mode[t, axis] = _GENERAL if kk >= 1 else _SKIP
            continue
        for c in range(3):  # lattice points (0, 0), (k, 0), (0, k)
            u = kk / kk if c == 1 else 0 / kk
            v = kk / kk if c == 2 else 0 / kk
            w = 1.0 - (u + v)
            for x in range(3):
                rel[c, x] = _lattice_point(w, u, v, p[t, 0, x], p[t, 1, x], p[t, 2, x],
                                           origin[x], cell)
                smp[c, x] = rel[c, x] * m - 0.5
        reach = far + np.abs(rel).max()
        cost[t] = 0.0
        for axis in range(3):
            u = 1 if axis == 0 else 0
            v = 1 if axis == 2 else 2
            fill = _fill_plane(rel[0, axis], rel[1, axis], rel[2, axis], smp[0, u], smp[1, u],
                               smp[2, u], smp[0, v], smp[1, v], smp[2, v], kk, r, m, reach)
            mode[t, axis] = fill
            if fill != _OUTSIDE:
                cost[t] += kk * (1.0 + 12.0 / kk if fill >= 0 else
                                 0.1 if normal[t, axis] == 0.0 else 3.0) * kk
            if fill >= 0:
                row = nfill
                nfill += 1
                fills[row, 0] = axis
                fills[row, 1] = fill
                for c in range(3):
                    fills[row, 2 + c] = smp[c, u]
                    fills[row, 5 + c] = smp[c, v]
                work[axis * (r + 1) + fill] += _fill_work(smp[0, u], smp[1, u], smp[2, u],
                                                          smp[0, v], smp[1, v], smp[2, v],
                                                          rm, m)
        if cost[t] > 0.0:
            cost[t] += 0.5 * kk * kk  # (its lattice)
    return nfill


_SKIP = -4  # _project_lattices: nothing across this axis (_OUTSIDE, _EDGE_ON without offsets)
_OUTSIDE = -3  # _fill_plane: no sub-triangle's plane inside the grid
_EDGE_ON = -2  # _edge_on: no records (every sub-triangle edge-on to this axis's planes)
_GENERAL = -1  # _fill_plane: a record for every sub-triangle that covers something
_FILL = 8  # (axis, plane, u0, u1, u2, v0, v1, v2) per filled triangle and axis
_FILL_MIN_K = 4  # k from which a triangle's interior sub-triangles are filled, not scanned
_FILL_MARGIN = 1e-4  # the fill's samples are this far (sample units) inside the triangle


@jit.kernel
def _rounding(m, reach):
    """Bound, in sample units, with 1e4-fold slack, on the rounding of a lattice point's
    projection (reach: bounds |rel| + |origin| / cell there), and the same in cells."""
    cells = 1e-10 * (1.0 + reach)
    return m * cells + 1e-12 * (1.0 + m * reach), cells


@jit.kernel
def _fill_plane(r0, r1, r2, u0, u1, u2, v0, v1, v2, kk, r, m, reach):
    """How _project_lattices treats a triangle's k^2 sub-triangles across an axis: _OUTSIDE
    (no plane of theirs inside the grid), the plane inside the grid they all surely go to,
    where its interior is filled (_fill_part_kernel) and only the ring's records (sub-triangles
    touching its edges; _mark_band) are scanned, or _GENERAL. r0..r2: its corners across the
    axis (cells); u, v: its corners on the planes (sample units); reach: bounds |rel| +
    |origin| / cell (rounding).

    Sure, with 1e4-fold slack on the rounding of the lattice points (whose centroids stay in
    the corners' hull and whose projections are the triangle's, 1/k the size, up to it): the
    fill (samples _FILL_MARGIN inside the triangle) is covered by the sub-triangles tiling
    it, and the interior ones (not touching its edges) reach no sample outside it: each is
    at least h = the triangle's least height / k from its edges, and a sub-triangle grown by
    the scan's tolerances (1e-9) reaches at most 3e-9 L^2 / |area2| past its edges (its
    incircle grown by 1e-9), below 3e-7 where |area2| >= L^2 / 100 (no sliver). So what
    the ring's records add to the fill lies within 2 _FILL_MARGIN of the triangle's edges."""
    err, err_cells = _rounding(m, reach)  # (a centroid's too: in the corners' hull)
    lo = math.floor(min(r0, r1, r2) - err_cells + 0.5 - 1e-6)
    hi = math.floor(max(r0, r1, r2) + err_cells + 0.5 - 1e-6)
    if hi < 0.0 or lo > r:
        return _OUTSIDE
    if lo != hi or kk < _FILL_MIN_K or not err < 1e-6 or not m * reach < 1e7:
        return _GENERAL
    area2 = (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0)
    span = max(max(u0, u1, u2) - min(u0, u1, u2), max(v0, v1, v2) - min(v0, v1, v2)) / kk
    span += 2.0 * err
    sub = abs(area2) / (kk * kk)  # each sub-triangle's, up to slack
    slack = 16.0 * err * (span + 1.0) + 1e-14 * (span + 1.0) ** 2
    longest2 = max((u1 - u0) ** 2 + (v1 - v0) ** 2, (u2 - u1) ** 2 + (v2 - v1) ** 2,
                   (u0 - u2) ** 2 + (v0 - v2) ** 2)
    s = max(span, 1.0)
    if (abs(area2) >= 1e-2 * longest2 and abs(area2) / math.sqrt(longest2) / kk >= 1e-3
            and sub - slack > 1.000001e-9 * s * s):  # (above _projection's edge-on threshold)
        return lo
    return _GENERAL


@jit.kernel
def _edge_on(spread_u, spread_v, ext_u, ext_v):
    """True where every sub-triangle of a triangle is surely edge-on to an axis's planes
    (below _projection's threshold, 1e-9 max(span, 1)^2): twice its area is at most
    2 min(spread_u ext_v, ext_u spread_v) (up to rounding), with spread: the spread of the
    triangle's lattice points in a coordinate (sample units; ~0 across an aligned wall), ext:
    bounds any sub-triangle's extent there."""
    return 2.000001 * min(spread_u * ext_v, ext_u * spread_v) < 1e-9


@jit.kernel
def _fill_window(smp, kk, axis, m, reach, window):
    """window[axis] grown by the sample windows of a filled triangle's sub-triangles (lattice
    points smp, as _project_lattices), kept though most have no records: each needs at most
    floor(its extents + 2e-9) (its extents: the triangle's / k, up to rounding), computed
    one by one only where that bound exceeds the window so far."""
    u = 1 if axis == 0 else 0
    v = 1 if axis == 2 else 2
    q1 = kk * (kk + 1)
    slack = 1e-8 + 8.0 * _rounding(m, reach)[0]
    ext_u = max(smp[0, u], smp[q1, u], smp[kk, u]) - min(smp[0, u], smp[q1, u], smp[kk, u])
    ext_v = max(smp[0, v], smp[q1, v], smp[kk, v]) - min(smp[0, v], smp[q1, v], smp[kk, v])
    if (math.floor(ext_u / kk + slack) <= window[axis, 0]
            and math.floor(ext_v / kk + slack) <= window[axis, 1]):
        return
    for i in range(kk):
        for j in range(kk - i):
            q = i * (kk + 1) + j
            width, height = _window(smp[q, u], smp[q + kk + 1, u], smp[q + 1, u], smp[q, v],
                                    smp[q + kk + 1, v], smp[q + 1, v])  # upright
            window[axis, 0] = max(window[axis, 0], width)
            window[axis, 1] = max(window[axis, 1], height)
            if i + j + 2 <= kk:  # inverted
                width, height = _window(smp[q + kk + 1, u], smp[q + kk + 2, u], smp[q + 1, u],
                                        smp[q + kk + 1, v], smp[q + kk + 2, v], smp[q + 1, v])
                window[axis, 0] = max(window[axis, 0], width)
                window[axis, 1] = max(window[axis, 1], height)


@jit.kernel
def _mark_band(smp, kk, axis, rm, marks):
    """marks[e, x] for each edge e of a filled triangle (0: p0 -> p1, lattice i; 1: p1 -> p2,
    j; 2: p2 -> p0, j): whether a sample of the grid lies near lattice position x along it,
    within 2 _FILL_MARGIN (sample units) of its line: there the ring's records decide what
    the fill leaves out (no sample, no record: an aligned wall's edges on half-samples)."""
    u = 1 if axis == 0 else 0
    v = 1 if axis == 2 else 2
    marks[:, :kk + 1] = False
    for e in range(3):
        a = 0 if e == 0 else kk * (kk + 1) if e == 1 else kk
        b = kk * (kk + 1) if e == 0 else kk if e == 1 else 0
        ua, va, ub, vb = smp[a, u], smp[a, v], smp[b, u], smp[b, v]
        du = ub - ua
        dv = vb - va
        across = abs(du) >= abs(dv)  # (one sample per row can be that near: the nearest)
        major_a, minor_a, major_d, minor_d = (ua, va, du, dv) if across else (va, ua, dv, du)
        start = max(math.floor(min(major_a, major_a + major_d)) - 1, 0)
        stop = min(math.ceil(max(major_a, major_a + major_d)) + 1, rm - 1)
        slope = minor_d / major_d
        for s in range(start, stop + 1):
            line = minor_a + (s - major_a) * slope
            near = math.floor(line + 0.5)
            if not (abs(near - line) < 4.0 * _FILL_MARGIN and near >= 0 and near < rm):
                continue  # (|near - line| <= sqrt(2) x its distance from the line)
            su, sv = (s, near) if across else (near, s)
            along = ((su - ua) * du + (sv - va) * dv) / (du * du + dv * dv)
            at = math.floor((along if e < 2 else 1.0 - along) * kk)
            for x in range(max(at - 2, 0), min(at + 2, kk) + 1):
                marks[e, x] = True


@jit.kernel
def _fill_work(u0, u1, u2, v0, v1, v2, rm, m):
    """A fill's work for _parts_kernel, in records (a row of samples per face about 1/8 of one)."""
    rows = min(max(u0, u1, u2), rm) - max(min(u0, u1, u2), 0.0)
    cols = min(max(v0, v1, v2), rm) - max(min(v0, v1, v2), 0.0)
    if rows < 0.0 or cols < 0.0:
        return 0.0
    return 0.125 * (rows + 1.0) * (cols / m + 2.0)


@jit.kernel
def _project_lattices(p, order, k, o0, o1, mode, normal, area2, origin, cell, far, r, m, rec,
                      row, nrec, window, work, touched, total, moment, log, logged, nlog):
    """The triangles p[order[o0:o1]] cut into k^2 sub-triangles as _subdivide_kernel cuts
    them, in its order, and each one projected as _project_run projects it (with offset
    terms; planes with any marked in touched), across each axis as the triangle's mode
    (_classify_kernel, then _edge_on) says: _SKIP: nothing (outside, or edge-on without offset
    terms); _EDGE_ON: only offset terms; a filled plane: records only for the sub-triangles
    along its edges where samples are within reach (_mark_band), the plane known for all
    (_fill_window for their sample windows); _GENERAL: as _project_run. Corners computed
    once per lattice point (i, j) / k, in cells (rel) and sample units (smp); an aligned
    wall (filled or skipped across every axis) adds its offset terms in a loop of its own,
    a face's run of them summed in registers."""
    kmax = 1
    for o in range(o0, o1):
        kmax = max(kmax, k[order[o]])
    rel = np.empty(((kmax + 1) * (kmax + 1), 3))
    smp = np.empty(((kmax + 1) * (kmax + 1), 3))
    cen = np.empty(3)
    wgt = np.empty(3)
    md = np.empty(3, np.int64)
    lo = np.empty(3)
    hi = np.empty(3)
    band = np.zeros((3, 3, kmax + 1), np.bool_)  # _mark_band's, per filled axis
    frac = np.empty(kmax + 1)  # j / k
    need = np.zeros(3, np.bool_)
    ox, oy, oz = origin[0], origin[1], origin[2]
    for o in range(o0, o1):
        t = order[o]
        kk = k[t]
        for x in range(3):
            md[x] = mode[t, x]
        if md[0] < _GENERAL and md[1] < _GENERAL and md[2] < _GENERAL:
            continue  # (outside the grid across every axis)
        if (kk > 1 and md[0] < 0 and md[1] < 0 and md[2] < 0
                and _flat_outside(p, t, kk, md, normal, origin, cell, far, m)):
            continue  # (an aligned wall outside the grid: one coordinate's lattice tells)
        # (the corners and extremes in registers: the compiler cannot tell rel from p)
        p0x, p0y, p0z = p[t, 0, 0], p[t, 0, 1], p[t, 0, 2]
        p1x, p1y, p1z = p[t, 1, 0], p[t, 1, 1], p[t, 1, 2]
        p2x, p2y, p2z = p[t, 2, 0], p[t, 2, 1], p[t, 2, 2]
        lox = loy = loz = np.inf
        hix = hiy = hiz = -np.inf
        for j in range(kk + 1):
            frac[j] = j / kk
        for i in range(kk + 1):
            u = frac[i]
            for j in range(kk + 1 - i):
                v = frac[j]
                w = 1.0 - (u + v)
                q = i * (kk + 1) + j
                x = _lattice_point(w, u, v, p0x, p1x, p2x, ox, cell)
                y = _lattice_point(w, u, v, p0y, p1y, p2y, oy, cell)
                z = _lattice_point(w, u, v, p0z, p1z, p2z, oz, cell)
                rel[q, 0] = x
                rel[q, 1] = y
                rel[q, 2] = z
                x = x * m - 0.5
                y = y * m - 0.5
                z = z * m - 0.5
                smp[q, 0] = x
                smp[q, 1] = y
                smp[q, 2] = z
                lox = min(lox, x)
                loy = min(loy, y)
                loz = min(loz, z)
                hix = max(hix, x)
                hiy = max(hiy, y)
                hiz = max(hiz, z)
        lo[0], lo[1], lo[2] = lox, loy, loz
        hi[0], hi[1], hi[2] = hix, hiy, hiz
        a = 0.5 * area2[t] / (kk * kk)
        reach = far
        for x in range(3):
            wgt[x] = a * abs(normal[t, x])
            for q in (0, kk * (kk + 1), kk):
                reach = max(reach, far + abs(rel[q, x]))
        err = 4.0 * _rounding(m, reach)[0]
        q1 = kk * (kk + 1)
        for axis in range(3):
            u = 1 if axis == 0 else 0
            v = 1 if axis == 2 else 2
            if kk > 1 and md[axis] == _GENERAL and _edge_on(  # (k = 1: as its one's test)
                    hi[u] - lo[u], hi[v] - lo[v],
                    _extent(smp[0, u], smp[q1, u], smp[kk, u]) / kk + err,
                    _extent(smp[0, v], smp[q1, v], smp[kk, v]) / kk + err):
                md[axis] = _EDGE_ON
            if md[axis] == _OUTSIDE or (md[axis] == _EDGE_ON and not wgt[axis] > 0.0):
                md[axis] = _SKIP
        if md[0] == _SKIP and md[1] == _SKIP and md[2] == _SKIP:
            continue  # (an aligned wall outside the grid)
        for axis in range(3):
            if md[axis] >= 0:
                _mark_band(smp, kk, axis, r * m, band[axis])
        # Every axis filled or skipped (an aligned wall): the interior sub-triangles add only
        # the offset terms of the one filled axis with any (fa), on its plane.
        fast = True
        fa = -1
        for x in range(3):
            if md[x] >= 0 and wgt[x] > 0.0:
                fast = fast and fa < 0
                fa = x
            elif md[x] < 0 and md[x] != _SKIP:
                fast = False
        fu = 1 if fa == 0 else 0
        fv = 1 if fa == 2 else 2
        fw = wgt[fa] if fa >= 0 else 0.0
        fp = md[fa] if fa >= 0 else 0
        base = (fa * (r + 1) + fp) * r * r
        if fast and fa >= 0:
            touched[fa * (r + 1) + fp] = True
        held = -1  # the face whose sums acc_t, acc_m hold (not yet written back)
        acc_t = acc_m = 0.0
        for i in range(kk):
            for j in range(kk - i):
                q = i * (kk + 1) + j
                for inverted in range(2 if i + j < kk - 1 else 1):  # upright, its neighbour
                    if inverted == 0:
                        ca = q
                        cb = q + kk + 1
                        cc = q + 1
                        far_edge = i + j + 1 == kk
                    else:
                        ca = q + kk + 1
                        cb = q + kk + 2
                        cc = q + 1
                        far_edge = i + j + 2 == kk
                    # A ring sub-triangle (touching the triangle's edges) is scanned across a
                    # filled axis where that edge has samples within reach there (band).
                    scan = False
                    if i == 0 or j == 0 or far_edge:
                        for x in range(3):
                            need[x] = md[x] >= 0 and (
                                (j == 0 and band[x, 0, i]) or (far_edge and band[x, 1, j])
                                or (i == 0 and band[x, 2, j]))
                            scan = scan or need[x]
                    if fast and not scan:
                        if fa < 0:
                            continue
                        iu = math.floor((rel[ca, fu] + rel[cb, fu] + rel[cc, fu]) / 3.0)
                        iv = math.floor((rel[ca, fv] + rel[cb, fv] + rel[cc, fv]) / 3.0)
                        if not (iu >= 0 and iu < r and iv >= 0 and iv < r):
                            continue
                        face = base + iu * r + iv
                        d = fw * ((rel[ca, fa] + rel[cb, fa] + rel[cc, fa]) / 3.0 - fp)
                        if log:
                            e = nlog[0]
                            nlog[0] = e + 1
                            logged[0, e] = face
                            logged[1, e] = fw
                            logged[2, e] = d
                        elif face == held:  # (the same sums in the same order, in registers)
                            acc_t += fw
                            acc_m += d
                        else:
                            if held >= 0:
                                total[held] = acc_t
                                moment[held] = acc_m
                            held = face
                            acc_t = total[face] + fw
                            acc_m = moment[face] + d
                        continue
                    if held >= 0:
                        total[held] = acc_t
                        moment[held] = acc_m
                        held = -1
                    for x in range(3):
                        cen[x] = (rel[ca, x] + rel[cb, x] + rel[cc, x]) / 3.0
                    for axis in range(3):
                        fill = md[axis]
                        if fill == _SKIP:
                            continue
                        u = 1 if axis == 0 else 0
                        v = 1 if axis == 2 else 2
                        if fill >= 0 and not (scan and need[axis]):
                            plane = fill  # (_fill_plane: surely every one's)
                        else:
                            plane = math.floor(cen[axis] + 0.5 - 1e-6)
                            if not (plane >= 0.0 and plane <= r):
                                continue
                            if fill != _EDGE_ON:
                                u0 = smp[ca, u]
                                u1 = smp[cb, u]
                                u2 = smp[cc, u]
                                v0 = smp[ca, v]
                                v1 = smp[cb, v]
                                v2 = smp[cc, v]
                                area, width, height = _projection(u0, u1, u2, v0, v1, v2)
                                if area != 0.0:
                                    window[axis, 0] = max(window[axis, 0], width)
                                    window[axis, 1] = max(window[axis, 1], height)
                                    n = row + nrec[axis]
                                    nrec[axis] += 1
                                    rec[axis, n, 0] = plane
                                    rec[axis, n, 1] = u0
                                    rec[axis, n, 2] = u1
                                    rec[axis, n, 3] = u2
                                    rec[axis, n, 4] = v0
                                    rec[axis, n, 5] = v1
                                    rec[axis, n, 6] = v2
                                    rec[axis, n, 7] = area
                                    work[axis * (r + 1) + plane] += 1.0
                        w = wgt[axis]
                        if not w > 0.0:
                            continue
                        face = _offset_face(cen[u], cen[v], axis, plane, r)
                        if face >= 0:
                            touched[axis * (r + 1) + plane] = True
                            d = w * (cen[axis] - plane)
                            if log:
                                e = nlog[0]
                                nlog[0] = e + 1
                                logged[0, e] = face
                                logged[1, e] = w
                                logged[2, e] = d
                            else:
                                total[face] += w
                                moment[face] += d
        if held >= 0:
            total[held] = acc_t
            moment[held] = acc_m
        for axis in range(3):
            if md[axis] >= 0:
                _fill_window(smp, kk, axis, m, reach, window)


@jit.kernel
def _flat_outside(p, t, kk, md, normal, origin, cell, far, m):
    """True where triangle p[t] (k > 1, modes md) adds nothing across any axis without its
    whole lattice: flat in a coordinate whose planes it is _OUTSIDE of, and surely edge-on
    (_edge_on, from that coordinate's lattice spread) without offset terms (normal 0) across
    the other two."""
    if kk < 2 or md[0] >= 0 or md[1] >= 0 or md[2] >= 0:
        return False
    for a in range(3):
        if not (md[a] == _OUTSIDE and p[t, 0, a] == p[t, 1, a] and p[t, 1, a] == p[t, 2, a]):
            continue
        reach = far + 1.0
        for c in range(3):
            for x in range(3):
                reach = max(reach, far + 1.0 + 1.000001 * abs(p[t, c, x] - origin[x]) / cell)
        err = 4.0 * _rounding(m, reach)[0]
        spread = _lattice_spread(p[t, 0, a], p[t, 1, a], p[t, 2, a], origin[a], cell, m, kk)
        for b in range(3):
            if b == a or md[b] == _OUTSIDE:
                continue
            c = 3 - a - b  # (the other coordinate on b's planes)
            ext = (max(p[t, 0, c], p[t, 1, c], p[t, 2, c]) - min(p[t, 0, c], p[t, 1, c],
                                                                 p[t, 2, c]))
            ext = ext * m / cell / kk * 1.000001 + err
            if normal[t, b] != 0.0 or not _edge_on(spread, 1e300, 1e300, ext):
                return False
        return True
    return False


@jit.kernel
def _lattice_spread(p0, p1, p2, origin, cell, m, kk):
    """max - min of one coordinate of a triangle's lattice points in sample units, as
    _project_lattices computes them."""
    lo = np.inf
    hi = -np.inf
    for i in range(kk + 1):
        u = i / kk
        for j in range(kk + 1 - i):
            v = j / kk
            x = _lattice_point(1.0 - (u + v), u, v, p0, p1, p2, origin, cell) * m - 0.5
            lo = min(lo, x)
            hi = max(hi, x)
    return hi - lo


@jit.kernel
def _extent(a, b, c):
    """The extent of three coordinates: max - min."""
    return max(a, b, c) - min(a, b, c)


@jit.kernel
def _offset_face(cu, cv, axis, plane, r):
    """The face (flat index into (3, R + 1, R, R)) a face_offsets term of a sub-triangle with
    centroid (cu, cv) on the plane goes to, or -1 (outside the grid)."""
    iu = math.floor(cu)
    iv = math.floor(cv)
    if iu >= 0.0 and iu < r and iv >= 0.0 and iv < r:
        return ((axis * (r + 1) + np.int64(plane)) * r + np.int64(iu)) * r + np.int64(iv)
    return -1


@jit.kernel
def _project_run(rel, smp, corners, count, r, rec, row, nrec, window, work, wgt, total, moment,
                 offsets, log, logged, nlog):
    """Sub-triangles corners[:count] (indices into rel: cell units, and smp: the same times m,
    minus 1/2: sample units) projected onto their nearest face planes across each axis, as
    face_coverage computes them: where one covers something (not edge-on, plane inside the
    grid), its record appended to rec[axis] (from row ``row``: nrec[axis] so far), the largest
    sample window (width, height) any needs grown in window[axis], its plane's record count in
    work. With ``offsets``, their face_offsets terms too (weight wgt[axis], centroid and plane
    as face_offsets computes them), added to total and moment (flat), or with ``log`` appended
    to logged ((face, weight, weighted distance), nlog[0] so far)."""
    cen = np.empty(3)
    for s in range(count):
        a = corners[s, 0]
        b = corners[s, 1]
        c = corners[s, 2]
        for x in range(3):
            cen[x] = (rel[a, x] + rel[b, x] + rel[c, x]) / 3.0
        for axis in range(3):
            plane = math.floor(cen[axis] + 0.5 - 1e-6)
            if not (plane >= 0.0 and plane <= r):
                continue
            u = 1 if axis == 0 else 0
            v = 1 if axis == 2 else 2
            u0 = smp[a, u]
            u1 = smp[b, u]
            u2 = smp[c, u]
            v0 = smp[a, v]
            v1 = smp[b, v]
            v2 = smp[c, v]
            area2, width, height = _projection(u0, u1, u2, v0, v1, v2)
            if area2 != 0.0:
                window[axis, 0] = max(window[axis, 0], width)
                window[axis, 1] = max(window[axis, 1], height)
                i = row + nrec[axis]
                nrec[axis] += 1
                rec[axis, i, 0] = plane
                rec[axis, i, 1] = u0
                rec[axis, i, 2] = u1
                rec[axis, i, 3] = u2
                rec[axis, i, 4] = v0
                rec[axis, i, 5] = v1
                rec[axis, i, 6] = v2
                rec[axis, i, 7] = area2
                work[axis * (r + 1) + np.int64(plane)] += 1
            if not (offsets and wgt[axis] > 0.0):  # (none across 2 axes from an aligned wall)
                continue
            w = wgt[axis]
            iu = math.floor(cen[u])
            iv = math.floor(cen[v])
            if iu >= 0.0 and iu < r and iv >= 0.0 and iv < r:
                face = ((axis * (r + 1) + np.int64(plane)) * r + np.int64(iu)) * r + np.int64(iv)
                d = w * (cen[axis] - plane)
                if log:
                    j = nlog[0]
                    nlog[0] = j + 1
                    logged[0, j] = face
                    logged[1, j] = w
                    logged[2, j] = d
                else:
                    total[face] += w
                    moment[face] += d


@jit.kernel
def _projection(u0, u1, u2, v0, v1, v2):
    """A sub-triangle's projection, corners (u, v) in sample units, onto a face plane inside
    the grid, as face_coverage tests it: (twice its signed area, 0.0 where it covers nothing
    (edge-on); the sample window (width, height) it needs)."""
    area2 = (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0)
    if area2 == 0.0:  # (most sub-triangles of an axis-aligned wall, across 2 of the 3 axes)
        return 0.0, 0.0, 0.0
    lo_u = min(u0, u1, u2)
    hi_u = max(u0, u1, u2)
    lo_v = min(v0, v1, v2)
    hi_v = max(v0, v1, v2)
    span = max(hi_u - lo_u, hi_v - lo_v)
    s = max(span, 1.0)
    if not abs(area2) > 1e-9 * (s * s):
        return 0.0, 0.0, 0.0
    return (area2, math.floor(hi_u + 1e-9) - math.ceil(lo_u - 1e-9),
            math.floor(hi_v + 1e-9) - math.ceil(lo_v - 1e-9))


@jit.kernel
def _window(u0, u1, u2, v0, v1, v2):
    """_projection's sample window (width, height) of a sub-triangle that covers something."""
    return (math.floor(max(u0, u1, u2) + 1e-9) - math.ceil(min(u0, u1, u2) - 1e-9),
            math.floor(max(v0, v1, v2) + 1e-9) - math.ceil(min(v0, v1, v2) - 1e-9))


@jit.kernel
def _fill_part_kernel(fills, nfill, r, m, b0, b1, hit):
    """The first nfill fills (_classify_kernel) of planes b0 <= b < b1 as bits in hit
    (_cover_part_kernel's layout): the samples at least _FILL_MARGIN inside each filled
    triangle, row by row (u), each row's interval of v solved from the three edges; m rows (a
    row of faces) at a time, a face inside all of them set whole."""
    rm = r * m
    words = hit.shape[4]
    flat = hit.reshape(-1)
    first = np.empty(m, np.int64)  # each row's interval of samples (v) in the row of faces
    last = np.empty(m, np.int64)
    for n in range(nfill):
        axis = np.int64(fills[n, 0])
        plane = np.int64(fills[n, 1])
        b = axis * (r + 1) + plane
        if b < b0 or b >= b1:
            continue
        u0 = fills[n, 2]
        u1 = fills[n, 3]
        u2 = fills[n, 4]
        v0 = fills[n, 5]
        v1 = fills[n, 6]
        v2 = fills[n, 7]
        sign = 1.0 if (u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0) > 0.0 else -1.0
        # edge i: corner i -> i + 1, inside: du (v - av) - dv (u - au) >= margin |d|
        du0, dv0 = (u1 - u0) * sign, (v1 - v0) * sign
        du1, dv1 = (u2 - u1) * sign, (v2 - v1) * sign
        du2, dv2 = (u0 - u2) * sign, (v0 - v2) * sign
        g0 = _FILL_MARGIN * math.hypot(du0, dv0)
        g1 = _FILL_MARGIN * math.hypot(du1, dv1)
        g2 = _FILL_MARGIN * math.hypot(du2, dv2)
        ja = np.int64(max(np.ceil(min(u0, u1, u2)), 0.0))
        jb = np.int64(min(np.floor(max(u0, u1, u2)), rm - 1.0))
        for iu in range(ja // m, jb // m + 1 if ja <= jb else 0):
            lo = rm  # the rows' least first, greatest last; greatest first, least last
            hi = -1
            inner_lo = -1
            inner_hi = rm
            for s in range(m):
                ju = iu * m + s
                fu = float(ju)
                top = math.inf if ja <= ju <= jb else -math.inf
                bottom = -math.inf
                bottom, top = _bound(bottom, top, du0, v0, g0 + dv0 * (fu - u0))
                bottom, top = _bound(bottom, top, du1, v1, g1 + dv1 * (fu - u1))
                bottom, top = _bound(bottom, top, du2, v2, g2 + dv2 * (fu - u2))
                first[s] = np.int64(max(np.ceil(bottom), 0.0)) if bottom < rm else rm
                last[s] = np.int64(min(np.floor(top), rm - 1.0)) if top >= 0.0 else -1
                if first[s] <= last[s]:
                    lo = min(lo, first[s])
                    hi = max(hi, last[s])
                inner_lo = max(inner_lo, first[s])
                inner_hi = min(inner_hi, last[s])
            base = ((axis * (r + 1) + plane) * r + iu) * r * words
            for iv in range(lo // m, hi // m + 1 if lo <= hi else 0):
                at = base + iv * words
                whole = inner_lo <= iv * m and iv * m + m - 1 <= inner_hi
                for s in range(1 if whole else m):
                    bit = 0 if whole else s * m + max(first[s], iv * m) - iv * m
                    stop = m * m - 1 if whole else s * m + min(last[s], iv * m + m - 1) - iv * m
                    while bit <= stop:  # (word by word)
                        word = bit >> 6
                        top = min(stop, word * 64 + 63)
                        flat[at + word] |= _bits(bit & 63, top & 63)
                        bit = top + 1


@jit.kernel
def _bits(bit, stop):
    """An int64 with bits bit..stop (0 <= bit <= stop <= 63) set."""
    count = stop - bit + 1
    return (np.int64(-1) if count == 64 else (np.int64(1) << count) - 1) << bit


@jit.kernel
def _bound(lo, top, du, av, c):
    """(lo, top) narrowed by one edge's condition du (v - av) >= c on v: (-inf, inf) emptied
    to (inf, -inf) where it holds nowhere."""
    if du > 0.0:
        return max(lo, av + c / du), top
    if du < 0.0:
        return lo, min(top, av + c / du)
    if c > 0.0:
        return math.inf, -math.inf
    return lo, top


@jit.kernel
def _add_logged_kernel(logged, n, total, moment):
    """The first n logged face_offsets terms (_project_lattices) added to total and moment, in
    order (a face's run of terms summed in registers)."""
    total_flat = total.reshape(-1)
    moment_flat = moment.reshape(-1)
    held = -1
    acc_t = acc_m = 0.0
    for j in range(n):
        face = np.int64(logged[0, j])
        if face != held:
            if held >= 0:
                total_flat[held] = acc_t
                moment_flat[held] = acc_m
            held = face
            acc_t = total_flat[face]
            acc_m = moment_flat[face]
        acc_t += logged[1, j]
        acc_m += logged[2, j]
    if held >= 0:
        total_flat[held] = acc_t
        moment_flat[held] = acc_m


@jit.kernel
def _cover_part_kernel(rec, first, nrec, r, m, window, b0, b1, hit):
    """The samples covered on planes b0 <= b < b1 (_parts_kernel's numbering) by their records
    (_project_run; run h's from row first[h], nrec[h, axis] of them) as bits in hit (3, R + 1,
    R, R, words): face by face, its m x m samples in words of 64 (the union; 8x less memory
    than numpy's booleans, no pass over them).

    Each record's projection covers a sample inside its three edges (same edge functions and
    tolerances as face_coverage). Numpy scans every sub-triangle over the largest sample
    window any of them needs (window[axis]), from its own first sample; so does this, so that
    a sample just past a sliver's tip, inside all three edges' tolerance, counts there too.
    The edge functions' terms are the same products and differences, each computed once per
    window column (col: du (v - a_v)) or row (dv (u - a_u))."""
    rm = r * m
    col = np.empty((3, rm))
    col_word = np.empty(rm, np.int64)
    col_bit = np.empty(rm, np.int64)
    words = hit.shape[4]
    flat = hit.reshape(-1)
    runs = first.shape[0]
    for ah in range(3 * runs):
        axis = ah // runs
        h = ah - axis * runs
        lo = max(b0 - axis * (r + 1), 0)
        hi = min(b1 - axis * (r + 1), r + 1)
        if lo >= hi:
            continue
        width = window[axis, 0]
        height = window[axis, 1]
        for n in range(first[h], first[h] + nrec[h, axis]):
            plane = np.int64(rec[axis, n, 0])
            if plane < lo or plane >= hi:
                continue
            u0 = rec[axis, n, 1]
            u1 = rec[axis, n, 2]
            u2 = rec[axis, n, 3]
            v0 = rec[axis, n, 4]
            v1 = rec[axis, n, 5]
            v2 = rec[axis, n, 6]
            j0 = math.ceil(min(u0, u1, u2) - 1e-9)
            l0 = math.ceil(min(v0, v1, v2) - 1e-9)
            wide, high = _own_window(u0, u1, u2, v0, v1, v2, rec[axis, n, 7], width, height)
            ja = max(j0, 0.0)
            jb = min(j0 + wide, rm - 1.0)
            la = max(l0, 0.0)
            lb = min(l0 + high, rm - 1.0)
            if ja > jb or la > lb:
                continue
            sign = 1.0 if rec[axis, n, 7] > 0.0 else -1.0
            # edge i: corner i -> i + 1, oriented inside >= tolerance (relative to its length)
            du0, dv0 = (u1 - u0) * sign, (v1 - v0) * sign
            du1, dv1 = (u2 - u1) * sign, (v2 - v1) * sign
            du2, dv2 = (u0 - u2) * sign, (v0 - v2) * sign
            # The tolerances (-1e-9 x each edge's length) only decide a sample within their
            # reach of an edge (at most twice 1e-9 (|du| + |dv|)): computed (hypot) only then.
            reach0 = 2e-9 * (abs(du0) + abs(dv0))
            reach1 = 2e-9 * (abs(du1) + abs(dv1))
            reach2 = 2e-9 * (abs(du2) + abs(dv2))
            tol0 = tol1 = tol2 = 0.0
            exact = False
            lv = np.int64(la)
            cols = np.int64(lb) - lv + 1
            iv = lv // m  # (faces and samples in them counted on, not divided for)
            sv = lv - iv * m
            for q in range(cols):
                fv = float(lv + q)
                col[0, q] = du0 * (fv - v0)
                col[1, q] = du1 * (fv - v1)
                col[2, q] = du2 * (fv - v2)
                col_word[q] = iv * words  # (its face's first word in a row of faces)
                col_bit[q] = sv
                sv += 1
                if sv == m:
                    sv = 0
                    iv += 1
            start = np.int64(ja)
            iu = start // m
            su = start - iu * m
            for ju in range(start, np.int64(jb) + 1):
                fu = float(ju)
                row0 = dv0 * (fu - u0)
                row1 = dv1 * (fu - u1)
                row2 = dv2 * (fu - u2)
                row = su * m
                base = ((axis * (r + 1) + plane) * r + iu) * r * words
                su += 1
                if su == m:
                    su = 0
                    iu += 1
                # The row's bits gathered word by word in a register, each word written
                # once. The samples in are one run (each edge's test is monotonic along the
                # row, as rounding is): the row ends at the first one out after it.
                word = -1
                bits = 0
                entered = False
                for q in range(cols):
                    e0 = col[0, q] - row0
                    e1 = col[1, q] - row1
                    e2 = col[2, q] - row2
                    if e0 >= 0.0 and e1 >= 0.0 and e2 >= 0.0:
                        inside = True
                    elif e0 < -reach0 or e1 < -reach1 or e2 < -reach2:
                        inside = False
                    else:
                        if not exact:
                            tol0 = -1e-9 * math.hypot(du0, dv0)
                            tol1 = -1e-9 * math.hypot(du1, dv1)
                            tol2 = -1e-9 * math.hypot(du2, dv2)
                            exact = True
                        inside = e0 >= tol0 and e1 >= tol1 and e2 >= tol2
                    if inside:
                        bit = row + col_bit[q]
                        at = base + col_word[q] + (bit >> 6)
                        if at != word:
                            if bits:
                                flat[word] |= bits
                            word = at
                            bits = 0
                        bits |= np.int64(1) << (bit & 63)
                        entered = True
                    elif entered:
                        break
                if bits:
                    flat[word] |= bits


@jit.kernel
def _own_window(u0, u1, u2, v0, v1, v2, area2, width, height):
    """The sample window (width, height) _cover_part_kernel scans for a record: the largest any
    needs (width, height), as numpy scans, but its own where no sample past that can count:
    the scan's tolerances (1e-9 from each edge) reach at most 3e-9 L^2 / |area2| past its
    corners (_fill_plane), short of the next sample unless a sliver's or a corner a hair
    before it."""
    hu = max(u0, u1, u2)
    hv = max(v0, v1, v2)
    longest2 = max((u1 - u0) ** 2 + (v1 - v0) ** 2, (u2 - u1) ** 2 + (v2 - v1) ** 2,
                   (u0 - u2) ** 2 + (v0 - v2) ** 2)
    reach = 3e-9 * longest2 / abs(area2) + 1e-10 * (1.0 + abs(hu) + abs(hv))
    end_u = math.floor(hu + 1e-9)
    end_v = math.floor(hv + 1e-9)
    own_u = end_u - math.ceil(min(u0, u1, u2) - 1e-9)
    own_v = end_v - math.ceil(min(v0, v1, v2) - 1e-9)
    return (width if not end_u + 1.0 - hu > reach else min(own_u, width),
            height if not end_v + 1.0 - hv > reach else min(own_v, height))


@jit.kernel
def _popcount(x):
    """Set bits of the int64 x (the arithmetic shifts' sign bits are masked off)."""
    x = x - ((x >> 1) & 0x5555555555555555)
    x = (x & 0x3333333333333333) + ((x >> 2) & 0x3333333333333333)
    x = (x + (x >> 4)) & 0x0F0F0F0F0F0F0F0F
    return (x * 0x0101010101010101) >> 56


@jit.kernel
def _finish_coverage_kernel(hit, m, r, b0, b1, out):
    """face_coverage (3, R + 1, R, R) of planes b0 <= b < b1: the mean over each face's m x m
    samples."""
    for b in range(b0, b1):
        axis = b // (r + 1)
        plane = b - axis * (r + 1)
        for iu in range(r):
            for iv in range(r):
                count = 0
                for word in range(hit.shape[4]):
                    count += _popcount(hit[axis, plane, iu, iv, word])
                out[axis, plane, iu, iv] = count / (m * m)


@jit.kernel
def _finish_volume_kernel(hit, m, r, total, moment, busy, b0, b1, vis, gaps):
    """occluder_volume's visibility and gaps (6, R, R, R) across planes b0 <= b < b1, from
    their coverage and face_offsets' sums, as face_coverage, face_offsets, _transmittance and
    cell_gaps compute them (np.maximum(x, 0.0): x where x > 0 or NaN, else +0.0), but only
    on busy planes: vis and gaps come filled with 1 and 0, all a plane without records, fills
    or offset terms (all-zero bits and sums) gives (the planes across z scattered through
    both). Each plane is crossed by +axis from the cell below it
    (axis index plane - 1) and -axis from the cell above (plane)."""
    for b in range(b0, b1):
        if not busy[b]:
            continue
        axis = b // (r + 1)
        plane = b - axis * (r + 1)
        for iu in range(r):
            for iv in range(r):
                count = 0
                for word in range(hit.shape[4]):
                    count += _popcount(hit[axis, plane, iu, iv, word])
                w = total[axis, plane, iu, iv]
                if count == 0 and not w > 0.0:  # (most faces: nothing there)
                    trans = np.float32(1.0)
                    up = down = np.float32(0.0)
                else:
                    cover = count / (m * m)
                    trans = np.float32(1.0 - cover)
                    offset = moment[axis, plane, iu, iv] / w if w > 0.0 else 0.0
                    d = offset if cover > GAP_COVERAGE else 0.0
                    up = np.float32(d if (d > 0.0 or math.isnan(d)) else 0.0)
                    down = np.float32(-d if (-d > 0.0 or math.isnan(d)) else 0.0)
                if plane >= 1:
                    if axis == 0:
                        vis[0, plane - 1, iu, iv] = trans
                        gaps[0, plane - 1, iu, iv] = down
                    elif axis == 1:
                        vis[2, iu, plane - 1, iv] = trans
                        gaps[2, iu, plane - 1, iv] = down
                    else:
                        vis[4, iu, iv, plane - 1] = trans
                        gaps[4, iu, iv, plane - 1] = down
                if plane < r:
                    if axis == 0:
                        vis[1, plane, iu, iv] = trans
                        gaps[1, plane, iu, iv] = up
                    elif axis == 1:
                        vis[3, iu, plane, iv] = trans
                        gaps[3, iu, plane, iv] = up
                    else:
                        vis[5, iu, iv, plane] = trans
                        gaps[5, iu, iv, plane] = up


@jit.kernel
def _splits_kernel(p, step, normal, area2, k):
    """_splits' outputs: the same differences, products and sums, in numpy's order (np.cross;
    np.linalg.norm adds the squares first to last), and roundings; step: max(spacing, 1e-30)."""
    e = np.empty((3, 3))  # edges p1 - p0, p2 - p0, p2 - p1
    for t in range(p.shape[0]):
        for x in range(3):
            e[0, x] = p[t, 1, x] - p[t, 0, x]
            e[1, x] = p[t, 2, x] - p[t, 0, x]
            e[2, x] = p[t, 2, x] - p[t, 1, x]
        c0 = e[0, 1] * e[1, 2] - e[0, 2] * e[1, 1]
        c1 = e[0, 2] * e[1, 0] - e[0, 0] * e[1, 2]
        c2 = e[0, 0] * e[1, 1] - e[0, 1] * e[1, 0]
        a = math.sqrt((c0 * c0 + c1 * c1) + c2 * c2)
        area2[t] = a
        d = a if a > 0 else 1.0
        normal[t, 0] = c0 / d
        normal[t, 1] = c1 / d
        normal[t, 2] = c2 / d
        longest = 0.0
        nan = False
        for i in range(3):
            length = math.sqrt((e[i, 0] * e[i, 0] + e[i, 1] * e[i, 1]) + e[i, 2] * e[i, 2])
            nan = nan or math.isnan(length)
            longest = max(longest, length)
        # (an edge that is an exact multiple of the spacing must not get one more split)
        split = np.ceil(longest / step - 1e-6) if not nan else math.nan
        k[t] = 0 if math.isnan(split) else np.int64(min(max(split, 1.0), 64.0))  # MAX_SPLITS


@jit.kernel
def _subdivide_kernel(p, order, k, start, normal, area2, sub, index, nrm, area):
    """_subdivide's outputs for triangles p[order] (the i-th from row start[i]): its k^2
    sub-triangles in _sub_corners' order, each with its triangle, normal and area."""
    for o in range(order.shape[0]):
        t = order[o]
        kk = k[t]
        a = 0.5 * area2[t] / (kk * kk)
        n = start[o]
        for i in range(kk):
            for j in range(kk - i):
                for inverted in range(2 if i + j < kk - 1 else 1):  # upright, its neighbour
                    for c in range(3):
                        # lattice corner (ci, cj): upright (i, j), (i + 1, j), (i, j + 1),
                        # inverted (i + 1, j), (i + 1, j + 1), (i, j + 1)
                        ci = i + (1 if c == 1 or (c == 0 and inverted == 1) else 0)
                        cj = j + (1 if c == 2 or (c == 1 and inverted == 1) else 0)
                        u = ci / kk
                        v = cj / kk
                        w = 1.0 - (u + v)
                        for x in range(3):
                            sub[n, c, x] = w * p[t, 0, x] + u * p[t, 1, x] + v * p[t, 2, x]
                    n += 1
        for row in range(start[o], n):
            index[row] = t
            for x in range(3):
                nrm[row, x] = normal[t, x]
            area[row] = a


@jit.kernel
def _offsets_kernel(tri, normals, areas, origin, cell, r, total, moment):
    """face_offsets' sums (3, R + 1, R, R): weight and weighted distance per face, added in
    sub-triangle order as its bincounts add them."""
    c = np.empty(3)
    for n in range(tri.shape[0]):
        for x in range(3):
            c[x] = ((tri[n, 0, x] - origin[x]) / cell + (tri[n, 1, x] - origin[x]) / cell
                    + (tri[n, 2, x] - origin[x]) / cell) / 3.0
        for axis in range(3):
            u = 1 if axis == 0 else 0
            v = 1 if axis == 2 else 2
            plane = math.floor(c[axis] + 0.5 - 1e-6)
            iu = math.floor(c[u])
            iv = math.floor(c[v])
            w = areas[n] * abs(normals[n, axis])
            if (plane >= 0.0 and plane <= r and iu >= 0.0 and iu < r and iv >= 0.0 and iv < r
                    and w > 0.0):
                face = (axis, np.int64(plane), np.int64(iu), np.int64(iv))
                total[face] += w
                moment[face] += w * (c[axis] - plane)
