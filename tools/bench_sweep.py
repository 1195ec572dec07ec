"""Scaling sweep of the LPV engine: per-stage medians, cost-growth exponents and a roofline.

Used by ``python -m tools.bench --sweep`` (full, a few minutes) and ``--sweep-quick`` (tiny,
for tests). Everything here is a pure function returning plain dicts (JSON-ready); nothing is
printed except by :func:`table`.

What is measured, and why this way:

* **Engine sweep** (:func:`engine_sweep`): one factor at a time around a base configuration,
  ``Engine.update`` + ``deferred.render`` on the demo Cornell box, for each backend, with the
  default transport model (``GISettings.angular``, "dom"); the medians of ``Stats.ms`` per
  stage. dom solves the limit of infinitely many steps in one sweep per propagation
  (``settings.iterations`` applies to sh only), so its figures are the cost of a converged
  update.
  Triangle counts are scaled by subdividing every demo triangle into k^2 (same scene, same
  lighting, only the cost changes); lights by replicating the demo spot light.
* **Propagation microbenchmark** (:func:`propagation_sweep`): one step on a *dense* grid (every
  cell lit, with visibility; dom also without), per backend and angular model: ``kd10.step``
  for sh, one step of ``dom_steps.propagate_steps``' loop for dom (:func:`dom_step`:
  ``ordinates.advance``, the shell, the accumulation and the flux sum). The engine's
  propagation is sparse (dom skips the cells without light), so this is the worst case and
  the one the roofline applies to.
* **Machine limits** (:func:`machine_limits`): float32 GFLOP/s of a large numpy matmul and
  memory bandwidth of a large array copy, measured in the same run.
* **Roofline** (:func:`roofline`): FLOPs and bytes of one propagation step counted from the
  algorithm (:func:`step_counts`), time at the machine's limit vs time measured.
* **Lookup** (:func:`lookup_bench`): ``backend.irradiance`` on a 1280x720 G-buffer's worth of
  points (921,600) in the grid, per backend and angular model (dom: bands 0-2, sh: KD10's
  clamped lobe with its gradient damping).
* **Exponents** (:func:`exponents`): least-squares slope of log(time) vs log(size) per series.

A combination that cannot run (no GL context, an exception) is recorded with its reason
instead of stopping the sweep.
"""

from __future__ import annotations

import math
import statistics
import time
import traceback

import numpy as np

from lpv_core import engine, propagation, sh
from lpv_core.grid import Grid
from lpv_core.propagation import kd10, ordinates, quadrature
from lpv_core.render import deferred
from lpv_core.scene import GISettings, make_scene
from tools import core_scenes as demo
from tools import dom_steps

BACKENDS = ("numpy", "gl")
# Transport models swept, the default first ("dom"); sh (KD10) for comparison.
ANGULARS = ("dom", "sh")
# The model the engine sweep runs: the add-on's default.
ENGINE_ANGULAR = GISettings().angular

# Full sweep: the ranges issue 6 asks for. Quick: the same shape, tiny, for tests.
FULL = {
    "grid_resolution": (16, 32, 48, 64),
    "cascades": (1, 2, 3, 4),
    "rsm_resolution": (64, 128, 256, 512),
    "triangles": (1_000, 10_000, 100_000, 1_000_000),
    "lights": (1, 2, 4, 8, 16),
    "base": {"grid_resolution": 16, "cascades": 1, "rsm_resolution": 128, "triangles": 34,
             "lights": 1},
    "iterations": 2,  # fixed propagation steps per update (not convergence, see module doc)
    "angular": ENGINE_ANGULAR,
    "render": (128, 96),
    "shadow_resolution": 512,
    "repeat": 3,
    "prop_sizes": (16, 24, 32, 48, 64),
    "prop_steps": 2,
    "lookup_points": 1280 * 720,
    "lookup_grid": 32,
    "matmul_n": 2048,
    "copy_mb": 256,
}
QUICK = {
    "grid_resolution": (8, 12, 16),
    "cascades": (1, 2, 3),
    "rsm_resolution": (16, 32, 64),
    "triangles": (136, 544, 2176),
    "lights": (1, 2, 4),
    "base": {"grid_resolution": 8, "cascades": 1, "rsm_resolution": 32, "triangles": 34,
             "lights": 1},
    "iterations": 1,
    "angular": ENGINE_ANGULAR,
    "render": (32, 24),
    "shadow_resolution": 128,
    "repeat": 3,
    "prop_sizes": (8, 12, 16),
    "prop_steps": 1,
    "lookup_points": 20_000,
    "lookup_grid": 12,
    "matmul_n": 384,
    "copy_mb": 16,
}
DIMENSIONS = ("grid_resolution", "cascades", "rsm_resolution", "triangles", "lights")


