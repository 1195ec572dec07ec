"""Reflective shadow maps [KD10 sec. 3, after Dachsbacher & Stamminger 2005].

Each texel of a light's view becomes a virtual point light (VPL): world position, normal and the
flux it reflects. Perspective texels carry I(w) x (texel solid angle); sun texels carry
E x (texel footprint area): the texel area term most public code leaves out. The reflected
flux uses the material's GI reflectance (bleed colour x intensity where the artist set one).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import jit, ordinates
from . import lights as lights_mod
from .raster import Rasterizer
from .scene import Light


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
    Only the position, normal and reflectance targets are read back, and only the covered,
    reflecting texels are converted and lit (the rest of the map costs nothing more); with
    jit.enabled() in one compiled pass over the texels (``_vpl_kernel``)."""
    parts = []
    texels = 0
    color = np.asarray(light.color, np.float64)
    for view in lights_mod.light_views(light, bounds, fit):
        p4, n4, r4 = raster.read(view.view, view.projection, resolution, resolution,
                                 view.ortho, (0, 1, 3))
        texels += resolution * resolution
        if jit.enabled():
            parts.append(_vpls(light, view, p4, n4, r4, raster.origin))
            continue
        rows, cols = np.nonzero((p4[..., 3] > 0.5) & (r4[..., :3].max(axis=-1) > 0))
        position = p4[rows, cols, :3].astype(np.float64) + raster.origin
        normal = n4[rows, cols, :3].astype(np.float64)
        incident, surf_area = texel_flux(light, view, rows, cols, resolution, position, normal)
        phi = incident[:, None] * r4[rows, cols, :3] * color
        keep = (phi.max(axis=-1) > 0) & np.isfinite(phi).all(axis=-1)
        parts.append((position[keep], normal[keep], phi[keep], surf_area[keep]))
    if not parts:
        empty = np.zeros((0, 3))
        return RSM(light, empty, empty, empty, np.zeros(0), texels)
    if len(parts) == 1:
        return RSM(light, *parts[0], texels)
    return RSM(light, *(np.concatenate(f) for f in zip(*parts)), texels)


_KINDS = {"POINT": 0, "SPOT": 1, "AREA": 2, "SUN": 3}


def _vpls(light: Light, view: lights_mod.LightView, p4, n4, r4, origin) -> tuple:
    """(position, normal, flux, area) of the VPLs of one view's read-back targets: the
    compiled twin of render_rsm's numpy pass (texel_flux, lights.intensity)."""
    if light.type not in _KINDS:
        lights_mod.intensity(light, np.zeros((1, 3)))  # raises the named error
    size = p4.shape[0]
    inv = np.linalg.inv(np.asarray(view.view, np.float64))
    cos_half = float(np.cos(0.5 * light.spot_size)) if light.type == "SPOT" else 0.0
    args = (p4, n4, r4, np.asarray(origin, np.float64), bool(view.ortho),
            float(view.tan_half), float(view.half_extent),
            np.ascontiguousarray(inv[:3, 0]), np.ascontiguousarray(inv[:3, 1]),
            np.ascontiguousarray(-inv[:3, 2]), np.asarray(light.position, np.float64),
            np.asarray(light.direction, np.float64), _KINDS[light.type], float(light.power),
            cos_half,
            (1.0 - cos_half) * float(light.spot_blend) if light.type == "SPOT" else 0.0,
            np.asarray(light.color, np.float64), size)
    out = (np.empty((size * size, 3)), np.empty((size * size, 3)), np.empty((size * size, 3)),
           np.empty(size * size))
    # The rows in two parts of equal covered texels, on two threads (the kernel releases the
    # GIL): Cornell box spot RSM, 256^2, 1.6-2.5 -> 1.2-1.4 ms; the second part's VPLs then move
    # down behind the first part's.
    covered = np.cumsum(np.count_nonzero(p4[..., 3] > 0.5, axis=1))
    half = min(max(int(np.searchsorted(covered, covered[-1] / 2.0)), 1), size - 1)
    counts = list(ordinates._pool().map(lambda rows: _vpl_kernel(*args, *rows, *out),
                                        ((0, half), (half, size))))
    n0, n1 = counts
    if n0 < half * size:
        for a in out:
            a[n0:n0 + n1] = a[half * size:half * size + n1]
    return tuple(a[:n0 + n1] for a in out)


@jit.kernel
def _vpl_kernel(p4, n4, r4, origin, ortho, tan_half, half_extent, right, up, fwd, eye, axis,
                kind, power, cos_half, smooth, color, size, row0, row1, pos, nrm, flux, area):
    """One pass over rows row0..row1-1 of a view's texels (rows top-first, as ``p4`` is given):
    the VPL of every covered texel that reflects a finite, non-zero flux, with the formulas of
    texel_rays, texel_flux and lights.intensity (point, spot cone smoothstep, area cosine; sun:
    irradiance ``power`` times the texel area), written in texel order into pos, nrm, flux,
    area from row row0 * size on; returns how many."""
    texel_area = (2.0 * half_extent / size) * (2.0 * half_extent / size)
    n = row0 * size
    for row in range(row0, row1):
        for col in range(size):
            if not p4[row, col, 3] > 0.5:
                continue
            if not max(r4[row, col, 0], max(r4[row, col, 1], r4[row, col, 2])) > 0:
                continue
            px = np.float64(p4[row, col, 0]) + origin[0]
            py = np.float64(p4[row, col, 1]) + origin[1]
            pz = np.float64(p4[row, col, 2]) + origin[2]
            nx = np.float64(n4[row, col, 0])
            ny = np.float64(n4[row, col, 1])
            nz = np.float64(n4[row, col, 2])
            if ortho:
                incident = power * texel_area
                a = texel_area / max(abs(nx * axis[0] + ny * axis[1] + nz * axis[2]), 0.05)
            else:
                u = ((col + 0.5) / size * 2.0 - 1.0) * tan_half
                v = (1.0 - (row + 0.5) / size * 2.0) * tan_half
                r2 = 1.0 + u * u + v * v
                root = np.sqrt(r2)
                dx = (u * right[0] + v * up[0] + fwd[0]) / root
                dy = (u * right[1] + v * up[1] + fwd[1]) / root
                dz = (u * right[2] + v * up[2] + fwd[2]) / root
                solid = (2.0 * tan_half / size) * (2.0 * tan_half / size) / (r2 * root)
                if kind == 0:
                    strength = power / (4.0 * np.pi)
                else:
                    cos_a = dx * axis[0] + dy * axis[1] + dz * axis[2]
                    if kind == 1:
                        if smooth > 0:
                            x = min(max((cos_a - cos_half) / smooth, 0.0), 1.0)
                            falloff = x * x * (3.0 - 2.0 * x)
                        else:
                            falloff = 1.0 if cos_a > cos_half else 0.0
                        strength = power / (4.0 * np.pi) * falloff
                    else:
                        strength = power / np.pi * max(cos_a, 0.0)
                incident = strength * solid
                tx, ty, tz = px - eye[0], py - eye[1], pz - eye[2]
                dist2 = tx * tx + ty * ty + tz * tz
                a = solid * dist2 / max(abs(nx * dx + ny * dy + nz * dz), 0.05)
            f0 = incident * np.float64(r4[row, col, 0]) * color[0]
            f1 = incident * np.float64(r4[row, col, 1]) * color[1]
            f2 = incident * np.float64(r4[row, col, 2]) * color[2]
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
