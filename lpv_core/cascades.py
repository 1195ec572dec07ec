"""Cascaded LPVs [KD10 sec. 4.1]: nested grids of equal resolution, cell size doubling.

The coarsest cascade is fitted to the scene (full coverage). Each finer one halves the cell
size and is centred in front of the camera (pushed a quarter of its width along the view
direction, as KD10 pushes cascades towards what the camera sees), clamped inside its parent and
snapped to whole cells of its own size on the coarsest grid's lattice: placement depends only on
the scene and on which cell the camera is in, never on where the scene sits in the world.

Each VPL goes to the finest cascade that holds it with a cell to spare, so no light is counted
twice; light leaving a cascade is handed to the next coarser one (KD10's inner-to-outer
propagation), and a lookup adds what every cascade holding the point says.
"""

from __future__ import annotations

import numpy as np

from .grid import Grid, fit_grid

PUSH = 0.25  # fraction of a cascade's width it is moved along the view direction


def place(lo, hi, resolution: int, count: int, camera=None) -> list[Grid]:
    """Cascade grids, finest first; the last one is fitted to the scene bounds [lo, hi]."""
    outer = fit_grid(lo, hi, resolution)
    chain = [outer]
    if count <= 1 or camera is None:
        return chain
    inv = np.linalg.inv(np.asarray(camera.view, np.float64))
    eye, forward = inv[:3, 3], -inv[:3, 2]
    anchor = outer.origin_array
    for _ in range(count - 1):
        parent = chain[-1]
        cell = parent.cell_size / 2.0
        side = cell * resolution
        centre = eye + forward * (PUSH * side)
        origin = centre - 0.5 * side
        origin = anchor + np.round((origin - anchor) / cell) * cell
        p_lo = parent.origin_array
        p_hi = p_lo + parent.cell_size * parent.resolution - side
        origin = np.clip(origin, p_lo, p_hi)  # parent bounds lie on this lattice: still snapped
        chain.append(Grid(tuple(float(v) for v in origin), float(cell), int(resolution)))
    return chain[::-1]


def assign(chain: list[Grid], positions: np.ndarray, margin_cells: float = 1.0) -> np.ndarray:
    """Index into ``chain`` of the finest cascade holding each point with a margin, (N,)."""
    level = np.full(positions.shape[0], len(chain) - 1, np.int64)
    free = np.ones(positions.shape[0], bool)
    for i, g in enumerate(chain[:-1]):
        lo, hi = g.bounds()
        m = margin_cells * g.cell_size
        inside = np.all((positions >= lo + m) & (positions <= hi - m), axis=1) & free
        level[inside] = i
        free &= ~inside
    return level


def hand_on(finer: Grid, outflow: np.ndarray, coarser: Grid, target: np.ndarray) -> None:
    """Add the light that left ``finer`` (shell of its padded (R+2)^3 ``outflow``) to the
    coarser cascade's injected grid ``target``, in the coarse cell holding each shell cell."""
    flat = outflow.reshape(-1, 12)
    live = np.nonzero(np.abs(flat).max(axis=1) > 0)[0]
    if live.size == 0:
        return
    rp = outflow.shape[0]
    idx = np.stack(np.unravel_index(live, (rp, rp, rp)), axis=1)
    centres = finer.origin_array + (idx - 1 + 0.5) * finer.cell_size
    cell = np.floor((centres - coarser.origin_array) / coarser.cell_size).astype(np.int64)
    r = coarser.resolution
    ok = np.all((cell >= 0) & (cell < r), axis=1)
    flat_target = target.reshape(-1, 12)
    dest = (cell[ok, 0] * r + cell[ok, 1]) * r + cell[ok, 2]
    np.add.at(flat_target, dest, flat[live[ok]])
