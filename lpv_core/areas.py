"""GI areas: clip boxes that confine propagation, transition boxes that scale and tint GI.

An area is a box: the image of [-1, 1]^3 under its 4x4 ``matrix`` (an Empty's cube display,
display size included). Matrices are translation x rotation x scale (an Empty's world matrix);
a sheared matrix still works for the inside test, and its distances are approximate.

- CLIP: light does not propagate across the box's boundary. ``clip_visibility`` gives, per
  axis direction of ``propagation.AXES`` and source cell, 1 where the source cell and the cell
  it sends to lie on the same side of every clip box and 0 where they differ. Injection and
  lookup are trilinear, so a clip boundary leaks at most about one cell: put clip boxes on the
  walls of the interior they confine.
- TRANSITION: GI inside the box is multiplied by ``intensity x tint``; outside it the factor
  blends back to 1 over ``falloff`` metres with a smoothstep (C1-continuous, no visible edge).
  Overlapping areas multiply.
"""

from __future__ import annotations

import numpy as np

from .grid import Grid
from .propagation import AXES
from .scene.model import Area


def _local(area: Area, positions: np.ndarray) -> np.ndarray:
    """(M, 3) world positions in the box's local frame ([-1, 1]^3 is the box)."""
    m = np.asarray(area.matrix, np.float64)
    try:
        inv = np.linalg.inv(m)
    except np.linalg.LinAlgError:
        return np.full(positions.shape, np.inf)
    return positions @ inv[:3, :3].T + inv[:3, 3]


def inside(area: Area, positions) -> np.ndarray:
    """(M,) bool: which positions lie inside the box (boundary included)."""
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    q = _local(area, p)
    with np.errstate(invalid="ignore"):
        return (np.abs(q) <= 1.0).all(axis=1)


def distance_outside(area: Area, positions) -> np.ndarray:
    """(M,) world distance from each position to the box (0 inside); exact for T R S."""
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    q = _local(area, p)
    if not np.isfinite(q).all():
        return np.where(np.isfinite(q).all(axis=1), 0.0, np.inf)
    delta = q - np.clip(q, -1.0, 1.0)  # local offset from the nearest point of the box
    m3 = np.asarray(area.matrix, np.float64)[:3, :3]
    return np.linalg.norm(delta @ m3.T, axis=1)


def smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def transition_weight(area: Area, positions) -> np.ndarray:
    """(M,) blend weight of one transition area: 1 inside, smoothly 0 at ``falloff`` outside."""
    d = distance_outside(area, positions)
    falloff = float(area.falloff)
    if falloff <= 0.0:
        return (d <= 0.0).astype(np.float64)
    return 1.0 - smoothstep(0.0, falloff, d)


def transition_factor(areas, positions) -> np.ndarray:
    """(M, 3) float32 multiplier of looked-up indirect light from all TRANSITION areas."""
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    out = np.ones((p.shape[0], 3), np.float64)
    for area in areas or ():
        if area.type != "TRANSITION":
            continue
        w = transition_weight(area, p)[:, None]
        target = float(area.intensity) * np.asarray(area.tint, np.float64).reshape(1, 3)
        out *= 1.0 + w * (target - 1.0)
    return out.astype(np.float32)


def has_transition(areas) -> bool:
    return any(a.type == "TRANSITION" for a in areas or ())


def has_clip(areas) -> bool:
    return any(a.type == "CLIP" for a in areas or ())


def cell_centres(grid: Grid) -> np.ndarray:
    """(R, R, R, 3) world positions of the cell centres, indexed [x, y, z]."""
    r = grid.resolution
    i = (np.arange(r, dtype=np.float64) + 0.5) * grid.cell_size
    o = grid.origin_array
    x, y, z = np.meshgrid(o[0] + i, o[1] + i, o[2] + i, indexing="ij")
    return np.stack([x, y, z], axis=-1)


def clip_visibility(grid: Grid, areas) -> np.ndarray:
    """(6, R, R, R) float32: 1 where cell and its neighbour along AXES[i] are on the same side
    of every CLIP box, else 0 (what a source cell sends towards AXES[i] is multiplied by it)."""
    r = grid.resolution
    vis = np.ones((6, r, r, r), np.float32)
    clips = [a for a in areas or () if a.type == "CLIP"]
    if not clips:
        return vis
    centres = cell_centres(grid).reshape(-1, 3)
    for area in clips:
        ins = inside(area, centres).reshape(r, r, r)
        for i, d in enumerate(AXES.astype(int)):
            axis = int(np.argmax(np.abs(d)))
            src = [slice(None)] * 3
            dst = [slice(None)] * 3
            if d[axis] > 0:
                src[axis], dst[axis] = slice(None, -1), slice(1, None)
            else:
                src[axis], dst[axis] = slice(1, None), slice(None, -1)
            differ = ins[tuple(src)] != ins[tuple(dst)]
            vis[i][tuple(src)][differ] = 0.0
    return vis


def apply_transition_to_grid(grid: Grid, values: np.ndarray, areas) -> np.ndarray:
    """LPV values with the transition factor of each cell centre multiplied in (the viewport
    overlay's approximation of the per-pixel factor: exact inside and far outside a box, the
    falloff resolved at cell size)."""
    if not has_transition(areas) or values is None:
        return values
    r = grid.resolution
    f = transition_factor(areas, cell_centres(grid).reshape(-1, 3)).reshape(r, r, r, 3, 1)
    return (values * f).astype(np.float32)
