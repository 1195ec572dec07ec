"""Compiled discrete-ordinates steps around the sweep: the twins of ordinates.unfold_rows,
launch, emission_directions and add_emission_band2 (kernels/__init__.py), and the unfold and
launch geometry the compiled octant sweep (kernels/sweep.py) reuses.

Each kernel does the numpy reference's float32 arithmetic in its order (the band-2 term in
float64, as there), cell by cell over the lit cells only; the tests hold them to the numpy code
(tests/test_jit_launch.py, test_jit_fused.py, test_jit_octants.py).
"""

from __future__ import annotations

import numpy as np

from .. import sh
from ..propagation import emission
from ..propagation.quadrature import LAUNCH_CELLS, tables
from ..runtime import jit, pool


def unfold_rows(cells: np.ndarray, rows: np.ndarray, dest: np.ndarray,
                out: np.ndarray) -> None:
    """ordinates.unfold_rows compiled: ``_unfold_kernel`` into the columns ``dest`` of ``out``
    (q, columns)."""
    if rows.size == 0:
        return
    unfold_rows_at(cells, rows, dest, tables()[0], out)


@jit.kernel
def _unfold_kernel(cells, rows, dest, dirs, out, base):  # pragma: no cover - compiled
    """``unfold`` row by row (compiled): out[base[j] + dest[t]] = the flux along direction j of
    the moments cells[rows[t]] (emission.moments, then emission_density normalised to the
    row's flux; zero where band 0 <= 0), ``out`` flat: base[j] = j columns for a (q, columns)
    array, or any other layout (kernels/sweep.py's lanes). float32 throughout, as the numpy
    code. A row whose mean cosine and direction are those of the row before (bit for bit:
    the colours of a cell lit by one surface, 97-100% of the Cornell box's rows) reuses its
    density: the same numbers, a third of the time."""
    q = dirs.shape[0]
    sqrt_4pi = np.float32(sh.SQRT_4PI)
    to_flux = np.float32(emission.FLUX_FROM_BAND1)
    max_cos = np.float32(emission.MAX_MEAN_COSINE)
    lo, hi = np.float32(0.5 + 1e-6), np.float32(emission.LAMBERTIAN_MEAN_COSINE)
    zero = np.float32(0.0)
    w = np.empty(q, np.float32)
    nan = np.float32(np.nan)
    last = (nan, nan, nan, nan)  # the (r, direction) w holds the density of
    total = zero
    for t in range(rows.shape[0]):
        row, col = rows[t], dest[t]
        c0 = cells[row, 0]
        if not c0 > zero:
            for j in range(q):
                out[base[j] + col] = zero
            continue
        held = c0 * sqrt_4pi
        vx, vy, vz = -cells[row, 3] * to_flux, -cells[row, 1] * to_flux, cells[row, 2] * to_flux
        norm = _norm_kernel(vx, vy, vz)
        r = min(max(norm / held, zero), max_cos)
        if norm > zero:
            vx, vy, vz = vx / norm, vy / norm, vz / norm
        else:
            vx, vy, vz = zero, zero, zero
        if (r, vx, vy, vz) != last:
            total = _emission_weights_kernel(dirs, r, vx, vy, vz, min(max(r, lo), hi), hi, w)
            last = (r, vx, vy, vz)
        scale = held / total
        for j in range(q):
            out[base[j] + col] = w[j] * scale


@jit.kernel
def _norm_kernel(vx, vy, vz):  # pragma: no cover - compiled
    """|v| of a float32 vector as emission.moments forms it: squared and summed in float64
    (no overflow or underflow at any flux), rounded to float32."""
    x, y, z = np.float64(vx), np.float64(vy), np.float64(vz)
    return np.float32(np.sqrt((x * x + y * y) + z * z))


