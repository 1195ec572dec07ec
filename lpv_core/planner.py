"""Leave-out planner: which cascades, lights and geometry volumes a scene does not need.

Pure numpy (no bpy, no GL). Each function returns a Decision (keep or skip, and why) so the
engine can drop the work and list it in Stats.skip. Every test is conservative: a piece of work
is skipped only when it provably adds nothing (geometry tested exactly with triangles, never
with vertices alone; shadows are ignored, so a shadowed light is kept).

How far the work reaches, derived from the code that does it:
- injection (injection.inject) moves a VPL half a cell along its normal and splats it
  trilinearly onto the cell centres around it, so a VPL up to 1/2 + 1/2 = 1 cell outside a
  grid's box still lands in its boundary cells;
- the geometry volume (geometry_volume) puts each piece of an occluder on the face plane
  nearest it (half a cell) and spreads it over that plane by at most the piece's own length
  (bilinear splat of a surfel, or the projection of a sub-triangle SURFEL_SPACING long);
- a VPL lies on the pixel-centre ray of its RSM texel and carries the light's intensity along
  that ray (rsm.texel_flux), so it lies inside the spot cone / area hemisphere; a texel's
  diagonal of angle is added anyway against rounding in the render targets.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass

import numpy as np

from . import cascades as cascades_mod
from . import geometry_volume, injection
from .grid import Grid, fit_grid
from .kernels import planner as _compiled
from .runtime import jit
from .scene import lights as lights_mod
from .scene.model import Light, Scene, cross3

# Cells outside a grid's box from which a VPL still reaches its cells (see module docstring):
# the normal offset of injection.inject plus half a cell of trilinear splat to the cell centre.
_OFFSET_CELLS = inspect.signature(injection.inject).parameters["offset_cells"].default
INJECTION_REACH_CELLS = float(_OFFSET_CELLS) + 0.5
# An occluder's reach outside the box in the geometry volume: half a cell to the nearest face
# plane plus the length of the pieces it is cut into (at least half a cell of bilinear splat).
OCCLUDER_REACH_CELLS = 0.5 + max(float(getattr(geometry_volume, "SURFEL_SPACING", 0.5)), 0.5)
# Margin geometry needs inside a cascade for it to hold the whole scene: what fit_grid pads and
# what cascades.assign keeps free at the border (VPLs nearer the border go to the next cascade).
FIT_MARGIN_CELLS = float(max(
    inspect.signature(fit_grid).parameters["padding_cells"].default,
    inspect.signature(cascades_mod.assign).parameters["margin_cells"].default))
# RSM positions come back from float32 targets relative to the scene's centre: 24-bit
# mantissa, a few roundings. 2^-16 of the scene's extent (256 ulps) covers them with room.
POSITION_SLACK = 2.0 ** -16
_CHUNK = 1 << 15  # triangles per vectorised batch (bounds temporary memory to a few MB)


@dataclass
class Decision:
    """Keep or skip one piece of work: ``what`` names it, ``reason`` says why (for Stats)."""

    keep: bool
    reason: str
    what: str


def record(decisions, stats, stage: str) -> list[bool]:
    """Report every skip in ``decisions`` (a Decision or a list) as stats.skip(stage, what,
    reason); ``stats`` is anything with that method, or None. Returns the keep flags in order."""
    if isinstance(decisions, Decision):
        decisions = [decisions]
    for d in decisions:
        if not d.keep and stats is not None:
            stats.skip(stage, d.what, d.reason)
    return [d.keep for d in decisions]


def cascade_label(index: int, grid: Grid) -> str:
    """How a cascade is named in reasons: 'cascade 1 (cell 0.125 m)'."""
    return f"cascade {index} (cell {grid.cell_size:.4g} m)"


def _grid_label(grid: Grid) -> str:
    return f"the grid (cell {grid.cell_size:.4g} m)"


# ---------------------------------------------------------------------------------- cascades

# How many cascades a view needs (cascade_count). The finest cascade should resolve the nearest
# part of what the camera sees as finely, in angle, as the outer cascade resolves the scene
# from a distance of its own width: each cascade halves the cell, so n - 1 = log2(extent / d),
# d the distance to the nearest tenth of the visible surface (KD10 sec. 4.1: cell size grows
# with the distance to the camera, as with cascaded shadow maps).
NEAR_QUANTILE = 0.10
# A count is kept until log2(extent / d) is this far past the rounding boundary (0.5): a
# camera moving back and forth does not make the cascade count, and all propagation, flip.
COUNT_HYSTERESIS = 0.25
# An enclosed view (the camera inside the scene's box, sky in under this share of the view)
# keeps one cascade. Measured against Cycles (96 x 96, "dom"): a room lit by a point light
# 0.173 / 0.174 / 0.175 with 1 / 2 / 3 cascades, a sunlit room 0.531 / 0.503 / 0.503, a
# 16 m library 0.365 / 0.358 / 0.357, at 1.5-3x the time: the light stays inside the room,
# which one grid already resolves. Open views gain: sun yard 1.56 / 1.07 / 1.02, a 200 m
# city 1.09 / 0.94 / 0.83.
ENCLOSED_SKY_SHARE = 0.05


def cascade_count(max_count: int, lo, hi, eye, visible: np.ndarray, sky_share: float,
                  previous: int | None = None, space: float | None = None) -> tuple[int, str]:
    """(number of cascades, why) for a view: ``visible`` (N, 3) surface points the camera
    sees (a small G-buffer), ``sky_share`` the share of its pixels that see no geometry,
    ``previous`` the count of the last update (hysteresis), ``space`` the size of the space
    around the eye (cascades.Surroundings.size; None: not known). At most ``max_count``.

    A view is enclosed (one cascade) when the eye is inside the box [lo, hi], sees geometry in
    all but ENCLOSED_SKY_SHARE of its pixels, and the space around it is not much smaller than
    the box (at least cascades.ENCLOSURE_SCALE of it): a camera in a small room of a large
    LPV box needs finer cascades like any near view."""
    max_count = max(int(max_count), 1)
    if max_count == 1:
        return 1, "one cascade allowed"
    if eye is None:
        return 1, "no camera to centre finer cascades on"
    lo, hi, eye = (np.asarray(v, np.float64) for v in (lo, hi, eye))
    if visible is None or len(visible) == 0:
        return 1, "the camera sees no geometry"
    inside = bool(np.all(eye >= lo) and np.all(eye <= hi))
    roomy = space is None or space >= cascades_mod.ENCLOSURE_SCALE * float(np.max(hi - lo))
    if inside and sky_share < ENCLOSED_SKY_SHARE and roomy:
        return 1, (f"enclosed view: the camera is inside the scene and sees geometry in "
                   f"{100 * (1 - sky_share):.0f}% of its pixels (the light stays in a space "
                   "one grid resolves)")
    extent = float(np.max(hi - lo))
    near = float(np.quantile(np.linalg.norm(np.asarray(visible, np.float64) - eye, axis=1),
                             NEAR_QUANTILE))
    ratio = np.log2(extent / near) if near > 0 and extent > 0 else 0.0
    count = int(np.clip(1 + np.floor(ratio + 0.5), 1, max_count))
    if (previous is not None and 1 <= previous <= max_count and previous != count
            and abs(ratio - (previous - 1)) <= 0.5 + COUNT_HYSTERESIS):
        count = previous
    return count, (f"the nearest tenth of the view is {near:.3g} m away, the scene "
                   f"{extent:.3g} m wide (log2 ratio {ratio:.2f}): {count} of at most "
                   f"{max_count} cascades")


def cascade_plan(chain: list[Grid], scene: Scene) -> list[Decision]:
    """One Decision per cascade of ``chain`` (finest first, as cascades.place returns it).

    A finer cascade no caster or receiver triangle overlaps is skipped: no VPL is injected in
    it and no lookup reads it. When a finer cascade already holds all that geometry (with the
    border margin VPLs need), the coarser ones would only carry light past the geometry: at
    equal resolution every cascade costs the same, so the finest such one is kept alone. The
    outer cascade is kept otherwise, so geometry always has a cascade.
    """
    n = len(chain)
    labels = [cascade_label(i, g) for i, g in enumerate(chain)]
    if n == 0:
        return []
    if scene.triangle_count == 0:
        return [Decision(False, "the scene has no geometry", lab) for lab in labels]
    relevant = scene.flag("caster") | scene.flag("receiver")
    tris = scene.positions[relevant]
    if tris.shape[0] == 0:
        out = [Decision(False, "no caster or receiver geometry in the scene", lab)
               for lab in labels[:-1]]
        return out + [Decision(True, "outer cascade kept: the scene has geometry (none casts "
                               "or receives GI)", labels[-1])]
    slack = POSITION_SLACK * _extent(scene.bounds())
    counts = [int(_tri_box_overlap(tris, *_box(g, 0.0, slack)).sum()) for g in chain]
    glo = np.array([tris[:, :, c].min() for c in range(3)])
    ghi = np.array([tris[:, :, c].max() for c in range(3)])
    fits = []
    for g in chain:
        lo, hi = _box(g, -FIT_MARGIN_CELLS, slack)
        fits.append(bool(np.all(glo >= lo) and np.all(ghi <= hi)))
    top = next((i for i in range(n - 1) if fits[i]), n - 1)
    res = chain[0].resolution
    out = []
    for i, g in enumerate(chain):
        if i > top:
            out.append(Decision(False, (
                f"{labels[top]} already holds all caster and receiver geometry: coarser "
                f"cascades would only carry light past it, and at {res}^3 each costs as much "
                f"as {labels[top]} with coarser cells"), labels[i]))
        elif i == top:
            if top < n - 1:
                why = (f"holds all {tris.shape[0]} caster/receiver triangles with a "
                       f"{FIT_MARGIN_CELLS:g}-cell margin: kept instead of the {n - 1 - top} "
                       f"coarser cascades ({top + 1} {res}^3 grids instead of {n}, and finer "
                       "cells than the outer one)")
            elif counts[i]:
                why = f"outer cascade: {counts[i]} caster/receiver triangles inside"
            else:
                why = "outer cascade kept: the scene has geometry"
            out.append(Decision(True, why, labels[i]))
        elif counts[i] == 0:
            out.append(Decision(False, f"no caster or receiver geometry inside {labels[i]}",
                                labels[i]))
        else:
            out.append(Decision(True, f"{counts[i]} caster/receiver triangles inside",
                                labels[i]))
    return out


# ------------------------------------------------------------------------------------ lights

def light_reach(light: Light, grid: Grid, scene: Scene, label: str | None = None) -> Decision:
    """Whether ``light`` can put any light into ``grid``: some VPL of its RSM lands within
    injection reach of the grid's box. ``label`` names the grid in the reason."""
    return light_plan([light], grid, scene, label)[0]


