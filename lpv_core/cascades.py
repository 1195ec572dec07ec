"""Cascaded LPVs [KD10 sec. 4.1]: nested grids of equal resolution, cell size doubling.

The coarsest cascade is fitted to the scene (full coverage). Each finer one halves the cell
size and is centred in front of the camera (pushed a quarter of its width along the view
direction, as KD10 pushes cascades towards what the camera sees), clamped inside its parent and
snapped to whole cells of its parent (each of those lies wholly inside it or outside):
placement depends only on the scene and on which cell the camera is in, never on where the
scene sits in the world.

Each VPL goes to the finest cascade that holds it with a cell to spare, so no light is counted
twice; light leaving a cascade is handed to the next coarser one (KD10's inner-to-outer
propagation). So a coarser cascade's cells inside a finer one hold only their own VPLs' light:
a receiver reads the finest cascade holding it, made whole (``whole``: the finer cascades' light
summed into its cells inside them), and adds the coarser ones as they are (``reads``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .grid import Grid, fit_grid
from .kernels import cascades as _compiled
from .runtime import jit

PUSH = 0.25  # fraction of a cascade's width it is moved along the view direction

# Tukey's fence for fit_bounds, in interquartile ranges beyond the quartiles. It must exceed the
# largest tail one planar triangle has, so that no surface is fenced out by its own shape: a
# triangle's area along an axis has a triangular density, and in the worst case (falling
# linearly to 0 at one end) the quartiles are at 1 - sqrt(3)/2 and 1/2 of its length, its far
# end (1/2) / (1/2 - (1 - sqrt(3)/2)) = (1 + sqrt(3)) / 2 = 1.37 interquartile ranges beyond the
# upper quartile. That bound is tight (a finely cut worst-case triangle loses its tip piece to
# the discrete quartiles), so we take Tukey's outlier fence 1.5, the next conventional value
# above it: a finely tessellated big triangle, a floor or a terrain always stays inside.
SINGLE_TRIANGLE_TAIL = (1.0 + np.sqrt(3.0)) / 2.0
FENCE_IQR = 1.5


FACE_SLACK = 1e-6  # of the LPV box's extent: a point this near a face lies on it
FACING_OUT = 1e-3  # a normal component above this points out through the face


def facing_into(positions: np.ndarray, normals: np.ndarray, lo, hi) -> np.ndarray:
    """(N,) bool: the points inside the LPV box [lo, hi] that do not lie on one of its faces
    with their normal pointing out through it (a flat box's thin axis aside). Light a surface
    sends out of the box meets nothing there (the box bounds the geometry, or it is the
    closed space around the camera): the lit sides of a closed room's outer walls and roof
    are left out, which the grid, a cell wide, could not keep apart from the inner sides.
    "On a face" allows FACE_SLACK of the box's extent (an RSM's float32 positions are exact
    to ~1e-7 of it) and "out" a normal component above FACING_OUT (float32 normals' noise
    is ~1e-7), so that which points count does not depend on the scene's scale or place."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    eps = FACE_SLACK * max(float(np.max(hi - lo)), 1e-30)
    p, n = np.asarray(positions), np.asarray(normals)
    keep = np.ones(p.shape[0], bool)
    for a in range(3):  # a column at a time: no (N, 3) float64 copies
        if hi[a] - lo[a] <= 2 * eps:
            continue
        x, d = p[:, a].astype(np.float64), n[:, a]
        keep &= (x >= lo[a] - eps) & (x <= hi[a] + eps)
        keep &= ~((x >= hi[a] - eps) & (d > FACING_OUT)) & ~((x <= lo[a] + eps) & (d < -FACING_OUT))
    return keep