@jit.kernel
def _emission_weights_kernel(dirs, r, vx, vy, vz, rr, hi, w):  # pragma: no cover - compiled
    """w[j] = emission.emission_density of mean cosine r (rr: r clipped to [1/2, hi]) around
    direction v, at dirs[j], in float32 as the numpy code; all 1 where they sum to 0. Returns
    their sum."""
    q = dirs.shape[0]
    zero, half, one, two, four = (np.float32(0.0), np.float32(0.5), np.float32(1.0),
                                  np.float32(2.0), np.float32(4.0))
    total = zero
    if r > half and rr >= hi:  # emission.emission_exponent: n = 1, a plain cosine
        for j in range(q):
            c = dirs[j, 0] * vx + dirs[j, 1] * vy + dirs[j, 2] * vz
            w[j] = max(zero, c)
            total += w[j]
    elif r > half:
        n = (two * rr - one) / (one - rr)
        for j in range(q):
            c = dirs[j, 0] * vx + dirs[j, 1] * vy + dirs[j, 2] * vz
            w[j] = np.exp(n * np.log(c)) if c > zero else zero
            total += w[j]
    else:
        for j in range(q):
            c = dirs[j, 0] * vx + dirs[j, 1] * vy + dirs[j, 2] * vz
            w[j] = (one - two * r) + (four * r if c > zero else zero)
            total += w[j]
    if not total > zero:
        for j in range(q):
            w[j] = one
        total = np.float32(q)
    return total


def unfold_rows_at(cells, rows, dest, dirs, out, base=None) -> None:
    """_unfold_kernel over ``rows`` in parts on the pool's threads (each writes its own
    columns ``dest`` of ``out``): what unfold, the launch and the octant sweep run. ``base``:
    where each direction's values start in ``out`` flattened (default: its row of a
    (q, columns) array)."""
    if base is None:
        base = np.arange(dirs.shape[0]) * out.shape[1]
    flat = out.reshape(-1)
    if out.size and not np.shares_memory(flat, out):
        raise ValueError("unfold_rows_at needs a contiguous out array")
    pool.in_parts(lambda sl: _unfold_kernel(cells, rows[sl], dest[sl], dirs, flat, base),
                  rows.size, smallest=0)


@jit.kernel
def launch_corners_kernel(dx, dy, dz, mx, my, mz):  # pragma: no cover - compiled
    """Where the launch puts light leaving along (dx, dy, dz) a cell whose emission direction
    is (mx, my, mz): moved LAUNCH_CELLS sideways along the part of d across m, the base
    corner offset (bx, by, bz) in {-1, 0}^3 and the trilinear fractions (fx, fy, fz) towards
    base + 1 (the corners are base + {0, 1}^3), float32 in the numpy code's order. Scalars in
    and out: the compiled launches (here and kernels/sweep.py) inline it."""
    half, eps = np.float32(LAUNCH_CELLS), np.float32(1e-6)
    zero, one = np.float32(0.0), np.float32(1.0)
    cos = dx * mx + dy * my + dz * mz
    sx, sy, sz = dx - cos * mx, dy - cos * my, dz - cos * mz
    sin = np.sqrt(sx * sx + sy * sy + sz * sz)
    scale = half / max(max(cos, sin), eps) if cos > zero else zero
    mvx = min(max(dx + scale * sx, -one), one)
    mvy = min(max(dy + scale * sy, -one), one)
    mvz = min(max(dz + scale * sz, -one), one)
    bx, by, bz = -1 if mvx < zero else 0, -1 if mvy < zero else 0, -1 if mvz < zero else 0
    fx = mvx + one if mvx < zero else mvx
    fy = mvy + one if mvy < zero else mvy
    fz = mvz + one if mvz < zero else mvz
    return bx, by, bz, fx, fy, fz


@jit.kernel
def _launch_kernel(flux, m, start, dirs, vis, p, out, j0, j1):  # pragma: no cover - compiled
    """``launch``'s scatter (compiled) for directions j0 <= j < j1 (``_launch_direction_kernel``),
    direction outermost: out[j] (3 (R+2)^3) stays in cache."""
    for j in range(j0, j1):
        _launch_direction_kernel(flux, m, start, dirs, vis, p, out, j)