def light_plan(lights: list[Light], grid: Grid, scene: Scene,
               label: str | None = None) -> list[Decision]:
    """light_reach for several lights on one grid (finds the grid's casters once)."""
    label = label or _grid_label(grid)
    bounds = scene.bounds()
    lo, hi = _box(grid, INJECTION_REACH_CELLS, POSITION_SLACK * _extent(bounds))
    if scene.triangle_count:
        refl = scene.reflectance_per_triangle()  # 0 for non-casters: they make no VPL
        bounce = (refl[:, 0] > 0) | (refl[:, 1] > 0) | (refl[:, 2] > 0)
        glossy = scene.specular_per_triangle()  # a glossy caster's mirror VPLs
        if glossy is not None:
            bounce |= glossy.max(axis=1) > 0
        tris = scene.positions[bounce]
        tris = tris[_tri_box_overlap(tris, lo, hi)]
    else:
        tris = np.zeros((0, 3, 3))
    casters = _Casters(tris, lo, hi)
    res = max(int(getattr(scene.settings, "rsm_resolution", 1) or 1), 1)
    return [_reach(light, casters, bounds, res, label) for light in lights]


class _Casters:
    """Caster triangles overlapping a box, with what every light's test reuses: whether each
    lies wholly inside the box, and a bounding sphere (centroid, radius) per triangle."""

    def __init__(self, tris: np.ndarray, lo, hi):
        self.tris, self.lo, self.hi = tris, lo, hi
        # (vertex, coordinate, T) contiguous rows: element-wise maths instead of short-axis
        # reductions, which numpy does slowly
        self.v = np.ascontiguousarray(np.transpose(tris, (1, 2, 0)))
        inside = np.ones(tris.shape[0], bool)
        for k in range(3):
            for c in range(3):
                inside &= (self.v[k, c] >= lo[c]) & (self.v[k, c] <= hi[c])
        self.inside = inside
        self.centre = (self.v[0] + self.v[1] + self.v[2]) / 3.0  # (3, T)
        r2 = np.zeros(tris.shape[0])
        for k in range(3):
            d = self.v[k] - self.centre
            r2 = np.maximum(r2, d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        self.radius = np.sqrt(r2)

    @property
    def count(self) -> int:
        return int(self.tris.shape[0])

    def lit(self, apex, axis, half: float) -> int:
        """How many of the triangles' parts inside the box meet the cone (apex, axis, half).

        Cheap tests first: a vertex in the cone of a triangle wholly inside the box is lit;
        a triangle whose bounding sphere misses the cone (half < 90 deg), or with no vertex
        in it (half >= 90 deg, see _cone_hits), is not; the rest are clipped and tested."""
        cos_h, sin_h = np.cos(half), np.sin(half)
        vert_lit = np.zeros(self.count, bool)
        for k in range(3):
            rx, ry, rz = (self.v[k, c] - apex[c] for c in range(3))
            dist = np.sqrt(rx * rx + ry * ry + rz * rz)
            vert_lit |= (rx * axis[0] + ry * axis[1] + rz * axis[2] > cos_h * dist) | (dist <= 0)
        sure = vert_lit & self.inside
        if half >= 0.5 * np.pi:
            out = ~vert_lit
        else:
            # the sphere (c, r) misses the cone when angle(c - apex, axis) > half + asin(r/|c-a|),
            # i.e. (c - a).axis < cos(half) sqrt(|c-a|^2 - r^2) - sin(half) r
            cx, cy, cz = (self.centre[c] - apex[c] for c in range(3))
            d2 = cx * cx + cy * cy + cz * cz
            r = self.radius
            room = d2 - r * r
            bound = cos_h * np.sqrt(np.maximum(room, 0.0)) - sin_h * r
            out = (room > 0) & (cx * axis[0] + cy * axis[1] + cz * axis[2] < bound)
        todo = np.nonzero(~sure & ~out)[0]
        hits = int(sure.sum())
        if todo.size:
            t = self.tris
            whole = todo[self.inside[todo]]
            hits += int(_cone_hits(t[whole], np.full(whole.size, 3), apex, axis, half).sum())
            cut = todo[~self.inside[todo]]
            poly, count = _clip_to_box(t[cut], self.lo, self.hi)
            hits += int(_cone_hits(poly, count, apex, axis, half).sum())
        return hits


def _reach(light: Light, casters: _Casters, bounds, rsm_resolution: int,
           label: str) -> Decision:
    what = f"light '{light.name}'"
    n = casters.count
    if light.type not in ("POINT", "SPOT", "SUN", "AREA"):
        return Decision(True, f"unknown light type {light.type!r}: kept", what)
    if n == 0:
        return Decision(False, f"no caster geometry inside {label}: nothing there to bounce "
                        "its light", what)
    half = _half_angle(light)
    if half is None:  # point, sun, or a cone covering every direction
        return Decision(True, f"{n} caster triangles inside {label}", what)
    apex, axis = light.position, light.direction
    half += _angle_slack(light, bounds, rsm_resolution)
    if light.type == "SPOT":
        shape = f"its {np.degrees(light.spot_size):.0f}\u00b0 spot cone"
    else:
        shape = "its -Z hemisphere (area lights emit only to their front)"
    if not _inside(apex, casters.lo, casters.hi):
        faces = _box_triangles(casters.lo, casters.hi)  # a cone meeting the box meets its surface
        if not _cone_hits(faces, np.full(12, 3), apex, axis, half).any():
            return Decision(False, f"{label} lies outside {shape}", what)
    lit = casters.lit(apex, axis, half)
    if lit == 0:
        return Decision(False, f"none of the {n} caster triangles inside {label} lies in "
                        f"{shape}", what)
    return Decision(True, f"{shape} reaches {lit} of {n} caster triangles inside {label}",
                    what)


def _half_angle(light: Light) -> float | None:
    """Half-angle (rad) of the cone of directions the light emits into; None: all of them."""
    if light.type == "SPOT":
        half = 0.5 * float(light.spot_size)
        return half if half < np.pi else None
    if light.type == "AREA":
        return 0.5 * np.pi
    return None


def _angle_slack(light: Light, bounds, res: int) -> float:
    """One texel diagonal of the light's RSM views at their centre (the widest texel)."""
    views = lights_mod.light_views(light, bounds)
    tan_half = max((v.tan_half for v in views if not v.ortho), default=1.0)
    return float(np.hypot(1.0, 1.0) * 2.0 * tan_half / res) + POSITION_SLACK


# ------------------------------------------------------------------------- small enclosures

# A closed space around a light narrower than this many cells of the cascade that carries it
# is not resolved: it holds no whole cell between walls snapped to cell faces, and most of its
# light leaks out. Measured (a crate on the floor of a 6 m room, light at its centre, 16^3;
# share of the free light's indirect light in the room): 1 cell 93 %, 1.5 cells 43 %, 2 cells
# 17 %; beyond, it depends on where the walls fall: on cell faces 4 cells 6 %, 6 cells 2.5 %,
# 8 cells 0.1 %; on cell centres 3 cells 34 %, 5 cells 19 %, 7 cells 10 %, 9 cells 6 %.
# (Measured before the lookup left out the corners behind the receiver's plane: the test's
# crate of 0.93 cells leaked 99.5 % then, 80 % since.)
SMALL_ENCLOSURE_CELLS = 2.0


def enclosure_reach(cell: float) -> float:
    """How far from a light the walls of an enclosure narrower than SMALL_ENCLOSURE_CELLS
    cells can be (the diagonal of its box): a light with no occluder that near is not in one."""
    return SMALL_ENCLOSURE_CELLS * cell * float(np.sqrt(3.0))


def occluders_around(scene: Scene, point, reach: float) -> bool:
    """Whether occluder triangles overlapping the cube of half-side ``reach`` around ``point``
    reach past it on both sides of every axis: what a closed space within ``reach`` needs (a
    lamp under a ceiling has occluders above it only)."""
    if not scene.triangle_count:
        return False
    p = np.asarray(point, np.float64)
    tris = scene.positions[scene.flag("occluder")]
    tris = tris[_tri_box_overlap(tris, p - reach, p + reach)]
    return bool(tris.size) and all(tris[:, :, a].max() > p[a] > tris[:, :, a].min()
                                   for a in range(3))


def enclosure_note(light: Light, around, grid: Grid, label: str, largest: int) -> dict | None:
    """A stats entry when ``light`` sits in a closed space (``around``:
    cascades.Surroundings of its position) narrower than SMALL_ENCLOSURE_CELLS cells of
    ``grid``, the cascade that carries it: its size, in cells, and the smallest grid
    resolution whose cells resolve it (cells scale as 1 / (R - 2), fit_grid's padding);
    ``largest`` the largest resolution allowed. None when resolved or open."""
    if around is None or not around.enclosed:
        return None
    size = float(np.max(around.points.max(axis=0) - around.points.min(axis=0)))
    cells = size / grid.cell_size
    if cells >= SMALL_ENCLOSURE_CELLS * (1.0 - 1e-6):  # float32 hits: a hair under is 2 cells
        return None
    needed = int(np.ceil(2 + SMALL_ENCLOSURE_CELLS * (grid.resolution - 2) / cells - 1e-6))
    fix = (f"grid_resolution {needed} gives it {SMALL_ENCLOSURE_CELLS:g} cells" if needed <= largest else
           f"it needs grid_resolution {needed}, above the largest allowed ({largest}): "
           "enlarge the enclosure or move the light out")
    reason = (f"inside a closed space {size:.3g} m across, {cells:.2f} cells of {label}: "
              f"narrower than {SMALL_ENCLOSURE_CELLS:g} cells, most of its indirect light "
              f"leaks through the walls; {fix}")
    return {"what": f"light '{light.name}'", "enclosure_m": size, "cells": cells,
            "cascade": label, "resolving_grid_resolution": needed, "reason": reason}


# --------------------------------------------------------------------------------- occlusion

def occlusion_needed(scene: Scene, grid: Grid, label: str | None = None) -> Decision:
    """Whether ``grid`` needs a geometry volume: some occluder triangle within its reach."""
    label = label or _grid_label(grid)
    what = f"geometry volume of {label}"
    if not getattr(scene.settings, "occlusion", True):
        return Decision(False, "occlusion is off in the GI settings", what)
    occ = scene.flag("occluder") if scene.triangle_count else np.zeros(0, bool)
    if not occ.any():
        return Decision(False, "no occluder in the scene", what)
    lo, hi = _box(grid, OCCLUDER_REACH_CELLS, POSITION_SLACK * _extent(scene.bounds()))
    inside = int(_tri_box_overlap(scene.positions[occ], lo, hi).sum())
    if inside == 0:
        return Decision(False, f"no occluder triangle inside {label}", what)
    return Decision(True, f"{inside} occluder triangles inside {label}", what)


# -------------------------------------------------------------------------------- geometry

def _extent(bounds) -> float:
    """Largest side of the scene's bounds (RSM positions are stored relative to its centre)."""
    lo, hi = bounds
    return max(float(np.max(hi - lo)), 1e-12)


def _box(grid: Grid, cells: float, slack: float) -> tuple[np.ndarray, np.ndarray]:
    """The grid's box grown by ``cells`` cells (shrunk when negative) and by ``slack``."""
    lo, hi = grid.bounds()
    pad = cells * grid.cell_size
    return lo - pad - slack, hi + pad + slack


def _inside(p, lo, hi) -> bool:
    return bool(np.all(p >= lo) and np.all(p <= hi))


def _box_triangles(lo, hi) -> np.ndarray:
    """The 12 triangles of the box's surface."""
    c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                  for z in (lo[2], hi[2])])
    quads = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    return np.array([c[[a, b, d]] for a, b, _, d in quads] + [c[[b, cc, d]]
                                                              for _, b, cc, d in quads])


