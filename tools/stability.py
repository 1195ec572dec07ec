"""Stability suite: stiff and extreme scenes through the real engine, measured, not just passed.

Each ``case_*`` function runs the core engine (``Engine.update`` + ``deferred.render`` at the
engine's default settings: the "dom" transport solved by the sweep, on the CPU backend, its
compiled kernels included) on numpy-built scenes and returns a *figure*: a dict with a title, what the invariant
answer is, and one row per variant with

- ``nonfinite``: NaN/Inf values in the LPV grid and the rendered passes (before the renderer's
  own clean-up, which counts them in ``stats.dropped``);
- ``energy_growth``: the largest flux(after) / flux(before) over the steps of every
  propagation the engine ran (recorded by wrapping ``propagation.propagate``, re-stepped by
  energy_balance; must never exceed 1), and ``energy_balance``: the largest
  |flux the engine's propagation returned / flux its steps carry - 1| (0 up to rounding);
- ``deviation``: the relative L1 deviation, sum |a - b| / sum |b|, of the Diffuse Indirect pass
  from the case's invariant answer (``deviation_direct`` the same for Diffuse Direct);
- ``time_s``: wall time of the update and render.

``run_suite(profile)`` runs them all ("test": tiny sizes for the unit tests; "report": the
sizes of the report). The report (lpv_addon/report.py) plots the figures; the tests
(tests/test_stability.py) assert the invariants. Nothing here imports bpy or matplotlib.
"""

from __future__ import annotations

import contextlib
import dataclasses
import inspect
import math
import time
from dataclasses import dataclass, field

import numpy as np

from lpv_core import engine, propagation, sh
from lpv_core.propagation import kd10, ordinates, quadrature
from lpv_core.propagation import sweep as transport_sweep
from lpv_core.render import deferred
from lpv_core.scene import Camera, GISettings, Light, Material, Scene, make_scene
from tools import core_scenes as demo
from tools import dom_steps

# Tolerances the tests assert (and the report draws). In exact arithmetic the engine is
# covariant under scaling (with power x scale^2) and translation, and linear in light power and
# (one bounce) in albedo: the grid is fitted to the scene's bounds, the rasteriser works
# relative to the scene centre, and every threshold (early stop, clamps) is relative or at 0.
# What remains is float32 rounding, ~6e-8 relative per operation through ~1e2 operations per
# value: 1e-5 with margin for the linear cases; 1e-4 for the geometric ones, whose positions
# also pass through float32 rasterisation. Diffuse Direct may additionally flip a shadow-map
# depth test at a shadow edge: 2e-3 is about two pixels of a 32x32 image. Energy growth per
# step: <= 1 + 1e-5 (float32 sums of up to ~1e4 terms).
TOLERANCES = {"scale": 1e-4, "translation": 1e-4, "power": 1e-5, "albedo": 1e-5,
              "direct": 2e-3, "energy": 1e-5}

PROFILES = {
    "test": {
        "resolution": (32, 32), "grid": 8, "rsm": 32, "shadow": 128,
        "scales": (1e-3, 1e-1, 1.0, 1e2, 1e4),
        "offsets": (0.0, 1e3, 1e5, 1e6),
        "powers": (1e-6, 1e-2, 300.0, 1e5, 1e9),
        "wall_cells": (0.05, 0.5, 1.0, 2.0),
        "crate_cells": (0.5, 1.0, 2.0),
        "albedos": (0.0, 0.5, 1.0),
        "grids": (4, 8, 16, 32),
        "trace_grid": 4, "trace_steps": 1000,
        "f16_powers": (1e-6, 1.0, 300.0, 1e9),
    },
    "report": {
        "resolution": (64, 64), "grid": 16, "rsm": 64, "shadow": 256,
        "scales": (1e-3, 1e-2, 1e-1, 1.0, 10.0, 1e2, 1e3, 1e4),
        "offsets": (0.0, 1e2, 1e3, 1e4, 1e5, 1e6),
        "powers": (1e-6, 1e-3, 1.0, 300.0, 1e3, 1e6, 1e9),
        "wall_cells": (0.05, 0.25, 0.5, 1.0, 2.0, 4.0),
        "crate_cells": (0.5, 1.0, 2.0, 4.0),
        "albedos": (0.0, 0.25, 0.5, 0.8, 1.0),
        "grids": (4, 8, 16, 32, 64, 128),
        "trace_grid": 16, "trace_steps": 1000,
        "f16_powers": (1e-6, 1e-3, 1.0, 300.0, 1e3, 1e6, 1e9),
    },
}


