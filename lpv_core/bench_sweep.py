"""Scaling sweep of the LPV engine: per-stage medians, cost-growth exponents and a roofline.

Used by ``python -m lpv_core.bench --sweep`` (full, a few minutes) and ``--sweep-quick`` (tiny,
for tests). Everything here is a pure function returning plain dicts (JSON-ready); nothing is
printed except by :func:`table`.

What is measured, and why this way:

* **Engine sweep** (:func:`engine_sweep`): one factor at a time around a base configuration,
  ``Engine.update`` + ``deferred.render`` on the demo Cornell box, for each backend; the medians
  of ``Stats.ms`` per stage. Propagation runs a *fixed, small* number of steps
  (``settings.iterations``) instead of running to convergence (m1 converges after up to 3 R
  steps: minutes per update on 64^3 here), so the figures are per-step costs, not the cost of a
  converged update; ``propagation_per_step_ms`` divides by the steps actually run.
  Triangle counts are scaled by subdividing every demo triangle into k^2 (same scene, same
  lighting, only the cost changes); lights by replicating the demo spot light.
* **Propagation microbenchmark** (:func:`propagation_sweep`): ``step`` on a *dense* grid (every
  cell lit, with visibility), per backend and angular model. The engine's early steps are
  sparse (the m1 step skips empty cells), so this is the worst case and the one the roofline
  applies to.
* **Machine limits** (:func:`machine_limits`): float32 GFLOP/s of a large numpy matmul and
  memory bandwidth of a large array copy, measured in the same run.
* **Roofline** (:func:`roofline`): FLOPs and bytes of one propagation step counted from the
  algorithm (:func:`step_counts`), time at the machine's limit vs time measured.
* **Lookup** (:func:`lookup_bench`): ``backend.irradiance`` on a 1280x720 G-buffer's worth of
  points (921,600) in the grid, per backend and angular model.
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

from . import deferred, demo, engine, propagation
from .grid import Grid
from .scene import GISettings, make_scene

BACKENDS = ("numpy", "gl")

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
    "direction_groups": 1,
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
    "direction_groups": 1,
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
        steps.append(int(sum(stats.info.get("iterations") or [0])))
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
                                      direction_groups=cfg["direction_groups"],
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


def step_counts(resolution: int, angular: str = "m1", visibility: bool = True) -> dict:
    """FLOPs and bytes of one propagation step on a dense (all cells lit) R^3 grid.

    Counted from the algorithm (propagation.step / step_m1), per cell and colour (row):

    * m1: moments (~30), kappa (~6), <d, w_q> for 64 bundle directions (2 x 3 x 64), kappa x
      that and exp (2 x 64; exp counted as one FLOP), normalisation (64 + 2), bundle -> 27
      neighbours x 4 SH matmul (2 x 64 x 108), scale (108), gather with visibility
      (108 multiplies + 108 adds) and the visibility products per offset (~54 per cell);
    * sh: 30 face evaluations (2 x 4 x 30), clamp / sum / rescale (~95), six 5 -> 4
      re-projections (6 x 2 x 5 x 4), visibility (24) and the shift-adds (24).

    ``bytes`` is the compulsory traffic: read the grid (48 B/cell) and visibility (24 B/cell),
    write the result (48 B/cell). ``bytes_materialised`` estimates what the numpy code moves
    through the arrays it materialises (each written once and read once), which is what its
    memory roof really is.
    """
    cells = resolution**3
    rows = 3 * cells
    q, k = propagation.M1_DIRECTIONS, len(propagation.OFFSETS)
    vis = 1 if visibility else 0
    if angular == "m1":
        per_row = 30 + 6 + 2 * 3 * q + 2 * q + q + 2 + 2 * q * 4 * k + 4 * k + 4 * k * (1 + vis)
        flops = rows * per_row + cells * 54 * vis
        # moments (16 in, ~36 out), bundles (q floats: dot, scale, exp, sum: 4 passes r+w),
        # arrivals (4k: matmul out, scale, scatter, transpose: r+w each), gather (k offsets:
        # slice read, visibility product, += into out: ~6 x 16 B).
        per_row_bytes = 16 + 36 + 4 * q * 4 * 2 + 4 * (4 * k) * 4 * 2 + k * 6 * 16
        materialised = rows * per_row_bytes + cells * k * 4 * 3 * vis
    elif angular == "sh":
        per_row = 2 * 4 * 30 + 95 + 6 * 2 * 5 * 4 + 24 * vis + 24
        flops = rows * per_row
        # face flux (30 floats: matmul out, clamp, sum, scale: r+w), six re-projections
        # (out 16 B, visibility product, shift-add: ~5 x 16 B each).
        per_row_bytes = 16 + 120 * 4 * 2 + 6 * 5 * 16
        materialised = rows * per_row_bytes + cells * 24 * vis
    else:
        raise ValueError(f"angular must be 'm1' or 'sh', not {angular!r}")
    compulsory = cells * (48 + 24 * vis + 48)
    return {"flops": float(flops), "bytes": float(compulsory),
            "bytes_materialised": float(materialised), "cells": cells,
            "flops_per_cell": flops / cells}


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
        from .gl_backend import GLBackend

        return GLBackend(), None
    except Exception as exc:  # noqa: BLE001 - recorded: no GL context
        return None, f"no GL backend: {type(exc).__name__}: {exc}"


def propagation_sweep(sizes, steps: int, repeat: int, limits: dict,
                      angulars=("m1", "sh"), backends=BACKENDS) -> list[dict]:
    """Median ms per step of ``steps`` fixed steps on dense grids, with the roofline of each.

    numpy: ``propagation.step`` called ``steps`` times; gl: ``GLBackend.propagate`` with
    ``min_fraction=0`` and no readback (the grid stays on the GPU, as between steps).
    """
    rng = np.random.default_rng(1)
    gl, gl_reason = _gl_backend() if "gl" in backends else (None, None)
    rows = []
    for r in sizes:
        values, vis = _dense_grid(r, rng)
        for angular in angulars:
            counts = step_counts(r, angular)
            for name in backends:
                row = {"backend": name, "angular": angular, "resolution": r, "cells": r**3,
                       "steps": steps, "flops": counts["flops"], "bytes": counts["bytes"]}
                rows.append(row)
                try:
                    if name == "numpy":
                        def run(v=values, a=angular, vv=vis):
                            cur = v
                            for _ in range(steps):
                                cur = propagation.step(cur, vv, angular=a)
                    else:
                        if gl is None:
                            row["skipped"] = gl_reason
                            continue
                        on_gpu = gl.upload(values)

                        def run(g=on_gpu, a=angular, vv=vis):
                            gl.propagate(g, steps, min_fraction=0.0, visibility=vv,
                                         angular=a, occlude_first_step=True, readback=False)
                    sec = _median_s(run, repeat)
                    if name == "gl":
                        on_gpu.release()
                    row["step_ms"] = sec * 1000.0 / steps
                    row["roofline"] = roofline(row["step_ms"], counts, limits)
                except Exception as exc:  # noqa: BLE001 - recorded, the sweep goes on
                    row["skipped"] = f"{type(exc).__name__}: {exc}"
    return rows


def lookup_bench(points: int, resolution: int, repeat: int, angulars=("m1", "sh"),
                 backends=BACKENDS) -> list[dict]:
    """Median ms of ``backend.irradiance`` on ``points`` receivers (a 1280x720 G-buffer is
    921,600), on a propagated grid with occlusion visibility, as deferred.render calls it."""
    rng = np.random.default_rng(2)
    g = Grid((-1.0, -1.0, 0.0), 2.0 / resolution, resolution)
    values, vis = _dense_grid(resolution, rng)
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
                sec = _median_s(lambda b=be, a=angular: b.irradiance(
                    g, values, pos, nrm, angular=a, visibility=vis), repeat)
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
    for angular in ("m1", "sh"):
        for backend in BACKENDS:
            rows = [r for r in prop_rows if r["backend"] == backend and r["angular"] == angular
                    and "step_ms" in r]
            if not any(r["angular"] == angular for r in prop_rows):
                continue
            fits.setdefault(f"dense {angular} step vs cells", {})[backend] = fit_exponent(
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
            row["roofline"] = roofline(row["step_ms"], step_counts(row["resolution"],
                                                                   row["angular"]), best)
    gl, _ = _gl_backend()
    return {
        "quick": quick,
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg.items()},
        "notes": [
            (f"propagation runs a fixed {cfg['iterations']} step(s) per update "
             f"(settings.iterations), not to convergence; direction_groups = "
             f"{cfg['direction_groups']}: figures are per-step costs"),
            "one factor varied at a time around config.base",
            "triangle counts: demo Cornell box triangles each subdivided into k^2",
            ("numpy_fallbacks > 0 on a gl case: that many backend calls ran the numpy code "
             "(e.g. propagation of inner cascades, capture_outflow, is not ported to GL)"),
            (f"dense propagation: every cell lit, visibility on, {cfg['prop_steps']} step(s) "
             "timed per run"),
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

TABLE_STAGES = ("planner", "rsm", "injection", "propagation", "propagation_per_step", "geometry_volume",
                "upload", "combine", "lpv_update", "gbuffer", "direct", "lookup", "total")


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
    lines += ["Dense propagation step (every cell lit, visibility on) and roofline", "",
              ("| backend | model | grid | ms/step | GFLOP/step | GFLOP/s | flop frac | GB/s "
               "| bw frac | bw frac (materialised) | roofline frac | bound |"),
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sweep["propagation"]:
        if "step_ms" not in r:
            lines.append(f"| {r['backend']} | {r['angular']} | {r['resolution']}^3 | "
                         f"skipped: {r.get('skipped')} |")
            continue
        rf = r["roofline"]
        lines.append(
            f"| {r['backend']} | {r['angular']} | {r['resolution']}^3 | {r['step_ms']:.2f} | "
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