# -- scenes -------------------------------------------------------------------------------------

def subdivide(triangles: np.ndarray, k: int) -> np.ndarray:
    """Split each triangle (T, 3, 3) into k^2 congruent ones (T k^2, 3, 3), same surface.

    Scaling the triangle count this way keeps the scene (and so the lighting) identical: only
    the per-triangle costs (upload, rasterisation, geometry volume) grow.
    """
    tris = np.asarray(triangles, np.float64).reshape(-1, 3, 3)
    if k <= 1:
        return tris.copy()
    bary = []
    for i in range(k):
        for j in range(k - i):
            a, b, c = (i, j), (i + 1, j), (i, j + 1)
            bary.append([a, b, c])  # upright
            if i + j < k - 1:
                bary.append([(i + 1, j), (i + 1, j + 1), (i, j + 1)])  # inverted
    uv = np.asarray(bary, np.float64) / k  # (k^2, 3 corners, 2)
    w = np.concatenate([1.0 - uv.sum(-1, keepdims=True), uv], axis=-1)  # (k^2, 3, 3) bary
    return np.einsum("scb,tbx->tscx", w, tris).reshape(-1, 3, 3)


def sweep_scene(triangles: int, lights: int, settings: GISettings,
                resolution: tuple[int, int]):
    """The demo Cornell box with about ``triangles`` triangles and ``lights`` spot lights.

    The demo's 34 triangles are each subdivided into k^2 with k = round(sqrt(triangles / 34));
    the actual count is ``scene.triangle_count``. Lights are the demo spot, replicated around
    the ceiling centre with the total power kept.
    """
    base = demo.cornell_box("SPOT", resolution, settings)
    k = max(1, round(math.sqrt(triangles / base.triangle_count)))
    scene = base
    if k > 1:
        pos = subdivide(base.positions, k)
        mats = np.repeat(base.material_index, k * k)
        scene = make_scene(pos, material_index=mats, materials=base.materials,
                           lights=base.lights, camera=base.camera, settings=settings)
    spot = base.lights[0]
    scene.lights = []
    for i in range(lights):
        m = spot.matrix.copy()
        if lights > 1:
            m[:3, 3] += [0.5 * np.cos(2 * np.pi * i / lights), 0.5 * np.sin(2 * np.pi * i / lights),
                         -0.02 * i]
        scene.lights.append(type(spot)(f"Spot{i}", "SPOT", m, power=spot.power / lights,
                                        spot_size=spot.spot_size, spot_blend=spot.spot_blend))
    return scene


# -- engine sweep -------------------------------------------------------------------------------

def _engine_case(eng: engine.Engine, scene, repeat: int) -> dict:
    """Median ms per Stats.ms stage over ``repeat`` full updates + renders (after a warm-up)."""
    samples: dict[str, list[float]] = {}
    steps = []
    be = eng.backend(scene.settings)
    fallbacks0 = getattr(be, "fallbacks", 0)
    for i in range(repeat + 1):  # the first run compiles shaders and fills caches
        eng.clear_cache()
        stats = engine.Stats()
        t0 = time.perf_counter()
        result = eng.update(scene, stats)
        deferred.render(eng, scene, result, stats)
        stats.ms["total"] = (time.perf_counter() - t0) * 1000.0
        if i == 0:
            continue
        for k, v in stats.ms.items():
            samples.setdefault(k, []).append(v)
        # steps per update: a "sweep" entry (dom: one pass to convergence) counts as one
        steps.append(int(sum(1 if n == "sweep" else n for n in stats.info.get("iterations")
                             or [0] if n == "sweep" or isinstance(n, int))))
    med = {k: statistics.median(v) for k, v in samples.items()}
    n_steps = statistics.median(steps) if steps else 0
    if n_steps and "propagation" in med:
        med["propagation_per_step"] = med["propagation"] / n_steps
    # Calls the GL backend handed to the numpy code (modes it has not ported), all runs.
    fallbacks = getattr(be, "fallbacks", 0) - fallbacks0
    return {"median_ms": med, "steps": n_steps, "runs": repeat,
            "triangles": scene.triangle_count, "lights": len(scene.lights),
            "numpy_fallbacks": fallbacks}


