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

The product solves the limit of infinitely many steps in one sweep (sweep.py); one step
(``advance``) is what the GL compute backend repeats, and tools/dom_steps.py takes the steps
one by one (the oracle the tests hold the sweep and the GL steps to).

This is the discrete ordinates method of radiative transfer (Chandrasekhar 1960, "Radiative
Transfer"; on a grid with semi-Lagrangian advection, e.g. Fattal 2009, "Participating media
illumination using light propagation maps", ACM TOG 28(1)), applied to the LPV's cells.
"""

from __future__ import annotations

import numpy as np

from .. import sh
from ..kernels import ordinates as _compiled
from ..runtime import jit, pool
from . import emission
from .quadrature import DIRECTIONS, LAUNCH_CELLS, offset_index, offset_visibilities, tables


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
    unfold_rows(cells, lit, lit, out)
    return out.reshape(len(dirs), 3, *shape)


def unfold_rows(cells: np.ndarray, rows: np.ndarray, dest: np.ndarray,
                out: np.ndarray) -> None:
    """out[:, dest] = the flux per direction of the moments cells[rows] (rows (n, 4) with band
    0 > 0): emission.moments, then emission_density normalised to each row's flux; what
    unfold and unfold_sparse run."""
    if jit.enabled():
        return _compiled.unfold_rows(cells, rows, dest, out)
    if rows.size == 0:
        return
    dirs = tables()[0]
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
    unfold_rows(cells, rows, np.arange(rows.size), flux)
    return index, flux


def emission_directions(cells: np.ndarray, lit: np.ndarray) -> np.ndarray:
    """emission.moments' unit direction (n, 3) float32 of each lit cell's colours summed
    (``cells`` (R^3 3, 4), as kernels/ordinates.py's lit_rows gives them): where ``launch``
    moves a cell's light sideways from (the compiled launches' geometry)."""
    if jit.enabled():
        return _compiled.emission_directions(cells, lit)
    _, _, m = emission.moments(cells.reshape(-1, 3, 4)[lit].sum(axis=1))
    return np.ascontiguousarray(m, np.float32)


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
        return _compiled.launch(injected, offset_visibility)
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


def add_emission_band2(values: np.ndarray, injected: np.ndarray) -> None:
    """values (..., 9) += emission_band2(injected (..., 4)), in place."""
    if jit.enabled():
        return _compiled.add_emission_band2(values, injected)
    values += emission_band2(injected)


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
