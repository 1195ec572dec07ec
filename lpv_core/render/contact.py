"""Contact light: the first bounce a receiver gets from surfaces nearer than one cell, which
the grid cannot resolve, gathered from the camera's G-buffer (screen space), and a sun's from
the sun's own view, which sees every surface it lights.

The grid holds light per cell, so an emitting surface closer to a receiver than about a cell
reads as if it stood a cell away: within half a cell of a sunlit box's face the grid reads
0.63-1.03 of the exact bounce (by where the face falls in its cell), and close to it from
about a cell out (docs/algorithm.md, "Contact light"). The gather adds what that leaves out.
Over pixels j within the reach rho (REACH_CELLS cells of the receiver's finest cascade) of
receiver i, each a patch of area A_j and GI radiosity B_j
(direct irradiance weighted as the grids are x GI reflectance):

    E_i += sum_j B_j max(0, F_ij - cos_i cos_j A_j / (pi rho^2))

F_ij the patch's exact form factor: the pixel's footprint on its surface's plane (a
parallelogram, patch_edges) by Lambert's contour integral clipped to the receiver's
hemisphere (scene.lights.polygon_irradiance / pi), so that the steep near field at a face's
foot, where the receiver lies almost in the emitter's plane, is integrated over the patch
instead of sampled at its centre. A pixel seen edge-on has no footprint and takes the disk
form factor cos_i cos_j A / (pi r^2 + A) (Bunnell, GPU Gems 2 ch. 14), finite where two
surfaces meet. The subtracted term is the share the grid resolves, the patch as if
at rho: the sum is 0 from rho out, so light the grid carries is not counted twice there.
In the camera's view only what the camera sees emits (a hidden face's contact light is
missing); a sun's patches are the texels of its view fitted to the receiver's cascade
(sun_source), its taps around the texel the receiver projects into (gather_at). Nothing
between i and j shadows (within a cell the cosines cut what is behind either surface). A
window of up to (2 TAP_RADIUS + 1)^2 taps on a circle, the stride growing with rho in pixels,
bounds the cost; a tap stands for stride^2 pixels, its patch stride times the pixel's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..kernels import contact as _compiled
from ..runtime import jit
from ..scene.lights import LightView, polygon_irradiance
from ..scene.model import Light
from .raster import Rasterizer, to_eye

REACH_CELLS = 1.0  # the grid resolves light from about one cell out (docs/algorithm.md)
TAP_RADIUS = 5  # taps per side: a disk of 2 T + 1 taps across, 80 taps with the centre out
FACE_TOLERANCE = 1e-4  # cells: a receiver this near a cascade's face counts as inside it
# The sun's view sees both sides of a single-face surface, a float32 rounding apart (a
# roof's sunlit top and the ceiling under it): a tap and its receiver must each be this share
# of the reach in front of the other's plane.
FRONT_TOLERANCE = 1e-3
# A sun view's texels per cell of its cascade: the reach is 8 texels, the taps 2 apart (the
# TAP_RADIUS window spans 10), a tap's patch a quarter cell across. Measured 5 / 8 / 10 / 16
# a cell: sky_yard 0.454 / 0.431 / 0.438 / 0.430, the city 0.490 / 0.460 / 0.472 / 0.472
# (docs/decisions.md, "The sun's first bounce gathered in the sun's view").
SUN_TEXELS_PER_CELL = 8
MAX_SUN_VIEW = 1024  # texels a side of a sun view at most
GRAZING = 1e-3  # |cos| of the view ray to a surface under which a pixel's area is floored
# (the disk form factor caps it) and it has no footprint (patch_edges)


def footprints(view: np.ndarray, projection: np.ndarray, width: int, height: int,
               positions: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(area (M,) m^2 of the surface each pixel sees, size (M,) m of a pixel across the view
    ray at its depth) for points ``positions`` seen through the camera: the pixel's
    cross-section at its view depth (orthographic: at any depth) x cos of the ray to the view
    axis, over |cos| of the ray to the surface."""
    view = np.asarray(view, np.float64)
    proj = np.asarray(projection, np.float64)
    p = np.asarray(positions, np.float64)
    sx, sy = 2.0 / (width * abs(proj[0, 0])), 2.0 / (height * abs(proj[1, 1]))
    if abs(float(proj[3, 3])) > 0.5:  # orthographic
        cross = np.full(p.shape[0], sx * sy)
    else:
        depth = -(p @ view[2, :3] + view[2, 3])
        cross = sx * sy * depth * depth
    eye = to_eye(view, proj, p)
    axis = np.linalg.inv(view)[:3, 2]  # the camera's +Z, back along its view
    cos_axis = np.abs(eye @ axis)
    cos_surface = np.maximum(np.abs((eye * np.asarray(normals, np.float64)).sum(-1)), GRAZING)
    return cross * cos_axis / cos_surface, np.sqrt(cross * cos_axis)


