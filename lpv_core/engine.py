"""The LPV engine: plans and runs RSM, injection and propagation for a scene.

Propagation is linear in the injected light, so each light's propagated grid is kept apart and
the result is their sum weighted by per-light GI intensity and the global intensity. Stats keep
milliseconds per stage and every piece of work that was left out, with the reason.
"""

from __future__ import annotations

import hashlib
import operator
import time
from dataclasses import dataclass, field, replace

import numpy as np

from . import areas, cascades, geometry_volume, injection, lookup, planner, propagation, sources
from .grid import Grid
from .propagation import sweep
from .runtime import blas, heap, jit
from .scene import textures
from .scene.model import Scene, max_grid_resolution


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
class LightGrids:
    """A light's propagated grids, valid while the scene key holds (Engine._light)."""

    key: tuple  # light_key of the light they were made for
    grids: list  # propagated grid per cascade, finest first (unweighted)
    sample: tuple  # (positions (N, 3), flux (N, 3)): a VPL subsample for debug views
    flux: np.ndarray | str | None  # the RSM's VPL flux or its digest (same_vpls)
    resolution: int = 0  # the RSM's resolution (Engine._rsm_plan)


@dataclass
class Volume:
    """A cascade's propagation visibility and its occluders' cell gaps (Engine.occlusion)."""

    visibility: np.ndarray | None  # (6, R, R, R) or None when nothing blocks
    gaps: np.ndarray | None  # geometry_volume.cell_gaps, or None


@dataclass
class Bounds:
    """The LPV box of one geometry (cascades.fit_bounds)."""

    geometry: str  # geometry_key it was fitted to
    lo: np.ndarray
    hi: np.ndarray
    outside: int  # triangles left out as far outliers
    outside_share: float  # their share of the surface area


@dataclass
class Focus:
    """What the camera sees (Engine._focus): the cascades are placed and counted from it."""

    key: tuple  # geometry key, camera view and projection
    points: np.ndarray  # world positions of the covered pixels
    sky_share: float  # share of the pixels that see no geometry


@dataclass
class LPVResult:
    """The combined LPV (SH intensity per cell) and the grid it lives on."""

    grid: Grid | None
    values: np.ndarray | None  # (R, R, R, 3, 4) float32, or None when there is no GI
    per_light: dict  # light name -> propagated grid (unweighted)
    stats: Stats
    # light name -> (positions (N, 3), flux (N, 3)): a subsample of its VPLs (debug views)
    vpls: dict = field(default_factory=dict)
    # (6, R, R, R) propagation visibility used (occlusion x clip areas), None if all clear
    visibility: np.ndarray | None = None
    # Finer cascades inside ``grid`` (finest first): (Grid, combined values, visibility);
    # lookups read them as cascades.reads says.
    fine: list = field(default_factory=list)
    # Grid -> geometry_volume.cell_gaps of its occluders (or None): where lookups must not
    # sample (lookup.gap_corrected)
    gaps: dict = field(default_factory=dict)
    # Per cascade coarser than the finest (finest first): its values with the finer cascades'
    # light added in its cells inside them (cascades.whole)
    whole: list = field(default_factory=list)


