"""Reflective shadow maps [KD10 sec. 3, after Dachsbacher & Stamminger 2005].

Each texel of a light's view becomes a virtual point light (VPL): world position, normal and the
flux it reflects. Perspective texels carry I(w) x (texel solid angle); sun texels carry
E x (texel footprint area): the texel area term most public code leaves out. The reflected
flux uses the material's GI reflectance (bleed colour x intensity where the artist set one),
times the corner colour and the texture at the texel's point where the scene has them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import mirror_lobe
from .kernels import rsm as _compiled
from .render.raster import Rasterizer
from .runtime import jit
from .scene import lights as lights_mod
from .scene.model import Light


@dataclass
class RSM:
    """VPLs of one light: (N, 3) positions, normals and reflected flux (W), (N,) surfel area;
    ``lift`` (N, 3) or None: what moves a VPL's injection offset from its normal onto its
    surface's (a mirror VPL's surface normal less its lobe axis, 0 for the rest)."""

    light: Light
    position: np.ndarray
    normal: np.ndarray
    flux: np.ndarray
    area: np.ndarray
    texels: int  # texels rendered (for stats)
    lift: np.ndarray | None = None

    @property
    def count(self) -> int:
        return int(self.position.shape[0])


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
    area = solid * dist2 / np.maximum(cos_s, 0.05)
    if light.type in ("POINT", "SPOT") and light.radius > 0:  # the round emitter's irradiance
        inten = lights_mod.intensity(light, dirs)
        inten[lights_mod.inside_sphere(light, dist2)] = light.power / (4.0 * np.pi)
        incident = inten * lights_mod.round_geometry(light, cos_s, dist2) * area
    return incident, area


def render_rsm(raster: Rasterizer, light: Light, bounds, resolution: int, fit=None) -> RSM:
    """The RSM of ``light``: VPLs for every covered texel that reflects any flux.
    ``fit`` (sun only): the box the view's window is fitted to (lights.light_views).
    Each view is one two-target pass (Rasterizer.read_rsm: position, normal and the triangle,
    whose reflectance the uploaded table gives), converted by view_vpls; a textured scene's
    pass adds the texel's point on its triangle, and each texel its own reflectance
    (Rasterizer.rsm_texels: the texture's colour where the light falls)."""
    parts = []
    texels = 0
    for view in lights_mod.light_views(light, bounds, fit):
        p4, n4, table = raster.rsm_texels(view.view, view.projection, resolution, view.ortho)
        texels += resolution * resolution
        parts.append(view_vpls(light, view, p4, n4, table, raster.origin))
    if not parts:
        empty = np.zeros((0, 3))
        return RSM(light, empty, empty, empty, np.zeros(0), texels)
    joined = parts[0] if len(parts) == 1 else [np.concatenate(f) for f in zip(*parts)]
    return RSM(light, *joined[:4], texels, *joined[4:])


def view_vpls(light: Light, view: lights_mod.LightView, p4, n4, reflectance, origin) -> tuple:
    """(position, normal, flux, area) of the VPLs of one view's read-back targets ``p4``,
    ``n4`` (Rasterizer.read_rsm, positions relative to ``origin``; ``reflectance`` the
    uploaded per-triangle table): only the covered, reflecting texels are converted and lit
    (the rest of the map costs nothing more). A 6-column table (Rasterizer.rsm_texels with
    glossy reflectance) adds, after them, each glossy texel's mirror VPL (mirror_vpls), and
    a fifth array: the lift (RSM.lift)."""
    if jit.enabled():
        return _compiled.view_vpls(light, view, p4, n4, reflectance, origin)
    size = p4.shape[0]
    rows, cols = np.nonzero(p4[..., 3] > 0.5)
    table = reflectance[Rasterizer.triangles(p4[rows, cols], n4[rows, cols])]
    lit = table.max(axis=-1) > 0
    rows, cols, table = rows[lit], cols[lit], table[lit]
    refl = table[:, :3]
    position = p4[rows, cols, :3].astype(np.float64) + origin
    normal = n4[rows, cols, :3].astype(np.float64)
    gain = np.linalg.norm(normal, axis=1)  # the shading normal's (RSM_FRAGMENT_SHADER)
    normal /= np.where(gain > 0, gain, 1.0)[:, None]
    incident, surf_area = texel_flux(light, view, rows, cols, size, position, normal)
    color = np.asarray(light.color, np.float64)
    phi = (incident * gain)[:, None] * refl * color
    keep = (phi.max(axis=-1) > 0) & np.isfinite(phi).all(axis=-1)
    out = position[keep], normal[keep], phi[keep], surf_area[keep]
    if table.shape[1] == 3:
        return out
    if view.ortho:
        incoming = np.broadcast_to(np.asarray(light.direction, np.float64), normal.shape)
    else:
        incoming = lights_mod.texel_rays(view, rows, cols, size, size)[0]
    mirror = mirror_vpls(position, normal, incoming, incident[:, None] * table[:, 3:] * color,
                         surf_area)
    return tuple(np.concatenate(pair) for pair in zip((*out, np.zeros_like(out[1])), mirror))


def mirror_vpls(position, normal, incoming, flux, area) -> tuple:
    """The glossy bounce as VPLs (position, normal, flux, area, lift): at each surface point
    (normal facing the light), flux ``flux`` (incident x glossy reflectance) leaving around the
    mirror direction of the unit ``incoming`` direction; the VPL's normal is the axis of
    injection's cosine lobe (a wider lobe than a glossy one: docs/algorithm.md), which
    carries exactly ``flux``: that lobe's part above the surface (mirror_lobe.above). Its
    lift (normal less axis) puts its injection offset along the surface normal, as a diffuse
    VPL's: along the axis it would cross a floor under a wall."""
    dn = np.einsum("nc,nc->n", incoming, normal)
    keep = (dn < 0) & (flux.max(axis=-1) > 0) & np.isfinite(flux).all(axis=-1)
    normal = normal[keep]
    axis = mirror_lobe.above(incoming[keep] - 2.0 * dn[keep, None] * normal, normal)
    return position[keep], axis, flux[keep], area[keep], normal - axis

