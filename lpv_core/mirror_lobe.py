"""The lobe a mirror VPL (the glossy bounce, rsm.mirror_vpls) emits: injection's cosine lobe
around the mirror direction, cut to the reflecting surface's hemisphere. Light reflected off
a surface leaves above it (Cycles' multiscatter GGX keeps the energy a grazing lobe's lower
part would lose), but a cosine lobe around a mirror direction at angle theta from the normal
reaches up to theta below the surface; the part above is carried by its first moment, the two
moments the injected SH holds, with the VPL's whole flux."""

from __future__ import annotations

import numpy as np


def lune_table(samples: int = 1024, entries: int = 513) -> tuple[np.ndarray, np.ndarray]:
    """(cos theta ascending, tilt): for a cosine lobe around an axis at angle theta from the
    normal, the angle from the axis towards the normal of its above-surface part's mean
    direction. About the axis (polar angle beta, azimuth alpha measured towards the normal)
    the part is |alpha| < alpha0(beta), cos alpha0 = -cot theta cot beta, so the azimuth
    integrates in closed form (2 alpha0, 2 sin alpha0); beta by the midpoint rule."""
    theta = np.linspace(0.0, 0.5 * np.pi, entries)[:, None]
    beta = (np.arange(samples) + 0.5) * (0.5 * np.pi / samples)
    sb, cb = np.sin(beta), np.cos(beta)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = -np.cos(theta) * cb / (np.sin(theta) * sb)  # theta = 0: -inf, the whole lobe
    alpha0 = np.arccos(np.clip(np.nan_to_num(c, nan=-1.0, neginf=-1.0, posinf=1.0), -1.0, 1.0))
    towards = (cb * sb * sb * 2.0 * np.sin(alpha0)).sum(axis=1)  # cos w.axis x w.(to normal)
    along = (cb * cb * sb * 2.0 * alpha0).sum(axis=1)  # cos w.axis x w.axis
    return np.cos(theta[:, 0])[::-1].copy(), np.arctan2(towards, along)[::-1].copy()


_TABLE: list = []


def above(axis: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(N, 3) unit mean directions of the cosine lobes around unit ``axis`` (N, 3, facing the
    side of the unit ``normal``) cut to the hemispheres of ``normal`` (N, 3): ``axis`` tilted
    towards the normal by lune_table's angle (0 along the normal, atan(2 / pi) = 32.5 deg on
    the surface's plane)."""
    if not _TABLE:
        _TABLE.extend(lune_table())
    axis = np.asarray(axis, np.float64)
    normal = np.asarray(normal, np.float64)
    cos_t = np.clip(np.einsum("nc,nc->n", axis, normal), 0.0, 1.0)
    tilt = np.interp(cos_t, *_TABLE)
    t = normal - cos_t[:, None] * axis  # towards the normal, across the axis
    norm = np.linalg.norm(t, axis=1)
    t = np.divide(t, norm[:, None], out=np.zeros_like(t), where=norm[:, None] > 1e-9)
    out = np.cos(tilt)[:, None] * axis + np.sin(tilt)[:, None] * t
    return out / np.linalg.norm(out, axis=1, keepdims=True)
