"""The benchmark's output: the quick JSON keys, and the tiny scaling sweep (bench_sweep.py).

No timed assertions: only that every swept value has its figures, that they are positive and
finite, that exponents are fitted from at least 3 points, and that roofline ratios are in
(0, 1] or carry the note explaining why not.
"""

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT

from lpv_core.scene import GISettings
from tools import bench_sweep, dom_steps

QUICK_KEYS = ("full_update_ms", "light_intensity_tweak_ms", "one_light_moved_ms",
              "camera_in_cell_ms")


@pytest.fixture(scope="module")
def quick_json() -> dict:
    """One run of the CLI as documented: --quick --json plus the tiny sweep."""
    proc = subprocess.run([sys.executable, "-m", "tools.bench", "--quick", "--json",
                           "--sweep-quick"], check=False, cwd=ROOT, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout)  # exactly one JSON object (json.loads rejects extra data)


def _finite_positive(v) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v) and v > 0


def test_quick_json_keys(quick_json):
    for key in QUICK_KEYS:
        assert _finite_positive(quick_json[key]), key
    assert quick_json["backend"] in ("numpy", "gl", "auto")
    assert quick_json["angular"] == quick_json["settings"]["angular"] == GISettings().angular
    assert isinstance(quick_json["backend_used"], str) and quick_json["backend_used"]
    assert all(math.isfinite(v) and v >= 0 for v in quick_json["median_ms"].values())
    # issue 6's stated quality (3 x 32^3): the full update and the cascades the planner ran
    stated = quick_json["stated"]
    assert stated["settings"]["grid_resolution"] == 32 and stated["settings"]["cascades"] == 3
    assert _finite_positive(quick_json["full_update_stated_ms"])
    assert quick_json["full_update_stated_ms"] == stated["full_update_ms"]
    assert stated["cascades_run"] + len(stated["skipped"]) == 3 and stated["cascades_run"] >= 1
    assert _finite_positive(stated["median_ms"]["propagation"])


def test_sweep_has_every_value(quick_json):
    sweep = quick_json["sweep"]
    assert sweep["quick"] is True
    assert sweep["config"]["angular"] == bench_sweep.ENGINE_ANGULAR == GISettings().angular
    for dim in bench_sweep.DIMENSIONS:
        cases = sweep["engine"][dim]
        for backend in bench_sweep.BACKENDS:
            got = [c["value"] for c in cases if c["backend"] == backend]
            assert got == list(bench_sweep.QUICK[dim]), (dim, backend)
        for c in cases:
            if "skipped" in c:
                assert c["backend"] != "numpy", c  # the numpy backend always runs
                assert isinstance(c["skipped"], str) and c["skipped"], c
                continue
            ms = c["median_ms"]
            for stage in ("rsm", "injection", "propagation", "propagation_per_step",
                          "geometry_volume", "lpv_update", "lookup", "total"):
                assert _finite_positive(ms[stage]), (dim, c["value"], c["backend"], stage)
            assert all(math.isfinite(v) and v >= 0 for v in ms.values())
            assert c["steps"] >= 1
            assert ms["propagation_per_step"] == pytest.approx(ms["propagation"] / c["steps"])


def test_sweep_scales_what_it_says(quick_json):
    engine_out = quick_json["sweep"]["engine"]
    tris = [c["triangles"] for c in engine_out["triangles"] if c["backend"] == "numpy"]
    assert tris == sorted(tris) and len(set(tris)) == len(tris)
    lights = [c["lights"] for c in engine_out["lights"] if c["backend"] == "numpy"]
    assert lights == list(bench_sweep.QUICK["lights"])


def test_exponents_fitted_from_three_points(quick_json):
    fits = quick_json["sweep"]["exponents"]
    for name, *_ in bench_sweep.ENGINE_FITS:
        assert name in fits
    for angular in bench_sweep.ANGULARS:
        assert f"dense {angular} step vs cells" in fits, angular
    assert "dense dom step vs cells (no visibility)" in fits
    for name, per in fits.items():
        fit = per["numpy"]
        assert fit["points"] >= 3, name
        assert math.isfinite(fit["exponent"]), name
        gl = per.get("gl")
        if gl is not None and gl["exponent"] is None:
            assert gl["reason"], name


