"""Compiled twin of rsm.view_vpls (kernels/__init__.py): the VPLs of one view's read-back
targets in one pass over the texels, split over two threads from SPLIT_MIN rows."""

from __future__ import annotations

import numpy as np

from .. import mirror_lobe
from ..render.raster import TRIANGLE_SPLIT
from ..runtime import jit, pool
from ..scene import lights as lights_mod
from ..scene.model import Light
from .direct import round_args, round_geometry

KINDS = {"POINT": 0, "SPOT": 1, "AREA": 2, "SUN": 3}  # light type -> the kernel's kind
SPLIT_MIN = 64  # rows: smaller maps are converted on one thread


def view_vpls(light: Light, view: lights_mod.LightView, p4, n4, reflectance, origin) -> tuple:
    """rsm.view_vpls by ``_vpl_kernel``: one compiled pass over the texels, with the formulas
    of texel_flux and lights.intensity (and rsm.mirror_vpls' for a 6-column table, written
    to arrays of their own and appended).
    The rows are cut in two parts of equal covered texels, converted on two threads (the
    kernel releases the GIL); the second part's VPLs then move down behind the first's."""
    if light.type not in KINDS:
        lights_mod.intensity(light, np.zeros((1, 3)))  # raises the named error
    size = p4.shape[0]
    inv = np.linalg.inv(np.asarray(view.view, np.float64))
    cos_half = float(np.cos(0.5 * light.spot_size)) if light.type == "SPOT" else 0.0
    args = (p4, n4, np.ascontiguousarray(reflectance, np.float32),
            np.asarray(origin, np.float64), bool(view.ortho),
            float(view.tan_half), float(view.half_extent),
            np.ascontiguousarray(inv[:3, 0]), np.ascontiguousarray(inv[:3, 1]),
            np.ascontiguousarray(-inv[:3, 2]), np.asarray(light.position, np.float64),
            np.asarray(light.direction, np.float64), KINDS[light.type], float(light.power),
            cos_half,
            (1.0 - cos_half) * float(light.spot_blend) if light.type == "SPOT" else 0.0,
            *round_args(light), np.asarray(light.color, np.float64), size)
    glossy = reflectance.shape[1] == 6
    m = size * size if glossy else 0
    out = (np.empty((size * size, 3)), np.empty((size * size, 3)), np.empty((size * size, 3)),
           np.empty(size * size), np.empty((m, 3)), np.empty((m, 3)), np.empty((m, 3)),
           np.empty(m), np.empty((m, 3)))
    if size < SPLIT_MIN:
        n, k = _vpl_kernel(*args, glossy, 0, size, *out)
        return _joined(out, n, k, glossy)
    half = _half_row_kernel(p4)
    (n0, k0), (n1, k1) = pool.executor().map(lambda rows: _vpl_kernel(*args, glossy, *rows,
                                                                          *out),
                                               ((0, half), (half, size)))
    if n0 < half * size and n1:
        _move_rows_kernel(*out[:4], half * size, n0, n1)
    if glossy and k0 < half * size and k1:
        _move_rows_kernel(*out[4:8], half * size, k0, k1)
        out[8][k0:k0 + k1] = out[8][half * size:half * size + k1].copy()
    return _joined(out, n0 + n1, k0 + k1, glossy)


def _joined(out: tuple, n: int, k: int, glossy: bool) -> tuple:
    """The first ``n`` VPLs of out[:4], then (glossy) the first ``k`` mirror VPLs of out[4:8]
    and the lift (rsm.view_vpls), the kernel's mirror directions turned into their lobes'
    axes (mirror_lobe.above, as rsm.mirror_vpls)."""
    if not glossy:
        return tuple(a[:n] for a in out[:4])
    surface = out[5][:k] + out[8][:k]  # the kernel's lift: normal less mirror direction
    out[5][:k] = mirror_lobe.above(out[5][:k], surface)
    out[8][:k] = surface - out[5][:k]
    return tuple(np.concatenate((a[:n], b[:k])) for a, b in
                 zip((*out[:4], np.zeros((n, 3))), out[4:]))


@jit.kernel
def _half_row_kernel(p4):
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
def _move_rows_kernel(pos, nrm, flux, area, src, dst, count):
    """Rows src..src+count-1 of the four VPL arrays moved down to dst (dst < src)."""
    for k in range(count):
        for c in range(3):
            pos[dst + k, c] = pos[src + k, c]
            nrm[dst + k, c] = nrm[src + k, c]
            flux[dst + k, c] = flux[src + k, c]
        area[dst + k] = area[src + k]