# ---------------------------------------------------------------------------------------------
# Running the engine with measurements
# ---------------------------------------------------------------------------------------------


@dataclass
class Run:
    """One engine update + render, with what the stability figures need."""

    passes: dict
    others: list  # passes rendered from the extra cameras
    result: engine.LPVResult
    seconds: float
    nonfinite: int
    balances: list = field(default_factory=list)  # energy_balance of each propagation
    injected: np.ndarray | None = None  # the input of the first propagation chain

    @property
    def energy_growth(self) -> float:
        """max flux(out) / flux(in) over every propagation's steps (0.0 when none ran)."""
        return max((b["growth"] for b in self.balances), default=0.0)

    @property
    def energy_balance(self) -> float:
        """max |returned flux / the steps' flux - 1| over the propagations (values and
        outflow; 0.0 when none ran)."""
        return max((abs(b[k] - 1.0) for b in self.balances for k in ("values", "outflow")
                    if k in b and b["injected"] > FLUX_FLOOR), default=0.0)

    def indirect(self, which: int = -1) -> np.ndarray:
        p = self.passes if which < 0 else self.others[which]
        return p["Diffuse Indirect"][..., :3].astype(np.float64)

    def direct(self, which: int = -1) -> np.ndarray:
        p = self.passes if which < 0 else self.others[which]
        return p["Diffuse Direct"][..., :3].astype(np.float64)


# Fluxes below this (W) are left out of growth ratios: there the grid's float32 values are
# subnormal (< 1.2e-38), rounding is absolute, and a ratio of two such sums means nothing.
FLUX_FLOOR = 1e-30
# The reference steps of energy_balance stop once a step carries less than this share of the
# injected flux: the tail left out is then below it times the steps a path can still take.
STEPS_FLOOR = 1e-9
# energy_balance re-steps in numpy: grids above this many cells per axis are left unchecked
# (64^3: ~1 GB per step's arrays; the report's largest grids), counted in the log.
BALANCE_MAX_RESOLUTION = 32


def growth(steps) -> float:
    """max flux(out) / flux(in) over (flux in, flux out) pairs above FLUX_FLOOR (0.0 if none)."""
    ratios = [b / a for a, b in steps if a > FLUX_FLOOR]
    return float(max(ratios)) if ratios else 0.0


def energy_balance(injected: np.ndarray, result, visibility: np.ndarray | None = None,
                   occlude_first_step: bool = False, passing: np.ndarray | None = None,
                   max_steps: int | None = None) -> dict:
    """The energy balance of one discrete-ordinates propagation (angular="dom") the engine ran.

    Transport moves flux: a step's arrivals, those that leave the grid (the padded layout's
    shell) counted too, carry at most the flux the step started from (equal in free space;
    less where face transmittances absorb). The propagated grid holds the injected light
    itself (its moments, ordinates.add_emission_band2) plus every step's arrivals inside the
    grid, folded to SH, and the fold keeps band 0's flux (flux(fold(x)) = sum x:
    Y00 sqrt(4 pi) = 1). So, with Phi_0 the injected flux (handed-on light included) and Phi_k
    the flux arriving at step k (the launch, ordinates.first_arrivals, then numpy's
    ordinates.advance, until a step carries < STEPS_FLOOR of Phi_0):

    - ``growth`` = max_k Phi_k(everywhere) / Phi_(k-1)(inside): <= 1;
    - ``values`` = flux(result.values) / (Phi_0 + sum_k Phi_k(inside)): 1 (the sweep is the
      limit of the steps);
    - ``outflow`` = flux(result.outflow) / sum_k Phi_k(shell), when there is an outflow: 1.

    A transport that gains 1 % per step fails the first, one that gains 1 % anywhere between
    the steps and the lookup's grid (the sweep, the fold, the hand-on) the others."""
    r = injected.shape[0]
    offvis = quadrature.offset_visibilities(visibility)
    cur, total = ordinates.first_arrivals(injected, visibility, occlude_first_step, passing)
    phi0 = float(propagation.flux(total).sum(dtype=np.float64))
    table = ordinates.factors(r, offvis)
    steps, inside, shell = [], 0.0, 0.0
    before = phi0
    for _ in range(max_steps or 40 * r):
        arrived = float(cur.sum(dtype=np.float64))
        ordinates.take_shell(cur, r)
        here = float(cur.sum(dtype=np.float64))
        steps.append((before, arrived))
        inside += here
        shell += arrived - here
        if here <= STEPS_FLOOR * phi0:
            break
        before = here
        cur = ordinates.advance(cur, table)
    else:
        raise RuntimeError(f"energy_balance: flux left after {len(steps)} steps")
    got = float(propagation.flux(result.values).sum(dtype=np.float64))
    held = phi0 + inside
    out = {"injected": phi0, "growth": growth(steps), "steps": len(steps),
           "values": got / held if held > FLUX_FLOOR else (0.0 if got == 0 else math.inf)}
    if result.outflow is not None:
        left = float(propagation.flux(result.outflow).sum(dtype=np.float64))
        out["outflow"] = left / shell if shell > FLUX_FLOOR else (0.0 if left == 0 else math.inf)
    return out