def test_roofline_ratios(quick_json):
    sweep = quick_json["sweep"]
    limits = sweep["machine_limits"]
    assert _finite_positive(limits["gflops"]) and _finite_positive(limits["bandwidth_gbs"])
    rows = sweep["propagation"]
    sizes = bench_sweep.QUICK["prop_sizes"]
    assert bench_sweep.ANGULARS[0] == "dom"  # the default model first
    cases = [("dom", True), ("dom", False), ("sh", True)]
    assert sorted((r["backend"], r["angular"], r["visibility"], r["resolution"]) for r in rows) \
        == sorted((b, a, v, s) for b in bench_sweep.BACKENDS for a, v in cases for s in sizes)
    assert all("step_ms" in r for r in rows if r["backend"] == "numpy")  # numpy always runs
    for r in rows:
        if "skipped" in r:
            assert r["backend"] == "gl" and r["skipped"]
            continue
        assert _finite_positive(r["step_ms"])
        rf = r["roofline"]
        for key in ("flop_fraction", "bandwidth_fraction", "roofline_fraction"):
            assert _finite_positive(rf[key]), (r, key)
        assert rf["roofline_fraction"] == pytest.approx(
            max(rf["flop_fraction"], rf["bandwidth_fraction"]))
        assert rf["roofline_fraction"] <= 1.0 or rf["note"], r
        counts = bench_sweep.step_counts(r["resolution"], r["angular"], r["visibility"])
        assert r["flops"] == counts["flops"] and r["bytes"] == counts["bytes"]
        if r["backend"] == "gl" and r["angular"] == "dom":  # steps timed without unfold/fold
            assert _finite_positive(r["unfold_fold_ms"]) and _finite_positive(r["propagate_ms"])


def test_lookup_rows(quick_json):
    rows = quick_json["sweep"]["lookup"]
    assert {(r["backend"], r["angular"]) for r in rows} == {
        (b, a) for b in bench_sweep.BACKENDS for a in bench_sweep.ANGULARS}
    for r in rows:
        assert r["points"] == bench_sweep.QUICK["lookup_points"]
        assert _finite_positive(r["ms"]) if "ms" in r else r["skipped"]


def test_fit_exponent_recovers_a_power_law():
    xs = [10, 100, 1000, 10000]
    fit = bench_sweep.fit_exponent(xs, [3.0 * x**1.5 for x in xs])
    assert fit["exponent"] == pytest.approx(1.5)
    assert fit["points"] == 4 and fit["r2"] == pytest.approx(1.0)
    few = bench_sweep.fit_exponent([1, 2, 2, 3], [1.0, 2.0, 2.0, float("nan")])
    assert few["exponent"] is None and few["reason"]


def test_step_counts_follow_the_algorithm():
    sh = bench_sweep.step_counts(16, "sh")
    # per cell: 3 colours x (30 face evaluations 2 x 4 x 30, clamp / sum / rescale 95, six
    # 5 -> 4 re-projections 6 x 2 x 5 x 4, visibility 24, shift-adds 24)
    assert sh["flops_per_cell"] == 3 * (240 + 95 + 240 + 24 + 24)
    assert bench_sweep.step_counts(32, "sh")["flops"] == pytest.approx(8 * sh["flops"])
    assert sh["bytes"] == 16**3 * (48 + 24 + 48)
    assert bench_sweep.step_counts(16, "sh", visibility=False)["bytes"] == 16**3 * 96
    for retired in ("p1", "m1"):
        with pytest.raises(ValueError):
            bench_sweep.step_counts(16, retired)