def _tri_box_overlap(tris: np.ndarray, lo, hi) -> np.ndarray:
    """(T,) True where triangle (T, 3, 3) and the closed box [lo, hi] share a point.

    Separating axis test (Akenine-Moller 2001): box axes, the triangle's normal and the 9
    edge x box-axis crosses; touching counts as overlapping."""
    tris = np.asarray(tris, np.float64).reshape(-1, 3, 3)
    out = np.zeros(tris.shape[0], bool)
    centre = 0.5 * (np.asarray(lo, np.float64) + np.asarray(hi, np.float64))
    h = 0.5 * (np.asarray(hi, np.float64) - np.asarray(lo, np.float64))
    if np.any(h < 0):
        return out
    if jit.enabled():
        return _compiled._tri_box_overlap(tris, centre, h, out)
    for s in range(0, tris.shape[0], _CHUNK):
        v = tris[s:s + _CHUNK] - centre
        v0, v1, v2 = v[:, 0], v[:, 1], v[:, 2]  # column-wise: much faster than axis reductions
        low = np.minimum(np.minimum(v0, v1), v2) <= h
        high = np.maximum(np.maximum(v0, v1), v2) >= -h
        aabb = low[:, 0] & low[:, 1] & low[:, 2] & high[:, 0] & high[:, 1] & high[:, 2]
        vert_in = np.zeros(v.shape[0], bool)
        for vk in (v0, v1, v2):
            a = np.abs(vk) <= h
            vert_in |= a[:, 0] & a[:, 1] & a[:, 2]
        res = aabb & vert_in
        todo = np.nonzero(aabb & ~vert_in)[0]
        if todo.size:
            w = v[todo]
            e = np.stack([w[:, 1] - w[:, 0], w[:, 2] - w[:, 1], w[:, 0] - w[:, 2]], axis=1)
            axes = [np.cross(e[:, 0], e[:, 1])[:, None]]
            for k in range(3):
                unit = np.zeros(3)
                unit[k] = 1.0
                axes.append(np.cross(unit, e))  # (t, 3, 3): unit x each edge
            ax = np.concatenate(axes, axis=1)  # (t, 10, 3)
            p = np.einsum("tvc,tac->tav", w, ax)
            r = np.abs(ax) @ h
            sep = np.any((p.min(axis=2) > r) | (p.max(axis=2) < -r), axis=1)
            res[todo] = ~sep
        out[s:s + _CHUNK] = res
    return out


