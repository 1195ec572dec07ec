"""Stability suite invariants (lpv_core/stability.py) at the suite's "test" sizes.

One run of every case (a few seconds) feeds all assertions. Tolerances and their reasons are
in tools.stability.TOLERANCES: the engine is covariant under scaling and translation and
linear in light power and (one bounce) albedo in exact arithmetic; float32 rounding remains.
"""

import math

import numpy as np
import pytest

from lpv_core import propagation
from tools import stability

TOL = stability.TOLERANCES


@pytest.fixture(scope="module")
def suite():
    return {f["name"]: f for f in stability.run_suite("test")}


def _rows(suite, name):
    rows = suite[name]["rows"]
    assert rows, name
    return rows


def test_every_case_reports_the_four_measures(suite):
    assert set(suite) == {c.__name__[len("case_"):] for c in stability.CASES}
    for f in suite.values():
        for r in f["rows"]:
            for key in ("nonfinite", "energy_growth", "deviation", "time_s"):
                assert key in r, (f["name"], r["label"], key)
            assert r["time_s"] >= 0


def test_no_nan_or_inf_in_grids_or_passes(suite):
    # float16 is the exception by design: it shows where an unscaled half-float grid overflows.
    for name, f in suite.items():
        if name == "float16":
            continue
        for r in f["rows"]:
            assert r["nonfinite"] == 0, (name, r["label"])
            assert r["deviation"] is not None and not math.isnan(r["deviation"]), (name, r)


def test_energy_never_grows_in_any_propagation_step(suite):
    for name, f in suite.items():
        for r in f["rows"]:
            assert r["energy_growth"] <= 1.0 + TOL["energy"], (name, r["label"],
                                                                r["energy_growth"])


def test_propagation_steps_were_recorded(suite):
    # The energy measure is only meaningful if the engine's steps went through record_steps.
    rows = _rows(suite, "scale") + _rows(suite, "thin_wall") + _rows(suite, "grids")
    assert all(r["steps"] > 0 for r in rows)


@pytest.mark.parametrize("case", ["scale", "translation"])
def test_scale_and_translation_invariance(suite, case):
    # Covers scales 1e-3 .. 1e4 and offsets up to 1e6 m.
    xs = [r["x"] for r in _rows(suite, case)]
    assert (min(xs), max(xs)) == ((1e-3, 1e4) if case == "scale" else (1.0, 1e6))
    for r in _rows(suite, case):
        assert r["deviation"] <= TOL[case], (case, r["label"], r["deviation"])
        assert r["deviation_direct"] <= TOL["direct"], (case, r["label"])


def test_linear_in_light_power_from_1e_minus_6_to_1e9_watts(suite):
    rows = _rows(suite, "power")
    assert min(r["x"] for r in rows) == 1e-6 and max(r["x"] for r in rows) == 1e9
    for r in rows:
        assert r["deviation"] <= TOL["power"], (r["label"], r["deviation"])
        assert r["deviation_direct"] <= TOL["power"], r["label"]


def test_linear_in_albedo_and_no_gi_at_albedo_zero(suite):
    rows = {r["x"]: r for r in _rows(suite, "albedo")}
    assert rows[0.0]["deviation"] == 0.0  # exactly nothing bounces
    assert rows[1.0]["nonfinite"] == 0
    for a, r in rows.items():
        assert r["deviation"] <= TOL["albedo"], (a, r["deviation"])


def test_degenerate_triangles_are_dropped_or_harmless(suite):
    rows = {r["label"]: r for r in _rows(suite, "degenerate")}
    for label, key in (("zero-area", "zero_area_triangles"), ("collinear", "zero_area_triangles"),
                       ("NaN vertex", "nonfinite_vertices"), ("Inf vertex", "nonfinite_vertices")):
        assert rows[label]["dropped"][key] == 64, label
        assert rows[label]["deviation"] == 0.0, label
    # Kept but sub-pixel: they may cover a texel or pixel centre now and then.
    for label in ("needle (1e-7 m)", "tiny (1e-9 m)"):
        assert rows[label]["deviation"] <= 1e-2, (label, rows[label]["deviation"])