def test_step_counts_dom_follow_the_algorithm():
    r, p, q = 16, 18, 64
    dom = bench_sweep.step_counts(r, "dom")
    # 64 directions x 8 neighbour offsets, each 1 multiply + 1 add per colour
    assert dom["direction_offset_pairs"] == q * 8
    live = (r - 1) * (p * p + p + 1) + 1  # flat range from cell (1, 1, 1) to (R, R, R)
    assert dom["live_cells"] == live and dom["padded_cells"] == p**3
    # advection over the live range + scan, accumulation and flux sum over the padded grid
    assert dom["flops"] == 3 * q * 8 * 2 * live + 3 * q * 3 * p**3
    assert 3 * 1024 < dom["flops_per_cell"] < 3 * (1024 + 192) * (p / r) ** 3
    assert dom["flops_per_cell"] > bench_sweep.step_counts(r, "sh")["flops_per_cell"]
    # compulsory: read the flux, write the arrivals, read + write the accumulation, visibility
    assert dom["bytes"] == r**3 * (4 * q * 3 * 4 + 24)
    free = bench_sweep.step_counts(r, "dom", visibility=False)
    assert free["bytes"] == r**3 * 4 * q * 3 * 4 and free["flops"] == dom["flops"]
    # the weight x transmittance table is read per (direction, offset, cell) with visibility
    assert dom["bytes_materialised"] - free["bytes_materialised"] == q * 8 * live * 4
    assert dom["bytes_materialised"] > 10 * dom["bytes"] > 0
    # advection flops grow as the live range, ~(1 + 2/R)^2 R^3: per cell they fall with R
    assert bench_sweep.step_counts(32, "dom")["flops_per_cell"] < dom["flops_per_cell"]


def test_dom_step_is_the_propagation_loop():
    """bench_sweep.dom_step (what the dense dom rows time) is one step of
    dom_steps.propagate_steps: the same result after the same number of steps."""
    from lpv_core.propagation import ordinates, quadrature

    rng = np.random.default_rng(3)
    r = 6
    injected = np.zeros((r, r, r, 3, 4), np.float32)
    injected[2:4, 1:5, 3, :, 0] = 1.0
    injected[2:4, 1:5, 3, :, 3] = 0.5
    vis = rng.uniform(0.5, 1.0, (6, r, r, r)).astype(np.float32)
    ref = dom_steps.propagate_steps(injected, 3, min_fraction=0.0, visibility=vis,
                                    occlude_first_step=True)
    cur = ordinates.pad(ordinates.unfold(injected))
    acc = np.zeros_like(cur)
    table = ordinates.factors(r, quadrature.offset_visibilities(vis))
    for _ in range(3):
        cur, moved = bench_sweep.dom_step(cur, acc, table, r)
    assert moved == pytest.approx(float(cur.sum(dtype=np.float64))) and moved > 0
    got = (ordinates.fold(np.ascontiguousarray(ordinates.interior(acc, r)), 9)
           + ordinates.emission_band2(injected))
    np.testing.assert_allclose(got, ref.values, rtol=1e-5, atol=1e-7)


def test_roofline_notes_a_step_faster_than_the_limit():
    counts = {"flops": 1e9, "bytes": 1e6, "bytes_materialised": 1e7}
    limits = {"gflops": 10.0, "bandwidth_gbs": 10.0}
    slow = bench_sweep.roofline(1000.0, counts, limits)  # 1 s for 0.1 s of FLOPs
    assert slow["roofline_fraction"] == pytest.approx(0.1) and slow["bound"] == "compute"
    assert "note" not in slow
    fast = bench_sweep.roofline(10.0, counts, limits)
    assert fast["roofline_fraction"] == pytest.approx(10.0) and fast["note"]


def test_subdivide_keeps_the_surface():
    tris = np.array([[[0, 0, 0], [2, 0, 0], [0, 1, 0]], [[0, 0, 1], [0, 3, 1], [1, 0, 2]]], float)
    sub = bench_sweep.subdivide(tris, 5)
    assert sub.shape == (2 * 25, 3, 3)

    def area(t):
        return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)

    assert area(sub).sum() == pytest.approx(area(tris).sum())
    # same orientation: every sub-triangle's normal matches its parent's
    n = np.cross(sub[:, 1] - sub[:, 0], sub[:, 2] - sub[:, 0])
    parent = np.repeat(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), 25, axis=0)
    assert np.all(np.einsum("ij,ij->i", n, parent) > 0)