def _clip(poly: np.ndarray, count: np.ndarray, normal, offset: float):
    """Clip convex polygons (T, M, 3) with ``count`` vertices to the half-space
    normal . p <= offset (Sutherland-Hodgman, all polygons at once)."""
    t, m, _ = poly.shape
    if t == 0:
        return poly, count
    k = np.arange(m)
    valid = k[None, :] < count[:, None]
    nxt_idx = (k[None, :] + 1) % np.maximum(count, 1)[:, None]
    nxt = np.take_along_axis(poly, nxt_idx[..., None], axis=1)
    d = poly @ np.asarray(normal, np.float64) - offset
    dn = np.take_along_axis(d, nxt_idx, axis=1)
    cur_in = d <= 0
    emit_cur = valid & cur_in
    emit_x = valid & (cur_in != (dn <= 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(emit_x, d / (d - dn), 0.0)
    x = poly + f[..., None] * (nxt - poly)
    cand = np.stack([poly, x], axis=2).reshape(t, 2 * m, 3)
    mask = np.stack([emit_cur, emit_x], axis=2).reshape(t, 2 * m)
    order = np.argsort(~mask, axis=1, kind="stable")
    new_count = mask.sum(axis=1)
    width = max(int(new_count.max()), 1)
    return np.take_along_axis(cand, order[:, :width, None], axis=1), new_count


def _clip_to_box(tris: np.ndarray, lo, hi):
    """Triangles (T, 3, 3) clipped to the box: polygons (T, M, 3) and vertex counts (T,)."""
    poly = np.asarray(tris, np.float64).reshape(-1, 3, 3)
    if jit.enabled():
        return _compiled._clip_to_box(poly, lo, hi)
    count = np.full(poly.shape[0], 3, np.int64)
    for a in range(3):
        unit = np.zeros(3)
        unit[a] = 1.0
        poly, count = _clip(poly, count, unit, float(hi[a]))
        poly, count = _clip(poly, count, -unit, -float(lo[a]))
    return poly, count


def _cone_hits(poly: np.ndarray, count: np.ndarray, apex, axis, half: float) -> np.ndarray:
    """(T,) True where convex polygon (T, M, 3) meets the closed cone of half-angle ``half``
    around unit ``axis`` from ``apex``.

    half >= 90 deg: the unlit set is a convex cone around -axis, so a polygon is unlit only
    if all its vertices are. Below: the part in front of the apex, projected centrally onto
    the plane at distance 1, is a convex polygon; the cone is the disc of radius tan(half)."""
    apex = np.asarray(apex, np.float64)
    axis = np.asarray(axis, np.float64)
    if poly.shape[0] == 0:
        return np.zeros(0, bool)
    valid = np.arange(poly.shape[1])[None, :] < count[:, None]
    rel = poly - apex
    if half >= 0.5 * np.pi:
        dist = np.linalg.norm(rel, axis=2)
        lit = rel @ axis > np.cos(half) * dist  # strictly outside the unlit cone
        lit |= dist <= 0  # the apex itself: kept (conservative)
        return np.any(valid & lit, axis=1)
    # keep the part in front of the apex; closer than 2^-40 of the scene never rasterises
    scale = max(float(np.max(np.abs(rel[valid]))) if valid.any() else 1.0, 1e-30)
    offset = -float(axis @ apex) - scale * 2.0 ** -40
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = cross3(axis, helper)
    u /= np.linalg.norm(u)
    w = cross3(axis, u)
    if jit.enabled():
        return _compiled._cone_hits(poly, count, apex, axis, half, offset, u, w)
    poly, count = _clip(poly, count, -axis, offset)
    if poly.shape[0] == 0 or count.max() == 0:
        return np.zeros(poly.shape[0], bool)
    valid = np.arange(poly.shape[1])[None, :] < count[:, None]
    rel = poly - apex
    z = np.where(valid, rel @ axis, 1.0)
    q = np.stack([rel @ u, rel @ w], axis=2) / z[..., None]  # (T, M, 2)
    r2 = np.tan(half) ** 2
    nxt_idx = (np.arange(q.shape[1])[None, :] + 1) % np.maximum(count, 1)[:, None]
    b = np.take_along_axis(q, nxt_idx[..., None], axis=1)
    ab = b - q
    len2 = np.einsum("tmc,tmc->tm", ab, ab)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.clip(np.where(len2 > 0, -np.einsum("tmc,tmc->tm", q, ab) / len2, 0.0), 0.0, 1.0)
    closest = q + s[..., None] * ab
    near = np.einsum("tmc,tmc->tm", closest, closest) <= r2
    cross = ab[..., 0] * (-q[..., 1]) - ab[..., 1] * (-q[..., 0])  # origin left of edge > 0
    pos = np.any(valid & (cross > 0), axis=1)
    neg = np.any(valid & (cross < 0), axis=1)
    centre_in = (count >= 3) & ~(pos & neg)
    return (count > 0) & (np.any(valid & near, axis=1) | centre_in)
