"""The discrete-ordinates transport taken one step at a time: the oracle the sweep (the limit
of infinitely many steps, lpv_core/propagation/sweep.py) and the GL backend's steps are held to
in the tests, and the step the benchmarks and the stability suite count. Not shipped: the
product always solves the limit."""

from __future__ import annotations

import numpy as np

from lpv_core import sh
from lpv_core.propagation import ordinates
from lpv_core.propagation.quadrature import DIRECTIONS, offset_visibilities
from lpv_core.propagation.result import PropagationResult
from lpv_core.propagation.result import flux as grid_flux
from lpv_core.runtime import pool


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
        ordinates._advance_octant(flat[sl], row, out)
        ordinates.take_shell(out, r, None if outflow is None else outflow[sl])
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
    out = ordinates.advance(ordinates.pad(flux), ordinates.factors(r, offset_visibility))
    return np.ascontiguousarray(ordinates.interior(out, r))


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
    ordinates.check_memory(r, capture_outflow)
    total = injected if passing is None else injected + passing
    offvis = offset_visibilities(visibility)
    free = ordinates.factors(r)
    occluded = free if visibility is None else ordinates.factors(r, offvis)
    acc = np.zeros((DIRECTIONS, 3, (r + 2) ** 3), np.float32)
    outflow = np.zeros_like(acc) if capture_outflow else None
    done = 0
    if launch:
        cur, _ = ordinates.first_arrivals(injected, visibility, occlude_first_step, passing)
        total0 = float(ordinates.unfold(total).sum(dtype=np.float64))
        if total0 > 0 and iterations > 0:
            ordinates.take_shell(cur, r, outflow)
            acc += cur
            done = 1
            moved = float(cur.sum(dtype=np.float64))
    else:
        cur = ordinates.pad(ordinates.unfold(total))
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
    values = ordinates.fold(np.ascontiguousarray(ordinates.interior(acc, r)), sh.BANDS2)
    ordinates.add_emission_band2(values, total)
    if outflow is not None:
        q = outflow.shape[0]
        outflow = ordinates.fold(outflow.reshape(q, 3, r + 2, r + 2, r + 2))
    return PropagationResult(values, done, grid_flux(total), fraction, early, outflow)