def engine_sweep(cfg: dict, backends=BACKENDS) -> dict:
    """One factor at a time around ``cfg['base']``: {dimension: [case, ...]} per backend.

    Each case is {"value", "backend", "median_ms": {stage: ms}, ...} or, when it could not run,
    {"value", "backend", "skipped": reason}.
    """
    out: dict = {d: [] for d in DIMENSIONS}
    for name in backends:
        eng = engine.Engine()
        reason = None
        try:
            eng.backend(GISettings(backend=name))  # makes the GL backend now: fail early
        except Exception as exc:  # noqa: BLE001 - recorded: no GL context on this machine
            reason = f"backend {name!r} unavailable: {type(exc).__name__}: {exc}"
        for dim in DIMENSIONS:
            for value in cfg[dim]:
                case = {"value": value, "backend": name}
                out[dim].append(case)
                if reason:
                    case["skipped"] = reason
                    continue
                p = dict(cfg["base"], **{dim: value})
                settings = GISettings(grid_resolution=p["grid_resolution"],
                                      cascades=p["cascades"], rsm_resolution=p["rsm_resolution"],
                                      iterations=cfg["iterations"],
                                      angular=cfg.get("angular", ENGINE_ANGULAR),
                                      shadow_resolution=cfg["shadow_resolution"], backend=name)
                try:
                    scene = sweep_scene(p["triangles"], p["lights"], settings, cfg["render"])
                    case.update(_engine_case(eng, scene, cfg["repeat"]))
                except Exception as exc:  # noqa: BLE001 - one failing case must not end the sweep
                    case["skipped"] = f"{type(exc).__name__}: {exc}"
                    case["traceback"] = traceback.format_exc(limit=3)
    return out


# -- machine limits and roofline ----------------------------------------------------------------

