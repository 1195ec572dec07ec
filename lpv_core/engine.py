"""The LPV engine: plans and runs RSM, injection and propagation for a scene.

Propagation is linear in the injected light, so each light's propagated grid is kept apart and
the result is their sum weighted by per-light GI intensity and the global intensity. Stats keep
milliseconds per stage and every piece of work that was left out, with the reason.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from . import injection, propagation
from .grid import Grid, fit_grid
from .scene import Scene


@dataclass
class Stats:
    """Milliseconds per stage, dropped input counts and skipped work with reasons."""

    ms: dict = field(default_factory=dict)
    dropped: dict = field(default_factory=dict)
    skipped: list = field(default_factory=list)
    info: dict = field(default_factory=dict)

    def add_ms(self, stage: str, seconds: float) -> None:
        self.ms[stage] = self.ms.get(stage, 0.0) + seconds * 1000.0

    def skip(self, stage: str, what: str, reason: str) -> None:
        self.skipped.append({"stage": stage, "what": what, "reason": reason})

    def as_dict(self) -> dict:
        return {"ms": dict(self.ms), "dropped": dict(self.dropped), "skipped": list(self.skipped),
                "info": dict(self.info)}


class Timer:
    """Context manager adding elapsed time to a stage of ``stats``."""

    def __init__(self, stats: Stats, stage: str):
        self.stats, self.stage = stats, stage

    def __enter__(self):
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.stats.add_ms(self.stage, time.perf_counter() - self.t0)


@dataclass
class LPVResult:
    """The combined LPV (SH intensity per cell) and the grid it lives on."""

    grid: Grid | None
    values: np.ndarray | None  # (R, R, R, 3, 4) float32, or None when there is no GI
    per_light: dict  # light name -> propagated grid (unweighted)
    stats: Stats


class Engine:
    """Computes LPV GI for core Scenes; owns the GL rasteriser of this process."""

    def __init__(self, raster=None):
        self._raster = raster

    @property
    def raster(self):
        if self._raster is None:
            from .raster import Rasterizer

            self._raster = Rasterizer()
        return self._raster

    def upload(self, scene: Scene, stats: Stats) -> None:
        with Timer(stats, "upload"):
            self.raster.upload(scene.positions, scene.normals, scene.albedo_per_triangle(),
                               scene.reflectance_per_triangle())

    def update(self, scene: Scene, stats: Stats | None = None) -> LPVResult:
        """RSM -> injection -> propagation -> combine for every light that contributes GI."""
        from .rsm import render_rsm

        stats = stats or Stats()
        stats.dropped.update(scene.dropped)
        settings = scene.settings
        t0 = time.perf_counter()
        if scene.triangle_count == 0:
            stats.skip("lpv", "scene", "no geometry")
            stats.ms["lpv_update"] = 0.0
            return LPVResult(None, None, {}, stats)
        lo, hi = scene.bounds()
        grid = fit_grid(lo, hi, settings.grid_resolution)
        stats.info["grid"] = {"origin": list(grid.origin), "cell_size": grid.cell_size,
                              "resolution": grid.resolution}
        active = []
        for light in scene.lights:
            reason = _no_gi_reason(light, settings.intensity)
            if reason:
                stats.skip("rsm", f"light '{light.name}'", reason)
            else:
                active.append(light)
        if not active:
            if not scene.lights:
                stats.skip("lpv", "scene", "no lights")
            stats.ms["lpv_update"] = (time.perf_counter() - t0) * 1000.0
            return LPVResult(grid, None, {}, stats)
        self.upload(scene, stats)
        iterations = settings.iterations or auto_iterations(settings.grid_resolution)
        per_light = {}
        combined = grid.zeros()
        vpl_count = 0
        run_iterations = []
        for light in active:
            with Timer(stats, "rsm"):
                rsm = render_rsm(self.raster, light, (lo, hi), settings.rsm_resolution)
            vpl_count += rsm.count
            with Timer(stats, "injection"):
                injected = injection.inject(grid, rsm.position, rsm.normal, rsm.flux)
            with Timer(stats, "propagation"):
                prop = propagation.propagate(injected, iterations,
                                             reprojection=settings.reprojection)
            run_iterations.append(prop.iterations)
            with Timer(stats, "combine"):
                per_light[light.name] = prop.values
                combined += np.float32(light.gi_intensity) * prop.values
        with Timer(stats, "combine"):
            combined *= np.float32(settings.intensity)
        stats.info["vpls"] = vpl_count
        stats.info["iterations"] = run_iterations
        stats.ms["lpv_update"] = (time.perf_counter() - t0) * 1000.0
        return LPVResult(grid, combined, per_light, stats)


def auto_iterations(resolution: int) -> int:
    """Default propagation steps: KD10 uses 8 on a 32^3 cascade, i.e. resolution / 4."""
    return max(1, round(resolution / 4))


def _no_gi_reason(light, global_intensity: float) -> str:
    """Why a light contributes no GI (empty string: it does)."""
    if global_intensity == 0:
        return "global GI intensity is 0"
    if light.gi_intensity == 0:
        return "GI intensity is 0"
    if light.power <= 0:
        return "power is 0"
    if float(np.max(np.asarray(light.color))) <= 0:
        return "colour is black"
    return ""