@jit.kernel
def _launch_direction_kernel(flux, m, start, dirs, vis, p, out, j):  # pragma: no cover - compiled
    """``launch``'s scatter of direction j (compiled): lit cell i's flux
    flux[j, 3 i + colour] moves along j, shifted sideways by its emission direction m[i], split
    trilinearly over the 8 cells around, each share times vis[i, offset] (when vis has
    columns), into out[j, colour, start[i] + shift] (padded flat layout). One loop over (cell,
    corner, colour) in place of the numpy code's dense octant step plus np.add.at; float32
    weights formed in the numpy code's order. Scalars only in the loop (a small work array
    would be re-read after every store to ``out``: 1.3x slower)."""
    has_vis = vis.shape[1] > 0
    zero, one = np.float32(0.0), np.float32(1.0)
    dx, dy, dz = dirs[j, 0], dirs[j, 1], dirs[j, 2]
    for i in range(m.shape[0]):
        f0, f1, f2 = flux[j, 3 * i], flux[j, 3 * i + 1], flux[j, 3 * i + 2]
        if f0 == zero and f1 == zero and f2 == zero:
            continue  # nothing emitted this way (behind the surface): it would add zeros
        bx, by, bz, fx, fy, fz = launch_corners_kernel(dx, dy, dz, m[i, 0], m[i, 1], m[i, 2])
        corner = start[i] + (bx * p + by) * p + bz
        for cx in range(2):
            wx = fx if cx else one - fx
            for cy in range(2):
                wxy = wx * (fy if cy else one - fy)
                for cz in range(2):
                    w = wxy * (fz if cz else one - fz)
                    if has_vis:
                        w = w * vis[i, ((bx + cx + 1) * 3 + by + cy + 1) * 3 + bz + cz + 1]
                    cell = corner + (cx * p + cy) * p + cz
                    out[j, 0, cell] += w * f0
                    out[j, 1, cell] += w * f1
                    out[j, 2, cell] += w * f2


def launch(injected: np.ndarray, offset_visibility: list | None = None) -> np.ndarray:
    """ordinates.launch compiled: the lit cells' unfold (_unfold_kernel, those cells only) and
    one scatter loop (_launch_kernel), each in parts on the pool's threads."""
    dirs, _, _ = tables()
    q = len(dirs)
    p = injected.shape[0] + 2
    out = np.zeros((q, 3, p**3), np.float32)
    inputs = launch_inputs(injected, offset_visibility)
    # parts of the directions on the pool's threads: disjoint, no shared writes
    pool.in_parts(lambda sl: _launch_kernel(*inputs, p, out, sl.start, sl.stop), q, smallest=0)
    return out


def launch_inputs(injected: np.ndarray, offset_visibility: list | None) -> tuple:
    """What ``_launch_direction_kernel`` reads: (flux (q, 3 n) of the n lit cells, cell-major and
    colour-minor, their emission directions m (n, 3), padded flat cells (n,), directions
    (q, 3), transmittances (n, 27) or (n, 0)); n = 0 when nothing is lit."""
    dirs, _, _ = tables()
    cells, lit, rows = lit_rows(injected)
    flux = np.empty((len(dirs), rows.size), np.float32)  # (q, 3 n): cell-major, colour-minor
    unfold_rows_at(cells, rows, np.arange(rows.size), dirs, flux)
    return (flux,) + launch_geometry(cells, lit, injected.shape[0], offset_visibility)


def lit_rows(injected: np.ndarray) -> tuple:
    """(cells (R^3 3, 4) float32, the lit cells (n,), their 3 n (cell, colour) rows): a cell
    is lit where its colours' band 0 sum is > 0, summed as ordinates.launch does (same
    order, same bits)."""
    cells = np.ascontiguousarray(injected, np.float32).reshape(-1, 4)
    band0 = cells[:, 0].reshape(-1, 3)
    lit = np.flatnonzero(band0[:, 0] + band0[:, 1] + band0[:, 2] > 0)
    return cells, lit, (lit[:, None] * 3 + np.arange(3)).reshape(-1)


def launch_geometry(cells: np.ndarray, lit: np.ndarray, r: int,
                    offset_visibility: list | None) -> tuple:
    """The rest of ``launch_inputs`` for the lit cells of ``lit_rows``: (emission directions
    m (n, 3), padded flat cells (n,), directions (q, 3), transmittances (n, 27) or (n, 0))."""
    p = r + 2
    m = emission_directions(cells, lit)
    ijk = np.stack(np.unravel_index(lit, (r, r, r)), axis=1) + 1  # (n, 3) padded cells
    start = (ijk[:, 0] * p + ijk[:, 1]) * p + ijk[:, 2]
    if offset_visibility is None:
        vis = np.zeros((lit.size, 0), np.float32)
    else:  # (n, 27): a cell's transmittances side by side
        vis = np.stack([np.asarray(v, np.float32).reshape(-1)[lit] for v in offset_visibility],
                       axis=1)
    return m, start, tables()[0], vis