class Engine:
    """Computes LPV GI for core Scenes; owns the GL rasteriser of this process."""

    def __init__(self, raster=None):
        heap.retain_freed_memory()  # big arrays reused, not re-faulted, every update (heap.py)
        blas.single_threaded()  # no spinning BLAS threads beside the engine's own (blas.py)
        self._raster = raster
        self._gl = None  # GLBackend on the rasteriser's context, made on first use
        # Incremental updates: propagated grids per light, valid while the scene key holds.
        self._cache_key = None
        self._lights: dict[str, LightGrids] = {}
        self._volumes: dict[tuple, Volume] = {}  # by cascade placement (origin, cell size)
        self._plans: dict = {}  # the planner's cascade decisions for the last chain
        self._bounds: Bounds | None = None
        self._focus_cache: Focus | None = None
        # (cap, count) of the last update's planner.cascade_count: its hysteresis holds a count
        # for a moving camera, never across a change of the cap (settings.cascades)
        self._cascade_count = None
        self._count_memo = None  # (inputs, result) of the last cascade_count
        self._last_chain = None  # the cascades of the last update (placement hysteresis)
        self._cache_base = self._cache_chain = None  # the cache's key without inner cascades
        self._refl_key = None  # reflectance digest the cached grids were made with
        self._around = None  # (geometry key, cascades.Surroundings of the camera's eye)
        self._enclosure = None  # (Surroundings, cascades.enclosure_bounds of it)
        self._light_spaces: dict = {}  # (light position, cell) -> planner.enclosure_note
        from .render.shadows import ShadowCache

        self._shadows = ShadowCache()  # direct-light shadow maps of the current geometry
        self.source_maps = sources.SourceMaps()  # the World's and the emitters' shadow maps
        self._shadow_memo = None  # (inputs, plan) of _shadow_plan
        self._rsm_memo = None  # (inputs, plan) of _rsm_plan

    @property
    def raster(self):
        if self._raster is None:
            from .render.raster import Rasterizer

            self._raster = Rasterizer()
        return self._raster

    def backend(self, settings, stats: Stats | None = None):
        """The compute backend for ``settings.backend``: "numpy" (the CPU code), "gl" (moderngl
        compute shaders for the dom propagation and lookup, gl/backend.py; the rest on the CPU)
        or "auto" (gl.backend.auto_backend: the CPU on a software renderer such as llvmpipe,
        without timing anything; on a GPU per stage the faster of the two, measured once per
        machine and kept on disk). stats.info["backend_auto"] says what auto chose and why.
        Each has inject, propagate, irradiance and discard.
        The CPU stages run numba-compiled kernels where numba is installed (jit.py): the
        stats' "cpu_kernels" says which. While they compile (jit.warming) auto takes the CPU
        untimed: GL is timed against the compiled kernels, by the warm-up run."""
        name = getattr(settings, "backend", "numpy")
        if stats is not None:
            stats.info["cpu_kernels"] = jit.name()
        if name == "auto" and jit.warming():
            if stats is not None:
                stats.info["backend_auto"] = {"backend": "numpy", "reason": "kernels compiling"}
                stats.info["backend"] = NUMPY_BACKEND.name
            return NUMPY_BACKEND
        if name == "auto":
            from .gl import backend as gl_backend

            try:
                gl = self._gl_backend()
            except Exception:  # noqa: BLE001 - no usable GL context: auto falls back to numpy
                gl = None
            t0 = time.perf_counter()
            be, choice = gl_backend.auto_select(gl, NUMPY_BACKEND,
                                                getattr(settings, "angular", "dom"))
            took = time.perf_counter() - t0
            if stats is not None:
                # on a GPU the first call per process and model measures (seconds) unless the
                # choice came from the disk cache (~1 ms to read); a software renderer none
                if took > 1e-3 and not choice.get("cached"):
                    stats.add_ms("backend_choice", took)
                stats.info["backend_auto"] = dict(choice)
                stats.info["backend"] = be.name
            return be
        if name == "gl":
            be = self._gl_backend()
        elif name == "numpy":
            be = NUMPY_BACKEND
        else:
            raise ValueError(f"backend must be 'numpy', 'gl' or 'auto', not {name!r}")
        if stats is not None:
            stats.info["backend"] = be.name
        return be

    def _gl_backend(self):
        if self._gl is None:
            from .gl.backend import GLBackend

            self._gl = GLBackend(self.raster.ctx)
        return self._gl

    def upload(self, scene: Scene, stats: Stats, geo: str | None = None):
        """Send the scene's triangles to the rasteriser, relative to the LPV box's centre (so a
        far outlier does not cost the scene float32 precision); returns that box (lo, hi).
        ``geo``: the scene's geometry_key when the caller has it (saves hashing again)."""
        lo, hi = self.lpv_bounds(scene, stats, geo)
        self._send(scene, stats, 0.5 * (lo + hi))
        return lo, hi

    def _send(self, scene: Scene, stats: Stats | None, origin) -> None:
        with Timer(stats or Stats(), "upload"):
            surface = textures.layout(scene.materials, scene.material_index, scene.uvs,
                                      scene.corner_colors)
            self.raster.upload(scene.positions, scene.normals, scene.albedo_per_triangle(),
                               scene.reflectance_per_triangle(),
                               receiver=None if scene.receiver is None else scene.flag("receiver"),
                               origin=origin, surface=surface,
                               specular=scene.specular_per_triangle(),
                               shares=textures.view_shares(scene.materials,
                                                           scene.material_index),
                               hidden=scene.ray_hidden, alpha=scene.alpha_per_triangle(),
                               translucency=scene.translucency_per_triangle(),
                               alpha_maps=_alpha_maps(scene), normal_maps=_normal_maps(scene))
            if self.raster.surface is not None and stats is not None:
                stats.info["textures"] = self.raster.surface.info

    def lpv_bounds(self, scene: Scene, stats: Stats | None = None, geo: str | None = None):
        """The box the LPV covers (cascades.fit_bounds: far outliers left out; or the closed
        space around the camera where that is much smaller, cascades.enclosure_bounds), what
        it leaves out listed in the stats; cached per geometry and camera surroundings."""
        geo = geo or geometry_key(scene)
        if self._bounds is None or self._bounds.geometry != geo:
            self._bounds = Bounds(geo, *cascades.fit_bounds(scene))
        b = self._bounds
        lo, hi, outside, share = b.lo, b.hi, b.outside, b.outside_share
        around = self.surroundings(scene, geo, stats)
        if self._enclosure is None or self._enclosure[0] is not around:
            self._enclosure = (around, cascades.enclosure_bounds(scene, lo, hi, around))
        enclosed = self._enclosure[1]
        if enclosed is not None:
            lo, hi, outside, share = enclosed
        if stats is not None:
            stats.info["lpv_bounds"] = {"lo": lo.tolist(), "hi": hi.tolist(),
                                        "outside_triangles": outside,
                                        "outside_area_share": share,
                                        "enclosed": enclosed is not None}
            if outside and not any(s["stage"] == "lpv" and s["what"].endswith("surface area)")
                                   for s in stats.skipped):
                why = ("outside the closed space enclosing the camera (no light passes its walls): "
                       "outside the LPV, they get no GI" if enclosed is not None
                       else "far outliers: outside the LPV, they get no GI")
                stats.skip("lpv", f"{outside} triangles ({share:.2%} of the surface area)", why)
        return lo, hi

    def surroundings(self, scene: Scene, geo: str, stats: Stats | None = None):
        """cascades.Surroundings of the camera's eye (a SURROUND_PIXELS^2 cube map), None
        without a perspective camera; rendered again when the geometry changes or the eye
        moves more than a cell of the fitted box's grid from where it was rendered."""
        cam = scene.camera
        proj = None if cam is None else np.asarray(cam.projection, np.float64)
        if proj is None or abs(proj[3, 3]) > 0.5:  # none, or orthographic: no eye point
            return None
        eye, b = cam.position, self._bounds
        cell = float(np.max(b.hi - b.lo)) / max(scene.settings.grid_resolution - 2, 1)
        if (self._around is not None and self._around[0] == geo
                and np.max(np.abs(self._around[1].origin - eye)) <= cell):
            return self._around[1]
        self._send(scene, stats, 0.5 * (b.lo + b.hi))
        near = float(proj[2, 3] / (proj[2, 2] - 1.0))  # the camera's clip start
        near = near if np.isfinite(near) and near > 0 else 1e-6 * float(np.max(b.hi - b.lo))
        far = float(np.linalg.norm(np.maximum(np.abs(b.lo - eye), np.abs(b.hi - eye)))) * 1.01
        with Timer(stats or Stats(), "planner"):
            points, solid, missed, tol = self.raster.surroundings(eye, near, max(far, 2 * near),
                                                                  SURROUND_PIXELS)
        around = cascades.Surroundings(eye, points, solid, missed / (4.0 * np.pi), tol)
        self._around = (geo, around)
        return around

    def _small_enclosures(self, scene: Scene, lights: list, chain: list, geo: str,
                          stats: Stats) -> None:
        """List in the stats (skip "resolution", info "unresolved_enclosures") every point,
        spot or area light inside a closed space the cascade carrying it does not resolve
        (planner.enclosure_note), with the grid resolution that does. A light gets a
        SURROUND_PIXELS^2 cube map only with an occluder within planner.enclosure_reach;
        cached per geometry, light position and cell size."""
        lights = [li for li in lights if li.type != "SUN"]
        if not lights:
            return
        if self._light_spaces.get("geo") != geo:
            self._light_spaces = {"geo": geo}
        level = cascades.assign(chain, np.array([li.position for li in lights]))
        for light, c in zip(lights, level):
            grid = chain[c]
            key = (light.position.tobytes(), grid.cell_size, grid.resolution)
            if key not in self._light_spaces:
                note, reach = None, planner.enclosure_reach(grid.cell_size)
                if planner.occluders_around(scene, light.position, reach):
                    with Timer(stats, "planner"):
                        points, solid, missed, tol = self.raster.surroundings(
                            light.position, 1e-3 * grid.cell_size, 1.01 * reach,
                            SURROUND_PIXELS)
                    around = cascades.Surroundings(light.position, points, solid,
                                                   missed / (4.0 * np.pi), tol)
                    note = planner.enclosure_note(light, around, grid,
                                                  planner.cascade_label(int(c), grid),
                                                  max_grid_resolution())
                self._light_spaces[key] = note
            note = self._light_spaces[key]
            if note is not None:
                stats.skip("resolution", note["what"], note["reason"])
                stats.info.setdefault("unresolved_enclosures", []).append(
                    {k: v for k, v in note.items() if k != "reason"})

    def shadow_map(self, scene: Scene, light, bounds, resolution: int,
                   stats: Stats | None = None):
        """direct.render_shadow_map at the light's share of the shadow budget
        (shadows.resolutions: ``resolution`` for every light while all fit), cached per
        geometry, light and resolution, least recently used out past the budget: frames of
        an animation whose geometry and lights hold still (a camera move) reuse them."""
        from .render import direct

        geo = self._bounds.geometry if self._bounds is not None else geometry_key(scene)
        lkey = light_key(light)
        res = self._shadow_plan(scene, bounds, int(resolution), geo).get(lkey, int(resolution))
        key = (lkey, res, np.asarray(bounds, np.float64).tobytes())
        if self._shadows.tag != geo:
            self._shadows.clear(geo)
        shadow = self._shadows.get(key)
        if shadow is None:
            shadow = direct.render_shadow_map(self.raster, light, bounds, res)
            self._shadows.put(key, shadow)
        elif stats is not None:
            stats.skip("direct", f"shadow map of '{light.name}'", "unchanged: reused")
        if stats is not None:
            info = stats.info.setdefault("shadow_maps", {})
            info.update(budget_mib=self._shadows.budget / 2**20, evicted=self._shadows.evicted,
                        cached_mib=round(self._shadows.bytes / 2**20, 3),
                        cached=len(self._shadows.maps))
            if res < resolution:
                if not info.get("reduced"):
                    stats.skip("direct", f"{resolution}^2 shadow maps of some lights",
                               f"past the shadow budget ({self._shadows.budget / 2**20:.0f} "
                               "MiB): sized by their share of the light (info shadow_maps)")
                info.setdefault("reduced", {})[light.name] = res
        return shadow

    def _shadow_plan(self, scene: Scene, bounds, resolution: int, geo: str) -> dict:
        """light_key -> shadow resolution of every light (shadows.resolutions by its share of
        the irradiance on what the camera sees), memoised for the scene's lights and view."""
        from .render import shadows

        lights = scene.lights
        cam = scene.camera
        memo = (geo, resolution, np.asarray(bounds, np.float64).tobytes(),
                None if cam is None else np.r_[cam.view, cam.projection].tobytes(),
                _lights_digest(lights))
        if self._shadow_memo is not None and self._shadow_memo[0] == memo:
            return self._shadow_memo[1]
        views = [shadows.view_count(li) if li.power > 0 else 0 for li in lights]
        plan: dict = {}
        if resolution ** 2 * sum(views) * 4 > self._shadows.budget:  # else all at full size
            points = None if cam is None else self._focus(scene, Stats(), geo)[0]
            res = shadows.resolutions(shadows.frame_shares(lights, points), views, resolution,
                                      self._shadows.budget / 4)
            plan = {light_key(li): int(r) for li, r in zip(lights, res)}
        self._shadow_memo = (memo, plan)
        return plan

    def update(self, scene: Scene, stats: Stats | None = None,
               reproject: bool = False) -> LPVResult:
        """RSM -> injection -> propagation (-> bounces) -> combine for every light that
        contributes GI, on a chain of cascades (a single grid is a chain of one).

        ``reproject`` (interactive use): when only the camera moved and inner cascades moved by
        whole cells, their cached content is shifted instead of recomputed (no RSM, no
        propagation; light that enters from outside is missing), stats.info["refresh_pending"]
        is set, and the next update recomputes everything (the refresh fills in the rest)."""

        stats = stats or Stats()
        stats.dropped.update(scene.dropped)
        if scene.approximated:
            stats.info["approximated"] = list(scene.approximated)
        settings = scene.settings
        t0 = time.perf_counter()
        if scene.triangle_count == 0:
            stats.skip("lpv", "scene", "no geometry")
            stats.ms["lpv_update"] = 0.0
            return LPVResult(None, None, {}, stats)
        with Timer(stats, "change_tracking"):
            geo = geometry_key(scene)
        active = _active_lights(scene, stats)
        with Timer(stats, "change_tracking"):
            refl = reflectance_key(scene)
        srcs = sources.gi_sources(scene, refl, stats)  # the World, emissive materials
        lo, hi, chain = self._chain(scene, stats, geo, len(active) + len(srcs))
        if settings.angular == "dom":  # a clear error before the RSMs, not a MemoryError
            sweep.check_memory(chain[-1].resolution, len(chain) > 1)
        grid = chain[-1]
        with Timer(stats, "change_tracking"):
            content = content_key(scene, geo)
            key = scene_key(scene, chain, content=content)
            base = scene_key(scene, chain[-1:], content=content)  # inner cascades aside
        if key != self._cache_key and reproject and (active or srcs):
            shifted = self._reprojected(chain, base, active + srcs, stats)
            if shifted is not None:
                per_light, vpl_sample = shifted
                visibilities = [self._visibility(scene, g, stats) for g in chain]
                self._cache_key = None  # the next update is the refresh
                stats.info["refresh_pending"] = True
                return self._result(chain, per_light, vpl_sample, active + srcs,
                                    settings.intensity, visibilities, stats, 0, [], t0,
                                    {g: self.gaps(g) for g in chain})
        if key != self._cache_key:
            self._cache_key, self._lights, self._volumes = key, {}, {}
            self._cache_base, self._cache_chain = base, chain
            self._refl_key = None
        # GI reflectance (albedo x bleed) only changes what the lights' RSMs reflect: a light
        # is recomputed when its re-rendered RSM differs, i.e. when it sees a changed material.
        refl_changed = self._refl_key is not None and refl != self._refl_key
        self._refl_key = refl
        if not active and not srcs:
            if not scene.lights:
                stats.skip("lpv", "scene", "no lights")
            stats.ms["lpv_update"] = (time.perf_counter() - t0) * 1000.0
            return LPVResult(grid, None, {}, stats)
        self.upload(scene, stats, geo)
        backend = self.backend(settings, stats)
        iterations = propagation_steps(settings)
        visibilities = [self._visibility(scene, g, stats) for g in chain]
        run = _ChainRun(chain, visibilities, iterations, settings, backend, stats)
        per_light, vpl_sample = {}, {}
        vpl_count = 0
        for light in active:
            grids, sample, count = self._light(scene, light, chain, run, (lo, hi), refl_changed,
                                               stats)
            per_light[light.name], vpl_sample[light.name] = grids, sample
            vpl_count += count
        for src in srcs:  # no RSM: caster surfels lit by the source's direct light
            per_light[src.name] = self._source(scene, src, run, (lo, hi), stats)
            vpl_sample[src.name] = self._lights[src.name].sample
        self._small_enclosures(scene, active, chain, geo, stats)
        return self._result(chain, per_light, vpl_sample, active + srcs, settings.intensity,
                            visibilities, stats, vpl_count, run.iterations, t0,
                            {g: self.gaps(g) for g in chain})

    def _chain(self, scene: Scene, stats: Stats, geo: str, entries: int = 1):
        """The LPV box (lo, hi) and this update's cascade chain (finest first): placed around
        what the camera sees, held still within a cell, pruned by the planner; its resolution
        within the grid budget of ``entries`` lights and sources (budget_resolution)."""
        settings = scene.settings
        lo, hi = self.lpv_bounds(scene, stats, geo)
        focus, count = None, settings.cascades
        if settings.cascades > 1 and scene.camera is not None:
            focus, sky = self._focus(scene, stats, geo)
            if settings.cascades_auto:
                around = self._around[1] if self._around is not None else None
                space = None if around is None else around.size()
                last = self._cascade_count
                previous = last[1] if last is not None and last[0] == settings.cascades else None
                memo = (self._focus_cache.key, settings.cascades, lo.tobytes(), hi.tobytes(),
                        previous, space)
                if self._count_memo is None or self._count_memo[0] != memo:
                    eye = np.linalg.inv(np.asarray(scene.camera.view, np.float64))[:3, 3]
                    self._count_memo = (memo, planner.cascade_count(
                        settings.cascades, lo, hi, eye, focus, sky, previous, space))
                count, why = self._count_memo[1]
                self._cascade_count = (settings.cascades, count)
                stats.info["cascade_count"] = {"count": count, "why": why}
                if count < settings.cascades:
                    stats.skip("cascades", f"{settings.cascades - count} inner cascades", why)
        res = budget_resolution(settings, entries, count)
        if res < settings.grid_resolution:
            stats.info["grid_reduced"] = {"asked": settings.grid_resolution, "resolution": res,
                                          "entries": entries}
            stats.skip("cascades", f"{settings.grid_resolution}^3 cells",
                       f"{entries} lights and sources keep their grids: past the grid budget "
                       f"({GRID_BUDGET >> 20} MiB), {res}^3 cascades")
        chain = self._steady(cascades.place(lo, hi, res, count, scene.camera, focus))
        if len(chain) == 1 and count > 1:
            stats.skip("cascades", f"{count - 1} inner cascades",
                       "no camera to centre them on")
        with Timer(stats, "planner"):
            chain = self._plan_cascades(scene, chain, stats, geo)
        grid = chain[-1]
        stats.info["grid"] = {"origin": list(grid.origin), "cell_size": grid.cell_size,
                              "resolution": grid.resolution}
        if len(chain) > 1:
            stats.info["cascades"] = [{"origin": list(g.origin), "cell_size": g.cell_size}
                                      for g in chain]
        return lo, hi, chain

    def _light(self, scene: Scene, light, chain: list, run: _ChainRun, bounds,
               refl_changed: bool, stats: Stats):
        """(grids per cascade, VPL sample, VPLs injected) of one light: cached when nothing it
        depends on changed; after a material change, cached if its re-rendered RSM is the
        same; zeros without an RSM if the planner finds it reaches no caster."""
        res = self._rsm_plan(scene).get(light_key(light), scene.settings.rsm_resolution)
        if res < scene.settings.rsm_resolution:
            reduced = stats.info.setdefault("rsm_reduced", {})
            if not reduced:
                stats.skip("rsm", f"{scene.settings.rsm_resolution}^2 RSMs of some lights",
                           "past the RSM budget: sized by their share of the GI flux "
                           "(info rsm_reduced)")
            reduced[light.name] = res
        cached = self._cached(light, stats, report=not refl_changed, resolution=res)
        if cached is not None and not refl_changed:
            return cached[0], cached[1], 0
        with Timer(stats, "planner"):
            reach = [planner.light_reach(light, g, scene, planner.cascade_label(c, g))
                     for c, g in enumerate(chain)]
        planner.record(reach[-1], stats, "rsm")
        if not reach[-1].keep:  # reaches no caster at all: no RSM either
            return self._unlit(scene, light, chain, res,
                               (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)))
        planner.record(reach[:-1], stats, "injection")
        if light.type == "SUN" and len(chain) > 1:
            rsm, sample = self._sun_rsm(light, chain, [d.keep for d in reach], bounds,
                                        scene.settings, stats)
        else:
            rsm, sample = self._rsm(light, bounds, res, stats)
        facing = _facing_into(rsm, bounds, light, stats)
        if facing is not rsm:
            rsm, sample = facing, _vpl_sample(facing)
        if rsm.count == 0:  # it lights only sides facing out of the LPV box: no propagation
            return self._unlit(scene, light, chain, res, sample)
        entry = self._lights.get(light.name)
        if cached is not None and entry is not None and same_vpls(entry.flux, rsm.flux):
            stats.skip("injection", f"light '{light.name}'",
                       "materials changed, but none its RSM sees: grids reused")
            return cached[0], cached[1], 0
        totals = run.propagate(rsm.position, rsm.normal, rsm.flux, [d.keep for d in reach],
                               rsm.lift)
        if scene.settings.bounces > 1:
            totals = self._more_bounces(scene, run, totals)
        # the flux itself while the kept arrays fit in FLUX_KEPT (comparing it is cheaper than
        # hashing it), else its digest: 300 point lights' fluxes would hold 2.8 GB
        kept = sum(e.flux.nbytes for n, e in self._lights.items()
                   if n != light.name and isinstance(e.flux, np.ndarray))
        flux = rsm.flux if kept + rsm.flux.nbytes <= FLUX_KEPT else _digest(rsm.flux)
        self._lights[light.name] = LightGrids(light_key(light), totals, sample, flux, res)
        return totals, sample, rsm.count

    def _unlit(self, scene: Scene, light, chain: list, res: int, sample: tuple):
        """_light's result for a light with no VPL to propagate: zero grids, cached."""
        totals = [g.zeros(propagation.coefficients(scene.settings.angular)) for g in chain]
        self._lights[light.name] = LightGrids(light_key(light), totals, sample, None, res)
        return totals, sample, 0

    def _source(self, scene: Scene, src, run: _ChainRun, bounds, stats: Stats) -> list:
        """A sources.Source's grids per cascade (sources.propagate), cached like a light's
        while its source_key and the scene key hold."""
        entry = self._lights.get(src.name)
        if entry is not None and entry.key == src.source_key:
            stats.skip("sources", src.name, "unchanged since the last update: grids reused")
            return entry.grids
        totals = sources.propagate(self, scene, src, run, bounds, stats)
        empty = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
        self._lights[src.name] = LightGrids(src.source_key, totals, empty, None, 0)
        return totals

    @staticmethod
    def _result(chain, per_light, vpl_sample, active, intensity, visibilities, stats, vpl_count,
                iterations, t0, gaps=None) -> LPVResult:
        """Combine per-light grids (per cascade) into the LPVResult."""
        with Timer(stats, "combine"):
            levels = [combine(g, {n: v[c] for n, v in per_light.items()}, active,
                              intensity) for c, g in enumerate(chain)]
            whole = cascades.whole(chain, levels)[1:]
        stats.info["vpls"] = vpl_count
        stats.info["iterations"] = iterations
        stats.ms["lpv_update"] = (time.perf_counter() - t0) * 1000.0
        outer = {n: v[-1] for n, v in per_light.items()}
        return LPVResult(chain[-1], levels[-1], outer, stats, vpl_sample, visibilities[-1],
                         [(g, levels[c], visibilities[c]) for c, g in enumerate(chain[:-1])],
                         gaps, whole)

    def _reprojected(self, chain, base, active, stats: Stats):
        """(per-light grids, VPL samples) shifted by whole cells to ``chain`` when the last
        update differs only in where its inner cascades sat, else None."""
        last = self._cache_chain
        if (self._cache_key is None or base != self._cache_base or last is None
                or len(last) != len(chain) or last[-1] != chain[-1]):
            return None
        offsets = []
        for new, old in zip(chain, last):
            k = (new.origin_array - old.origin_array) / new.cell_size
            if (new.cell_size != old.cell_size or new.resolution != old.resolution
                    or np.max(np.abs(k - np.round(k))) > 1e-6):
                return None
            offsets.append(np.round(k).astype(int))
        entries = [self._lights.get(light.name) for light in active]
        if any(e is None or e.key != light_key(li) for e, li in zip(entries, active)):
            return None  # a light changed too: recompute
        with Timer(stats, "reprojection"):
            per_light = {li.name: [cascades.shift(v, off) for v, off in zip(e.grids, offsets)]
                         for e, li in zip(entries, active)}
        moved = [int(np.abs(o).max()) for o in offsets[:-1]]
        stats.skip("propagation", "all lights",
                   f"camera moved: cascade content shifted by {moved} cells, no RSM or "
                   "propagation; a refresh follows")
        return per_light, {li.name: e.sample for e, li in zip(entries, active)}

    def _steady(self, chain: list) -> list:
        """The chain with each finer cascade left where it was last update if it would move by
        at most one of its parent's cells (kept inside its parent): hysteresis, so that a camera
        moving back and forth over a snapping boundary does not make the cascades flicker
        (and a camera move within a cell does no LPV work)."""
        last, self._last_chain = self._last_chain, None
        if last is not None and len(last) == len(chain) and last[-1] == chain[-1]:
            steady = [chain[-1]]
            for new, old in zip(chain[-2::-1], last[-2::-1]):
                # one cell of its parent: placement snaps to those (cascades.place)
                moved = np.max(np.abs(new.origin_array - old.origin_array)) / steady[-1].cell_size
                pick = old if (new.cell_size == old.cell_size and moved <= 1.0 + 1e-9) else new
                # Nested in the (possibly kept) parent; parent bounds lie on this lattice.
                p_lo = steady[-1].origin_array
                p_hi = p_lo + steady[-1].cell_size * steady[-1].resolution \
                    - pick.cell_size * pick.resolution
                origin = np.clip(pick.origin_array, p_lo, p_hi)
                steady.append(Grid(tuple(float(v) for v in origin), pick.cell_size,
                                   pick.resolution))
            chain = steady[::-1]
        self._last_chain = chain
        return chain

    def _focus(self, scene: Scene, stats: Stats, geo: str) -> tuple[np.ndarray, float]:
        """(world positions the camera sees, share of its pixels that see no geometry), from a
        FOCUS_PIXELS^2 G-buffer (cascade count and placement), cached per geometry and
        camera."""
        key = (geo, np.asarray(scene.camera.view, np.float64).tobytes(),
               np.asarray(scene.camera.projection, np.float64).tobytes())
        if self._focus_cache is None or self._focus_cache.key != key:
            self.upload(scene, stats, geo)
            with Timer(stats, "planner"):
                w, h = scene.camera.resolution
                scale = FOCUS_PIXELS / max(w, h, 1)
                frame = self.raster.render(scene.camera.view, scene.camera.projection,
                                           max(1, round(w * scale)), max(1, round(h * scale)))
                points = frame.position[frame.covered].astype(np.float64)
                sky = 1.0 - float(np.mean(frame.covered)) if frame.covered.size else 1.0
            self._focus_cache = Focus(key, points, sky)
        return self._focus_cache.points, self._focus_cache.sky_share

    def _plan_cascades(self, scene: Scene, chain: list, stats: Stats, geo: str) -> list:
        """The chain without the cascades the planner finds no work for (cached per chain)."""
        if len(chain) == 1:
            return chain
        key = ("cascade_plan", tuple((g.origin, g.cell_size, g.resolution) for g in chain), geo)
        decisions = self._plans.get(key)
        if decisions is None:
            decisions = planner.cascade_plan(chain, scene)
            self._plans = {key: decisions}
        keep = planner.record(decisions, stats, "cascades")
        return [g for g, k in zip(chain, keep) if k]

    def _rsm(self, light, bounds, resolution: int, stats: Stats):
        """The light's RSM and a subsample of its VPLs (positions, flux) for debug views."""
        from .rsm import render_rsm

        with Timer(stats, "rsm"):
            rsm = render_rsm(self.raster, light, bounds, resolution)
        return rsm, _vpl_sample(rsm)

    def _rsm_plan(self, scene: Scene) -> dict:
        """light_key -> RSM resolution of the GI lights other than suns (shadows.resolutions
        within RSM_BUDGET texels by their share of the GI flux, shadows.gi_weight; empty while
        all fit at settings.rsm_resolution), memoised for the scene's lights."""
        from .render import shadows

        settings = scene.settings
        lights = [li for li in scene.lights if li.type != "SUN"
                  and not _no_gi_reason(li, settings.intensity)]
        memo = (settings.rsm_resolution, _lights_digest(lights))
        if self._rsm_memo is None or self._rsm_memo[0] != memo:
            views = [shadows.view_count(li) for li in lights]
            plan: dict = {}
            if settings.rsm_resolution ** 2 * sum(views) > shadows.RSM_BUDGET:
                w = np.array([shadows.gi_weight(li) for li in lights])
                res = shadows.resolutions(w / w.sum(), views, settings.rsm_resolution,
                                          shadows.RSM_BUDGET)
                plan = {light_key(li): int(r) for li, r in zip(lights, res)}
            self._rsm_memo = (memo, plan)
        return self._rsm_memo[1]

    def _sun_rsm(self, light, chain: list, reach: list, bounds, settings, stats: Stats):
        """A sun's VPLs with one RSM fitted to each cascade [KD10 sec. 4.1]: each cascade
        takes the VPLs of its own region (cascades.assign) from its own RSM, so the texels are
        as fine as its cells wherever it is the finest cascade, at the same RSM resolution.
        No RSM for an inner cascade the planner found the sun cannot reach (``reach[c]``)."""
        from .rsm import RSM, render_rsm

        parts, counts = [], []
        with Timer(stats, "rsm"):
            for c, g in enumerate(chain):
                if not reach[c]:
                    counts.append(0)
                    continue
                fit = None if c == len(chain) - 1 else g.bounds()
                part = render_rsm(self.raster, light, bounds, settings.rsm_resolution, fit)
                own = cascades.assign(chain, part.position) == c
                parts.append((part, own))
                counts.append(int(own.sum()))
        rsm = RSM(light, *(np.concatenate([getattr(p, f)[own] for p, own in parts])
                           for f in ("position", "normal", "flux", "area")),
                  sum(p.texels for p, _ in parts),
                  None if parts[0][0].lift is None
                  else np.concatenate([p.lift[own] for p, own in parts]))
        stats.info.setdefault("sun_rsm_per_cascade", {})[light.name] = counts
        return rsm, _vpl_sample(rsm)

    def clear_cache(self) -> None:
        """Forget cached grids and shadow maps, and the last view's cascade count and placement
        (their hysteresis, so that the next update's cascades are a new Engine's): the next
        update recomputes everything but the view's G-buffers, kept by geometry and camera."""
        self._cache_key, self._lights, self._volumes = None, {}, {}
        self._cascade_count = self._count_memo = self._last_chain = None
        self._shadows.clear()
        self.source_maps.reset(None)
        self._shadow_memo = self._rsm_memo = None
        self._cache_base = self._cache_chain = None

    def _visibility(self, scene: Scene, grid: Grid, stats: Stats | None):
        """occlusion()'s visibility, cached with the per-light grids (same scene key)."""
        key = (grid.origin, grid.cell_size)
        if key not in self._volumes:
            self._volumes[key] = Volume(*occlusion(scene, grid, stats))
        elif stats is not None:
            stats.skip("geometry_volume", f"grid {grid.cell_size:.4g} m", "unchanged: reused")
        return self._volumes[key].visibility

    def gaps(self, grid: Grid):
        """geometry_volume.cell_gaps of ``grid``'s occluders from the last update, or None."""
        entry = self._volumes.get((grid.origin, grid.cell_size))
        return None if entry is None else entry.gaps

    def _cached(self, light, stats: Stats, report: bool = True, resolution: int | None = None):
        """(grids per cascade, VPL sample) of ``light`` if nothing it depends on changed
        (materials aside: see update), its RSM ``resolution`` included when given."""
        entry = self._lights.get(light.name)
        if entry is None or entry.key != light_key(light) or (
                resolution is not None and entry.resolution != resolution):
            return None
        if report:
            stats.skip("rsm", f"light '{light.name}'",
                       "unchanged since the last update: its propagated grids are reused")
        return entry.grids, entry.sample

    def _more_bounces(self, scene: Scene, run: _ChainRun, first: list) -> list:
        """Add bounces 2..N [KD10 sec. 6]: every caster surfel reflects the light of the
        previous bounce (irradiance on each side, read from the cascades as a receiver reads
        them, cascades.reads, x area x GI reflectance) as new VPLs, injected and propagated like the RSM's. Each bounce carries
        at most the albedo's share of the last, so the series converges."""
        settings, stats, chain = scene.settings, run.stats, run.chain
        with Timer(stats, "bounces"):
            casters = np.nonzero(scene.flag("caster"))[0]
            pos, nrm, area, tri = geometry_volume.surfels(
                scene.positions[casters], 0.5 * chain[0].cell_size, with_index=True)
            refl = scene.reflectance_per_triangle()[casters][tri].astype(np.float64)
            if self.raster.surface is not None:  # the texture and corner colour at each surfel
                at = casters[tri]
                refl *= self.raster.surface.factor(
                    at, textures.barycentric(scene.positions[at], pos), gi=True)
            pos2 = np.concatenate([pos, pos])
            nrm2 = np.concatenate([nrm, -nrm])  # surfaces reflect on both sides
            area2 = np.concatenate([area, area])[:, None]
            refl2 = np.concatenate([refl, refl])
        total = [v.copy() for v in first]
        previous = first
        for _ in range(settings.bounces - 1):
            with Timer(stats, "bounces"):
                e = np.zeros((pos2.shape[0], 3))
                for r in cascades.chain_reads(chain, previous, cascades.whole(chain, previous),
                                              run.visibilities):
                    take = r.takes(pos2)
                    if take.any():
                        e[take] += run.backend.irradiance(
                            r.grid, r.values, lookup.sample_points(
                                r.grid, pos2[take], nrm2[take], self.gaps(r.grid)),
                            nrm2[take], offset_cells=0.0, angular=settings.angular,
                            visibility=r.visibility)
                flux = e * area2 * refl2
                keep = flux.max(axis=1) > 0
            if not keep.any():
                stats.skip("bounces", "further bounces", "no light reaches any caster")
                break
            bounce = run.propagate(pos2[keep], nrm2[keep], flux[keep])
            for c in range(len(chain)):
                total[c] += bounce[c]
            previous = bounce
        return total