def fit_bounds(scene) -> tuple[np.ndarray, np.ndarray, int, float]:
    """Box (lo, hi) the outer cascade is fitted to, the number of triangles left outside it and
    their share of the surface area.

    Plain scene bounds let one stray triangle 10 km from a 1 m room make every cell ~700 m
    wide. Instead: each triangle counts with its area at its centroid; per axis, the area's
    quartiles Q1, Q3 give a fence [Q1 - F S, Q3 + F S], where S is the largest interquartile
    range over the three axes (the grid is cubic: a scene that is flat along one axis, e.g. a
    ground plane holding 80 % of the area, must not fence its buildings out along that axis)
    and F = FENCE_IQR. Triangles whose centroid lies outside the fence on any axis are left out
    of the LPV (they get no GI; VPLs and receivers there see a zero grid); the box is the exact
    bounds of the others, so for a scene without such outliers it equals ``scene.bounds()``
    and nothing changes. Area-weighted, because what matters for GI is surface that exchanges
    light: a far-away triangle with little of the area exchanges little (form factor ~ A/d^2)
    and would cost every other surface most of its resolution. A far surface with a quarter of
    the area or more moves the quartiles and is kept.

    The camera and the lights are not added: lookups happen on visible surfaces and VPLs sit on
    lit ones, both geometry, which the box already holds unless fenced out; a camera far
    outside (a long lens) would only fill the grid with empty space. Everything is a function
    of the triangles only, so the placement moves and scales with the scene.
    """
    p = np.asarray(scene.positions, np.float64).reshape(-1, 3, 3)
    if p.shape[0] == 0:
        return np.zeros(3), np.zeros(3), 0, 0.0
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    total = float(area.sum())
    weight = area if total > 0 else np.ones(len(area))
    centroid = (p[:, 0] + p[:, 1] + p[:, 2]) / 3.0
    q1 = np.array([_weighted_quantile(centroid[:, a], weight, 0.25) for a in range(3)])
    q3 = np.array([_weighted_quantile(centroid[:, a], weight, 0.75) for a in range(3)])
    spread = float(np.max(q3 - q1))
    keep = np.all((centroid >= q1 - FENCE_IQR * spread)
                  & (centroid <= q3 + FENCE_IQR * spread), axis=1)
    if not keep.any():  # cannot happen (the median triangle is inside), kept for safety
        keep[:] = True
    kept = p[keep].reshape(-1, 3)
    outside = int((~keep).sum())
    share = float(area[~keep].sum() / total) if total > 0 else 0.0
    return kept.min(axis=0), kept.max(axis=0), outside, share


# A point's space is enclosed when at most this share of the sphere around it sees no geometry
# (the share planner.ENCLOSED_SKY_SHARE allows a camera's pixels).
ENCLOSED_OPEN_SHARE = 0.05
# The LPV box becomes the space enclosing the camera when that is at most this fraction of the
# fitted box's extent: a cascade level (cells halve) or more gained; below it the fitted box
# (exact triangle bounds) is kept, and nothing changes for a room that is the whole scene.
ENCLOSURE_SCALE = 0.5


@dataclass(frozen=True)
class Surroundings:
    """What a point sees in every direction (Engine.surroundings: a small cube map from it):
    the surface points hit (N, 3) with the solid angle of each sample (N,) sr, and the share
    of the sphere that sees no geometry."""

    origin: np.ndarray
    points: np.ndarray
    solid: np.ndarray
    open_share: float
    tolerance: float = 0.0  # position error of the points (float32 targets), m

    @property
    def enclosed(self) -> bool:
        return self.open_share <= ENCLOSED_OPEN_SHARE and len(self.points) > 0

    def size(self, share: float = 1.0 - 2.0 * ENCLOSED_OPEN_SHARE) -> float:
        """Diameter of the space around the point: twice the distance within which ``share``
        of the sphere hits geometry (inf when more than 1 - share of it is open)."""
        if len(self.points) == 0:
            return float("inf")
        dist = np.linalg.norm(self.points - self.origin, axis=1)
        order = np.argsort(dist)
        cum = np.cumsum(self.solid[order]) / (4.0 * np.pi)
        i = int(np.searchsorted(cum, share, side="left"))
        return float("inf") if i >= len(order) else 2.0 * float(dist[order[i]])


def enclosure_bounds(scene, lo, hi, around: Surroundings | None):
    """(lo, hi, triangles left out, their area share) of the closed space around the camera,
    when it is one (``around.enclosed``) at most ENCLOSURE_SCALE of the fitted box [lo, hi]
    wide, else None.

    A room standing on a 2 km ground: the area-weighted fence keeps the ground (it holds the
    area), the cells become 140 m wide and the room gets no indirect light. Light cannot pass
    the closed space's walls: lamps outside it add nothing to what the camera sees, lamps
    inside keep their light inside, so the LPV needs only that space. Its box is the bounds of
    the points the camera's eye sees all around, each face moved onto the triangle corners
    within the points' float32 error (walls are exact planes: the box is the same wherever the
    eye stands in the room, and the room's own bounds when the room is the scene)."""
    if around is None or not around.enclosed:
        return None
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    e_lo, e_hi = around.points.min(axis=0), around.points.max(axis=0)
    if float(np.max(e_hi - e_lo)) > ENCLOSURE_SCALE * float(np.max(hi - lo)):
        return None
    p = np.asarray(scene.positions, np.float64).reshape(-1, 3, 3)
    tol = max(around.tolerance, 1e-12 * float(np.max(np.abs(e_hi)) + np.max(np.abs(e_lo))))
    corners = p.reshape(-1, 3)
    for a in range(3):
        c = corners[:, a]
        near = c[np.abs(c - e_lo[a]) <= tol]
        e_lo[a] = near.min() if near.size else e_lo[a] - tol
        near = c[np.abs(c - e_hi[a]) <= tol]
        e_hi[a] = near.max() if near.size else e_hi[a] + tol
    out = np.any(p.max(axis=1) < e_lo, axis=1) | np.any(p.min(axis=1) > e_hi, axis=1)
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    total = float(area.sum())
    return e_lo, e_hi, int(out.sum()), float(area[out].sum() / total) if total > 0 else 0.0


