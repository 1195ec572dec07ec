"""Discrete-ordinates propagation (angular="dom"): each cell carries its light as flux along
64 fixed directions (quadrature.py) for the whole propagation, instead of re-reading a
4-coefficient lobe at every step.

A two-moment cell (KD10's 2-band SH) must fold the light crossing it from all sides into one
lobe per step; the fold blurs beams, and the error compounds over the ~R steps light travels.
Here the injected lobe is unfolded once into the quadrature directions (emission.emission_density:
a VPL's cos lobe), each direction's flux is advected one cell length
per step semi-Lagrangian (trilinear split over the 8 cells it lands between), and the moments
are folded back only once, for the lookup. Transport is linear and each direction keeps its
own light, so crossing beams pass through each other and light from a diffuse patch spreads as
it should; flux is conserved exactly (weights sum to one, transmittances <= 1). The lookup's
grid is folded into SH bands 0-2 (9 coefficients, not KD10's 4): a two-moment lobe cannot tell
a beam from the uniform hemisphere of light above a lit floor, and read as a lobe that
hemisphere has a tail behind it that lights the floor with its own light; band 2 tells them
apart, and the irradiance kernel is exact to band 2 (lookup.py). Light handed on to the next
cascade stays 4 moments. Cost per step: 64 directions x 8 neighbours per cell and colour.

The product solves the limit of infinitely many steps in one sweep (sweep.py); the step
itself (``advance``, ``propagate_steps``) stays as the reference a stepping backend (the GL
compute backend) is checked against.

This is the discrete ordinates method of radiative transfer (Chandrasekhar 1960, "Radiative
Transfer"; on a grid with semi-Lagrangian advection, e.g. Fattal 2009, "Participating media
illumination using light propagation maps", ACM TOG 28(1)), applied to the LPV's cells.
"""

from __future__ import annotations

import numpy as np

from .. import sh
from ..runtime import jit, pool
from . import emission
from .quadrature import DIRECTIONS, offset_index, offset_visibilities, tables
from .result import PropagationResult
from .result import flux as grid_flux


def unfold(values: np.ndarray) -> np.ndarray:
    """(R, R, R, 3, 4) injected moments -> (q, 3, R, R, R) flux per direction, read as light
    just emitted by diffuse surfaces (emission.emission_density); the flux is kept exactly.
    Only cells holding light are evaluated (most of a grid is empty)."""
    dirs, _, _ = tables()
    shape = values.shape[:3]
    cells = np.ascontiguousarray(values.transpose(3, 0, 1, 2, 4), dtype=np.float32)
    cells = cells.reshape(-1, 4)
    out = np.zeros((len(dirs), cells.shape[0]), np.float32)
    lit = np.flatnonzero(cells[:, 0] > 0)
    _unfold_rows(cells, lit, lit, out)
    return out.reshape(len(dirs), 3, *shape)


def _unfold_rows(cells: np.ndarray, rows: np.ndarray, dest: np.ndarray,
                 out: np.ndarray) -> None:
    """out[:, dest] = the flux per direction of the moments cells[rows] (rows (n, 4) with band
    0 > 0): emission.moments, then emission_density normalised to each row's flux. Compiled
    when ``jit.enabled()`` (_unfold_rows_compiled); what unfold and unfold_sparse run."""
    if rows.size == 0:
        return
    dirs = tables()[0]
    if jit.enabled():
        _unfold_rows_compiled(cells, rows, dest, dirs, out)
        return
    held, mean_cos, d = emission.moments(cells[rows])
    w = emission.emission_density(mean_cos[None, :], dirs @ d.T).astype(np.float32)
    w = np.where(w.sum(axis=0) > 0, w, np.float32(1.0))
    out[:, dest] = w * (held / w.sum(axis=0)).astype(np.float32)[None, :]