def _median_s(fn, repeat: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def machine_limits(matmul_n: int = 2048, copy_mb: int = 256, repeat: int = 5) -> dict:
    """This machine's float32 GFLOP/s (n x n matmul, 2 n^3 FLOPs, best BLAS case) and memory
    bandwidth (copy of a ``copy_mb`` MiB float32 array: its bytes read + written) in GB/s.

    Both are measured, not looked up, because the machine is shared and its effective limits
    are what this run's times can be compared with.
    """
    rng = np.random.default_rng(0)
    a = rng.random((matmul_n, matmul_n), dtype=np.float32)
    b = rng.random((matmul_n, matmul_n), dtype=np.float32)
    t_mm = _median_s(lambda: a @ b, repeat)
    n = copy_mb * (1 << 20) // 4
    src = np.ones(n, np.float32)
    dst = np.empty_like(src)
    t_cp = _median_s(lambda: np.copyto(dst, src), repeat)
    return {"gflops": 2.0 * matmul_n**3 / t_mm / 1e9, "matmul_n": matmul_n,
            "bandwidth_gbs": 2.0 * src.nbytes / t_cp / 1e9, "copy_mib": copy_mb,
            "repeat": repeat}


def step_counts(resolution: int, angular: str = "dom", visibility: bool = True) -> dict:
    """FLOPs and bytes of one propagation step on a dense (all cells lit) R^3 grid.

    Counted from the algorithm (kd10.step / ordinates.advance), per cell and colour (row):

    * sh: 30 face evaluations (2 x 4 x 30), clamp / sum / rescale (~95), six 5 -> 4
      re-projections (6 x 2 x 5 x 4), visibility (24) and the shift-adds (24).
    * dom: one step of dom_steps.propagate_steps' loop (:func:`dom_step`) on the padded
      flat layout ((R + 2)^3 cells of q = 64 directions x 3 colours): the advection, 64
      directions x 8 neighbour offsets x (1 multiply by weight x transmittance + 1 add) over
      the flat range of cells holding light (for a dense grid (R - 1)((R+2)^2 + (R+2) + 1) + 1
      cells, ~(1 + 2/R)^2 R^3: the padding rows in between are multiplied too), then over
      all (R + 2)^3 cells 1 compare each for the live-range scan (``any``), 1 add for
      ``acc += cur`` and 1 for the float64 flux sum. The shell is emptied (stores, no FLOPs;
      the microbenchmark captures no outflow). Visibility costs no FLOPs per step: the
      weight x transmittance tables are made once per propagation (ordinates.factors).
      Per cell: 3 x (1024 x live / R^3 + 192 x (R + 2)^3 / R^3), 4.7k at 16^3, 4.2k at 32^3
      (3.6k as R grows: 3 x (1024 + 192)).

    ``bytes`` is the compulsory traffic: sh reads the grid (48 B/cell) and visibility
    (24 B/cell) and write the result (48 B/cell); dom reads the flux (q x 3 x 4 = 768 B/cell)
    and the visibility (24 B/cell), writes the arrivals (768 B/cell) and reads and writes the
    accumulated flux (2 x 768 B/cell), since its timed step includes the accumulation.
    ``bytes_materialised`` estimates what the numpy code moves through the arrays it
    materialises (each written once and read once), which is what its memory roof really is;
    for dom, per (direction, offset) and live cell: the multiply reads the source and the
    weight x transmittance (4 B, with visibility) and writes a buffer, the add reads the
    destination and the buffer and writes the destination (5 x 12 B + 4 B); plus per padded
    cell the zeroed output (768 B), the scan (768 B + 1), ``acc += cur`` (3 x 768 B), the sum
    (768 B) and the emptied shell (6 (R + 2)^2 cells x 768 B).
    """
    cells = resolution**3
    rows = 3 * cells
    vis = 1 if visibility else 0
    extra = {}
    if angular == "sh":
        per_row = 2 * 4 * 30 + 95 + 6 * 2 * 5 * 4 + 24 * vis + 24
        flops = rows * per_row
        # face flux (30 floats: matmul out, clamp, sum, scale: r+w), six re-projections
        # (out 16 B, visibility product, shift-add: ~5 x 16 B each).
        per_row_bytes = 16 + 120 * 4 * 2 + 6 * 5 * 16
        materialised = rows * per_row_bytes + cells * 24 * vis
        compulsory = cells * (48 + 24 * vis + 48)
    elif angular == "dom":
        _, _, groups = ordinates.tables()
        qd, c = ordinates.DIRECTIONS, 3
        pairs = sum((sl.stop - sl.start) * len(row) for sl, row in groups)  # 64 x 8
        p = resolution + 2
        padded = p**3
        # flat index range [lo, hi) of a dense interior: cell (1, 1, 1) to (R, R, R)
        live = (resolution - 1) * (p * p + p + 1) + 1
        flops = 2 * c * pairs * live + 3 * qd * c * padded
        state = 4 * qd * c  # bytes of one cell's flux
        materialised = (pairs * live * (5 * 4 * c + 4 * vis)
                        + padded * (state + state + 1 + 3 * state + state)
                        + 6 * p * p * state)
        compulsory = cells * (4 * state + 24 * vis)
        extra = {"direction_offset_pairs": pairs, "padded_cells": padded, "live_cells": live}
    else:
        raise ValueError(f"angular must be one of {ANGULARS}, not {angular!r}")
    return {"flops": float(flops), "bytes": float(compulsory),
            "bytes_materialised": float(materialised), "cells": cells,
            "flops_per_cell": flops / cells, **extra}


def roofline(step_ms: float, counts: dict, limits: dict) -> dict:
    """Achieved / limit for one measured step: FLOP rate / peak, byte rate / bandwidth, and
    the roofline fraction (time at the limit, max(FLOPs / peak, bytes / bandwidth), over the
    time measured). Values above 1 mean the step beat the measured 'limit' (the counts are
    an upper bound or the limits were measured while the machine was busy): noted."""
    t = step_ms / 1000.0
    t_flop = counts["flops"] / (limits["gflops"] * 1e9)
    t_byte = counts["bytes"] / (limits["bandwidth_gbs"] * 1e9)
    t_mat = counts["bytes_materialised"] / (limits["bandwidth_gbs"] * 1e9)
    out = {"achieved_gflops": counts["flops"] / t / 1e9,
           "achieved_gbs": counts["bytes"] / t / 1e9,
           "flop_fraction": t_flop / t, "bandwidth_fraction": t_byte / t,
           "bandwidth_fraction_materialised": t_mat / t,
           "roofline_fraction": max(t_flop, t_byte) / t,
           "bound": "compute" if t_flop >= t_byte else "memory",
           "arithmetic_intensity": counts["flops"] / counts["bytes"]}
    if out["roofline_fraction"] > 1.0:
        out["note"] = ("faster than the measured limit: the FLOP count (exp as one FLOP) or "
                       "the limits (measured on a shared machine) are off by that much")
    return out


def _dense_grid(r: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """An (R, R, R, 3, 4) grid with every cell lit (lobes of random direction) and a (6, R^3)
    visibility in [0.7, 1]: the dense worst case of a step."""
    v = np.zeros((r, r, r, 3, 4), np.float32)
    v[..., 0] = rng.uniform(0.5, 1.0, (r, r, r, 3))
    v[..., 1:] = rng.uniform(-0.2, 0.2, (r, r, r, 3, 3))
    vis = rng.uniform(0.7, 1.0, (6, r, r, r)).astype(np.float32)
    return v, vis


def _gl_backend():
    """(GLBackend, None) or (None, reason it cannot be made)."""
    try:
        from lpv_core.gl.backend import GLBackend

        return GLBackend(), None
    except Exception as exc:  # noqa: BLE001 - recorded: no GL context
        return None, f"no GL backend: {type(exc).__name__}: {exc}"


def _dense_dom(r: int, rng) -> np.ndarray:
    """A dense dom state: the padded flat layout (q, 3, (R + 2)^3) with every interior cell
    holding flux along every direction (random, [0.5, 1) / q), the shell empty."""
    q = ordinates.DIRECTIONS
    flux = (rng.random((q, 3, r, r, r), dtype=np.float32) * 0.5 + 0.5) / q
    return ordinates.pad(flux)


def dom_step(cur: np.ndarray, acc: np.ndarray, table: list, r: int) -> tuple[np.ndarray, float]:
    """One step of dom_steps.propagate_steps' loop on the padded flat layout: advance
    every direction one cell (ordinates.advance), empty the shell (what left the grid; no
    outflow kept), accumulate, and sum the moved flux in float64 (the early-stop test).
    Returns the new state and the moved flux (dom_steps.loop_step, the loop's own step)."""
    return dom_steps.loop_step(cur, table, r, acc)


def _cases(angulars):
    """(angular, visibility) per dense row: every model with visibility, dom also without
    (its visibility is a per-propagation weight x transmittance table, not per-step work)."""
    return [(a, v) for a in angulars for v in ((True, False) if a == "dom" else (True,))]


def propagation_sweep(sizes, steps: int, repeat: int, limits: dict,
                      angulars=ANGULARS, backends=BACKENDS) -> list[dict]:
    """Median ms per step of ``steps`` fixed steps on dense grids, with the roofline of each.

    numpy: ``kd10.step`` (sh) or :func:`dom_step` (dom, on a dense random flux
    state, every direction lit) called ``steps`` times; gl: ``GLBackend.propagate`` with
    ``min_fraction=0`` on light launched from surfaces (the engine's case). A gl
    dom propagation launches, uploads and folds once per call: its step is (time of ``steps`` steps -
    time of 0 steps) / ``steps``, the fixed part recorded as ``unfold_fold_ms``.
    """
    rng = np.random.default_rng(1)
    gl, gl_reason = _gl_backend() if "gl" in backends else (None, None)
    rows = []
    for r in sizes:
        values, vis = _dense_grid(r, rng)
        for angular, use_vis in _cases(angulars):
            counts = step_counts(r, angular, use_vis)
            step_vis = vis if use_vis else None
            for name in backends:
                row = {"backend": name, "angular": angular, "resolution": r, "cells": r**3,
                       "visibility": use_vis, "steps": steps, "flops": counts["flops"],
                       "bytes": counts["bytes"]}
                rows.append(row)
                try:
                    if name == "numpy" and angular == "dom":
                        state = _dense_dom(r, rng)
                        table = ordinates.factors(
                            r, quadrature.offset_visibilities(step_vis))
                        acc = np.zeros_like(state)

                        def run(v=state, t=table, a=acc, rr=r):
                            cur = v
                            for _ in range(steps):
                                cur, _moved = dom_step(cur, a, t, rr)
                    elif name == "numpy":
                        def run(v=values, vv=step_vis):
                            cur = v
                            for _ in range(steps):
                                cur = kd10.step(cur, vv)
                    else:
                        if gl is None:
                            row["skipped"] = gl_reason
                            continue
                        if angular != "dom":
                            row["skipped"] = "the GL backend propagates dom only"
                            continue

                        def run(g=values, vv=step_vis, n=steps):
                            gl.propagate(g, n, min_fraction=0.0, visibility=vv, angular="dom",
                                         occlude_first_step=True, launch=True)
                    fallbacks0 = getattr(gl, "fallbacks", 0)
                    sec = _median_s(run, repeat)
                    if name == "gl" and angular == "dom":
                        fixed = _median_s(lambda: run(n=0), repeat)
                        row["unfold_fold_ms"] = fixed * 1000.0
                        row["propagate_ms"] = sec * 1000.0
                        sec = sec - fixed
                        if sec <= 0:
                            raise RuntimeError("steps not measurable over the unfold/fold "
                                               f"({row['propagate_ms']:.1f} ms vs "
                                               f"{row['unfold_fold_ms']:.1f} ms)")
                    if name == "gl" and gl.fallbacks > fallbacks0:
                        row["numpy_fallbacks"] = gl.fallbacks - fallbacks0
                    row["step_ms"] = sec * 1000.0 / steps
                    row["roofline"] = roofline(row["step_ms"], counts, limits)
                except Exception as exc:  # noqa: BLE001 - recorded, the sweep goes on
                    row["skipped"] = f"{type(exc).__name__}: {exc}"
    return rows


def lookup_bench(points: int, resolution: int, repeat: int, angulars=ANGULARS,
                 backends=BACKENDS) -> list[dict]:
    """Median ms of ``backend.irradiance`` on ``points`` receivers (a 1280x720 G-buffer is
    921,600), on a propagated grid with occlusion visibility, as deferred.render calls it:
    with the coefficients the model's propagation gives (dom: 9, bands 0-2, its band 2
    small; sh: 4)."""
    rng = np.random.default_rng(2)
    g = Grid((-1.0, -1.0, 0.0), 2.0 / resolution, resolution)
    values4, vis = _dense_grid(resolution, rng)
    values9 = np.zeros(values4.shape[:-1] + (sh.BANDS2,), np.float32)
    values9[..., :4] = values4
    values9[..., 4:] = rng.uniform(-0.05, 0.05, values9[..., 4:].shape)
    lo = g.origin_array + g.cell_size
    span = (resolution - 2) * g.cell_size
    pos = lo + rng.uniform(0.0, span, (points, 3))
    nrm = rng.normal(size=(points, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    gl, gl_reason = _gl_backend() if "gl" in backends else (None, None)
    rows = []
    for angular in angulars:
        for name in backends:
            row = {"backend": name, "angular": angular, "points": points,
                   "resolution": resolution}
            rows.append(row)
            be = engine.NUMPY_BACKEND if name == "numpy" else gl
            if be is None:
                row["skipped"] = gl_reason
                continue
            try:
                values = values9 if propagation.coefficients(angular) == sh.BANDS2 else values4
                sec = _median_s(lambda b=be, a=angular, v=values: b.irradiance(
                    g, v, pos, nrm, angular=a, visibility=vis), repeat)
                row["ms"] = sec * 1000.0
            except Exception as exc:  # noqa: BLE001 - recorded, the sweep goes on
                row["skipped"] = f"{type(exc).__name__}: {exc}"
    return rows


# -- exponents ----------------------------------------------------------------------------------

def fit_exponent(xs, ys) -> dict:
    """Least-squares slope of log(y) vs log(x): time ~ size^exponent. Needs >= 3 points with
    positive x and y (fewer: ``reason``)."""
    pts = [(float(x), float(y)) for x, y in zip(xs, ys)
           if x is not None and y is not None and x > 0 and y > 0
           and math.isfinite(x) and math.isfinite(y)]
    if len({x for x, _ in pts}) < 3:
        return {"exponent": None, "points": len(pts), "reason": "fewer than 3 distinct points"}
    lx = np.log([p[0] for p in pts])
    ly = np.log([p[1] for p in pts])
    slope, intercept = np.polyfit(lx, ly, 1)
    resid = ly - (slope * lx + intercept)
    ss = float(((ly - ly.mean()) ** 2).sum())
    r2 = 1.0 - float((resid**2).sum()) / ss if ss > 0 else 1.0
    return {"exponent": float(slope), "points": len(pts), "r2": r2,
            "x": [p[0] for p in pts], "y_ms": [p[1] for p in pts]}


# (name, dimension, size from the case, stage in median_ms)
ENGINE_FITS = (
    ("propagation_per_step vs cells", "grid_resolution", lambda c: c["value"] ** 3,
     "propagation_per_step"),
    ("injection vs cells", "grid_resolution", lambda c: c["value"] ** 3, "injection"),
    ("rsm vs texels", "rsm_resolution", lambda c: c["value"] ** 2, "rsm"),
    ("injection vs texels", "rsm_resolution", lambda c: c["value"] ** 2, "injection"),
    ("geometry_volume vs triangles", "triangles", lambda c: c["triangles"], "geometry_volume"),
    ("upload vs triangles", "triangles", lambda c: c["triangles"], "upload"),
    ("rsm vs triangles", "triangles", lambda c: c["triangles"], "rsm"),
    ("lpv_update vs lights", "lights", lambda c: c["lights"], "lpv_update"),
    ("total vs lights", "lights", lambda c: c["lights"], "total"),
    ("lpv_update vs cascades", "cascades", lambda c: c["value"], "lpv_update"),
)


def exponents(engine_out: dict, prop_rows: list[dict]) -> dict:
    """Cost-growth exponents: {series: {backend: fit}} from the engine sweep and the dense
    propagation microbenchmark (step ms vs cells, per backend and angular model)."""
    fits: dict = {}
    for name, dim, size, stage in ENGINE_FITS:
        for backend in BACKENDS:
            cases = [c for c in engine_out.get(dim, []) if c["backend"] == backend
                     and "median_ms" in c]
            xs = [size(c) for c in cases]
            ys = [c["median_ms"].get(stage) for c in cases]
            fits.setdefault(name, {})[backend] = fit_exponent(xs, ys)
    for angular, use_vis in _cases(ANGULARS):
        if not any(r["angular"] == angular and r.get("visibility", True) == use_vis
                   for r in prop_rows):
            continue
        name = f"dense {angular} step vs cells" + ("" if use_vis else " (no visibility)")
        for backend in BACKENDS:
            rows = [r for r in prop_rows if r["backend"] == backend and r["angular"] == angular
                    and r.get("visibility", True) == use_vis and "step_ms" in r]
            fits.setdefault(name, {})[backend] = fit_exponent(
                [r["cells"] for r in rows], [r["step_ms"] for r in rows])
    return fits


# -- the whole sweep ----------------------------------------------------------------------------

def run_sweep(quick: bool = False, backends=BACKENDS) -> dict:
    """The full sweep (``quick``: the tiny one) as one JSON-ready dict."""
    cfg = QUICK if quick else FULL
    t0 = time.perf_counter()
    limits = machine_limits(cfg["matmul_n"], cfg["copy_mb"], repeat=3 if quick else 5)
    prop = propagation_sweep(cfg["prop_sizes"], cfg["prop_steps"], cfg["repeat"], limits,
                             backends=backends)
    look = lookup_bench(cfg["lookup_points"], cfg["lookup_grid"], cfg["repeat"],
                        backends=backends)
    eng = engine_sweep(cfg, backends)
    limits_after = machine_limits(cfg["matmul_n"], cfg["copy_mb"], repeat=3 if quick else 5)
    # The machine is shared: the limit is the best of the two measurements, and the roofline
    # is redone against it (a busier moment would make the code look closer to its limit).
    best = dict(limits, gflops=max(limits["gflops"], limits_after["gflops"]),
                bandwidth_gbs=max(limits["bandwidth_gbs"], limits_after["bandwidth_gbs"]))
    for row in prop:
        if "step_ms" in row:
            row["roofline"] = roofline(row["step_ms"], step_counts(
                row["resolution"], row["angular"], row.get("visibility", True)), best)
    gl, _ = _gl_backend()
    return {
        "quick": quick,
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg.items()},
        "notes": [
            (f"engine: angular = {cfg.get('angular', ENGINE_ANGULAR)!r} (the default); "
             + ("dom solves each propagation to convergence in one sweep"
                if cfg.get("angular", ENGINE_ANGULAR) == "dom" else
                f"propagation runs a fixed {cfg['iterations']} step(s) per update "
                "(settings.iterations), not to convergence: figures are per-step costs")),
            "one factor varied at a time around config.base",
            "triangle counts: demo Cornell box triangles each subdivided into k^2",
            ("numpy_fallbacks > 0 on a gl case: that many backend calls ran the numpy code "
             "(e.g. propagation of inner cascades, capture_outflow, is not ported to GL)"),
            (f"dense propagation: every cell lit, visibility on (dom also off), "
             f"{cfg['prop_steps']} step(s) timed per run; dom: one step of the propagation "
             "loop (advance, shell, accumulation, flux sum) on the padded flat layout, gl dom: "
             "(propagate(steps) - propagate(0)) / steps, without the unfold and fold"),
            ("roofline: float32 matmul GFLOP/s and array-copy GB/s measured in this run "
             "(before and after the sweep; the better of the two is the limit)"),
        ],
        "machine_limits": best,
        "machine_limits_before": limits,
        "machine_limits_after": limits_after,
        "gl_renderer": gl.ctx.info.get("GL_RENDERER") if gl is not None else None,
        "engine": eng,
        "propagation": prop,
        "lookup": look,
        "exponents": exponents(eng, prop),
        "sweep_s": time.perf_counter() - t0,
    }


# -- table --------------------------------------------------------------------------------------

TABLE_STAGES = ("planner", "rsm", "injection", "propagation", "propagation_per_step",
                "geometry_volume", "upload", "combine", "lpv_update", "gbuffer", "direct",
                "lookup", "total")


def table(sweep: dict) -> str:
    """Markdown tables of the sweep: engine stages, dense steps + roofline, lookup, exponents."""
    lim = sweep["machine_limits"]
    pre, post = sweep["machine_limits_before"], sweep["machine_limits_after"]
    head = (f"Machine limits: {lim['gflops']:.1f} GFLOP/s (float32 matmul {lim['matmul_n']}), "
            f"{lim['bandwidth_gbs']:.1f} GB/s (copy of {lim['copy_mib']} MiB); measured "
            f"{pre['gflops']:.1f} / {pre['bandwidth_gbs']:.1f} before the sweep, "
            f"{post['gflops']:.1f} / {post['bandwidth_gbs']:.1f} after. "
            f"GL: {sweep.get('gl_renderer')}. Sweep took {sweep['sweep_s']:.0f} s.")
    lines = [head, ""]
    lines += [f"- {n}" for n in sweep["notes"]] + [""]
    stages = list(TABLE_STAGES)
    for dim in DIMENSIONS:
        lines += [f"Engine, varying {dim} (median ms)", "",
                  "| " + dim + " | backend | " + " | ".join(stages) + " |",
                  "|---|---|" + "---|" * len(stages)]
        for c in sweep["engine"].get(dim, []):
            label = c["value"] if dim != "triangles" else c.get("triangles", c["value"])
            if "median_ms" not in c:
                lines.append(f"| {label} | {c['backend']} | skipped: {c.get('skipped')} |")
                continue
            ms = c["median_ms"]
            cells = [f"{ms[s]:.1f}" if s in ms else "-" for s in stages]
            name = c["backend"] + (f" ({c['numpy_fallbacks']} numpy calls)"
                                   if c.get("numpy_fallbacks") else "")
            lines.append(f"| {label} | {name} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += [("Dense propagation step (every cell lit, visibility on unless 'no vis') and "
               "roofline"), "",
              ("| backend | model | grid | ms/step | GFLOP/step | GFLOP/s | flop frac | GB/s "
               "| bw frac | bw frac (materialised) | roofline frac | bound |"),
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sweep["propagation"]:
        model = r["angular"] + ("" if r.get("visibility", True) else ", no vis")
        if "step_ms" not in r:
            lines.append(f"| {r['backend']} | {model} | {r['resolution']}^3 | "
                         f"skipped: {r.get('skipped')} |")
            continue
        rf = r["roofline"]
        lines.append(
            f"| {r['backend']} | {model} | {r['resolution']}^3 | {r['step_ms']:.2f} | "
            f"{r['flops'] / 1e9:.3f} | {rf['achieved_gflops']:.2f} | {rf['flop_fraction']:.3f} | "
            f"{rf['achieved_gbs']:.2f} | {rf['bandwidth_fraction']:.4f} | "
            f"{rf['bandwidth_fraction_materialised']:.3f} | {rf['roofline_fraction']:.3f} | "
            f"{rf['bound']} |")
    lines += ["", "Lookup (backend.irradiance)", "",
              "| backend | model | points | grid | ms |", "|---|---|---|---|---|"]
    for r in sweep["lookup"]:
        ms = f"{r['ms']:.1f}" if "ms" in r else f"skipped: {r.get('skipped')}"
        lines.append(f"| {r['backend']} | {r['angular']} | {r['points']} | "
                     f"{r['resolution']}^3 | {ms} |")
    lines += ["", "Cost-growth exponents (time ~ size^k, least squares on log-log)", "",
              "| series | backend | k | points | r^2 |", "|---|---|---|---|---|"]
    for name, per in sweep["exponents"].items():
        for backend, fit in per.items():
            if fit["exponent"] is None:
                lines.append(f"| {name} | {backend} | - | {fit['points']} | {fit['reason']} |")
            else:
                lines.append(f"| {name} | {backend} | {fit['exponent']:.2f} | {fit['points']} | "
                             f"{fit['r2']:.3f} |")
    return "\n".join(lines)
