"""Reflective shadow maps [KD10 sec. 3, after Dachsbacher & Stamminger 2005].

Each texel of a light's view becomes a virtual point light (VPL): world position, normal and the
flux it reflects. Perspective texels carry I(w) x (texel solid angle); sun texels carry
E x (texel footprint area): the texel area term most public code leaves out. The reflected
flux uses the material's GI reflectance (bleed colour x intensity where the artist set one).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import lights as lights_mod
from .raster import Frame, Rasterizer
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


def render_views(
    raster: Rasterizer, light: Light, bounds, resolution: int, fit=None
) -> list[tuple[lights_mod.LightView, Frame]]:
    """Rasterise every view of ``light`` at ``resolution`` squared (``fit``: light_views)."""
    out = []
    for view in lights_mod.light_views(light, bounds, fit):
        frame = raster.render(view.view, view.projection, resolution, resolution, ortho=view.ortho)
        out.append((view, frame))
    return out


def texel_flux(light: Light, view: lights_mod.LightView, frame: Frame) -> tuple[np.ndarray, ...]:
    """Incident flux per texel (H, W) per unit colour, and surfel area (H, W), for one view."""
    h, w = frame.covered.shape
    if view.ortho:
        texel_area = (2.0 * view.half_extent / w) * (2.0 * view.half_extent / h)
        incident = np.full((h, w), light.power * texel_area)
        cos_s = np.abs(frame.normal @ light.direction.astype(np.float32))
        area = texel_area / np.maximum(cos_s, 0.05)
    else:
        dirs, solid = lights_mod.texel_directions(view, w, h)
        incident = lights_mod.intensity(light, dirs) * solid
        to_surf = frame.position - light.position
        dist2 = np.einsum("hwc,hwc->hw", to_surf, to_surf)
        cos_s = np.abs(np.einsum("hwc,hwc->hw", frame.normal.astype(np.float64), dirs))
        area = solid * dist2 / np.maximum(cos_s, 0.05)
    incident = np.where(frame.covered, incident, 0.0)
    return incident, np.where(frame.covered, area, 0.0)


def render_rsm(raster: Rasterizer, light: Light, bounds, resolution: int, fit=None) -> RSM:
    """The RSM of ``light``: VPLs for every covered texel that reflects any flux.
    ``fit`` (sun only): the box the view's window is fitted to (lights.light_views)."""
    pos, nrm, flux, area = [], [], [], []
    texels = 0
    color = np.asarray(light.color, np.float64)
    for view, frame in render_views(raster, light, bounds, resolution, fit):
        incident, surf_area = texel_flux(light, view, frame)
        texels += incident.size
        refl = frame.reflectance.astype(np.float64)
        phi = incident[..., None] * refl * color
        keep = frame.covered & (phi.max(axis=-1) > 0) & np.isfinite(phi).all(axis=-1)
        pos.append(frame.position[keep])
        nrm.append(frame.normal[keep].astype(np.float64))
        flux.append(phi[keep])
        area.append(surf_area[keep])
    if not pos:
        empty = np.zeros((0, 3))
        return RSM(light, empty, empty, empty, np.zeros(0), texels)
    return RSM(light, np.concatenate(pos), np.concatenate(nrm), np.concatenate(flux),
               np.concatenate(area), texels)