class _ChainRun:
    """Injection and propagation of VPL sets through one update's cascade chain (finest
    first): each VPL goes to its cascade (cascades.assign), and the light leaving a cascade is
    handed on to the next coarser one [KD10 sec. 4.1]. A single grid is a chain of one."""

    def __init__(self, chain: list, visibilities: list, iterations: int, settings, backend,
                 stats: Stats):
        self.chain, self.visibilities = chain, visibilities
        self.iterations_cap, self.settings = iterations, settings
        self.backend, self.stats = backend, stats
        self.iterations: list = []  # steps run per propagation ("sweep": solved exactly)

    def propagate(self, positions, normals, flux, reach: list | None = None,
                  lift=None) -> list:
        """Propagated grids (one per cascade) of the VPLs (N, 3) x3; ``reach[c]`` False: the
        planner found that these VPLs cannot land in cascade c. ``lift`` (rsm.RSM.lift): each
        VPL injected from ``lift`` x the injection offset further on (its surface's side)."""
        chain, stats, be, settings = self.chain, self.stats, self.backend, self.settings
        last = len(chain) - 1
        n = positions.shape[0]
        level = cascades.assign(chain, positions) if last else np.zeros(n, np.int64)
        totals = [None] * len(chain)  # zeros only where nothing lands (filled at the end)
        idx = np.arange(n)
        carry = None
        for c, g in enumerate(chain):
            sel = idx[level[idx] == c]
            if carry is None and (sel.size == 0 or (reach is not None and not reach[c])):
                continue  # nothing lands in this cascade and nothing comes in from inside
            if sel.size == n:  # all of them, in order (one cascade): no copies
                sel = slice(None)
            with Timer(stats, "injection"):
                at = positions if lift is None else positions + lift * (
                    INJECTION_OFFSET * g.cell_size)
                injected = _inject(be, g, at, normals, flux, self.visibilities[c], sel)
                passing = None
                if carry is not None:  # light leaving the finer cascade: no surface's
                    passing = g.zeros()
                    cascades.hand_on(chain[c - 1], carry, g, passing)
            with Timer(stats, "propagation"):
                kw = {}
                if settings.angular == "dom":
                    kw["launch"] = True  # VPLs start from their surfaces (ordinates.launch)
                if passing is not None:
                    kw["passing"] = passing
                prop = be.propagate(injected, self.iterations_cap,
                                    angular=settings.angular,
                                    visibility=self.visibilities[c],
                                    occlude_first_step=True,
                                    capture_outflow=c < last, **kw)
                be.discard(injected)
            self.iterations.append("sweep" if getattr(prop, "swept", False)
                                   else prop.iterations)
            with Timer(stats, "combine"):  # a copy where the backend may hold on to it
                totals[c] = (np.asarray(prop.values, np.float32)
                             if getattr(be, "fresh_results", False)
                             else np.array(prop.values, np.float32))
            carry = prop.outflow
        coefficients = propagation.coefficients(settings.angular)
        return [g.zeros(coefficients) if t is None else t for g, t in zip(chain, totals)]


