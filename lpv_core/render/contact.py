"""Contact light: the first bounce a receiver gets from surfaces nearer than one cell, which
the grid cannot resolve, gathered from the camera's G-buffer (screen space).

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
Only what the camera sees emits (a hidden face's contact light is missing) and nothing
between i and j shadows (within a cell the cosines cut what is behind either surface). A
window of up to (2 TAP_RADIUS + 1)^2 taps on a circle, the stride growing with rho in pixels,
bounds the cost; a tap stands for stride^2 pixels, its patch stride times the pixel's.
"""

from __future__ import annotations

import numpy as np

from ..kernels import contact as _compiled
from ..runtime import jit
from ..scene.lights import polygon_irradiance
from .raster import to_eye

REACH_CELLS = 1.0  # the grid resolves light from about one cell out (docs/algorithm.md)
TAP_RADIUS = 5  # taps per side: a disk of 2 T + 1 taps across, 80 taps with the centre out
FACE_TOLERANCE = 1e-4  # cells: a receiver this near a cascade's face counts as inside it
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
    if not covered.any():
        return out
    if jit.enabled():
        return _compiled.gather(positions, normals, covered, radiosity, area, size, reach,
                                region, edges, TAP_RADIUS)
    pos = np.asarray(positions, np.float64)
    nrm = np.asarray(normals, np.float64)
    edges = np.asarray(edges, np.float64)
    radiosity = np.asarray(radiosity, np.float64)
    rho = np.where(covered, np.asarray(reach, np.float64), 0.0)
    px = np.divide(rho, size, out=np.zeros((h, w)), where=size > 0)
    stride = np.maximum(1, np.ceil(px / TAP_RADIUS)).astype(np.int64)
    live = covered & (px >= 1.0)  # nearer neighbours than a pixel: none within reach
    ys, xs = np.mgrid[0:h, 0:w]
    inv_far = np.divide(1.0, np.pi * rho * rho, out=np.zeros((h, w)), where=rho > 0)
    t = TAP_RADIUS
    for dy in range(-t, t + 1):
        for dx in range(-t, t + 1):
            if (dx == 0 and dy == 0) or dx * dx + dy * dy > t * t:
                continue
            y, x = ys + dy * stride, xs + dx * stride
            ok = live & (y >= 0) & (y < h) & (x >= 0) & (x < w)
            y, x = np.where(ok, y, 0), np.where(ok, x, 0)
            ok &= covered[y, x] & (region[y, x] == region)
            v = pos[y, x] - pos
            r2 = (v * v).sum(-1)
            ok &= (r2 < rho * rho) & (r2 > 0)
            r2 = np.where(ok, r2, 1.0)
            ci = (nrm * v).sum(-1)
            cj = -(nrm[y, x] * v).sum(-1)
            ok &= cj > 0  # i in front of the patch
            a = (stride * stride) * area[y, x]
            cc = np.maximum(ci, 0.0) * cj / r2
            f = cc * a / (np.pi * r2 + a)  # the disk form factor
            exact = ok & (np.abs(edges[y, x]).sum((-2, -1)) > 0)  # a footprint (patch_edges)
            ok &= exact | (ci > 0)  # the disk's centre above i's plane
            if exact.any():  # the footprint's exact form factor, clipped to i's hemisphere
                c = pos[y, x][exact]
                s = stride[exact][:, None]
                du, dv = s * edges[y, x, 0][exact], s * edges[y, x, 1][exact]
                poly = np.stack([c - du - dv, c + du - dv, c + du + dv, c - du + dv], axis=1)
                f[exact] = polygon_irradiance(poly, pos[exact], nrm[exact]) / np.pi
            k = np.where(ok, np.maximum(0.0, f - cc * a * inv_far), 0.0)
            out += radiosity[y, x] * k[..., None]
    return out