def _weighted_quantile(x: np.ndarray, w: np.ndarray, q: float) -> float:
    """Smallest value of ``x`` whose cumulative weight (sorted by x) reaches ``q`` of the total
    (an actual data value: exact under translation and scaling)."""
    order = np.argsort(x, kind="stable")
    cum = np.cumsum(w[order])
    i = int(np.searchsorted(cum, q * cum[-1], side="left"))
    return float(x[order][min(i, len(x) - 1)])


def place(lo, hi, resolution: int, count: int, camera=None, focus=None) -> list[Grid]:
    """Cascade grids, finest first; the last one is fitted to the scene bounds [lo, hi].

    ``focus`` (N, 3): surface points the camera sees (a small G-buffer, one per pixel). A
    finer cascade is then centred on the median of those its parent holds: the middle of
    what the screen shows that it can hold (it is clamped inside its parent), not a point in
    front of the eye, which for a camera high above a city holds only air, nor the near
    ground, which for a camera looking at a group of objects beyond its width left them in
    coarser cells (docs/decisions.md). Without focus points in the parent, the KD10 rule:
    PUSH of the width along the view."""
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
        if focus is not None and len(focus):
            box_lo, box_hi = parent.bounds()
            held = focus[np.all((focus >= box_lo) & (focus <= box_hi), axis=1)]
            if len(held):
                centre = np.median(held, axis=0)
        origin = centre - 0.5 * side
        # on its parent's cells, so each of those lies wholly inside it or outside (whole)
        origin = anchor + np.round((origin - anchor) / parent.cell_size) * parent.cell_size
        p_lo = parent.origin_array
        p_hi = p_lo + parent.cell_size * parent.resolution - side
        origin = np.clip(origin, p_lo, p_hi)  # parent bounds lie on this lattice: still snapped
        chain.append(Grid(tuple(float(v) for v in origin), float(cell), int(resolution)))
    return chain[::-1]


def assign(chain: list[Grid], positions: np.ndarray, margin_cells: float = 1.0) -> np.ndarray:
    """Index into ``chain`` of the finest cascade holding each point with a margin, (N,)."""
    if jit.enabled() and len(chain) > 1:
        return _compiled.assign(chain, positions, margin_cells)
    level = np.full(positions.shape[0], len(chain) - 1, np.int64)
    free = np.ones(positions.shape[0], bool)
    for i, g in enumerate(chain[:-1]):
        lo, hi = g.bounds()
        m = margin_cells * g.cell_size
        inside = np.all((positions >= lo + m) & (positions <= hi - m), axis=1) & free
        level[inside] = i
        free &= ~inside
    return level


def _restricted(finer: Grid, values: np.ndarray, coarser: Grid) -> tuple[tuple, np.ndarray]:
    """(index slices into ``coarser``, the light of ``values`` in those of its cells that lie
    wholly inside ``finer``). Intensity scales with a cell's cross-section, so a cell of twice
    the side holds its 8 children's sum / 2 (a uniform field reads the same in both)."""
    k = (finer.origin_array - coarser.origin_array) / coarser.cell_size
    first = np.maximum(np.ceil(k - 1e-6).astype(int), 0)
    end = np.minimum(np.floor(k + finer.resolution * finer.cell_size / coarser.cell_size
                              + 1e-6).astype(int), coarser.resolution)
    start = np.rint((first - k) * 2).astype(int)  # the first child, in finer cells
    n = np.maximum(end - first, 0)
    block = values[start[0]:start[0] + 2 * n[0], start[1]:start[1] + 2 * n[1],
                   start[2]:start[2] + 2 * n[2]]
    block = block.reshape(n[0], 2, n[1], 2, n[2], 2, -1)
    out = block[:, 0, :, 0, :, 0].copy()  # the 8 children summed one at a time (no temporaries)
    for child in range(1, 8):
        out += block[:, child >> 2, :, (child >> 1) & 1, :, child & 1]
    out *= 0.5
    return (tuple(slice(f, f + m) for f, m in zip(first, n)),
            out.reshape(*n, *values.shape[3:]))