def _facing_into(rsm, bounds, light, stats: Stats):
    """The RSM without the VPLs on sides facing out of the LPV box (cascades.facing_into:
    their light meets nothing, a closed room's sunlit roof and outer walls), how many were
    left out in the stats (info "vpls_facing_out"; a skip when that is all of them)."""
    keep = cascades.facing_into(rsm.position, rsm.normal, *bounds)
    if keep.all():
        return rsm
    out = int(keep.size - keep.sum())
    stats.info.setdefault("vpls_facing_out", {})[light.name] = out
    if not keep.any():
        stats.skip("propagation", f"light '{light.name}'",
                   f"all its {out} VPLs lie on sides facing out of the LPV box (the outside "
                   "of the closed space around the camera): its light meets nothing in it")
    return replace(rsm, position=rsm.position[keep], normal=rsm.normal[keep],
                   flux=rsm.flux[keep], area=rsm.area[keep],
                   lift=None if rsm.lift is None else rsm.lift[keep])


def _vpl_sample(rsm) -> tuple[np.ndarray, np.ndarray]:
    """A subsample of an RSM's VPLs (positions, flux; at most ~VPL_SAMPLE) for debug views."""
    keep = slice(None, None, max(1, rsm.count // VPL_SAMPLE))
    return rsm.position[keep].astype(np.float32), rsm.flux[keep].astype(np.float32)


def _digest(*parts) -> str:
    """blake2b digest (hex) of arrays (their bytes) and strings, in order."""
    h = hashlib.blake2b(digest_size=16)
    for part in parts:
        h.update(part.encode() if isinstance(part, str)
                 else np.ascontiguousarray(part).tobytes())
    return h.hexdigest()


def geometry_key(scene: Scene) -> str:
    """Digest of the geometry, the caster / receiver / occluder flags (planner decisions), the
    ray visibility and the coverage (what the shadow and sky maps hold)."""
    maps = scene.alpha_maps()
    extra = tuple(a for a in (scene.ray_hidden, scene.alpha_per_triangle(),
                              None if maps is None else maps[0]) if a is not None)
    extra += tuple(m.alpha_texture.digest for m in scene.materials
                   if m.alpha_texture is not None)
    return _digest(scene.positions, scene.flag("caster"), scene.flag("occluder"),
                   scene.flag("receiver"), *extra)


def reflectance_key(scene: Scene) -> str:
    """Digest of the per-triangle GI reflectance (albedo x bleed colour and intensity) and of
    what multiplies it per point: the textures' digests and modes, UVs and corner colours."""
    lay = textures.layout(scene.materials, scene.material_index, scene.uvs,
                          scene.corner_colors)
    glossy = scene.specular_per_triangle()  # the mirror VPLs' reflectance (None: none)
    extra = () if glossy is None else (glossy,)
    if lay is None:
        return _digest(scene.reflectance_per_triangle(), *extra)
    modes = repr([(t.interpolation, t.extension) for t in lay.textures] + lay.digests)
    return _digest(scene.reflectance_per_triangle(), modes, lay.gi_texture, lay.gi_corners,
                   "" if lay.uvs is None else lay.uvs,
                   "" if lay.corner_colors is None else lay.corner_colors, *extra)


def same_vpls(flux, other) -> bool:
    """Whether two RSMs of an unchanged light in unchanged geometry inject the same light
    (Engine._light: the scene key holds both, so their positions and normals are the same):
    equal VPL flux arrays. The cache keeps the last RSM's flux array itself (it is made anew
    each update, never written after) instead of a digest: hashing it cost 1-2 ms of every
    update, the comparison is needed only after a material edit."""
    if isinstance(flux, str):  # a digest (FLUX_KEPT)
        return flux == _digest(other)
    return flux is not None and flux.shape == other.shape and bool(np.array_equal(flux, other))


# Settings the propagated grids do not depend on: the global intensity only re-combines; the
# others are read by the render (deferred.py) alone.
RENDER_ONLY = frozenset({"intensity", "antialias", "shadow_resolution", "contact_light"})


def content_key(scene: Scene, geo: str | None = None) -> str:
    """Digest of what every light's propagated grids depend on besides their placement:
    geometry and flags, normals, areas, the settings (not the global intensity, which only
    re-combines) and, with bounces > 1, the GI reflectance (later bounces reflect off every
    surface; one bounce's reflectance is tracked per light through its RSM, Engine._light)."""
    areas_repr = repr([(a.type, np.asarray(a.matrix).tobytes(), a.falloff, a.intensity)
                       for a in scene.areas])
    settings = {k: v for k, v in scene.settings.as_dict().items() if k not in RENDER_ONLY}
    bounce = reflectance_key(scene) if scene.settings.bounces > 1 else ""
    return _digest(geo or geometry_key(scene), scene.normals, bounce, areas_repr,
                   repr(sorted(settings.items())))


def scene_key(scene: Scene, chain, geo: str | None = None, content: str | None = None) -> str:
    """Digest of everything a light's propagated grid depends on besides the light itself:
    content_key (pass ``content`` to reuse it) and the grid placement."""
    return _digest(content or content_key(scene, geo),
                   repr([(g.origin, g.cell_size, g.resolution) for g in chain]))


def light_key(light) -> tuple:
    """What a light's propagated grid depends on (not gi_intensity / gi_color: combine only);
    a sources.Source's own key."""
    if isinstance(light, sources.Source):
        return light.source_key
    return (light.type, np.asarray(light.matrix, np.float64).tobytes(),
            np.asarray(light.color, np.float64).tobytes(), float(light.power),
            float(light.spot_size), float(light.spot_blend), tuple(light.size),
            bool(light.cast_shadow), float(light.radius), bool(light.soft_falloff))


_LIGHT_SCALARS = operator.attrgetter("type", "power", "spot_size", "spot_blend", "size",
                                     "cast_shadow", "radius", "soft_falloff", "gi_intensity")


def _lights_digest(lights) -> list:
    """Every light parameter light_key reads and the GI weights, in order (shadow and RSM
    plans compare it for each light's map of every render sample: ~2 us a light)."""
    return [(_LIGHT_SCALARS(li), np.asarray(li.matrix).tobytes(), np.asarray(li.color).tobytes(),
             np.asarray(getattr(li, "gi_color", 0.0)).tobytes()) for li in lights]


def _alpha_maps(scene: Scene):
    """(layer, UVs, maps, keys) of the scene's per-point coverage for Rasterizer.upload, or
    None."""
    maps = scene.alpha_maps()
    return None if maps is None else (maps[0], scene.uvs, maps[1], maps[2])


def _normal_maps(scene: Scene):
    """(layer, Strength, UVs, tangents, maps, keys) of the scene's normal maps for
    Rasterizer.upload, or None."""
    maps = scene.normal_maps()
    return None if maps is None else (maps[0], maps[1], scene.uvs, scene.tangents, *maps[2:])


def _inject(backend, grid: Grid, positions, normals, flux, visibility, sel=slice(None)):
    """The backend's injection (occlusion-aware splat when there are occluders) of the VPL
    rows ``sel`` (a slice, or an index array the numpy backend reads in place: three
    gathered copies cost ~1.3 ms per 3 x 32^3 Cornell box update)."""
    kw = {} if visibility is None else {"visibility": visibility}
    if isinstance(sel, slice):
        return backend.inject(grid, positions[sel], normals[sel], flux[sel], **kw)
    if backend is NUMPY_BACKEND:
        return backend.inject(grid, positions, normals, flux, index=sel, **kw)
    return backend.inject(grid, *(np.take(a, sel, axis=0) for a in (positions, normals, flux)),
                          **kw)


INJECTION_OFFSET = 0.5  # cells: injection.inject's offset along the VPL normal
FOCUS_PIXELS = 64  # longest side of the G-buffer that finds what the camera sees
SURROUND_PIXELS = 32  # cube map side of what the camera's eye sees all around (surroundings)
VPL_SAMPLE = 4096  # VPLs per light kept in LPVResult.vpls for debug views
FLUX_KEPT = 256 * 2**20  # bytes of RSM flux arrays kept for same_vpls (else digests)
# Bytes of the propagated grids kept per light and source (Engine._lights, 108 bytes a cell):
# 300 lights at three 16^3 cascades kept 380 MiB; 512 MiB (the shadow cache's budget) holds 50
# lights at three 32^3 cascades (10.1 MiB each), 300 at one 25^3 cascade or three 17^3.
GRID_BUDGET = 512 * 2**20
MIN_BUDGET_RESOLUTION = 8  # cells per side no budget goes below (8^3: 1.5-2.5x the error)


class NumpyBackend:
    """The reference backend: the numpy functions themselves (see Engine.backend)."""

    name = "numpy"
    fresh_results = True  # propagate returns new arrays, never kept: no copy needed

    @staticmethod
    def inject(*args, **kwargs):
        return injection.inject(*args, **kwargs)

    @staticmethod
    def propagate(*args, **kwargs):
        return propagation.propagate(*args, **kwargs)

    @staticmethod
    def irradiance(*args, **kwargs):
        return lookup.irradiance(*args, **kwargs)

    @staticmethod
    def discard(obj) -> None:
        pass


NUMPY_BACKEND = NumpyBackend()


def light_weight(light) -> np.ndarray:
    """(3, 1) float32 per-colour GI weight of a light: gi_intensity x gi_color."""
    tint = getattr(light, "gi_color", None)
    tint = np.ones(3) if tint is None else tint
    return np.float32(light.gi_intensity) * np.asarray(tint, np.float32).reshape(3, 1)


def combine(grid: Grid, per_light: dict, lights, intensity: float) -> np.ndarray:
    """The LPV: sum of per-light propagated grids x light weight, x global intensity.
    Propagation is linear, so art-direction changes (GI intensity, tint, global intensity)
    re-combine cached grids without recomputing them."""
    values = [v for v in per_light.values() if v is not None]
    k = values[0].shape[-1] if values else 4
    held = [light for light in lights if per_light.get(light.name) is not None]
    if not held:
        return grid.zeros(k)
    combined = np.empty(grid.shape(k), np.float32)
    flat = combined.reshape(-1, 3 * k)  # colour weights broadcast along the last axis (fast)
    scratch = None
    for n, light in enumerate(held):
        values = per_light[light.name].reshape(flat.shape)
        w = light_weight(light)[:, 0] * np.float32(intensity)
        # the first light written straight into the result (no zero fill, no scratch pass)
        out = flat if n == 0 else (scratch if scratch is not None else np.empty_like(flat))
        if w[0] == w[1] == w[2]:  # an untinted light: one scalar (3x faster than per colour)
            np.multiply(values, w[0], out=out)
        else:
            np.multiply(values, np.repeat(w, k), out=out)
        if n:
            scratch = out
            flat += scratch
    return combined


def occlusion(scene: Scene, grid: Grid, stats: Stats | None = None):
    """(visibility, gaps): the (6, R, R, R) factors for what each cell sends towards
    propagation.AXES[i] (or None), and the occluders' geometry_volume.cell_gaps (or None).

    The one place where every propagation visibility term is combined (multiplied): clip
    areas (areas.clip_visibility) and the geometry volume of the occluders."""
    visibility = gaps = None
    if areas.has_clip(scene.areas):
        visibility = areas.clip_visibility(grid, scene.areas)
        if stats is not None:
            stats.info["clip_areas"] = sum(a.type == "CLIP" for a in scene.areas)
    if scene.settings.occlusion:
        need = planner.occlusion_needed(scene, grid, f"the grid (cell {grid.cell_size:.4g} m)")
        if not need.keep:
            planner.record(need, stats, "occlusion")
        else:
            t0 = time.perf_counter()
            occluders = scene.flag("occluder")
            gv, gaps = geometry_volume.occluder_volume(grid, scene.positions[occluders])
            visibility = gv if visibility is None else visibility * gv
            if stats is not None:
                stats.add_ms("geometry_volume", time.perf_counter() - t0)
    return visibility, gaps


def propagation_steps(settings) -> int:
    """The step cap a propagation gets: ``settings.iterations`` for "sh" (0: automatic);
    "dom" always solves the limit of infinitely many steps (sweep.py) and ignores the
    setting, its cap (auto_iterations) only bounds a stepping backend's early stop (GL)."""
    if settings.angular == "dom" or not settings.iterations:
        return auto_iterations(settings.grid_resolution, settings.angular)
    return settings.iterations


def auto_iterations(resolution: int, angular: str = "dom") -> int:
    """Default cap on propagation steps.

    "sh": KD10 runs 8 steps on a 32^3 cascade (resolution / 4): its diffusive transport keeps
    counting the same light near its source, so more steps only add error. "dom": light moves
    up to one cell per step and leaves the grid or is absorbed by occluders, so a stepping
    backend iterates until a step carries < 1e-3 of the injected flux, capped at 3 grid widths
    (a light path that crosses the grid diagonally and back).
    """
    if angular == "dom":
        return 3 * resolution
    return max(1, round(resolution / 4))


def budget_resolution(settings, entries: int, cascades: int) -> int:
    """The cascades' resolution: ``settings.grid_resolution`` while the propagated grids that
    ``entries`` lights and sources keep for incremental updates (``cascades`` sets each, float32
    coefficients x 3 colours per cell) fit in GRID_BUDGET, else the largest that fits, at
    least MIN_BUDGET_RESOLUTION."""
    r = settings.grid_resolution
    per_cell = 4 * 3 * propagation.coefficients(settings.angular)
    sets = max(int(entries), 0) * max(int(cascades), 1)
    if sets == 0 or sets * per_cell * r**3 <= GRID_BUDGET:
        return r
    fit = int(np.floor((GRID_BUDGET / (sets * per_cell)) ** (1.0 / 3.0) + 1e-9))
    return max(min(fit, r), min(MIN_BUDGET_RESOLUTION, r))


def _active_lights(scene: Scene, stats: Stats) -> list:
    """The lights that contribute GI; every other one is listed in the stats with why."""
    active = []
    for light in scene.lights:
        reason = _no_gi_reason(light, scene.settings.intensity)
        if reason:
            stats.skip("rsm", f"light '{light.name}'", reason)
        else:
            active.append(light)
    return active


def _no_gi_reason(light, global_intensity: float) -> str:
    """Why a light contributes no GI (empty string: it does)."""
    if global_intensity == 0:
        return "global GI intensity is 0"
    if light.gi_intensity == 0:
        return "GI intensity is 0"
    tint = getattr(light, "gi_color", None)
    if tint is not None and float(np.max(np.abs(np.asarray(tint)))) <= 0:
        return "GI colour is black"
    if light.power <= 0:
        return "power is 0"
    if float(np.max(np.asarray(light.color))) <= 0:
        return "colour is black"
    return ""