def patch_edges(view: np.ndarray, projection: np.ndarray, width: int, height: int,
                positions: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(M, 2, 3) half-edges of each pixel's footprint on its surface's plane: half a pixel
    across the view ray at the point's depth, along the camera's x and y, slid along the ray
    onto the plane through ``positions`` with ``normals`` (the derivative of the ray-plane
    intersection); 0 where the ray runs within GRAZING of the plane (the gather then takes the
    disk form factor)."""
    view = np.asarray(view, np.float64)
    proj = np.asarray(projection, np.float64)
    p = np.asarray(positions, np.float64)
    n = np.asarray(normals, np.float64)
    half = (1.0 / (width * proj[0, 0]), 1.0 / (height * proj[1, 1]))  # NDC 1 / pixels
    if abs(float(proj[3, 3])) > 0.5:  # orthographic: parallel rays, a fixed footprint
        ray = np.broadcast_to(-view[2, :3], p.shape)
        depth = np.ones(len(p))
    else:
        ray = p - np.linalg.inv(view)[:3, 3]
        depth = -(p @ view[2, :3] + view[2, 3])
    along = (n * ray).sum(-1)
    ok = np.abs(along) > GRAZING * np.linalg.norm(ray, axis=-1)
    along = np.where(ok, along, 1.0)
    out = np.zeros((len(p), 2, 3))
    for k in range(2):
        e = (depth * half[k])[:, None] * view[k, :3]
        out[:, k] = e - ((n * e).sum(-1) / along)[:, None] * ray
    out[~ok] = 0.0
    return out


def gather(positions: np.ndarray, normals: np.ndarray, covered: np.ndarray,
           radiosity: np.ndarray, area: np.ndarray, size: np.ndarray, reach: np.ndarray,
           region: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Contact irradiance (H, W, 3) W/m^2 at every covered pixel from the covered pixels within
    its ``reach`` (module docstring). Images (H, W, ...): world positions and normals (3),
    ``covered`` bool, ``radiosity`` B (3) W/m^2, pixel ``area`` m^2 and ``size`` m
    (footprints), ``reach`` rho m (0: none), ``region`` int (pixels in different ones, on
    different sides of a clip area, do not light each other), ``edges`` (2, 3) the footprint's
    half-edges (patch_edges; 0: the disk form factor)."""
    h, w = covered.shape
    out = np.zeros((h, w, 3), np.float64)
    ys, xs = np.nonzero(covered)
    if ys.size:
        source = Source(positions, normals, covered, radiosity, area, region, edges)
        out[ys, xs] = gather_at(positions[ys, xs], normals[ys, xs], reach[ys, xs],
                                size[ys, xs], region[ys, xs], np.c_[ys, xs], source, True)
    return out


@dataclass
class Source:
    """An image of emitting patches (H, W, ...): world positions and unit normals (3),
    ``covered`` bool, radiosity B (3) W/m^2, patch area m^2, clip region int and the
    footprint's half-edges (2, 3) (patch_edges; 0: the disk form factor)."""

    position: np.ndarray
    normal: np.ndarray
    covered: np.ndarray
    radiosity: np.ndarray
    area: np.ndarray
    region: np.ndarray
    edges: np.ndarray


def gather_at(positions: np.ndarray, normals: np.ndarray, reach: np.ndarray, size: np.ndarray,
              region: np.ndarray, centre: np.ndarray, source: Source,
              own_view: bool) -> np.ndarray:
    """Contact irradiance (M, 3) W/m^2 at M receivers (positions, normals, reach rho m, the
    size m of a source pixel at the receiver, clip region) from the ``source`` patches
    within reach, on the module docstring's window of taps around ``centre`` (M, 2) (row,
    column) in the source image. ``own_view``: the source is the view the receivers were seen
    in (the camera's): the receiver's own pixel is no tap, and a patch whose centre is
    behind the receiver's plane sends its part above it (a floor's patch at a face's foot).
    Otherwise (the sun's view, which also sees the far sides of a single-face wall) a tap's
    centre and the receiver must each lie FRONT_TOLERANCE of the reach in front of the
    other's plane."""
    m = len(positions)
    out = np.zeros((m, 3), np.float64)
    if not m:
        return out
    if jit.enabled():
        return _compiled.gather_at(positions, normals, reach, size, region, centre, source,
                                   own_view, TAP_RADIUS, FRONT_TOLERANCE)
    spos = np.asarray(source.position, np.float64)
    snrm = np.asarray(source.normal, np.float64)
    edges = np.asarray(source.edges, np.float64)
    radiosity = np.asarray(source.radiosity, np.float64)
    h, w = source.covered.shape
    pos = np.asarray(positions, np.float64)
    nrm = np.asarray(normals, np.float64)
    rho = np.asarray(reach, np.float64)
    size = np.asarray(size, np.float64)
    px = np.divide(rho, size, out=np.zeros(m), where=size > 0)
    stride = np.maximum(1, np.ceil(px / TAP_RADIUS)).astype(np.int64)
    live = px >= 1.0  # nearer neighbours than a pixel: none within reach
    cy, cx = np.asarray(centre, np.int64).T
    inv_far = np.divide(1.0, np.pi * rho * rho, out=np.zeros(m), where=rho > 0)
    front = 0.0 if own_view else FRONT_TOLERANCE
    t = TAP_RADIUS
    for dy in range(-t, t + 1):
        for dx in range(-t, t + 1):
            if (own_view and dx == 0 and dy == 0) or dx * dx + dy * dy > t * t:
                continue
            y, x = cy + dy * stride, cx + dx * stride
            ok = live & (y >= 0) & (y < h) & (x >= 0) & (x < w)
            y, x = np.where(ok, y, 0), np.where(ok, x, 0)
            ok &= source.covered[y, x] & (source.region[y, x] == region)
            v = spos[y, x] - pos
            r2 = (v * v).sum(-1)
            ok &= (r2 < rho * rho) & (r2 > 0)
            r2 = np.where(ok, r2, 1.0)
            ci = (nrm * v).sum(-1)
            cj = -(snrm[y, x] * v).sum(-1)
            ok &= cj > front * rho  # i in front of the patch
            if not own_view:
                ok &= ci > front * rho  # the patch's centre in front of i
            a = (stride * stride) * source.area[y, x]
            cc = np.maximum(ci, 0.0) * cj / r2
            f = cc * a / (np.pi * r2 + a)  # the disk form factor
            exact = ok & (np.abs(edges[y, x]).sum((-2, -1)) > 0)  # a footprint (patch_edges)
            ok &= exact | (ci > 0)  # the disk's centre above i's plane
            if exact.any():  # the footprint's exact form factor, clipped to i's hemisphere
                c = spos[y, x][exact]
                s = stride[exact][:, None]
                du, dv = s * edges[y, x, 0][exact], s * edges[y, x, 1][exact]
                poly = np.stack([c - du - dv, c + du - dv, c + du + dv, c - du + dv], axis=1)
                f[exact] = polygon_irradiance(poly, pos[exact], nrm[exact]) / np.pi
            k = np.where(ok, np.maximum(0.0, f - cc * a * inv_far), 0.0)
            out += radiosity[y, x] * k[..., None]
    return out


def sun_view_size(view: LightView, cell: float) -> int:
    """Texels a side of a sun ``view`` whose receivers' cells are ``cell`` m: SUN_TEXELS_PER_CELL
    a cell, 16 to MAX_SUN_VIEW."""
    return int(np.clip(np.ceil(2.0 * view.half_extent * SUN_TEXELS_PER_CELL / cell), 16,
                       MAX_SUN_VIEW))


def sun_source(raster: Rasterizer, light: Light, view: LightView, size: int,
               weight: np.ndarray) -> Source:
    """The patches a sun lights, as its RSM sees them in ``view`` (``size`` texels a side,
    rows top-first): each texel's footprint on its surface and its GI radiosity
    B = reflectance x E x ``weight`` (3,), E = power x colour x cos to the sun x the shading
    normal's gain (rsm.view_vpls' flux over the texel's area); region 0. Texels that send
    nothing (unlit, or a surface that casts no GI) are left out."""
    p4, n4, table = raster.rsm_texels(view.view, view.projection, size, view.ortho)
    covered = p4[..., 3] > 0.5
    nrm = n4[covered][:, :3].astype(np.float64)
    refl = np.asarray(table, np.float64)[Rasterizer.triangles(p4[covered], n4[covered])][:, :3]
    gain = np.linalg.norm(nrm, axis=1)
    nrm /= np.where(gain > 0, gain, 1.0)[:, None]
    cos = np.maximum(nrm @ -np.asarray(light.direction, np.float64), 0.0)
    exitance = refl * (light.power * gain * cos)[:, None] * (
        np.asarray(light.color, np.float64) * np.asarray(weight, np.float64))
    lit = exitance.max(axis=1) > 0  # a texel that sends nothing is no tap
    covered[covered] = lit
    nrm, exitance = nrm[lit], exitance[lit]
    pos = p4[covered][:, :3].astype(np.float64) + raster.origin
    edges = patch_edges(view.view, view.projection, size, size, pos, nrm)
    area = 4.0 * np.linalg.norm(np.cross(edges[:, 0], edges[:, 1]), axis=-1)

    def image(values, shape=()):
        out = np.zeros((size, size) + shape, np.float64)
        out[covered] = values
        return out

    return Source(image(pos, (3,)), image(nrm, (3,)), covered, image(exitance, (3,)),
                  image(area), np.zeros((size, size), np.int64), image(edges, (2, 3)))


def view_texels(view: LightView, size: int, positions: np.ndarray) -> np.ndarray:
    """(row, column) (M, 2) int64 of the texel of a ``size`` squared ``view`` (rows top-first)
    that ``positions`` (M, 3) fall in."""
    q = np.c_[np.asarray(positions, np.float64), np.ones(len(positions))] @ (
        np.asarray(view.projection, np.float64) @ np.asarray(view.view, np.float64)).T
    ndc = q[:, :2] / q[:, 3:]
    col = np.floor((ndc[:, 0] + 1.0) * 0.5 * size)
    row = np.floor((1.0 - ndc[:, 1]) * 0.5 * size)
    return np.c_[row, col].astype(np.int64)