def emission_directions(cells: np.ndarray, lit: np.ndarray) -> np.ndarray:
    """ordinates.emission_directions compiled (``_directions_kernel``: the same float32
    operations)."""
    out = np.empty((lit.size, 3), np.float32)
    _directions_kernel(cells, lit, out)
    return out


@jit.kernel
def _directions_kernel(cells, lit, out):  # pragma: no cover - compiled
    """``emission_directions`` cell by cell: colours summed in order, then emission.moments'
    vector, its norm and the direction (0 where the norm is 0), all float32."""
    to_flux = np.float32(emission.FLUX_FROM_BAND1)
    zero = np.float32(0.0)
    for e in range(lit.shape[0]):
        row = lit[e] * 3
        s1 = (cells[row, 1] + cells[row + 1, 1]) + cells[row + 2, 1]
        s2 = (cells[row, 2] + cells[row + 1, 2]) + cells[row + 2, 2]
        s3 = (cells[row, 3] + cells[row + 1, 3]) + cells[row + 2, 3]
        vx, vy, vz = -s3 * to_flux, -s1 * to_flux, s2 * to_flux
        norm = _norm_kernel(vx, vy, vz)
        if norm > zero:
            out[e, 0], out[e, 1], out[e, 2] = vx / norm, vy / norm, vz / norm
        else:
            out[e, 0] = out[e, 1] = out[e, 2] = zero


@jit.kernel
def _emission_band2_kernel(c, out):  # pragma: no cover - compiled
    """``add_emission_band2`` row by row: out[i] += ordinates.emission_band2(c[i]), the
    arithmetic of emission.moments in float32 and of the band-2 term in float64, as the numpy
    code; rows of zeros skipped."""
    sqrt_4pi = np.float32(sh.SQRT_4PI)
    to_flux = np.float32(emission.FLUX_FROM_BAND1)
    max_cos = np.float32(emission.MAX_MEAN_COSINE)
    lo, hi = 0.5 + 1e-6, emission.LAMBERTIAN_MEAN_COSINE
    zero = np.float32(0.0)
    for i in range(c.shape[0]):
        if c[i, 0] == zero and c[i, 1] == zero and c[i, 2] == zero and c[i, 3] == zero:
            continue  # adds nothing (most cells: their values are not even read)
        for t in range(4):
            out[i, t] += c[i, t]
        if not c[i, 0] > zero:
            continue
        held = c[i, 0] * sqrt_4pi
        vx, vy, vz = -c[i, 3] * to_flux, -c[i, 1] * to_flux, c[i, 2] * to_flux
        norm = _norm_kernel(vx, vy, vz)
        r = min(max(norm / held, zero), max_cos)
        if not r > np.float32(0.5) or not norm > zero:
            continue  # E[P2] = 0: no band 2
        x, y, z = vx / norm, vy / norm, vz / norm
        rr = min(max(np.float64(r), lo), hi)
        n = 1.0 if rr >= hi else (2.0 * rr - 1.0) / (1.0 - rr)  # emission.emission_exponent
        s = np.float64(held) * (n / (n + 3.0))
        x, y, z = np.float64(x), np.float64(y), np.float64(z)
        out[i, 4] += s * (sh.Y2A * x * y)
        out[i, 5] += s * (sh.Y2A * y * z)
        out[i, 6] += s * (sh.Y2B * (3.0 * z * z - 1.0))
        out[i, 7] += s * (sh.Y2A * x * z)
        out[i, 8] += s * (sh.Y2C * (x * x - y * y))


def add_emission_band2(values: np.ndarray, injected: np.ndarray) -> None:
    """ordinates.add_emission_band2 compiled: ``_emission_band2_kernel`` row by row."""
    c = np.ascontiguousarray(injected, np.float32).reshape(-1, 4)
    out = values.reshape(-1, sh.BANDS2)
    if not np.shares_memory(out, values):
        raise ValueError("add_emission_band2 needs a contiguous values array")
    # rows are independent: parts on the pool's threads, the same bits
    pool.in_parts(lambda sl: _emission_band2_kernel(c[sl], out[sl]), c.shape[0],
                  smallest=8192)