@jit.kernel
def _vpl_kernel(p4, n4, reflectance, origin, ortho, tan_half, half_extent, right, up, fwd, eye,
                axis, kind, power, cos_half, smooth, lrad2, sphere, color, size, glossy, row0, row1, pos, nrm,
                flux, area, mpos, mnrm, mflux, marea, mlift):
    """One pass over rows row0..row1-1 of a view's texels (rows top-first, as ``p4`` is given):
    the VPL of every covered texel that reflects a finite, non-zero flux, with the formulas of
    texel_rays, texel_flux and lights.intensity (point, spot cone smoothstep, with a radius
    lights.round_geometry; area cosine; sun:
    irradiance ``power`` times the texel area), written in texel order into pos, nrm, flux,
    area from row row0 * size on; ``glossy``: also each texel's mirror VPL (rsm.mirror_vpls)
    into mpos, mnrm, mflux, marea, mlift likewise. Returns how many of each. The texel's reflectance
    is its triangle's (Rasterizer.triangles). Per-row and per-column terms are hoisted and divisions turned into
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
    k = row0 * size
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
            s0 = np.float64(reflectance[tri, 3]) if glossy else 0.0
            s1 = np.float64(reflectance[tri, 4]) if glossy else 0.0
            s2 = np.float64(reflectance[tri, 5]) if glossy else 0.0
            if not max(max(r0, max(r1, r2)), max(s0, max(s1, s2))) > 0:
                continue
            px = np.float64(p4[row, col, 0]) + origin[0]
            py = np.float64(p4[row, col, 1]) + origin[1]
            pz = np.float64(p4[row, col, 2]) + origin[2]
            nx = np.float64(n4[row, col, 0])
            ny = np.float64(n4[row, col, 1])
            nz = np.float64(n4[row, col, 2])
            gain = np.sqrt(nx * nx + ny * ny + nz * nz)  # the shading normal's
            if gain > 0:
                nx, ny, nz = nx / gain, ny / gain, nz / gain
            ix, iy, iz = ax, ay, az  # the incident direction (a sun's axis)
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
                ix, iy, iz = dx, dy, dz
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
                d2 = tx * tx + ty * ty + tz * tz
                cos_s = abs(nx * dx + ny * dy + nz * dz)
                a = solid * d2 / max(cos_s, 0.05)
                if lrad2 > 0:  # a round emitter's irradiance (rsm.texel_flux)
                    if sphere and d2 <= lrad2:  # inside a spot's sphere: no cone falloff
                        strength = point
                    incident = strength * round_geometry(cos_s, d2, lrad2, sphere) * a
            if glossy:
                g0 = incident * s0 * color[0]
                g1 = incident * s1 * color[1]
                g2 = incident * s2 * color[2]
                dn = ix * nx + iy * ny + iz * nz
                if (dn < 0 and max(g0, max(g1, g2)) > 0 and np.isfinite(g0)
                        and np.isfinite(g1) and np.isfinite(g2)):
                    mpos[k, 0], mpos[k, 1], mpos[k, 2] = px, py, pz
                    mnrm[k, 0] = ix - 2.0 * dn * nx
                    mnrm[k, 1] = iy - 2.0 * dn * ny
                    mnrm[k, 2] = iz - 2.0 * dn * nz
                    mflux[k, 0], mflux[k, 1], mflux[k, 2] = g0, g1, g2
                    mlift[k, 0] = nx - mnrm[k, 0]
                    mlift[k, 1] = ny - mnrm[k, 1]
                    mlift[k, 2] = nz - mnrm[k, 2]
                    marea[k] = a
                    k += 1
            f0 = incident * gain * r0 * color[0]
            f1 = incident * gain * r1 * color[1]
            f2 = incident * gain * r2 * color[2]
            if not max(f0, max(f1, f2)) > 0:
                continue
            if not (np.isfinite(f0) and np.isfinite(f1) and np.isfinite(f2)):
                continue
            pos[n, 0], pos[n, 1], pos[n, 2] = px, py, pz
            nrm[n, 0], nrm[n, 1], nrm[n, 2] = nx, ny, nz
            flux[n, 0], flux[n, 1], flux[n, 2] = f0, f1, f2
            area[n] = a
            n += 1
    return n - row0 * size, k - row0 * size