def test_duplicated_coplanar_triangles_change_nothing_without_occlusion(suite):
    rows = {r["label"]: r for r in _rows(suite, "coplanar")}
    assert rows["duplicated, same albedo"]["deviation"] <= 1e-3


def test_duplicated_coplanar_triangles_change_nothing_with_occlusion(suite):
    rows = {r["label"]: r for r in _rows(suite, "coplanar")}
    label = "duplicated, same albedo, occlusion"
    if label not in rows:
        pytest.skip("no occlusion setting in this engine")
    assert rows[label]["deviation"] <= 1e-3


def test_iterations_converge_and_stop_early(suite):
    rows = {r["x"]: r for r in _rows(suite, "iterations")}
    longest = rows[max(rows)]
    assert max(rows) == 1000
    assert longest["iterations"][0] < 1000  # stopped once a step carried < 1e-3 of the flux
    # The sum of steps converges: 64 steps are within 5 % of the converged sum.
    assert rows[64]["deviation"] <= 0.05


def test_energy_traces_decay_for_every_propagation_mode(suite):
    traces = suite["energy"]["traces"]
    assert traces  # every mode propagation.step accepts
    for mode, tr in traces.items():
        for name, t in tr.items():
            flux = np.asarray(t["flux"])
            assert len(flux) == 1001, (mode, name)
            assert t["nonfinite"] == 0, (mode, name)
            above = flux[:-1] > stability.FLUX_FLOOR  # float32 subnormals below
            assert np.all(flux[1:][above] <= flux[:-1][above] * (1 + TOL["energy"])), (mode,
                                                                                     name)
        assert tr["single VPL"]["flux"][-1] < 1e-3 * tr["single VPL"]["flux"][0]  # left the grid


def test_leak_cases_run_with_and_without_occlusion(suite):
    for case in ("thin_wall", "one_cell", "light_inside"):
        rows = _rows(suite, case)
        assert all(np.isfinite(r["deviation"]) and r["deviation"] >= 0 for r in rows), case
    labels = [r["label"] for r in _rows(suite, "thin_wall")]
    assert any("1 cells" in lab for lab in labels)  # the one-cell-thick wall


def test_float16_storage_is_close_in_range_and_flags_overflow_and_underflow(suite):
    rows = {r["x"]: r for r in _rows(suite, "float16")}
    assert rows[300.0]["deviation"] <= 1e-2  # 11-bit mantissa: ~5e-4 per rounding
    assert rows[300.0]["nonfinite"] == 0
    assert rows[1e9]["nonfinite"] > 0  # intensities beyond 65504 overflow to Inf
    assert rows[1e-6]["underflow"] > 0.5  # below 6e-8 they flush to zero


def test_grids_from_4_to_32_cells_run(suite):
    rows = _rows(suite, "grids")
    assert [r["x"] for r in rows] == [4, 8, 16, 32]
    assert all(r["indirect_mean"] > 0 for r in rows)


def test_record_steps_restores_propagation_step():
    original = propagation.step
    values = np.zeros((4, 4, 4, 3, 4), np.float32)
    values[1, 1, 1, :, 0] = 1.0
    with stability.record_steps() as log:
        assert propagation.step is not original
        propagation.step(values)
    assert propagation.step is original
    assert len(log["steps"]) == 1 and log["injected"] is not None
    f_in, f_out = log["steps"][0]
    assert f_out == pytest.approx(f_in, rel=1e-6)


def test_rel_dev():
    a = np.array([1.0, 2.0])
    assert stability.rel_dev(a, a) == 0.0
    assert stability.rel_dev(a * 1.1, a) == pytest.approx(0.1)
    assert stability.rel_dev(np.zeros(2), np.zeros(2)) == 0.0
    assert stability.rel_dev(a, np.zeros(2)) == math.inf
    assert stability.rel_dev(np.array([np.nan, 2.0]), a) == pytest.approx(1 / 3)