@contextlib.contextmanager
def record_propagations():
    """Wrap ``propagation.propagate`` (the numpy backend's propagation: the engine's CPU path,
    compiled kernels included) to log the energy_balance of every call, and keep the first
    call's input (the injected grid). Yields the log dict {"balances": [...], "injected": ...}.
    Refuses a transport other than "dom" (the default; the suite measures it)."""
    log: dict = {"balances": [], "injected": None, "unchecked": 0}
    original = propagation.propagate
    signature = inspect.signature(original)

    def wrapped(*args, **kwargs):
        out = original(*args, **kwargs)
        a = signature.bind(*args, **kwargs)
        a.apply_defaults()
        a = a.arguments
        if a["angular"] != "dom":
            raise ValueError(f"record_propagations measures angular='dom', not {a['angular']!r}")
        if not a["launch"]:
            raise ValueError("record_propagations measures the engine's launched propagation")
        if log["injected"] is None:
            log["injected"] = np.array(a["injected"], copy=True)
        if a["injected"].shape[0] > BALANCE_MAX_RESOLUTION:
            log["unchecked"] += 1
            return out
        log["balances"].append(energy_balance(a["injected"], out, a["visibility"],
                                              a["occlude_first_step"], a["passing"]))
        return out

    propagation.propagate = wrapped
    try:
        yield log
    finally:
        propagation.propagate = original


def _nonfinite(*arrays) -> int:
    return int(sum(int((~np.isfinite(a)).sum()) for a in arrays if a is not None))


class Runner:
    """Shares one rasteriser (GL context) across runs; a fresh Engine per run (no caching)."""

    def __init__(self, profile: str = "test", raster=None):
        if profile not in PROFILES:
            raise ValueError(f"profile must be one of {sorted(PROFILES)}, not {profile!r}")
        self.name = profile
        self.p = PROFILES[profile]
        self._raster = raster

    @property
    def raster(self):
        if self._raster is None:
            from lpv_core.render.raster import Rasterizer

            self._raster = Rasterizer()
        return self._raster

    def settings(self, **kw) -> GISettings:
        """The engine's defaults at the profile's sizes; a key GISettings lacks raises.
        The CPU backend (backend "numpy": the numpy reference with the compiled kernels the
        engine runs on the CPU): its propagations are the ones record_propagations() sees.
        One sample per pixel: the suite checks the LPV's invariance, not the rasteriser's
        coverage ties (a sub-pixel sample exactly on a scaled edge can fall either way)."""
        kw = {"grid_resolution": self.p["grid"], "rsm_resolution": self.p["rsm"],
              "shadow_resolution": self.p["shadow"], "backend": "numpy", "antialias": 1, **kw}
        return GISettings().updated(**kw)

    def run(self, scene: Scene, cameras: list[Camera] | None = None) -> Run:
        """Update + render from ``scene.camera`` (and each of ``cameras``)."""
        eng = engine.Engine(raster=self.raster)
        stats = engine.Stats()
        with record_propagations() as log:
            t0 = time.perf_counter()
            result = eng.update(scene, stats)
            passes = deferred.render(eng, scene, result, stats)
            seconds = time.perf_counter() - t0
        others = []
        for cam in cameras or []:
            view = dataclasses.replace(scene, camera=cam)
            others.append(deferred.render(eng, view, result, engine.Stats()))
        bad = sum(v for k, v in stats.dropped.items() if k.startswith("nonfinite_pixels"))
        bad += _nonfinite(result.values)
        return Run(passes, others, result, seconds, bad, log["balances"], log["injected"])


