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

This numpy sweep is the reference. With numba (``jit.enabled()``) ``launch_sweep_fold``, what
the engine runs, has one compiled twin, kernels/sweep.py (the octant sweep): the same
recurrence cell by cell in upwind order for all directions of an octant at once, launched and
folded to SH as it goes.
"""

from __future__ import annotations

import numpy as np

from .. import sh
from ..kernels import sweep as _compiled
from ..runtime import jit
from . import ordinates
from .quadrature import DIRECTIONS, SIGNED_OFFSETS, offset_visibilities, tables
from .result import PropagationResult, flux

_PLANS: dict = {}
_FACTORS: list = []  # [(visibility list or None, (R, shell), factors)], most recent first
FACTOR_CACHE = 4  # visibility arrays whose sweep factors are kept (one per cascade)


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
    q = DIRECTIONS
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
    dirs, _, groups = tables()
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
    pairs_of = {sl.start: pairs for sl, pairs in tables()[2]}
    inside = pl["inside"].astype(np.float32)
    n, k, q = pl["positions"], len(pl["octants"]), DIRECTIONS
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


def launch_solve(injected: np.ndarray, launch_visibility: list | None, passing: np.ndarray | None,
                 offset_visibility: list | None, shell: bool = True) -> np.ndarray:
    """``solve`` of ordinates.launch(injected, launch_visibility) plus the handed-on light
    ``passing`` unfolded in place (ordinates.unfold_sparse, (R, R, R, 3, 4) or None), less the
    latter (it is not an arrival): A in the padded flat layout."""
    r = injected.shape[0]
    index, light = ordinates.unfold_sparse(passing) if passing is not None else (None, None)
    source = ordinates.launch(injected, launch_visibility)
    if index is not None:
        source.reshape(source.shape[0], -1)[:, index] += light
    acc = np.ascontiguousarray(solve(source, r, offset_visibility, shell))  # reshape: a view
    if index is not None:
        acc.reshape(acc.shape[0], -1)[:, index] -= light
    return acc


def solve(source: np.ndarray, r: int, offset_visibility: list | None,
          shell: bool = True) -> np.ndarray:
    """A = source + T A for the light ``source`` in the padded flat layout (q, 3, (R+2)^3),
    interior cells only: returns A in the same layout. With ``shell`` the shell of A holds
    what left the grid, summed over all steps; without, it stays empty (the light is
    dropped). ``offset_visibility``: per propagation.OFFSETS entry the (R, R, R)
    transmittance of each cell towards it, or None."""
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


def fold_parts(light: np.ndarray, r: int, shell: bool) -> tuple:
    """(``fold(light, r, 9)``, ``fold(light, r, 4, "shell")`` or None): the lookup's grid and
    the outflow (what left the grid, handed on to the next cascade)."""
    return fold(light, r, sh.BANDS2), (fold(light, r, 4, "shell") if shell else None)


def launch_sweep_fold(injected: np.ndarray, visibility: np.ndarray | None,
                      passing: np.ndarray | None = None, shell: bool = True,
                      occlude_launch: bool = True) -> tuple:
    """The propagation of light launched from surfaces: ``injected`` (R, R, R, 3, 4) launched
    (ordinates.launch), ``passing`` (the same, or None) handed on, both swept through the
    face transmittances ``visibility`` (6, R, R, R) or None, the launch occluded by them when
    ``occlude_launch``. Returns (values (R, R, R, 3, 9), outflow (R+2, R+2, R+2, 3, 4) with a
    zero interior, or None without ``shell``)."""
    if jit.enabled():
        return _compiled.launch_sweep_fold(injected, visibility, passing, shell, occlude_launch)
    offvis = offset_visibilities(visibility)
    acc = launch_solve(injected, offvis if occlude_launch else None, passing, offvis, shell)
    return fold_parts(acc, injected.shape[0], shell)


def propagate(injected: np.ndarray, visibility: np.ndarray | None = None,
              occlude_first_step: bool = False, capture_outflow: bool = False,
              launch: bool = False, passing: np.ndarray | None = None) -> PropagationResult:
    """propagation.propagate(angular="dom"): A = y + T A solved in one sweep, y the first
    step's arrivals (the launch of ``injected`` with ``launch``: ``launch_sweep_fold``), or the
    unfolded light itself when ``occlude_first_step`` (A then less it). With ``launch``,
    ``passing`` takes plain steps; without, it is part of the injected grid. The folded
    result gets the band-2 part of the injected light itself (ordinates.add_emission_band2)."""
    r = injected.shape[0]
    check_memory(r, capture_outflow)
    shell = capture_outflow
    total = injected if passing is None else injected + passing
    if launch:
        values, outflow = launch_sweep_fold(injected, visibility, passing, shell,
                                            occlude_first_step)
    else:
        offvis = offset_visibilities(visibility)
        if occlude_first_step:  # the unfolded light is not an arrival: taken off A
            source = ordinates.pad(ordinates.unfold(total))
            acc = solve(source, r, offvis, shell)
            acc -= source
        else:  # the first step is unoccluded: take it as a step, sweep its arrivals
            source = ordinates.advance(ordinates.pad(ordinates.unfold(total)),
                                       ordinates.factors(r))
            acc = solve(source, r, offvis, shell)
        values, outflow = fold_parts(acc, r, shell)
    ordinates.add_emission_band2(values, total)
    return PropagationResult(values, 0, flux(total), 0.0, False, outflow, swept=True)