def unfold_sparse(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``pad(unfold(values))`` kept sparse: (index, flux) with flux (q, n) the unfolded light of
    the n (cell, colour) pairs holding any, at ``index`` (n,) into the padded flat layout
    flattened per direction (3 (R+2)^3); everything else is zero. For light handed on from a
    finer cascade, which fills few cells: adding it to a dense grid costs O(n), not a pad and
    unfold of the whole grid (32^3: 18 ms)."""
    dirs, _, _ = tables()
    r = values.shape[0]
    p = r + 2
    cells = np.ascontiguousarray(values, np.float32).reshape(-1, 4)  # (cell, colour) rows
    rows = np.flatnonzero(cells[:, 0] > 0)
    cell, colour = np.divmod(rows, 3)
    i, j, k = np.unravel_index(cell, (r, r, r))
    index = colour * p**3 + ((i + 1) * p + j + 1) * p + k + 1
    flux = np.zeros((len(dirs), rows.size), np.float32)
    _unfold_rows(cells, rows, np.arange(rows.size), flux)
    return index, flux


@jit.kernel
def _unfold_kernel(cells, rows, dest, dirs, out, base):  # pragma: no cover - compiled
    """``unfold`` row by row (compiled): out[base[j] + dest[t]] = the flux along direction j of
    the moments cells[rows[t]] (emission.moments, then emission_density normalised to the
    row's flux; zero where band 0 <= 0), ``out`` flat: base[j] = j columns for a (q, columns)
    array, or any other layout (octants.py's lanes). float32 throughout, as the numpy
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
        norm = np.sqrt(vx * vx + vy * vy + vz * vz)
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


def _unfold_rows_compiled(cells, rows, dest, dirs, out, base=None) -> None:
    """_unfold_kernel over ``rows`` in two halves on the pool's threads (each writes its own
    columns ``dest`` of ``out``): what unfold and launch both run. ``base``: where each
    direction's values start in ``out`` flattened (default: its row of a (q, columns)
    array)."""
    if base is None:
        base = np.arange(dirs.shape[0]) * out.shape[1]
    flat = out.reshape(-1)
    if out.size and not np.shares_memory(flat, out):
        raise ValueError("_unfold_rows_compiled needs a contiguous out array")
    h = rows.size // 2
    for _ in pool.executor().map(lambda sl: _unfold_kernel(cells, rows[sl], dest[sl], dirs, flat, base),
                         (slice(0, h), slice(h, None))):
        pass


@jit.kernel
def launch_corners_kernel(dx, dy, dz, mx, my, mz):  # pragma: no cover - compiled
    """Where the launch puts light leaving along (dx, dy, dz) a cell whose emission direction
    is (mx, my, mz): moved LAUNCH_CELLS sideways along the part of d across m, the base
    corner offset (bx, by, bz) in {-1, 0}^3 and the trilinear fractions (fx, fy, fz) towards
    base + 1 (the corners are base + {0, 1}^3), float32 in the numpy code's order. Scalars in
    and out: the compiled launches (here and octants.py) inline it."""
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


def _launch_compiled(injected: np.ndarray, offset_visibility: list | None) -> np.ndarray:
    """``launch`` by the compiled kernels: the lit cells' unfold (_unfold_kernel, those cells
    only) and one scatter loop (_launch_kernel), each in two halves on the pool's threads
    (Cornell box update, one process A/B: propagation 13.8 -> 12.3 ms; measured no faster
    before heap.py, when page faults dominated)."""
    dirs, _, _ = tables()
    q = len(dirs)
    p = injected.shape[0] + 2
    out = np.zeros((q, 3, p**3), np.float32)
    inputs = launch_inputs(injected, offset_visibility)
    halves = ((0, q // 2), (q // 2, q))  # disjoint directions: no shared writes
    for _ in pool.executor().map(lambda js: _launch_kernel(*inputs, p, out, *js), halves):
        pass
    return out


def launch_inputs(injected: np.ndarray, offset_visibility: list | None) -> tuple:
    """What ``_launch_direction_kernel`` reads: (flux (q, 3 n) of the n lit cells, cell-major and
    colour-minor, their emission directions m (n, 3), padded flat cells (n,), directions
    (q, 3), transmittances (n, 27) or (n, 0)); n = 0 when nothing is lit."""
    dirs, _, _ = tables()
    cells, lit, rows = lit_rows(injected)
    flux = np.empty((len(dirs), rows.size), np.float32)  # (q, 3 n): cell-major, colour-minor
    _unfold_rows_compiled(cells, rows, np.arange(rows.size), dirs, flux)
    return (flux,) + launch_geometry(cells, lit, injected.shape[0], offset_visibility)


def lit_rows(injected: np.ndarray) -> tuple:
    """(cells (R^3 3, 4) float32, the lit cells (n,), their 3 n (cell, colour) rows): a cell
    is lit where its colours' band 0 sum is > 0, summed as launch's numpy code does (same
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
    """emission.moments' unit direction (n, 3) float32 of each lit cell's colours summed
    (``cells`` (R^3 3, 4), as lit_rows gives them): where ``launch`` moves a cell's light
    sideways from. Compiled when ``jit.enabled()`` (the same float32 operations: 32^3
    Cornell box, 0.7 -> 0.02 ms)."""
    if jit.enabled():
        return _emission_directions_compiled(cells, lit)
    _, _, m = emission.moments(cells.reshape(-1, 3, 4)[lit].sum(axis=1))
    return np.ascontiguousarray(m, np.float32)


def _emission_directions_compiled(cells: np.ndarray, lit: np.ndarray) -> np.ndarray:
    """``emission_directions`` by ``_directions_kernel``."""
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
        norm = np.sqrt((vx * vx + vy * vy) + vz * vz)
        if norm > zero:
            out[e, 0], out[e, 1], out[e, 2] = vx / norm, vy / norm, vz / norm
        else:
            out[e, 0] = out[e, 1] = out[e, 2] = zero


LAUNCH_CELLS = 0.5  # injection.inject moves a VPL this far off its surface [KD10 sec. 4.2]


def launch(injected: np.ndarray, offset_visibility: list | None = None) -> np.ndarray:
    """The first step of light emitted by surfaces: the arrivals (padded, shell = what left).

    injection.inject puts a VPL half a cell off its surface (LAUNCH_CELLS, against
    self-illumination), and ``unfold`` starts all its directions from there. But light leaving
    a surface point x along w crosses that plane at x + s/2 w / <w, n>, displaced sideways by
    s/2 (w - n <w, n>) / <w, n>: started at x + s/2 n, every direction's light is that much
    nearer the emitter's normal line, as if the emitter were half a cell nearer everything in
    front of it (measured: 1.3x the analytic irradiance 8 cells above a lit floor patch).
    So the first step moves direction w by s (w + (1/2) (w - m <w, m>) / <w, m>), m the cell's
    mean emission direction (the injected lobe's, exact for a cell of one surface
    orientation), trilinearly split over the cells it lands between, each share scaled by the
    transmittance towards its neighbour offset (``offset_visibility``, per
    quadrature.OFFSETS, or None). The sideways shift is capped at half a cell (tan clipped
    at 1, beyond 45 degrees from m): a cell-centred grid places light only to within half a
    cell, and a larger shift pushed grazing light from a floor into the walls beside it
    (indirect relative RMSE against Cycles, uncapped: point room 0.149 -> 0.160, sun yard
    0.884 -> 0.932; capped: 0.150, 0.887; the sunlit room 0.517 -> 0.416 / 0.422).
    Directions behind m take a plain step.

    ``injected`` (R, R, R, 3, 4). Returns the padded flat layout (q, 3, (R+2)^3) that
    ``advance`` steps and sweep.solve takes."""
    if jit.enabled():
        return _launch_compiled(injected, offset_visibility)
    dirs, _, _ = tables()
    q = len(dirs)
    r = injected.shape[0]
    p = r + 2
    geometry = np.asarray(injected, np.float32).sum(axis=3).reshape(-1, 4)  # colours summed
    lit = np.flatnonzero(geometry[:, 0] > 0)
    if lit.size:
        flux = unfold(injected).reshape(q, 3, -1)[:, :, lit]  # (q, 3, n)
        _, _, m = emission.moments(geometry[lit])  # (n, 3): the cell's emission direction
        cos = dirs @ m.T  # (q, n)
        side = dirs[:, None, :] - cos[..., None] * m[None]  # (q, n, 3)
        sin = np.sqrt(np.sum(side * side, axis=-1))
        # tan clipped at 1: the sideways shift is at most LAUNCH_CELLS (see the docstring)
        scale = np.where(cos > 0, LAUNCH_CELLS / np.maximum(np.maximum(cos, sin), 1e-6),
                         np.float32(0.0)).astype(np.float32)
        move = np.clip(dirs[:, None, :] + scale[..., None] * side, -1.0, 1.0)
        base = np.minimum(np.floor(move), 0.0)  # -1 or 0: the corners are base + {0, 1}
        frac = np.ascontiguousarray((move - base).transpose(2, 0, 1), np.float32)  # (3, q, n)
        base = base.astype(np.int64)
        ijk = np.stack(np.unravel_index(lit, (r, r, r)), axis=1) + 1  # (n, 3) padded cells
        start = (ijk[:, 0] * p + ijk[:, 1]) * p + ijk[:, 2]
        vis = None
        if offset_visibility is not None:
            vis = np.stack([v.reshape(-1)[lit] for v in offset_visibility])  # (27, n)
        # Where a direction moves towards its own octant (every cell of an axis-aligned
        # surface), its corners are the octant's 8 step offsets: one ``advance`` with
        # per-cell weights (dense over the padded grid, zero off the lit cells). Other
        # (direction, cell) pairs (a tilted surface turning a direction's sideways shift
        # against it) go by bincount.
        octant_base = np.minimum(np.sign(dirs), 0).astype(np.int64)  # (q, 3)
        own = np.all(base == octant_base[:, None, :], axis=-1)  # (q, n)
        per_axis = np.stack([1.0 - frac, frac])  # (2, 3, q, n): corner 0 / 1 per axis
        w = (per_axis[:, None, None, 0] * per_axis[None, :, None, 1]
             * per_axis[None, None, :, 2]).reshape(8, q, -1) * own  # (8 corners, q, n)
        corners = np.array(list(np.ndindex(2, 2, 2)))  # (8, 3)
        offs = octant_base[None] + corners[:, None]  # (8, q, 3): each direction's offsets
        if vis is not None:
            w *= vis[offset_index(offs)]  # (8, q, n)
        dense = np.zeros((8, q, 1, p**3), np.float32)
        dense[:, :, 0, start] = w
        shifts = (offs[..., 0] * p + offs[..., 1]) * p + offs[..., 2]  # (8, q)
        table = [(sl, [(int(shifts[k, sl.start]), dense[k, sl], None) for k in range(8)])
                 for sl, _ in tables()[2]]
        source = np.zeros((q, 3, p**3), np.float32)
        source[:, :, start] = flux
        out = advance(source, table)
        frac = frac.transpose(1, 2, 0)  # (q, n, 3) for the pairs below
        other = np.nonzero(~own)
        if other[0].size:
            jj, nn = other
            fr, bs = frac[jj, nn], base[jj, nn]  # (k, 3)
            flat_out = out.reshape(-1)
            for corner in np.ndindex(2, 2, 2):
                c = np.array(corner)
                off = bs + c
                w = np.prod(np.where(c == 1, fr, 1.0 - fr), axis=-1)
                if vis is not None:
                    w = w * vis[offset_index(off), nn]
                flat = start[nn] + (off[:, 0] * p + off[:, 1]) * p + off[:, 2]
                for colour in range(3):
                    np.add.at(flat_out, (jj * 3 + colour) * p**3 + flat,
                              w * flux[jj, colour, nn])
    else:
        out = np.zeros((q, 3, p**3), np.float32)
    return out


def fold(flux: np.ndarray, coefficients: int = 4) -> np.ndarray:
    """(q, 3, R, R, R) flux per direction -> (R, R, R, 3, 4 or 9) SH (sum of flux x Y(w)):
    4 moments (what hand-on between cascades injects) or bands 0-2 (the lookup's grid)."""
    dirs, basis, _ = tables()
    if coefficients == sh.BANDS2:
        basis = sh.evaluate_basis2(dirs).astype(np.float32)
    elif coefficients != 4:
        raise ValueError(f"fold to 4 or {sh.BANDS2} coefficients, not {coefficients}")
    q = flux.shape[0]
    m = (basis.T @ flux.reshape(q, -1)).reshape(coefficients, *flux.shape[1:])
    return np.ascontiguousarray(m.transpose(2, 3, 4, 1, 0))


def emission_band2(values: np.ndarray) -> np.ndarray:
    """(..., 4) injected moments -> (..., 9): band 2 of the light ``unfold`` reads them as
    (emission.emission_density, axially symmetric around the mean direction d), added in closed
    form: c_2m = Phi E[P2(<d, w>)] Y_2m(d). For cos^n, E[P2] = n / (n + 3); for r <= 1/2 (a
    uniform hemisphere mixed with an isotropic part) E[P2] = 0."""
    c = np.asarray(values, np.float32)
    out = np.zeros(c.shape[:-1] + (sh.BANDS2,), np.float32)
    out[..., :4] = c
    lit = c[..., 0] > 0
    if lit.any():
        held, r, d = emission.moments(c[lit])
        n = emission.emission_exponent(r.astype(np.float64))
        p2 = np.where(r > 0.5, n / (n + 3.0), 0.0)
        band2 = sh.evaluate_basis2(d)[..., 4:]
        out[..., 4:][lit] = (held * p2)[..., None] * band2
    return out


@jit.kernel
def _emission_band2_kernel(c, out):  # pragma: no cover - compiled
    """``add_emission_band2`` row by row (compiled): out[i] += emission_band2(c[i]), the
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
        norm = np.sqrt(vx * vx + vy * vy + vz * vz)
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
    """values (..., 9) += emission_band2(injected (..., 4)), in place; compiled when
    ``jit.enabled()`` (32^3: about 4 ms in numpy, its lit cells' moments in float64)."""
    if jit.enabled():
        _add_emission_band2_compiled(values, injected)
        return
    values += emission_band2(injected)


def _add_emission_band2_compiled(values: np.ndarray, injected: np.ndarray) -> None:
    """``add_emission_band2`` by ``_emission_band2_kernel``, row by row."""
    c = np.ascontiguousarray(injected, np.float32).reshape(-1, 4)
    out = values.reshape(-1, sh.BANDS2)
    if not np.shares_memory(out, values):
        raise ValueError("add_emission_band2 needs a contiguous values array")
    # rows are independent: two halves on the pool (32^3: 0.34 -> ~0.2 ms), the same bits
    pool.in_halves(lambda sl: _emission_band2_kernel(c[sl], out[sl]), c.shape[0], 8192)


def pad(flux: np.ndarray) -> np.ndarray:
    """(q, 3, R, R, R) -> the padded flat layout (q, 3, (R + 2)^3) that ``advance`` steps: a
    one-cell shell of zeros around the grid, cells in C order. A neighbour offset becomes one
    shift of the flat index, so each (direction, offset) is one contiguous multiply-add, and
    light leaving the grid lands in the shell (the outflow) instead of wrapping."""
    q, c = flux.shape[:2]
    return np.pad(flux, ((0, 0), (0, 0), (1, 1), (1, 1), (1, 1))).reshape(q, c, -1)


def interior(flat: np.ndarray, r: int) -> np.ndarray:
    """The grid (q, 3, R, R, R) of a padded flat array (a view)."""
    return flat.reshape(*flat.shape[:-1], r + 2, r + 2, r + 2)[..., 1:-1, 1:-1, 1:-1]


def take_shell(flat: np.ndarray, r: int, into: np.ndarray | None = None) -> None:
    """Empty the shell of a padded flat array (what left the grid), adding it to ``into``
    (same layout) when given."""
    grid = flat.reshape(*flat.shape[:-1], r + 2, r + 2, r + 2)
    keep = None if into is None else into.reshape(grid.shape)
    for axis in range(3):
        for side in (0, -1):
            sl = [slice(None)] * grid.ndim
            sl[grid.ndim - 3 + axis] = side
            sl = tuple(sl)
            if keep is not None:
                keep[sl] += grid[sl]
            grid[sl] = 0.0


STATE_BYTES = 4 * 2**30  # the propagation's working arrays may take up to this much memory


def check_memory(r: int, capture_outflow: bool = False) -> None:
    """Raise ValueError (with the figure) when propagating an R^3 grid would need more than
    STATE_BYTES: the light, the arrivals, the accumulation and a scratch octant, plus the
    outflow, each 64 x 3 floats per padded cell (4 GB at about 96^3)."""
    arrays = 4.25 + (1 if capture_outflow else 0)
    need = arrays * DIRECTIONS * 3 * (r + 2) ** 3 * 4
    if need > STATE_BYTES:
        raise ValueError(
            f"grid_resolution {r} needs about {need / 2**30:.1f} GB for the discrete-ordinates "
            f"propagation (limit {STATE_BYTES / 2**30:.0f} GB): use a smaller grid, or more "
            "cascades for a large scene")


FACTOR_TABLE_BYTES = 128 * 2**20  # above this (R > ~36), weights and transmittances stay apart


def factors(r: int, offset_visibility: list | None = None) -> list:
    """Per octant: (direction slice, [(flat shift, weights (n, 1, 1), transmittance (1, 1, L)
    or None)]) for ``advance`` on an R^3 grid. ``offset_visibility``: per
    quadrature.OFFSETS entry the (R, R, R) transmittance from each source cell towards that
    neighbour (quadrature.offset_visibilities), or None. While the table stays under
    FACTOR_TABLE_BYTES the two are multiplied here once (one multiply per step instead of two;
    8 q (R + 2)^3 floats: 12 MB at 16^3, 80 MB at 32^3)."""
    _, _, groups = tables()
    p = r + 2
    padded = None
    if offset_visibility is not None:
        padded = [np.pad(v, 1).reshape(1, 1, -1).astype(np.float32) for v in offset_visibility]
    fuse = padded is not None and 8 * len(tables()[0]) * p**3 * 4 <= FACTOR_TABLE_BYTES
    out = []
    for sl, pairs in groups:
        row = []
        for k_off, off, w in pairs:
            shift = (off[0] * p + off[1]) * p + off[2]
            weight = w[:, :, 0, 0, 0, None]  # (n, 1, 1)
            if padded is None:
                row.append((shift, weight, None))
            elif fuse:
                row.append((shift, weight * padded[k_off], None))
            else:
                row.append((shift, weight, padded[k_off]))
        out.append((sl, row))
    return out


def _advance_octant(src: np.ndarray, row: list, out: np.ndarray) -> None:
    """Add one octant's arrivals to ``out`` (zeroed, same shape as ``src``): only the flat range
    of cells holding its light is read."""
    live = np.flatnonzero(src.any(axis=(0, 1)))
    if live.size == 0:
        return
    lo, hi = int(live[0]), int(live[-1]) + 1
    part = src[:, :, lo:hi]
    buf = np.empty_like(part)
    for shift, weight, vis in row:
        np.multiply(part, weight if weight.shape[-1] == 1 else weight[..., lo:hi], out=buf)
        if vis is not None:
            buf *= vis[..., lo:hi]
        out[:, :, lo + shift:hi + shift] += buf


def advance(flat: np.ndarray, factor_table: list) -> np.ndarray:
    """One step on the padded flat layout: every direction's flux moves one cell length.

    ``flat`` (q, 3, (R + 2)^3) holds light in the interior only; the result holds the arrivals,
    those that left the grid in the shell (take_shell). ``factor_table``: ``factors`` for this
    grid and visibility. Per octant only the flat range of cells holding its light is read
    (light reflected by a lit floor alone never travels down: half the octants stay empty).
    Octants run on the thread pool (runtime/pool.py); each writes only its own slice of directions."""
    out = np.zeros_like(flat)
    for _ in pool.executor().map(lambda item: _advance_octant(flat[item[0]], item[1], out[item[0]]),
                         factor_table):  # iterating re-raises an octant's exception here
        pass
    return out


def loop_step(flat: np.ndarray, factor_table: list, r: int, acc: np.ndarray,
              outflow: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """One step of ``propagate_steps``' loop: advance,
    move what left the grid to ``outflow`` (or drop it), add the arrivals to ``acc``.
    Returns the new light and the flux it holds (float64 sum: the early-stop test).
    A direction's light stays in its octant's slice, so each octant does all of this for its
    own slice on the thread pool."""
    nxt = np.empty_like(flat)

    def octant(item) -> float:
        sl, row = item
        out = nxt[sl]
        out[...] = 0.0
        _advance_octant(flat[sl], row, out)
        take_shell(out, r, None if outflow is None else outflow[sl])
        acc[sl] += out
        return float(out.sum(dtype=np.float64))

    moved = sum(pool.executor().map(octant, factor_table))
    return nxt, moved


def step(flux: np.ndarray, offset_visibility: list | None = None) -> np.ndarray:
    """Advect every direction's flux one cell length: (q, 3, R, R, R) -> the same (light that
    would land outside the grid leaves it). ``offset_visibility``: per quadrature.OFFSETS
    entry the (R, R, R) transmittance from each source cell towards that neighbour
    (quadrature.offset_visibilities), or None. The propagation itself stays in the padded
    layout between steps (``advance``)."""
    r = flux.shape[-1]
    out = advance(pad(flux), factors(r, offset_visibility))
    return np.ascontiguousarray(interior(out, r))


def first_arrivals(injected: np.ndarray, visibility: np.ndarray | None,
                   occlude_first_step: bool, passing: np.ndarray | None = None):
    """(arrivals, total): the first step of ``injected`` launched from its surfaces
    (``launch``) plus the plain first step of ``passing``, in the padded flat layout
    (q, 3, (R+2)^3; the shell holds what left), and the grid both came from (their sum):
    where a stepping backend takes over the steps after the launch."""
    r = injected.shape[0]
    offvis = offset_visibilities(visibility)
    arrivals = launch(injected, offvis if occlude_first_step else None)
    if passing is None:
        return arrivals, injected
    table = factors(r, offvis if occlude_first_step else None)
    arrivals += advance(pad(unfold(passing)), table)
    return arrivals, injected + passing


def propagate_steps(injected: np.ndarray, iterations: int, min_fraction: float = 1e-3,
                    visibility: np.ndarray | None = None, occlude_first_step: bool = False,
                    capture_outflow: bool = False, launch: bool = False,
                    passing: np.ndarray | None = None) -> PropagationResult:
    """The discrete-ordinates propagation taken ``iterations`` steps at a time, stopping once
    a step carries less than ``min_fraction`` of the unfolded flux: the numpy reference of a
    stepping backend (the GL compute backend); the product solves the limit of infinitely
    many steps instead (sweep.propagate). The injected lobes are unfolded once into flux per
    direction, advected step by step in the padded flat layout (``loop_step``), and folded back
    into bands 0-2 once at the end. What lands in the layout's shell left the grid: with
    ``capture_outflow`` it is kept as ``outflow`` ((R+2)^3 grid, 4 moments). With ``launch``
    the first step of ``injected`` is ``launch`` (``passing`` steps plainly); otherwise the
    two are one grid. The first step ignores ``visibility`` unless ``occlude_first_step``."""
    r = injected.shape[0]
    check_memory(r, capture_outflow)
    total = injected if passing is None else injected + passing
    offvis = offset_visibilities(visibility)
    free = factors(r)
    occluded = free if visibility is None else factors(r, offvis)
    acc = np.zeros((DIRECTIONS, 3, (r + 2) ** 3), np.float32)
    outflow = np.zeros_like(acc) if capture_outflow else None
    done = 0
    if launch:
        cur, _ = first_arrivals(injected, visibility, occlude_first_step, passing)
        total0 = float(unfold(total).sum(dtype=np.float64))
        if total0 > 0 and iterations > 0:
            take_shell(cur, r, outflow)
            acc += cur
            done = 1
            moved = float(cur.sum(dtype=np.float64))
    else:
        cur = pad(unfold(total))
        total0 = float(cur.sum(dtype=np.float64))
    fraction = 1.0 if total0 > 0 else 0.0
    early = total0 <= 0
    if done:
        fraction = moved / total0
        early = fraction < min_fraction
    for _ in range(0 if early else max(int(iterations) - done, 0)):
        table = occluded if (done > 0 or occlude_first_step) else free
        cur, moved = loop_step(cur, table, r, acc, outflow)
        done += 1
        fraction = moved / total0
        if fraction < min_fraction:
            early = True
            break
    values = fold(np.ascontiguousarray(interior(acc, r)), sh.BANDS2)
    add_emission_band2(values, total)
    if outflow is not None:
        q = outflow.shape[0]
        outflow = fold(outflow.reshape(q, 3, r + 2, r + 2, r + 2))
    return PropagationResult(values, done, grid_flux(total), fraction, early, outflow)