def rel_dev(a: np.ndarray, b: np.ndarray) -> float:
    """sum |a - b| / sum |b|; 0 when both are zero, inf when only ``b`` is."""
    a = np.nan_to_num(np.asarray(a, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    b = np.asarray(b, np.float64)
    num = float(np.abs(a - b).sum())
    den = float(np.abs(b).sum())
    if den == 0:
        return 0.0 if num == 0 else math.inf
    return num / den


def _row(label, x, run: Run, deviation: float, deviation_direct: float | None = None,
         **extra) -> dict:
    return {"label": str(label), "x": x, "nonfinite": run.nonfinite,
            "energy_growth": run.energy_growth, "energy_balance": run.energy_balance,
            "deviation": float(deviation),
            "deviation_direct": None if deviation_direct is None else float(deviation_direct),
            "time_s": run.seconds, "propagations": len(run.balances), **extra}


def _figure(name, title, x_label, invariant, rows, x_log=True, **extra) -> dict:
    return {"name": name, "title": title, "x_label": x_label, "x_log": x_log,
            "invariant": invariant, "rows": rows, **extra}


# ---------------------------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------------------------


def _cornell(r: Runner, **kw) -> Scene:
    settings = kw.pop("settings", None) or r.settings()
    return demo.cornell_box("SPOT", r.p["resolution"], settings, **kw)


def two_rooms(r: Runner, thickness: float, centre: float = 0.0, power: float = 100.0,
              settings: GISettings | None = None) -> tuple[Scene, Camera]:
    """Two 2 m rooms side by side (x in [-2, 2]) split by a wall ``thickness`` m thick at
    x = ``centre``; a point light in the left room. Returns the scene (its camera, at the left
    room's far end, looks at the wall) and a camera looking at the wall from the right room
    (which only leaked light reaches).
    """
    lo, hi = (-2.0, -1.0, 0.0), (2.0, 1.0, 2.0)
    tris = [demo.box_triangles(lo, hi, inward=True)]
    a, b = centre - thickness / 2, centre + thickness / 2
    tris.append(demo.quad((a, -1, 0), (a, -1, 2), (a, 1, 2), (a, 1, 0)))  # faces -x
    tris.append(demo.quad((b, -1, 0), (b, 1, 0), (b, 1, 2), (b, -1, 2)))  # faces +x
    light = Light("Point", "POINT", demo.light_matrix((-1.3 + centre / 2, 0.0, 1.5), (0, 0, -1)),
                  power=power)
    res = r.p["resolution"]
    fov = np.radians(90.0)
    left = Camera.look_at((-1.95, 0.0, 1.0), (centre, 0.0, 0.8), fov_y=fov, resolution=res,
                          near=0.01, far=20.0)
    right = Camera.look_at((1.95, 0.0, 1.0), (centre, 0.0, 0.8), fov_y=fov, resolution=res,
                           near=0.01, far=20.0)
    scene = make_scene(np.concatenate(tris), materials=[Material("white")], lights=[light],
                       camera=left, settings=settings or r.settings())
    return scene, right


def crate_room(r: Runner, crate: float | None, settings: GISettings | None = None) -> Scene:
    """A closed 6 x 6 x 3 m room with a point light at (0, 0, h); with ``crate`` (m) the light
    sits at the centre of a closed crate of that size on the floor. Camera outside the crate."""
    h = 0.5 * crate if crate else 0.5
    tris = [demo.box_triangles((-3.0, -3.0, 0.0), (3.0, 3.0, 3.0), inward=True)]
    if crate:
        c = crate / 2
        tris.append(demo.box_triangles((-c, -c, 0.0), (c, c, crate)))
    light = Light("Point", "POINT", demo.light_matrix((0.0, 0.0, h), (0, 0, -1)), power=200.0)
    cam = Camera.look_at((2.6, -2.6, 2.2), (0.0, 0.0, 0.3), fov_y=np.radians(70.0),
                         resolution=r.p["resolution"], near=0.01, far=30.0)
    return make_scene(np.concatenate(tris), materials=[Material("white")], lights=[light],
                      camera=cam, settings=settings or r.settings())


def _with_extra_triangles(scene: Scene, extra: np.ndarray, material: int = 0) -> Scene:
    pos = np.concatenate([scene.positions, extra])
    mat = np.concatenate([scene.material_index, np.full(len(extra), material, np.int32)])
    return make_scene(pos, material_index=mat, materials=list(scene.materials),
                      lights=scene.lights, camera=scene.camera, settings=scene.settings)


def _cell_size(r: Runner, lo, hi, resolution: int | None = None) -> float:
    from lpv_core.grid import fit_grid

    return fit_grid(np.asarray(lo, float), np.asarray(hi, float),
                    resolution or r.p["grid"]).cell_size


# ---------------------------------------------------------------------------------------------
# Cases
# ---------------------------------------------------------------------------------------------


def case_scale(r: Runner) -> dict:
    """Scene scale 1e-3 .. 1e4 m with power x scale^2: irradiance is scale-invariant."""
    base = r.run(_cornell(r))
    rows = []
    for s in r.p["scales"]:
        run = base if s == 1.0 else r.run(_cornell(r, scale=s))
        rows.append(_row(f"x{s:g}", s, run, rel_dev(run.indirect(), base.indirect()),
                         rel_dev(run.direct(), base.direct())))
    return _figure("scale", "Scene scale (power x scale^2)", "scale factor",
                   "the passes at scale 1 (irradiance does not change)", rows)


def case_translation(r: Runner) -> dict:
    """Translation up to 1e6 m: the grid and the G-buffer keep positions relative to the scene."""
    base = r.run(_cornell(r))
    rows = []
    for t in r.p["offsets"]:
        run = base if t == 0 else r.run(_cornell(r, offset=(t, -0.7 * t, 0.3 * t)))
        rows.append(_row(f"{t:g} m", max(t, 1.0), run, rel_dev(run.indirect(), base.indirect()),
                         rel_dev(run.direct(), base.direct())))
    return _figure("translation", "Translation far from the origin", "offset (m; 0 drawn at 1)",
                   "the passes at the origin", rows)


def case_power(r: Runner) -> dict:
    """Light power 1e-6 .. 1e9 W: every pass is linear in the power."""
    p0 = 300.0
    base = r.run(_cornell(r, power=p0))
    rows = []
    for p in r.p["powers"]:
        run = base if p == p0 else r.run(_cornell(r, power=p))
        rows.append(_row(f"{p:g} W", p, run, rel_dev(run.indirect() * (p0 / p), base.indirect()),
                         rel_dev(run.direct() * (p0 / p), base.direct())))
    return _figure("power", "Light power", "spot power (W)",
                   "the 300 W passes x power / 300 W (linearity)", rows)


def _occlusion_modes() -> list[dict]:
    """Leak cases run without and with occlusion (the geometry volume)."""
    return [{"occlusion": False}, {"occlusion": True}]


def _occl_tag(occl: dict) -> str:
    return ", occlusion" if occl.get("occlusion") else ""


def case_thin_wall(r: Runner) -> dict:
    """A wall between two rooms, 0.05 to 4 cells thick: light leaking into the dark room."""
    cell = _cell_size(r, (-2, -1, 0), (2, 1, 2))
    rows = []
    for occl in _occlusion_modes():
        for k in r.p["wall_cells"]:
            scene, right = two_rooms(r, k * cell, settings=r.settings(**occl))
            run = r.run(scene, [right])
            lit = run.indirect().mean()
            leak = run.indirect(0).mean() / lit if lit > 0 else math.inf
            dleak = run.direct(0).mean() / max(run.direct().mean(), 1e-30)
            rows.append(_row(f"{k:g} cells{_occl_tag(occl)}", k, run, leak, dleak,
                             thickness_m=k * cell, **occl))
    return _figure("thin_wall", "Thin wall between a lit and a dark room",
                   "wall thickness (cells)",
                   "0: no light reaches the dark room (deviation = its mean indirect / the lit "
                   "room's)", rows, cell_m=cell)


def case_one_cell(r: Runner) -> dict:
    """A wall exactly one cell thick at different alignments to the grid."""
    cell = _cell_size(r, (-2, -1, 0), (2, 1, 2))
    rows = []
    for occl in _occlusion_modes():
        for frac in (0.0, 0.25, 0.5):
            scene, right = two_rooms(r, cell, centre=frac * cell, settings=r.settings(**occl))
            run = r.run(scene, [right])
            lit = run.indirect().mean()
            leak = run.indirect(0).mean() / lit if lit > 0 else math.inf
            dleak = run.direct(0).mean() / max(run.direct().mean(), 1e-30)
            rows.append(_row(f"offset {frac:g} cell{_occl_tag(occl)}", frac, run, leak, dleak,
                             **occl))
    return _figure("one_cell", "One-cell-thick wall, shifted against the grid",
                   "wall centre offset (cells)",
                   "0: no light reaches the dark room", rows, x_log=False, cell_m=cell)


def case_light_inside(r: Runner) -> dict:
    """A point light inside a closed crate 0.5 to 4 cells wide: nothing outside is lit."""
    cell = _cell_size(r, (-3, -3, 0), (3, 3, 3))
    rows = []
    for occl in _occlusion_modes():
        for k in r.p["crate_cells"]:
            free = r.run(crate_room(r, None, r.settings(**occl)))
            run = r.run(crate_room(r, k * cell, r.settings(**occl)))
            rows.append(_row(f"{k:g} cells{_occl_tag(occl)}", k, run,
                             run.indirect().mean() / max(free.indirect().mean(), 1e-30),
                             run.direct().mean() / max(free.direct().mean(), 1e-30), **occl))
    return _figure("light_inside", "Point light inside a closed crate", "crate size (cells)",
                   "0: the room outside stays dark (deviation = its indirect / the same room "
                   "with the light free)", rows)


def case_coplanar(r: Runner) -> dict:
    """Every triangle duplicated (same material; and a different albedo: z-fighting)."""
    rows = []
    for occl in _occlusion_modes():
        clean = _cornell(r, settings=r.settings(**occl))
        base = r.run(clean)
        twice = np.concatenate([clean.positions, clean.positions])
        dup = make_scene(twice, material_index=np.concatenate([clean.material_index] * 2),
                         materials=list(clean.materials), lights=clean.lights,
                         camera=clean.camera, settings=clean.settings)
        grey = list(clean.materials) + [Material("grey", np.array([0.3, 0.3, 0.3], np.float32))]
        other = np.full(clean.triangle_count, len(grey) - 1, np.int32)
        fight = make_scene(twice, material_index=np.concatenate([clean.material_index, other]),
                           materials=grey, lights=clean.lights, camera=clean.camera,
                           settings=clean.settings)
        tag = _occl_tag(occl)
        for label, x, sc in (("clean", 0, clean), ("duplicated, same albedo", 1, dup),
                             ("duplicated, other albedo", 2, fight)):
            run = base if sc is clean else r.run(sc)
            rows.append(_row(label + tag, x, run, rel_dev(run.indirect(), base.indirect()),
                             rel_dev(run.direct(), base.direct()), **occl))
    return _figure("coplanar", "Coplanar (duplicated) triangles", "variant",
                   "the clean box (the z-fighting variant has no single answer)", rows,
                   x_log=False)


def _degenerate_sets(rng) -> dict:
    n = 64
    # Inside the box, so that the scene's bounds (hence the grid) stay the same.
    p = rng.uniform(-0.6, 0.6, size=(n, 3)) + np.array([0.0, 0.0, 1.0])
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    zero = np.stack([p, p, p + d * 0.1], axis=1)  # repeated vertex
    collinear = np.stack([p, p + d * 0.1, p + d * 0.3], axis=1)
    nan = zero.copy()
    nan[:, 1, 0] = np.nan
    inf = collinear.copy()
    inf[:, 2, 1] = np.inf
    e = np.cross(d, [0.0, 0.0, 1.0])
    e /= np.linalg.norm(e, axis=1, keepdims=True) + 1e-300
    needle = np.stack([p, p + d * 0.3, p + d * 0.3 + e * 1e-7], axis=1)
    tiny = np.stack([p, p + np.array([1e-9, 0, 0]), p + np.array([0, 1e-9, 0])], axis=1)
    stray = np.array([[[1e4, 0, 0], [1e4 + 0.1, 0, 0], [1e4, 0.1, 0]]])
    return {"zero-area": zero, "collinear": collinear, "NaN vertex": nan, "Inf vertex": inf,
            "needle (1e-7 m)": needle, "tiny (1e-9 m)": tiny, "stray triangle at 1e4 m": stray}


def case_degenerate(r: Runner) -> dict:
    """The box plus 64 degenerate triangles of one kind each."""
    clean = _cornell(r)
    base = r.run(clean)
    rows = []
    for i, (label, tris) in enumerate(_degenerate_sets(np.random.default_rng(5)).items()):
        sc = _with_extra_triangles(clean, tris)
        run = r.run(sc)
        rows.append(_row(label, i, run, rel_dev(run.indirect(), base.indirect()),
                         rel_dev(run.direct(), base.direct()), dropped=dict(sc.dropped)))
    return _figure("degenerate", "Degenerate triangles added to the box", "kind",
                   "the clean box (the stray triangle changes the scene's bounds, hence the "
                   "grid: no invariance expected)", rows, x_log=False)


def case_albedo(r: Runner) -> dict:
    """Every surface with albedo a in [0, 1], one bounce: indirect is linear in a."""
    ref_a = 0.5
    rows = []

    def scene(a):
        sc = _cornell(r, settings=r.settings(bounces=1))
        sc.materials = [Material(m.name, np.full(3, a, np.float32)) for m in sc.materials]
        return sc

    base = r.run(scene(ref_a))
    for a in r.p["albedos"]:
        run = base if a == ref_a else r.run(scene(a))
        if a > 0:
            dev = rel_dev(run.indirect() * (ref_a / a), base.indirect())
        else:
            dev = float(np.abs(run.indirect()).sum() / max(np.abs(base.indirect()).sum(), 1e-300))
        rows.append(_row(f"albedo {a:g}", a, run, dev, None,
                         injected_flux=float(propagation.flux(run.injected).sum())
                         if run.injected is not None else 0.0))
    return _figure("albedo", "Albedo 0 to 1 (one bounce)", "albedo of every surface",
                   "the albedo-0.5 indirect x a / 0.5 (exactly 0 at albedo 0)", rows,
                   x_log=False)


def case_grids(r: Runner) -> dict:
    """Grid resolution 4^3 .. 128^3 (the sweep); a resolution the engine refuses up front
    (sweep.check_memory: the discrete-ordinates arrays would pass ordinates.STATE_BYTES) is
    left out of the figure and named in its note."""
    runs, refused = {}, []
    for g in r.p["grids"]:
        try:
            transport_sweep.check_memory(g)
            settings = r.settings(grid_resolution=g)  # refuses what the guard refuses
        except ValueError as exc:
            refused.append(f"{g}^3 refused: {exc}")
            continue
        runs[g] = r.run(_cornell(r, settings=settings))
    finest = runs[max(runs)]
    rows = [_row(f"{g}^3", g, run, rel_dev(run.indirect(), finest.indirect()),
                 indirect_mean=float(run.indirect().mean()),
                 iterations=run.result.stats.info.get("iterations"))
            for g, run in runs.items()]
    note = f"; {'; '.join(refused)}" if refused else ""
    return _figure("grids", "Grid resolution (the sweep)", "cells per axis",
                   f"none (deviation from the finest grid, {max(runs)}^3){note}", rows,
                   refused=refused)


# The transports the energy traces step: the default (discrete ordinates, one
# ordinates.advance of the per-direction flux) and KD10's clamped SH (kd10.step), the
# baseline the report shows next to it.
TRACE_MODELS = ("dom", "sh")


def energy_trace(resolution: int = 16, steps: int = 1000, angular: str = "dom") -> dict:
    """Flux per step of one VPL in free space and of a random grid, ``steps`` steps.
    ``flux``: what the grid holds after each step (the first: injected); ``max_growth``: the
    largest flux arriving in a step / the flux it started from, for "dom" counting what
    arrives in the padded layout's shell (left the grid) too, so that it is 1 in free space
    up to rounding and a gain of any size shows."""
    from lpv_core import injection
    from lpv_core.grid import Grid

    g = Grid((0.0, 0.0, 0.0), 1.0, resolution)
    c = resolution / 2
    single = injection.inject(g, np.array([[c, c, c]]), np.array([[0.0, 0.0, 1.0]]),
                              np.ones((1, 3)))
    rng = np.random.default_rng(7)
    noisy = rng.normal(size=g.shape()).astype(np.float32)
    noisy[..., 0] = np.abs(noisy[..., 0]) + 0.1
    out = {}
    if angular not in TRACE_MODELS:
        raise ValueError(f"angular must be one of {TRACE_MODELS}, not {angular!r}")
    per_direction = angular == "dom"  # flux per direction between steps
    dom = ordinates
    table = dom.factors(resolution) if per_direction else None
    for name, start in (("single VPL", single), ("random cells", noisy)):
        cur = dom.pad(dom.unfold(start)) if per_direction else start
        fluxes = [float(propagation.flux(start).sum(dtype=np.float64))]
        pairs = []
        bad = 0
        t0 = time.perf_counter()
        for _ in range(steps):
            if per_direction:
                nxt = dom.advance(cur, table)
                arrived = float(nxt.sum(dtype=np.float64))
                dom.take_shell(nxt, resolution)
                moved = float(nxt.sum(dtype=np.float64))
            else:
                nxt = kd10.step(cur)
                arrived = moved = float(propagation.flux(nxt).sum(dtype=np.float64))
            bad += int((~np.isfinite(nxt)).sum())
            pairs.append((fluxes[-1], arrived))
            fluxes.append(moved)
            cur = nxt
        out[name] = {"flux": fluxes, "max_growth": growth(pairs), "nonfinite": bad,
                     "time_s": time.perf_counter() - t0}
    return out


def case_energy(r: Runner) -> dict:
    """Energy per iteration over 0..1000 steps for every propagation mode."""
    rows = []
    traces = {}
    for i, angular in enumerate(TRACE_MODELS):
        mode = f"angular={angular}"
        tr = energy_trace(r.p["trace_grid"], r.p["trace_steps"], angular=angular)
        traces[mode] = tr
        for name, t in tr.items():
            rows.append({"label": f"{name} ({mode})", "x": i, "nonfinite": t["nonfinite"],
                         "energy_growth": t["max_growth"], "energy_balance": 0.0,
                         "propagations": 0, "deviation": t["flux"][-1]
                         / t["flux"][0], "deviation_direct": None, "time_s": t["time_s"],
                         "steps": r.p["trace_steps"]})
    return _figure("energy", f"Flux per propagation step, {r.p['trace_steps']} steps on "
                   f"{r.p['trace_grid']}^3", "step",
                   "energy never grows (deviation = flux left after the last step / injected)",
                   rows, x_log=False, traces=traces)


def _propagate_storage(injected: np.ndarray, steps: int, dtype,
                       angular: str = "sh") -> np.ndarray:
    """sum_k P^k(I0) with the grid stored in ``dtype`` between steps (compute in float32).
    angular="dom": the per-direction flux is what is stored between steps."""
    dom = angular == "dom"
    advance = dom_steps.step if dom else kd10.step
    with np.errstate(over="ignore", invalid="ignore"):
        cur = (ordinates.unfold(injected) if dom else injected).astype(dtype)
    acc = np.zeros_like(cur) if dom else cur.copy()
    for _ in range(steps):
        with np.errstate(over="ignore", invalid="ignore"):
            nxt = advance(cur.astype(np.float32)).astype(dtype)
            acc = (acc.astype(np.float32) + nxt.astype(np.float32)).astype(dtype)
        cur = nxt
    if dom:
        with np.errstate(over="ignore", invalid="ignore"):
            return (ordinates.fold(acc.astype(np.float32), sh.BANDS2)
                    + ordinates.emission_band2(injected))
    return acc.astype(np.float32)


def case_float16(r: Runner) -> dict:
    """The Cornell box's injected grid propagated with float16 vs float32 storage, at light
    powers 1e-6 .. 1e9 W (the injected grid scales linearly with the power)."""
    p0 = 300.0
    run = r.run(_cornell(r, power=p0))
    injected = run.injected
    angular = r.settings().angular
    steps = engine.auto_iterations(r.p["grid"], angular)
    rows = []
    for p in r.p["f16_powers"]:
        inj = injected.astype(np.float64) * (p / p0)
        with np.errstate(over="ignore"):
            inj32 = inj.astype(np.float32)
        t0 = time.perf_counter()
        ref = _propagate_storage(inj32, steps, np.float32, angular)
        t32 = time.perf_counter() - t0
        t0 = time.perf_counter()
        half = _propagate_storage(inj32, steps, np.float16, angular)
        t16 = time.perf_counter() - t0
        bad = int((~np.isfinite(half)).sum())
        nz = ref != 0
        underflow = float(((half == 0) & nz).sum() / max(int(nz.sum()), 1))
        dev = rel_dev(half, ref)
        fake = Run({}, [], run.result, t16, bad)
        rows.append(_row(f"{p:g} W", p, fake, dev, None, underflow=underflow,
                         time_float32_s=t32, max_abs=float(np.abs(ref).max())))
    return _figure("float16", "float16 vs float32 grid storage", "spot power (W)",
                   "the float32 result (relative L1 deviation of the propagated grid)", rows,
                   steps=steps)


CASES = (case_scale, case_translation, case_power, case_thin_wall, case_one_cell,
         case_light_inside, case_coplanar, case_degenerate, case_albedo, case_grids,
         case_energy, case_float16)


def run_suite(profile: str = "test", cases=CASES, progress=None) -> list[dict]:
    """Every case's figure, in order. ``progress(name, seconds)`` is called after each."""
    r = Runner(profile)
    out = []
    for case in cases:
        t0 = time.perf_counter()
        fig = case(r)
        fig["seconds"] = time.perf_counter() - t0
        out.append(fig)
        if progress is not None:
            progress(fig["name"], fig["seconds"])
    return out