def whole(chain: list[Grid], levels: list[np.ndarray]) -> list[np.ndarray]:
    """Each coarser cascade's grid with the light of every finer one added in its cells inside
    them (finest first; the finest is its own grid): what a receiver outside the finer
    cascades reads, whose lookup reaches into them. Those cells held only their own VPLs'
    light, the finer cascades' being held until it leaves them: a box face just outside the
    finest cascade read 0.55 of its light."""
    out = [levels[0]]
    for c in range(1, len(chain)):
        cells, light = _restricted(chain[c - 1], out[-1], chain[c])
        t = np.array(levels[c], np.float32)
        t[cells] += light
        out.append(t)
    return out


@dataclass(frozen=True)
class Read:
    """One lookup of a cascade's grid, by the receivers inside ``inside`` (None: all) and not
    inside ``outside`` (None: none)."""

    grid: Grid
    values: np.ndarray
    visibility: np.ndarray | None
    inside: Grid | None
    outside: Grid | None

    def takes(self, positions: np.ndarray) -> np.ndarray:
        """(N,) bool: the receivers at ``positions`` that make this read."""
        p = np.asarray(positions, np.float64)
        keep = np.ones(p.shape[0], bool)
        for box, want in ((self.inside, True), (self.outside, False)):
            if box is not None:
                lo, hi = box.bounds()
                keep &= np.all((p >= lo) & (p < hi), axis=1) == want
        return keep


def reads(result) -> list[Read]:
    """The lookups that give a receiver its light (finest first) from an LPV result (``grid``,
    ``values``, ``visibility``, ``fine``, ``whole``: engine.LPVResult or the viewport's copy):
    the finest cascade holding it made whole (``whole``), then every coarser one's own grid."""
    if result.grid is None or result.values is None:
        return []
    fine = list(result.fine or [])
    chain = [g for g, _, _ in fine] + [result.grid]
    levels = [v for _, v, _ in fine] + [result.values]
    wholes = levels[:1] + list(result.whole or [])
    if len(wholes) != len(chain):  # a result without them: each grid as it is
        wholes = levels
    return chain_reads(chain, levels, wholes, [v for _, _, v in fine] + [result.visibility])


def chain_reads(chain: list[Grid], levels: list, wholes: list, visibilities: list) -> list[Read]:
    """reads of a chain's grids (finest first), their ``whole`` versions and visibilities."""
    out = []
    for c, g in enumerate(chain):
        if c:  # receivers inside the finer cascade: this cascade's own light
            out.append(Read(g, levels[c], visibilities[c], chain[c - 1], None))
        out.append(Read(g, wholes[c], visibilities[c], g if c < len(chain) - 1 else None,
                        chain[c - 1] if c else None))
    return out


def hand_on(finer: Grid, outflow: np.ndarray, coarser: Grid, target: np.ndarray) -> None:
    """Add the light that left ``finer`` (shell of its padded (R+2)^3 ``outflow``) to the
    coarser cascade's injected grid ``target``, in the coarse cell holding each shell cell.
    Compiled (kernels.cascades) when ``jit.enabled()`` and the interior of ``outflow`` is
    empty, as the propagation leaves it (the twin visits the shell only)."""
    if (jit.enabled() and outflow.flags.c_contiguous and target.flags.c_contiguous
            and outflow.dtype == target.dtype and not outflow[1:-1, 1:-1, 1:-1].any()):
        return _compiled.hand_on(finer, outflow, coarser, target)
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


def shift(values: np.ndarray, cells) -> np.ndarray:
    """A cascade's grid (R, R, R, ...) re-expressed on the same cascade moved by ``cells``
    (3 ints, in its own cells): new[i] = old[i + cells], zero where the old one held nothing.
    The seed's (KD10's) reprojection of cascade content when the camera crosses cells."""
    out = np.zeros_like(values)
    src, dst = [], []
    for axis, k in enumerate(np.asarray(cells, int)):
        r = values.shape[axis]
        if abs(k) >= r:
            return out
        src.append(slice(max(k, 0), r + min(k, 0)))
        dst.append(slice(max(-k, 0), r + min(-k, 0)))
    out[tuple(dst)] = values[tuple(src)]
    return out
