"""Budgets for per-light maps: resolutions shared out by each light's share of the light, and
an LRU cache of shadow maps bounded in bytes (Engine.shadow_map, Engine._rsm).

A scene whose maps all fit keeps the set resolution for every light (the same bits); past the
budget each light's texels follow its share (water-filling), rounded down to the resolution
over a power of two, never below MIN_RESOLUTION. See docs/algorithm.md, "Shadow budget".
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from ..scene import lights as lights_mod

# Cached shadow maps (float32 distances): 512 MiB holds 21 point lights' cube maps at the
# default 1024^2 per face (24 MiB each), or 128 spot lights' single views.
SHADOW_BUDGET = 512 * 2**20
# Texels of the lights' RSMs in one update: 20 point lights at the default 256^2 per face
# (the RSM stage ~2 s on llvmpipe), 120 spots; the VPLs injected and propagated follow it.
RSM_BUDGET = 8 * 2**20
MIN_RESOLUTION = 64  # no map shrinks below this per face (a 6-face map: 96 KiB)


def resolutions(shares, views, resolution: int, budget: float,
                floor: int = MIN_RESOLUTION) -> np.ndarray:
    """(n,) map resolutions of lights with ``shares`` (>= 0) of the light and ``views`` faces:
    ``resolution`` for all when their texels fit in ``budget``; else texels per face in
    proportion to the share, clipped to [floor^2, resolution^2], scaled to fill the budget,
    each then rounded down to resolution / 2^k."""
    shares = np.maximum(np.nan_to_num(np.asarray(shares, np.float64)), 0.0)
    views = np.asarray(views, np.float64)
    full = float(resolution) ** 2
    low = float(min(floor, resolution)) ** 2
    if full * views.sum() <= budget:
        return np.full(shares.shape, int(resolution))

    def texels(scale):
        return np.clip(scale * shares, low, full)

    lo, hi = 0.0, full / max(float(shares[shares > 0].min(initial=1.0)), 1e-300)
    for _ in range(200):  # bisection on the scale (monotone in it); ends at hi, within budget
        mid = 0.5 * (lo + hi)
        if (texels(mid) * views).sum() <= budget:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-12 * hi:
            break
    side = np.sqrt(texels(lo))
    halvings = np.ceil(np.log2(resolution / side) - 1e-9).clip(0, 30).astype(int)
    return np.maximum(int(resolution) >> halvings, min(floor, resolution))


def frame_shares(lights, points: np.ndarray | None) -> np.ndarray:
    """(n,) each light's share of the unshadowed irradiance (no cosine: the points carry no
    normals) summed over ``points`` (what the camera sees); without points, of the power."""
    if points is None or len(points) == 0:
        w = np.array([gi_weight(light) for light in lights])
    else:
        pts = np.asarray(points, np.float64)
        w = np.empty(len(lights))
        for i, light in enumerate(lights):
            col = float(np.max(light.color))
            if light.type == "SUN":
                w[i] = light.power * col * len(pts)
                continue
            to = pts - light.position
            d2 = np.maximum(np.einsum("ij,ij->i", to, to), 1e-30)
            w[i] = col * float(np.sum(lights_mod.intensity(light, to / np.sqrt(d2)[:, None])
                                      / d2))
    total = w.sum()
    return w / total if total > 0 else np.full(len(lights), 1.0 / max(len(lights), 1))


def gi_weight(light) -> float:
    """A light's emitted flux times its GI weight, up to a common factor: power x colour x GI
    intensity x tint, a spot's power (as if a point, Cycles) times its cone's solid-angle
    share."""
    w = float(light.power) * float(np.max(light.color)) * abs(float(light.gi_intensity))
    tint = getattr(light, "gi_color", None)
    if tint is not None:
        w *= float(np.max(np.abs(tint)))
    if light.type == "SPOT":
        w *= 0.5 * (1.0 - np.cos(0.5 * min(light.spot_size, np.pi)))
    return max(w, 0.0)


def view_count(light) -> int:
    """Faces of a light's maps (lights.light_views): 1 for a sun or a spot of at most
    SINGLE_FACE_MAX_CONE, 6 otherwise."""
    if light.type == "SUN" or (light.type == "SPOT"
                               and light.spot_size <= lights_mod.SINGLE_FACE_MAX_CONE):
        return 1
    return 6


class ShadowCache:
    """Shadow maps by key, least recently used first out once their bytes pass ``budget``
    (the map just added always stays)."""

    def __init__(self, budget: int = SHADOW_BUDGET):
        self.budget = budget
        self.maps: OrderedDict = OrderedDict()
        self.sizes: dict = {}  # the bytes counted per key (a map's pyramid may come later)
        self.bytes = 0
        self.evicted = 0  # maps dropped for the budget since the cache was made
        self.tag = None  # what the maps were made for (the geometry key); clear() sets it

    def get(self, key):
        shadow = self.maps.get(key)
        if shadow is not None:
            self.maps.move_to_end(key)
        return shadow

    def put(self, key, shadow) -> None:
        self.maps.pop(key, None)
        self.bytes -= self.sizes.pop(key, 0)
        self.maps[key] = shadow
        self.sizes[key] = shadow.nbytes
        self.bytes += self.sizes[key]
        while self.bytes > self.budget and len(self.maps) > 1:
            dropped, _ = self.maps.popitem(last=False)
            self.bytes -= self.sizes.pop(dropped)
            self.evicted += 1

    def clear(self, tag=None) -> None:
        self.maps.clear()
        self.sizes.clear()
        self.bytes, self.tag = 0, tag
