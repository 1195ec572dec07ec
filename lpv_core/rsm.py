"""Reflective shadow maps [KD10 sec. 3, after Dachsbacher & Stamminger 2005].

Each texel of a light's view becomes a virtual point light (VPL): world position, normal and the
flux it reflects. Perspective texels carry I(w) x (texel solid angle); sun texels carry
E x (texel footprint area): the texel area term most public code leaves out. The reflected
flux uses the material's GI reflectance (bleed colour x intensity where the artist set one).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .render.raster import TRIANGLE_SPLIT, Rasterizer
from .runtime import jit, pool
from .scene import lights as lights_mod
from .scene.model import Light


@dataclass
class RSM:
    """VPLs of one light: (N, 3) positions, normals and reflected flux (W), (N,) surfel area."""

    light: Light
    position: np.ndarray
    normal: np.ndarray
    flux: np.ndarray
    area: np.ndarray
    texels: int  # texels rendered (for stats)

    @property
    def count(self) -> int:
        return int(self.position.shape[0])

    def total_flux(self) -> np.ndarray:
        return self.flux.sum(axis=0) if self.count else np.zeros(3)


def texel_flux(light: Light, view: lights_mod.LightView, rows: np.ndarray, cols: np.ndarray,
               size: int, position: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, ...]:
    """Incident flux per unit colour (N,) and surfel area (N,) of texels (rows top-first,
    columns) of a ``size`` squared view, whose surfaces are at ``position`` (N, 3) with unit
    ``normal`` (N, 3)."""
    if view.ortho:
        texel_area = (2.0 * view.half_extent / size) ** 2
        incident = np.full(rows.shape, light.power * texel_area)
        cos_s = np.abs(normal @ np.asarray(light.direction, np.float64))
        return incident, texel_area / np.maximum(cos_s, 0.05)
    dirs, solid = lights_mod.texel_rays(view, rows, cols, size, size)
    incident = lights_mod.intensity(light, dirs) * solid
    to_surf = position - light.position
    dist2 = np.einsum("nc,nc->n", to_surf, to_surf)
    cos_s = np.abs(np.einsum("nc,nc->n", normal, dirs))
    return incident, solid * dist2 / np.maximum(cos_s, 0.05)


def render_rsm(raster: Rasterizer, light: Light, bounds, resolution: int, fit=None) -> RSM:
    """The RSM of ``light``: VPLs for every covered texel that reflects any flux.
    ``fit`` (sun only): the box the view's window is fitted to (lights.light_views).
    Each view is one two-target pass (Rasterizer.read_rsm: position, normal and the triangle,
    whose reflectance the uploaded table gives), and only the covered, reflecting texels are
    converted and lit (the rest of the map costs nothing more); with jit.enabled() in one
    compiled pass over the texels (``_vpl_kernel``)."""
    parts = []
    texels = 0
    color = np.asarray(light.color, np.float64)
    for view in lights_mod.light_views(light, bounds, fit):
        p4, n4 = raster.read_rsm(view.view, view.projection, resolution, view.ortho)
        texels += resolution * resolution
        if jit.enabled():
            parts.append(_vpls(light, view, p4, n4, raster.reflectance, raster.origin))
            continue
        rows, cols = np.nonzero(p4[..., 3] > 0.5)
        refl = raster.reflectance[raster.triangles(p4[rows, cols], n4[rows, cols])]
        lit = refl.max(axis=-1) > 0
        rows, cols, refl = rows[lit], cols[lit], refl[lit]
        position = p4[rows, cols, :3].astype(np.float64) + raster.origin
        normal = n4[rows, cols, :3].astype(np.float64)
        incident, surf_area = texel_flux(light, view, rows, cols, resolution, position, normal)
        phi = incident[:, None] * refl * color
        keep = (phi.max(axis=-1) > 0) & np.isfinite(phi).all(axis=-1)
        parts.append((position[keep], normal[keep], phi[keep], surf_area[keep]))
    if not parts:
        empty = np.zeros((0, 3))
        return RSM(light, empty, empty, empty, np.zeros(0), texels)
    if len(parts) == 1:
        return RSM(light, *parts[0], texels)
    return RSM(light, *(np.concatenate(f) for f in zip(*parts)), texels)


_KINDS = {"POINT": 0, "SPOT": 1, "AREA": 2, "SUN": 3}
SPLIT_MIN = 64  # rows: smaller maps are converted on one thread


def _vpls(light: Light, view: lights_mod.LightView, p4, n4, reflectance, origin) -> tuple:
    """(position, normal, flux, area) of the VPLs of one view's read-back targets: the
    compiled twin of render_rsm's numpy pass (texel_flux, lights.intensity).
    The rows are cut in two parts of equal covered texels, converted on two threads (the
    kernel releases the GIL); the second part's VPLs then move down behind the first's."""
    if light.type not in _KINDS:
        lights_mod.intensity(light, np.zeros((1, 3)))  # raises the named error
    size = p4.shape[0]
    inv = np.linalg.inv(np.asarray(view.view, np.float64))
    cos_half = float(np.cos(0.5 * light.spot_size)) if light.type == "SPOT" else 0.0
    args = (p4, n4, np.ascontiguousarray(reflectance, np.float32),
            np.asarray(origin, np.float64), bool(view.ortho),
            float(view.tan_half), float(view.half_extent),
            np.ascontiguousarray(inv[:3, 0]), np.ascontiguousarray(inv[:3, 1]),
            np.ascontiguousarray(-inv[:3, 2]), np.asarray(light.position, np.float64),
            np.asarray(light.direction, np.float64), _KINDS[light.type], float(light.power),
            cos_half,
            (1.0 - cos_half) * float(light.spot_blend) if light.type == "SPOT" else 0.0,
            np.asarray(light.color, np.float64), size)
    out = (np.empty((size * size, 3)), np.empty((size * size, 3)), np.empty((size * size, 3)),
           np.empty(size * size))
    if size < SPLIT_MIN:
        n = _vpl_kernel(*args, 0, size, *out)
        return tuple(a[:n] for a in out)
    half = _half_row(p4)
    n0, n1 = pool.executor().map(lambda rows: _vpl_kernel(*args, *rows, *out),
                                   ((0, half), (half, size)))
    if n0 < half * size and n1:
        _move_rows(*out, half * size, n0, n1)
    return tuple(a[:n0 + n1] for a in out)


@jit.kernel
def _half_row(p4):
    """The row (1 .. rows - 1) before which about half of ``p4``'s covered texels lie
    (every 4th column counted: enough to balance two threads, at a quarter of the reads)."""
    rows, cols = p4.shape[0], p4.shape[1]
    covered = np.zeros(rows, np.int64)
    for row in range(rows):
        for col in range(0, cols, 4):
            covered[row] += p4[row, col, 3] > 0.5
    total = covered.sum()
    below = 0
    for row in range(rows):
        below += covered[row]
        if 2 * below >= total:
            return min(max(row, 1), rows - 1)
    return rows - 1


@jit.kernel
def _move_rows(pos, nrm, flux, area, src, dst, count):
    """Rows src..src+count-1 of the four VPL arrays moved down to dst (dst < src)."""
    for k in range(count):
        for c in range(3):
            pos[dst + k, c] = pos[src + k, c]
            nrm[dst + k, c] = nrm[src + k, c]
            flux[dst + k, c] = flux[src + k, c]
        area[dst + k] = area[src + k]


@jit.kernel
def _vpl_kernel(p4, n4, reflectance, origin, ortho, tan_half, half_extent, right, up, fwd, eye,
                axis, kind, power, cos_half, smooth, color, size, row0, row1, pos, nrm, flux,
                area):
    """One pass over rows row0..row1-1 of a view's texels (rows top-first, as ``p4`` is given):
    the VPL of every covered texel that reflects a finite, non-zero flux, with the formulas of
    texel_rays, texel_flux and lights.intensity (point, spot cone smoothstep, area cosine; sun:
    irradiance ``power`` times the texel area), written in texel order into pos, nrm, flux,
    area from row row0 * size on; returns how many. The texel's reflectance is its triangle's
    (Rasterizer.triangles). Per-row and per-column terms are hoisted and divisions turned into
    products where that moves the result by a few ulps."""
    texel_area = (2.0 * half_extent / size) * (2.0 * half_extent / size)
    texel_solid = (2.0 * tan_half / size) * (2.0 * tan_half / size)
    point = power / (4.0 * np.pi)
    lambert = power / np.pi
    inv_smooth = 1.0 / smooth if smooth > 0 else 0.0
    ax, ay, az = axis[0], axis[1], axis[2]
    us = np.empty(size)  # plane coordinate u per column
    for col in range(size):
        us[col] = ((col + 0.5) / size * 2.0 - 1.0) * tan_half
    n = row0 * size
    for row in range(row0, row1):
        v = (1.0 - (row + 0.5) / size * 2.0) * tan_half
        vv = 1.0 + v * v
        bx = v * up[0] + fwd[0]
        by = v * up[1] + fwd[1]
        bz = v * up[2] + fwd[2]
        for col in range(size):
            if not p4[row, col, 3] > 0.5:
                continue
            tri = (np.int64(p4[row, col, 3]) - 1) * TRIANGLE_SPLIT + np.int64(n4[row, col, 3])
            r0 = np.float64(reflectance[tri, 0])
            r1 = np.float64(reflectance[tri, 1])
            r2 = np.float64(reflectance[tri, 2])
            if not max(r0, max(r1, r2)) > 0:
                continue
            px = np.float64(p4[row, col, 0]) + origin[0]
            py = np.float64(p4[row, col, 1]) + origin[1]
            pz = np.float64(p4[row, col, 2]) + origin[2]
            nx = np.float64(n4[row, col, 0])
            ny = np.float64(n4[row, col, 1])
            nz = np.float64(n4[row, col, 2])
            if ortho:
                incident = power * texel_area
                a = texel_area / max(abs(nx * ax + ny * ay + nz * az), 0.05)
            else:
                u = us[col]
                inv_root = 1.0 / np.sqrt(u * u + vv)
                dx = (u * right[0] + bx) * inv_root
                dy = (u * right[1] + by) * inv_root
                dz = (u * right[2] + bz) * inv_root
                solid = texel_solid * (inv_root * inv_root * inv_root)
                if kind == 0:
                    strength = point
                else:
                    cos_a = dx * ax + dy * ay + dz * az
                    if kind == 1:
                        if smooth > 0:
                            x = min(max((cos_a - cos_half) * inv_smooth, 0.0), 1.0)
                            strength = point * (x * x * (3.0 - 2.0 * x))
                        else:
                            strength = point if cos_a > cos_half else 0.0
                    else:
                        strength = lambert * max(cos_a, 0.0)
                incident = strength * solid
                tx, ty, tz = px - eye[0], py - eye[1], pz - eye[2]
                a = (solid * (tx * tx + ty * ty + tz * tz)
                     / max(abs(nx * dx + ny * dy + nz * dz), 0.05))
            f0 = incident * r0 * color[0]
            f1 = incident * r1 * color[1]
            f2 = incident * r2 * color[2]
            if not max(f0, max(f1, f2)) > 0:
                continue
            if not (np.isfinite(f0) and np.isfinite(f1) and np.isfinite(f2)):
                continue
            pos[n, 0], pos[n, 1], pos[n, 2] = px, py, pz
            nrm[n, 0], nrm[n, 1], nrm[n, 2] = nx, ny, nz
            flux[n, 0], flux[n, 1], flux[n, 2] = f0, f1, f2
            area[n] = a
            n += 1
    return n - row0 * size
